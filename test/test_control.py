"""
The controller's core (no ROS): planner, goals, closed loop.

On a forward model whose answer is known -- the drawn two-segment rod of
``model/synthetic.py`` -- so every check is exact.
"""

import json

import numpy as np
import pytest
import torch

from softshape_ros.control import (Bank, Goal, GoalError, GoalSpec, Planner, PlannerConfig,
                                   SceneContext, ShapeLoop)
from softshape_ros.control.forward import usable_limits
from softshape_ros.control.goal import camera_to_model_px, model_to_camera_px
from softshape_ros.control.objective import Objective
from softshape_ros.model import synthetic
from softshape_ros.model.synthetic import MAX_PA, centreline, contact_shape

VIEWS = ('main', 'side')
SPEC = GoalSpec(VIEWS, 1, 64)
OBJ = (0.62, 0.1, 0.18)                 # a cylinder beside the rod (x, y, radius)
CFG = PlannerConfig(bank_size=96, starts=2, lm_iterations=8)
DRAW_RADIUS = 0.2                       # 6 px: the robot's half-width in its 64 px images


def render(points, obj, view):
    """
    Draw the synthetic rod and cylinder of ``model/synthetic.py`` with anti-aliased edges.

    ``synthetic.render`` colours whole pixels, so its images change in pixel steps and a
    finite-difference Jacobian sees nothing between them; the simulator's renderer (and the
    network) are smooth. Same centreline, object, shades and views; coverage from the
    distance to the centreline polyline; drawn as thick as the robot is in its 64 px images
    (the 5 px synthetic rod would make the IoU tolerance a test of sub-pixel luck).
    """
    s = synthetic.SIZE
    u0, u1, z0, z1 = synthetic.EXTENT
    px = (u1 - u0) / s
    us = u0 + (np.arange(s) + 0.5) * px
    zs = z1 - (np.arange(s) + 0.5) * (z1 - z0) / s
    U, Z = (a.astype(np.float32) for a in np.meshgrid(us, zs))
    points = points.astype(np.float32)
    yaw = synthetic.VIEW_YAW[view]
    c, sn = np.cos(yaw), np.sin(yaw)
    pu = points[:, 0] * c + points[:, 1] * sn
    pd = -points[:, 0] * sn + points[:, 1] * c
    ax, az = pu[:-1], points[:-1, 2]
    bx, bz = pu[1:] - ax, points[1:, 2] - az
    qx, qz = U[..., None] - ax, Z[..., None] - az                      # S x S x K
    t = np.clip((qx * bx + qz * bz) / np.maximum(bx * bx + bz * bz, 1e-12), 0, 1)
    d2 = (qx - t * bx) ** 2 + (qz - t * bz) ** 2
    k = d2.argmin(-1)[..., None]
    dist = np.sqrt(np.take_along_axis(d2, k, -1)[..., 0])
    tk = np.take_along_axis(t, k, -1)[..., 0]
    depth_r = pd[:-1][k[..., 0]] + tk * (pd[1:] - pd[:-1])[k[..., 0]]
    alpha_r = np.clip((DRAW_RADIUS - dist) / px + 0.5, 0, 1)
    g = synthetic.GRAY
    if obj is None:
        img = g['robot'] * alpha_r + g['background'] * (1 - alpha_r)
    else:
        ox, oy, r = obj
        ou, od = ox * c + oy * sn, -ox * sn + oy * c
        du = np.abs(U - ou)
        alpha_o = np.clip((r - du) / px + 0.5, 0, 1) * ((Z > -1.9) & (Z < -0.25))
        depth_o = od - np.sqrt(np.clip(r * r - du * du, 0, None))
        behind = g['object'] * alpha_o + g['background'] * (1 - alpha_o)
        front_r = g['robot'] * alpha_r + behind * (1 - alpha_r)
        over_r = g['robot'] * alpha_r + g['background'] * (1 - alpha_r)
        front_o = g['object'] * alpha_o + over_r * (1 - alpha_o)
        img = np.where(depth_r <= depth_o, front_r, front_o)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)[None]


