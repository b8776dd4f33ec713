"""The placement path: reading a placement back (description, fit) and the folded head."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy import ndimage

from softshape_ros.config import load_rig_config
from softshape_ros.data import load_dataset
from softshape_ros.model.data import placements, scene_from_vector, scene_vector, shape_tensors
from softshape_ros.experiments.placement_head import (
    PlacementHeadError, ShapePredictor, ShapeProjection, folded_inputs, read_facing_out,
    train_shape_predictor)
from softshape_ros.scene import Scene
from softshape_ros.sim.generate import generate, make_plan
from softshape_ros.sim.objects import obstacle_from_scene
from softshape_ros.sim.placement_fit import (
    GOOD_MSE, MAX_EVALS, RETYPE_MSE, SCALES, FitError, PlacementFit, flipped, placement_params,
    placement_scene, retyped, turns, twin)
from softshape_ros.sim.symmetry import RigSymmetry

CFG = load_rig_config()
VIEWS = ['main', 'side']


@pytest.fixture(scope='module')
def stereo(tmp_path_factory):
    """320 stereo samples of the default contact-rich distribution over 64 placements."""
    ds, _ = generate(CFG, make_plan(CFG, 320, 64, seed=9), tmp_path_factory.mktemp('p') / 'ds',
                     VIEWS, workers=2, progress=False)
    return load_dataset(ds.path)


def test_a_description_reads_back_as_its_placement_whatever_order_the_sizes_came_in():
    prism = Scene(3, 'prism', (0.02, -0.01, 0.03), (0.0, 0.0, 0.4),
                  {'width_m': 0.012, 'depth_m': 0.009, 'height_m': 0.05, 'skew_rad': 0.2})
    shuffled = replace(prism, dims=dict(reversed(list(prism.dims.items()))))
    assert scene_vector(shuffled) == scene_vector(prism)
    back = scene_from_vector(scene_vector(prism), 3)
    assert back.object == 'prism' and back.dims == pytest.approx(prism.dims)
    assert back.position_m == pytest.approx(prism.position_m)
    assert back.rpy_rad[2] == pytest.approx(0.4)
    # Yaw is seen only up to a half turn: a prism turned by pi reads back as its twin.
    turned = scene_from_vector(scene_vector(replace(prism, rpy_rad=(0, 0, 0.4 + math.pi))))
    assert turned.rpy_rad[2] == pytest.approx(0.4)
    assert twin(twin(prism)).dims == pytest.approx(prism.dims)
    # A reader's nonsense sizes come back small but valid.
    vec = scene_vector(prism)
    vec[-4:] = [-3.0, 0.0, 40.0, 1.0]
    assert min(scene_from_vector(vec).dims.values()) > 0


@pytest.mark.parametrize('row', [0, 2])            # a cylinder, a prism
def test_the_fit_reads_a_placement_to_a_fraction_of_a_millimetre(stereo, row):
    scenes = placements(stereo, np.arange(len(stereo)))
    sid = int(np.unique(np.asarray(stereo.scene))[row])
    truth = scenes[sid]
    image = stereo.initial[int(np.nonzero(np.asarray(stereo.scene) == sid)[0][0])]
    fit = PlacementFit(CFG, VIEWS)
    # A reading 1.5 mm off in x and y, 1 mm in z; a prism also described the other way round.
    start = placement_params(truth)
    start[:3] += [1.5, -1.5, 1.0]
    reading = placement_scene(truth, start)
    if truth.object == 'prism':
        reading = twin(reading)
    r = fit.fit(image, reading)
    err = np.abs(np.subtract(r.scene.position_m, truth.position_m)) * 1e3
    assert r.mse < 0.1 and r.mse <= fit.mse(reading, np.asarray(image, np.float32)) / 10
    assert err[:2].max() < 0.2, err            # x, y: the main camera's plane and depth
    # Height: the lower end may leave the frame, trading centre for height; the top is seen.
    top = [sc.position_m[2] + sc.dims['height_m'] / 2 for sc in (r.scene, truth)]
    assert abs(top[0] - top[1]) < 2e-4, (err, top)
    with pytest.raises(FitError, match='sphere'):
        fit.fit(image, Scene(0, 'sphere', truth.position_m, (0, 0, 0), {'radius_m': 0.01}))


def test_the_fit_keeps_objects_upright_and_clear_of_the_robot(stereo):
    scenes = placements(stereo, np.arange(len(stereo)))
    ids = np.asarray(stereo.scene)
    sid = next(int(i) for i in np.unique(ids) if scenes[int(i)].object == 'cylinder')
    truth = scenes[sid]
    image = stereo.initial[int(np.nonzero(ids == sid)[0][0])]
    # A cylinder read tilted by a few hundredths of a radian is fitted standing on its end,
    # with two numbers fewer to move.
    tilted = replace(truth, rpy_rad=(0.03, -0.02, 0.0))
    assert len(placement_params(tilted, upright=True)) == len(placement_params(tilted)) - 2
    fit = PlacementFit(CFG, VIEWS)
    r = fit.fit(image, tilted)
    assert r.scene.rpy_rad[:2] == (0.0, 0.0)
    assert r.mse < 0.1
    # The clearance is the least distance to the robot's surface at rest; a fit asked to
    # keep more than the images show keeps it (the images alone would put it back).
    c = fit.clearance(truth)
    assert 0.0 < c < 0.012
    inside = replace(truth, position_m=tuple(np.asarray(truth.position_m) * 0.2))
    assert fit.clearance(inside) < 0
    far = PlacementFit(CFG, VIEWS, min_clearance_m=c + 0.004, max_starts=2)
    held = far.fit(image, truth)
    assert far.clearance(held.scene) > c + 0.004 - 3e-4
    assert held.mse > r.mse > 0
    assert held.scene.object == 'cylinder'   # held by the wall, not taken for another kind
    assert not far.misread(image, held.scene, held.mse)


def test_a_prism_fit_stalled_in_one_description_is_tried_in_the_others():
    """
    A poor prism match restarts from the fitted position in the prism's other descriptions.

    The stalled fit is one the placement study got for a test placement: yaw a whole turn
    round, centre 1.8 mm low and the prism 3.6 mm taller (its lower end near the frame's
    edge). Runs from there stay there; a quarter or half turn, lean flipped, gets out.
    """
    truth = Scene(116, 'prism', (-0.025524, -0.016242, 0.017324), (0.0, 0.0, 3.708307),
                  {'width_m': 0.013120, 'depth_m': 0.011715, 'height_m': 0.038255,
                   'skew_rad': 0.191056})
    stalled = Scene(116, 'prism', (-0.025224, -0.016048, 0.015481), (0.0, 0.0, -2.574942),
                    {'width_m': 0.013132, 'depth_m': 0.011681, 'height_m': 0.041818,
                     'skew_rad': 0.190950})
    fit = PlacementFit(CFG, VIEWS)
    image = np.round(fit.render(truth))             # gray levels, as a dataset holds them
    cost = fit.objective(image, stalled)
    x = placement_params(stalled, upright=True)
    _, f_plain = fit._run(cost, x, SCALES[0], MAX_EVALS)
    assert f_plain > 1.0                            # a plain run stays in the valley
    y, f = fit._redescribed(cost, stalled, x, cost(x))
    assert f < GOOD_MSE
    found = placement_scene(stalled, y, upright=True)
    top = [sc.position_m[2] + sc.dims['height_m'] / 2 for sc in (found, truth)]
    assert np.abs(np.subtract(found.position_m[:2], truth.position_m[:2])).max() < 3e-4
    assert abs(top[0] - top[1]) < 3e-4


def test_a_cylinder_read_as_a_prism_is_fitted_as_a_cylinder():
    """
    A match too poor for any description of the read kind is tried as the other kinds.

    The stalled fit is the placement study's for a test cylinder its reader took for a
    prism: a thin prism at the cylinder's place, 5.9 gray levels squared off.
    """
    truth = Scene(339, 'cylinder', (-0.008846, -0.026277, 0.034089), (0.0, 0.0, 0.0),
                  {'radius_m': 0.005464, 'height_m': 0.046240})
    stalled = Scene(339, 'prism', (-0.008888, -0.026336, 0.034049), (0.0, 0.0, 1.964043),
                    {'width_m': 0.004630, 'depth_m': 0.009898, 'height_m': 0.046991,
                     'skew_rad': 0.002291})
    fit = PlacementFit(CFG, VIEWS)
    image = np.round(fit.render(truth))
    x = placement_params(stalled, upright=True)
    f_stalled = fit.objective(image, stalled)(x)
    assert f_stalled > RETYPE_MSE
    evals = [0]
    kind, y, f, starts = fit._retyped(image, stalled, x, f_stalled, np.random.default_rng(0),
                                      evals)
    found = placement_scene(kind, y, upright=True)
    assert found.object == 'cylinder' and f < GOOD_MSE and starts >= 2 and evals[0] > 0
    assert fit.misread(image, stalled, f_stalled)
    # A match poor everywhere alike (frames resampled otherwise than the fit renders) is
    # not a misread: the truth, blurred a little, 29 gray levels squared off.
    soft = ndimage.gaussian_filter(fit.render(truth), (0, 0.6, 0.6))
    assert fit.mse(truth, soft) > 10 * RETYPE_MSE and not fit.misread(
        soft, truth, fit.mse(truth, soft))
    assert np.abs(np.subtract(found.position_m, truth.position_m)).max() < 3e-4
    assert abs(found.dims['radius_m'] - truth.dims['radius_m']) < 3e-4
    # Each kind as another of its extent, at its place; turned where turning shows.
    for a in (truth, stalled, retyped(truth, 'ring')):
        for b in ('cylinder', 'ring', 'prism'):
            other = retyped(a, b)
            assert other.object == b and other.position_m == a.position_m
            assert obstacle_from_scene(other) is not None        # a body, not a SceneError
            assert len(turns(other)) == (1 if b == 'cylinder' else 4)
    assert retyped(truth, 'prism').dims['height_m'] == truth.dims['height_m']
    assert [round(t.rpy_rad[2], 6) for t in turns(stalled)] == [
        round(math.remainder(1.964043 + k * math.pi / 8, 2 * math.pi), 6) for k in range(4)]


def test_a_prism_and_its_twin_are_one_input_to_the_head():
    sym = RigSymmetry.from_config(CFG)
    az = 0.7
    prism = Scene(3, 'prism', (0.03 * math.cos(az), 0.03 * math.sin(az), 0.03), (0.0, 0.0, az),
                  {'width_m': 0.012, 'depth_m': 0.009, 'height_m': 0.05, 'skew_rad': 0.2})
    p = [[1e4, 0, 0, 2e4, 0, 0]] * 3
    x, _ = folded_inputs(sym, [prism, twin(prism), flipped(prism)], p, [5e4] * 6)
    torch.testing.assert_close(x[1], x[0])
    assert not torch.allclose(x[2], x[0])        # leaning the other way: another object
    # A reader gives yaw up to a half turn, its lean meant facing out: turned, lean kept.
    read = replace(prism, rpy_rad=(0.0, 0.0, az - math.pi))
    assert read_facing_out(read, sym).rpy_rad[2] == pytest.approx(az)
    assert read_facing_out(read, sym).dims == prism.dims
    assert read_facing_out(prism, sym) is prism


def test_the_projection_goes_from_the_record_to_the_backbone_and_back(stereo):
    record, _ = shape_tensors(stereo, np.arange(len(stereo)))
    proj = ShapeProjection(CFG, VIEWS, 64)
    pts, radius = proj.backbone(record.numpy())
    assert np.ptp(radius) < 1e-5                                  # one tube radius
    back = proj.record(pts, radius.mean(0))
    np.testing.assert_allclose(back[..., :2], record[..., :2], atol=1e-3)   # px
    np.testing.assert_allclose(back[..., 2:], record[..., 2:], atol=2e-3)
    # The side view comes from the main view's points: the 3D backbone is right.
    assert float(np.abs(back[:, 1] - record.numpy()[:, 1]).max()) < 2e-3


@pytest.fixture(scope='module')
def head48(stereo):
    """Learn a placement head from the first 48 of the 64 placements (500 steps)."""
    ids = np.asarray(stereo.scene)
    seen = np.isin(ids, np.unique(ids)[:48])
    head, report = train_shape_predictor(stereo, CFG, VIEWS, steps=500, batch=128,
                                         rows=np.nonzero(seen)[0], progress=False)
    return head, report, seen


def test_the_head_learns_in_the_fold_and_turns_with_the_rig(stereo, head48, tmp_path):
    scenes = placements(stereo, np.arange(len(stereo)))
    ids = np.asarray(stereo.scene)
    head, report, seen = head48
    # Learnt from 48 placements, asked about the 16 others.
    assert report.placements == 48 and report.rows == int(seen.sum())
    record, _ = shape_tensors(stereo, np.arange(len(stereo)))
    kp = head.keypoints([scenes[int(i)] for i in ids], stereo.pressure[:])
    err = (kp[..., :2] - record[..., :2]).norm(dim=-1)[~seen]          # N x V x K px
    still = (record[..., :2] - record[seen][..., :2].mean(0)).norm(dim=-1)[~seen]
    assert float(err.mean()) < 0.4 * float(still.mean()), (float(err.mean()), float(still.mean()))
    # Folded inputs: a placement turned and mirrored with its pressures is the same input,
    # and the head's robot turns with it.
    sym = RigSymmetry.from_config(CFG)
    sc, p = scenes[int(ids[0])], np.asarray(stereo.pressure[0], dtype=float)
    proj = head.projection
    base = proj.backbone(head.keypoints([sc], [p]).numpy() - head.offset_px)[0]
    for steps, mirrored in ((1, False), (2, True)):
        f = sym.element(steps, mirrored)
        x0, _ = folded_inputs(sym, [sc], [p], head.max_pressure_pa)
        x1, _ = folded_inputs(sym, [f.scene(sc)], [f.pressures(p)], head.max_pressure_pa)
        torch.testing.assert_close(x0, x1, atol=1e-4, rtol=0)
        turned = proj.backbone(head.keypoints([f.scene(sc)], [f.pressures(p)]).numpy()
                               - head.offset_px)[0]
        np.testing.assert_allclose(turned[0], f.points(base[0]), atol=2e-5)      # metres
    # Saved and loaded, it predicts the same; another camera, or bad weights, are refused.
    saved = head.save(tmp_path / 'head')
    again = ShapePredictor.load(saved, CFG)
    torch.testing.assert_close(again.keypoints([sc], [p]), head.keypoints([sc], [p]))
    # It knows how far out it learned: each kind's farthest training placement.
    fit = PlacementFit(CFG, VIEWS)
    for kind in ('cylinder', 'ring'):       # gaps up to 10 mm, their clearance
        learnt = max(fit.clearance(scenes[int(i)]) for i in np.unique(ids[seen])
                     if scenes[int(i)].object == kind)
        assert again.reach_m[kind] == pytest.approx(learnt) and 0.005 < learnt < 0.0101
    assert set(again.reach_m) == {'cylinder', 'ring', 'prism'}
    moved = replace(CFG, cameras=dict(CFG.cameras, side=replace(CFG.cameras['side'], fx=1300.0)))
    with pytest.raises(PlacementHeadError, match="camera 'side'"):
        ShapePredictor.load(saved, moved)
    (saved / 'head.safetensors').write_bytes(b'not weights')
    with pytest.raises(PlacementHeadError, match='cannot read'):
        ShapePredictor.load(saved, CFG)
    meta = json.loads((saved / 'head.json').read_text())
    assert meta['format'] == 'softshape-placement-head' and meta['views'] == VIEWS
    saved = head.save(tmp_path / 'head2')
    del meta['cameras']
    (saved / 'head.json').write_text(json.dumps(meta))
    with pytest.raises(PlacementHeadError, match='incomplete or malformed'):
        ShapePredictor.load(saved, CFG)


def test_a_dataset_without_placements_cannot_teach_the_head(stereo):
    class Bare:                              # a dataset built from bags without a session
        meta, scene, shape, pressure = {}, stereo.scene, None, stereo.pressure

        def __len__(self):
            return len(stereo)
    bare = Bare()
    with pytest.raises(PlacementHeadError, match='placements and the shape record'):
        train_shape_predictor(bare, CFG, VIEWS, steps=1, progress=False)


def test_the_fit_renders_what_the_simulator_draws(stereo):
    # The fit's own rendering of the true rest scene matches the dataset's rest images to
    # rounding (mean squared error of a uniform +-0.5 rounding is 1/12).
    fit = PlacementFit(CFG, VIEWS)
    scenes = placements(stereo, np.arange(len(stereo)))
    for row in (0, 5):
        sid = int(stereo.scene[row])
        image = np.asarray(stereo.initial[row], np.float32)
        assert fit.mse(scenes[sid], image) < 0.1
        moved = replace(scenes[sid], position_m=tuple(np.add(scenes[sid].position_m,
                                                             [0.001, 0, 0])))
        assert fit.mse(moved, image) > 1.0
    with pytest.raises(ValueError, match='rest images must be'):
        fit.mse(scenes[0], np.zeros((1, 64, 64)))


def test_the_placement_predictor_fits_once_per_scene_and_draws_the_heads_robot(
        stereo, head48, monkeypatch):
    from softshape_ros.demo.pipeline import PRETRAINED
    from softshape_ros.model.checkpoint import load_checkpoint
    from softshape_ros.model.metrics import RobotSilhouette, evaluate_arrays
    from softshape_ros.experiments.placement_predictor import PlacementPredictor
    head, _, seen = head48
    model, config = load_checkpoint(PRETRAINED)
    pred = PlacementPredictor(model, config, head, CFG)
    fits = []
    real_fit = pred.fit.fit
    monkeypatch.setattr(pred.fit, 'fit', lambda *a, **k: fits.append(1) or real_fit(*a, **k))
    ids = np.asarray(stereo.scene)
    rows = np.nonzero(ids == np.unique(ids[~seen])[0])[0]          # an unseen placement
    truth = placements(stereo, rows)[int(ids[rows[0]])]
    initial = np.asarray(stereo.initial[rows])
    out = pred.predict_batch(initial, np.asarray(stereo.pressure[rows]))
    assert out.shape == initial.shape and out.dtype == np.uint8 and len(fits) == 1
    scene = pred.placement(initial[0])
    assert len(fits) == 1                                           # cached per rest images
    assert scene.object == truth.object
    assert np.abs(np.subtract(scene.position_m, truth.position_m))[:2].max() < 5e-4
    if 'height_m' in truth.dims:        # the lower end may leave the frame: its top is seen
        top = [sc.position_m[2] + sc.dims['height_m'] / 2 for sc in (scene, truth)]
        assert abs(top[0] - top[1]) < 5e-4
    r = evaluate_arrays(initial, np.asarray(stereo.target[rows]), out,
                        RobotSilhouette.fit(np.asarray(stereo.initial)))
    print('placement predictor', r['model']['silhouette_iou'], r['copy']['silhouette_iou'])
    assert r['model']['silhouette_iou'] > max(0.9, r['copy']['silhouette_iou'])
    one = pred.predict(initial[0], stereo.pressure[rows[0]])
    np.testing.assert_array_equal(one, out[0])
    mono = ShapePredictor.build(CFG, ['main'], 64, head.radius_m, head.offset_px[:1],
                                head.max_pressure_pa)
    with pytest.raises(PlacementHeadError, match="views \\['main'\\]"):
        PlacementPredictor(model, config, mono, CFG)


def behind_robot(fit: PlacementFit, view: str, turn: float = 0.0) -> Scene:
    """Stand a cylinder 2 mm behind the rest robot as ``view`` sees it (``turn``: about it)."""
    axis = fit.rest.backbone_m[0, :2]                   # the rest robot hangs straight
    u = axis - fit.rig.cameras[view].position[:2]
    u = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]]) @ (
        u / np.linalg.norm(u))
    radius = 0.006
    xy = axis + (fit.rest.radii_m.max() + 0.002 + radius) * u
    return Scene(id=1, object='cylinder', position_m=(*xy, 0.035),
                 dims={'radius_m': radius, 'height_m': 0.04})


def test_an_object_behind_the_robot_is_hidden_and_its_depth_is_not_in_the_images():
    fit = PlacementFit(CFG, VIEWS)
    hidden = behind_robot(fit, 'side')
    assert fit.hidden_views(hidden) == ('side',)
    assert fit.hidden_views(behind_robot(fit, 'main')) == ('main',)
    assert fit.hidden_views(behind_robot(fit, 'side', turn=math.pi / 2)) == ()
    # Slid 3 mm along the main camera's ray, grown as it recedes: the same rest images.
    cam = fit.rig.cameras['main'].position
    p = np.asarray(hidden.position_m)
    k = 1 + 0.003 / np.linalg.norm(p - cam)
    slid = replace(hidden, position_m=tuple(cam + (p - cam) * k),
                   dims={n: v * k for n, v in hidden.dims.items()})
    rest = fit.render(hidden)
    assert fit.hidden_views(slid) == ('side',) and fit.mse(slid, rest) < 0.1
    across = replace(hidden, position_m=tuple(p + [0.003, 0.0, 0.0]))
    assert fit.mse(across, rest) > 1.0                  # where a view sees it, it is held


def test_the_placement_predictor_draws_the_tube_models_own_bet_where_the_head_cannot_know(
        head48):
    from softshape_ros.demo.pipeline import PRETRAINED
    from softshape_ros.model.checkpoint import load_checkpoint
    from softshape_ros.model.predictor import Predictor
    from softshape_ros.experiments.placement_predictor import PlacementPredictor
    model, config = load_checkpoint(PRETRAINED)
    pred = PlacementPredictor(model, config, head48[0], CFG)
    scene = behind_robot(pred.fit, 'side')
    rest = np.clip(np.rint(pred.fit.render(scene)), 0, 255).astype(np.uint8)[:, None]
    initial = np.stack([rest, rest])
    pressures = [[0.0, 90e3, 0.0, 0.0, 90e3, 0.0], [60e3, 0.0, 0.0, 30e3, 0.0, 0.0]]
    out = pred.predict_batch(initial, pressures)
    assert pred.alone == 'hidden in side'               # the fit found it behind the robot
    alone = Predictor(model, config).predict_batch(initial, pressures)
    np.testing.assert_array_equal(out, alone)
    pred.know(scene)                                    # told where it is: the head draws
    told = pred.predict_batch(initial, pressures)
    assert pred.alone == '' and not np.array_equal(told, out)
    # Farther out than any placement it learned from, the head is not asked either.
    pred.shape = replace(pred.shape, reach_m={'cylinder': 0.0015})
    np.testing.assert_array_equal(pred.predict_batch(initial, pressures), alone)
    assert pred.alone == "2.0 mm clear, beyond the head's 1.5 mm"


def test_the_placement_head_command_trains_fits_and_scores_five_ways(stereo, tmp_path):
    from softshape_ros.cli import main
    from softshape_ros.demo.pipeline import PRETRAINED
    out = tmp_path / 'study'
    assert main(['placement-head', '--train', str(stereo.path), '--test', str(stereo.path),
                 '--checkpoint', str(PRETRAINED), '--out', str(out), '--steps', '20',
                 '--workers', '1', '--limit', '1', '--quiet']) == 0
    res = json.loads((out / 'placement_head.json').read_text())
    assert res['test_placements'] == 1 and res['head']['steps'] == 20
    assert set(res['predictions']) == {'tube model alone', 'head, true placement',
                                       'head, read placement (unfitted)',
                                       'head, fitted placement', 'placement path'}
    for row in res['predictions'].values():
        iou = row['iou_all_touching_free']
        assert all(0.0 <= v <= 1.0 for v in iou if v == v)            # NaN: no such rows
    fits = json.loads((out / 'fitted_placements.json').read_text())
    (fit,) = fits.values()
    assert fit['fitted']['object'] == fit['truth']['object']
    # The placement path is the fitted row where the object shows in both views.
    assert fit['hidden'] == [] and res['fit']['hidden_placements'] == 0
    assert res['fit']['tube_model_alone_placements'] == 0
    assert res['predictions']['placement path'] == res['predictions']['head, fitted placement']
    assert ShapePredictor.load(out / 'head', CFG).head.keypoints == 16
    # Again from the saved head: nothing trained, the same fit.
    again = tmp_path / 'again'
    assert main(['placement-head', '--train', 'unused', '--test', str(stereo.path),
                 '--checkpoint', str(PRETRAINED), '--out', str(again), '--head',
                 str(out / 'head'), '--workers', '1', '--limit', '1', '--quiet']) == 0
    assert json.loads((again / 'placement_head.json').read_text())['head'] == {
        'loaded': str(out / 'head')}
    assert json.loads((again / 'fitted_placements.json').read_text()) == fits