class DrawnRod:
    """The synthetic rod as a forward model: u in [0, 1]^6 -> images (known exactly)."""

    differentiable = False

    def __init__(self, limits=(MAX_PA,) * 6, gain=1.0, obj=OBJ):
        self.limits = usable_limits(limits)
        self.gain, self.obj = gain, obj
        self.evaluations = 0

    def images(self, pressures_pa) -> np.ndarray:
        pts = contact_shape(np.asarray(pressures_pa) * self.gain, self.obj)
        return np.stack([render(pts, self.obj, v) for v in VIEWS])

    def __call__(self, u):
        self.evaluations += len(u)
        out = [self.images(self.pressures(row)).astype(np.float32) / 255
               for row in np.asarray(u, dtype=np.float64)]
        return torch.from_numpy(np.stack(out))

    def pressures(self, u):
        return np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0) * self.limits


@pytest.fixture(scope='module')
def rod():
    fwd = DrawnRod()
    rest = np.stack([render(centreline(np.zeros(6)), OBJ, v) for v in VIEWS])
    ctx = SceneContext.from_initial(rest)
    return fwd, ctx, Bank.for_scene(fwd, ctx, CFG.bank_size, seed=1)


def differential(p):
    """Pressures less each segment's common mode (which bends nothing)."""
    seg = np.asarray(p, dtype=float).reshape(2, 3)
    return (seg - seg.mean(1, keepdims=True)).ravel()


@pytest.mark.parametrize('seed', [0, 1])
def test_planner_recovers_known_pressures_on_the_drawn_rod(rod, seed):
    fwd, ctx, bank = rod
    p_goal = np.random.default_rng(seed).uniform(0.1, 0.9, 6) * MAX_PA
    goal = Goal.images(SPEC, fwd.images(p_goal))
    plan = Planner(CFG).plan(Objective(ctx, goal), fwd, bank)
    # The model is the plant here: its images at the plan are what the rig would show.
    got = fwd.images(plan.pressures_pa)
    np.testing.assert_array_equal(got, plan.predicted)
    err = Objective(ctx, goal).describe(got)
    assert max(err['tip_error_px']) <= 1.0 and err['iou'] >= 0.9, err
    # Recovered up to the common mode of each segment, which moves nothing.
    assert np.abs(differential(plan.pressures_pa) - differential(p_goal)).max() < 0.08 * MAX_PA
    assert plan.evaluations > 0 and plan.iterations >= 1
    assert plan.history == sorted(plan.history, reverse=True)       # LM never goes uphill


def test_tip_and_silhouette_goals_are_reached_too(rod):
    fwd, ctx, bank = rod
    p_goal = np.array([0.8, 0.0, 0.3, 0.0, 0.6, 0.1]) * MAX_PA
    target = fwd.images(p_goal)
    tip_goal = Goal.tip(SPEC, ctx.tips(target[None])[0])
    plan = Planner(CFG).plan(Objective(ctx, tip_goal), fwd, bank)
    assert max(Objective(ctx, tip_goal).describe(fwd.images(plan.pressures_pa))
               ['tip_error_px']) <= 1.5
    sil_goal = Goal.silhouette(SPEC, ctx.masks(target[None])[0])
    # This rod is thin (5 px): a silhouette of it takes more steps to match than the robot's.
    plan = Planner(PlannerConfig(bank_size=CFG.bank_size, lm_iterations=20)).plan(
        Objective(ctx, sil_goal), fwd, bank)
    err = Objective(ctx, sil_goal).describe(fwd.images(plan.pressures_pa))
    assert err['iou'] >= 0.9 and max(err['tip_error_px']) <= 1.5, err


def test_plans_honour_lowered_limits(rod):
    _, ctx, _ = rod
    limits = np.array([40e3, 150e3, 150e3, 0.0, 150e3, 150e3])
    fwd = DrawnRod(limits)
    # A goal that needs chamber 0 far beyond 40 kPa and chamber 3 at 120 kPa.
    goal = Goal.images(SPEC, DrawnRod().images(np.array([150e3, 0, 0, 120e3, 0, 0])))
    bank = Bank.for_scene(fwd, ctx, 64, seed=2)
    plan = Planner(CFG).plan(Objective(ctx, goal), fwd, bank)
    assert np.all(plan.pressures_pa <= limits + 1e-9) and np.all(plan.pressures_pa >= 0)
    assert plan.pressures_pa[3] == 0.0
    assert np.all(bank.u.numpy() * limits <= limits)
    with pytest.raises(ValueError, match='limits must be 6'):
        usable_limits([1.0] * 5)
    with pytest.raises(ValueError, match='limits must be 6'):
        usable_limits([np.nan] + [1.0] * 5)


def test_closed_loop_corrects_a_biased_model(rod):
    _, ctx, _ = rod
    model = DrawnRod(gain=1.35)          # believes every chamber bends 35 % harder
    plant = DrawnRod()
    bank = Bank.for_scene(model, ctx, CFG.bank_size, seed=1)
    reached_first = 0
    for seed in range(2):
        p_goal = np.random.default_rng(10 + seed).uniform(0.2, 0.7, 6) * MAX_PA
        goal = Goal.images(SPEC, plant.images(p_goal))
        loop = ShapeLoop(model, ctx, goal, Planner(CFG), bank, max_iterations=3)
        while not loop.done:
            plan = loop.plan()
            loop.observe(plant.images(plan.pressures_pa))
        reached_first += loop.observations[0].success
        assert loop.success, [o.to_dict() for o in loop.observations]
        us = [p.u for p in loop.plans]                  # never the same command twice
        assert all(np.abs(a - b).max() >= 0.01 for i, a in enumerate(us) for b in us[:i])
        first, last = loop.observations[0], loop.observations[-1]
        if len(loop.observations) > 1:
            assert last.residual < first.residual
    assert reached_first < 2            # open loop alone misses: the loop is what reaches


def test_loop_order_is_enforced(rod):
    fwd, ctx, bank = rod
    loop = ShapeLoop(fwd, ctx, Goal.images(SPEC, fwd.images(np.full(6, 3e4))), Planner(CFG),
                     bank)
    with pytest.raises(RuntimeError, match='plan'):
        loop.observe(ctx.initial)
    loop.plan()
    with pytest.raises(RuntimeError, match='observe'):
        loop.plan()


@pytest.mark.parametrize('kind', ['images', 'silhouette', 'tip'])
@pytest.mark.parametrize('contact', ['any', 'touch', 'clear'])
def test_bank_cost_equals_the_residual_cost(rod, kind, contact):
    fwd, ctx, bank = rod
    target = fwd.images(np.array([0.7, 0.1, 0.0, 0.5, 0.0, 0.2]) * MAX_PA)
    goal = {'images': lambda: Goal.images(SPEC, target, contact),
            'silhouette': lambda: Goal.silhouette(SPEC, ctx.masks(target[None])[0], contact),
            'tip': lambda: Goal.tip(SPEC, ctx.tips(target[None])[0], contact)}[kind]()
    obj = Objective(ctx, goal)
    u0 = np.full(6, 0.3)
    obj.set_correction(target, fwd(torch.from_numpy(u0[None]).float())[0], u0)
    obj.anchor_at(u0, 1.0)
    y = bank.y_flat.reshape((len(bank),) + ctx.initial.shape)
    direct = obj.cost(y, bank.u)
    np.testing.assert_allclose(bank.costs(obj).numpy(), direct.numpy(), rtol=2e-4, atol=2e-4)


def test_contact_modes_steer_toward_or_away_from_the_object(rod):
    fwd, ctx, bank = rod
    assert ctx.has_object().all()
    # Bend toward the cylinder (+x): a tip goal at the object's near side.
    toward = fwd.images(np.array([0.0, 1.0, 1.0, 0.0, 1.0, 1.0]) * MAX_PA)
    tips = ctx.tips(toward[None])[0]
    planner = Planner(CFG)
    overlap = {}
    for mode in ('touch', 'clear'):
        obj = Objective(ctx, Goal.tip(SPEC, tips, mode))
        plan = planner.plan(obj, fwd, bank)
        m = ctx.masks(fwd.images(plan.pressures_pa)[None])[0]
        overlap[mode] = [int((m[v] & obj.contact_mask.numpy()[v].astype(bool)).sum())
                         for v in range(2)]
    assert min(overlap['touch']) > 0                 # touching: on the object in both views
    assert min(overlap['clear']) == 0                # clear: apart in at least one view


def test_bad_goals_are_refused_with_the_reason(rod):
    _, ctx, _ = rod
    good = ctx.initial
    cases = [
        (lambda: Goal.images(SPEC, good[:1]), r'must be \(2, 1, 64, 64\)'),
        (lambda: Goal.images(SPEC, good.astype(np.float32)), 'uint8'),
        (lambda: Goal.images(SPEC, good, contact='hug'), 'contact must be one of'),
        (lambda: Goal.silhouette(SPEC, np.zeros((2, 64, 64), bool)), 'empty'),
        (lambda: Goal.silhouette(SPEC, np.ones((2, 32, 32), bool)), 'must be'),
        (lambda: Goal.silhouette(SPEC, np.ones((2, 64, 64), np.float32)), 'bool or uint8'),
        (lambda: Goal.tip(SPEC, [[10, np.nan], [10, 10]]), 'finite'),
        (lambda: Goal.tip(SPEC, [[10, 10]]), 'must be'),
        (lambda: Goal.tip(SPEC, [[10, 70], [10, 10]]), 'lie in the 64x64'),
        (lambda: Goal.tip(SPEC, 'here'), 'numbers'),
        (lambda: camera_to_model_px(float('inf'), 3, [80, 0, 480, 480], 64), 'finite'),
        (lambda: camera_to_model_px(10, 3, [80, 0, 480, 480], 64), 'outside the camera crop'),
    ]
    for make, why in cases:
        with pytest.raises(GoalError, match=why):
            make()
    # A touch goal in a scene without an object.
    bare = np.stack([render(centreline(np.zeros(6)), None, v) for v in VIEWS])
    bare_ctx = SceneContext.from_initial(bare)
    with pytest.raises(GoalError, match='no object to touch'):
        Objective(bare_ctx, Goal.tip(SPEC, [[40, 32], [40, 32]], 'touch'))


def test_camera_and_network_pixels_round_trip():
    crop = [80, 0, 480, 480]
    for u, v in ((100.0, 20.0), (320.0, 240.0), (540.0, 460.0)):
        r, c = camera_to_model_px(u, v, crop, 64)
        assert 0 <= r <= 63 and 0 <= c <= 63
        np.testing.assert_allclose(model_to_camera_px(r, c, crop, 64), (u, v))
    assert camera_to_model_px(80.0, 0.0, crop, 64) == (0.0, 0.0)      # the corner pixel


def test_tip_goal_json_and_camera_frames(trained_checkpoint):
    from softshape_ros.config import load_rig_config
    from softshape_ros.control import Controller
    from softshape_ros.model import Predictor
    cfg = load_rig_config()
    ctl = Controller(Predictor.from_checkpoint(trained_checkpoint), cfg,
                     planner=PlannerConfig(bank_size=32))
    g = ctl.goal_from_tip_json(json.dumps({'tips_px': {'main': [320, 400], 'side': [300, 380]},
                                           'contact': 'clear'}))
    assert g.kind == 'tip' and g.contact == 'clear'
    np.testing.assert_allclose(g.target_tip_rc[0], camera_to_model_px(320, 400, [80, 0, 480,
                                                                                 480], 64))
    g = ctl.goal_from_tip_json('{"tips_px": {"main": [30, 50], "side": [31, 52]}, '
                               '"frame": "model"}')
    np.testing.assert_allclose(g.target_tip_rc, [[50, 30], [52, 31]])
    for text, why in (('nope', 'not JSON'), ('{"tips": {}}', 'needs'),
                      ('{"tips_px": {"main": [320, 400]}}', "'side'"),
                      ('{"tips_px": {"main": [320, 400], "side": [320, 400]}, "x": 1}',
                       'unknown key'),
                      ('{"tips_px": {"main": [320, 400], "side": [320, 400]}, "frame": "x"}',
                       'frame must be'),
                      ('{"tips_px": {"main": [NaN, 400], "side": [320, 400]}}', 'finite')):
        with pytest.raises(GoalError, match=why):
            ctl.goal_from_tip_json(text)
    frame = np.full((480, 640, 3), 200, np.uint8)
    with pytest.raises(GoalError, match="view 'side'"):
        ctl.goal_from_images({'main': frame})
    with pytest.raises(GoalError, match='unusable'):
        ctl.goal_from_images({'main': frame, 'side': frame[..., :2]})
    with pytest.raises(ValueError, match='may only lower'):
        Controller(ctl.predictor, cfg, limits_pa=[2e5] * 6)
    with pytest.raises(ValueError, match='beyond the limits'):
        ctl.check([2e5] + [0.0] * 5)
    with pytest.raises(ValueError, match='non-finite'):
        ctl.check([np.nan] + [0.0] * 5)


def test_control_eval_refuses_bad_arguments(capsys, tmp_path):
    from softshape_ros.cli import main
    for args, why in ((['--goals', '0'], '--goals must be >= 1'),
                      (['--methods', 'model,magic'], '--methods: choose from'),
                      (['--methods', 'random'], 'random search takes its budget')):
        code = main(['control-eval', '--model', str(tmp_path / 'none'), '--out',
                     str(tmp_path / 'out')] + args)
        assert code == 2 and why in capsys.readouterr().err
