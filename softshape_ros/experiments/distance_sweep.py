"""
The paper's Fig. 4(c) as a standing evaluation: one actuation, a cylinder moved away.

The simulator gives the truth: at each distance whether the robot touches the cylinder and
how far its tip is pushed from where the free robot would put it (px, main view). The model
sees only the initial image change with the distance, so a model that learned contact
tracks the push; one that did not draws the free shape through the cylinder every time.
One actuation is a thin check, so the same contact is also run turned about the robot
(:func:`setups`) and scored in every view.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from softshape_ros.config import load_rig_config
from softshape_ros.model.evaluate import prediction_panels
from softshape_ros.model.metrics import RobotSilhouette, intrusion, iou, rmse
from softshape_ros.model.predictor import Predictor
from softshape_ros.scene import Scene

DISTANCES_M = (0.020, 0.023, 0.026, 0.030, 0.036)
CYLINDER = {'radius_m': 0.006, 'height_m': 0.05}
SHIFT_TOLERANCE_PX = 1.5        # issue 18: predicted push within 1.5 px of the simulated one
SUPERSAMPLE = 4                 # the sweep's images: 4x4 samples a pixel (render_inputs')


@dataclass(frozen=True)
class SweepRow:
    """One distance: the simulated push, the predicted one and how the prediction scores."""

    distance_m: float
    touching: bool
    tip_shift_px_simulated: float
    tip_shift_px_predicted: float
    shift_error_px: float
    rmse: float
    silhouette_iou: float
    intrusion: float


@dataclass(frozen=True)
class Setup:
    """One bend and where the cylinder stands from it (bearings about the robot's axis, deg)."""

    bend_deg: float                 # the free tip's bearing under ``actuation``
    cylinder_deg: float             # the line the cylinder is moved along
    actuation: np.ndarray           # 6 pressures (Pa)


@dataclass(frozen=True)
class SetupRow:
    """One distance of one :class:`Setup`: the pushes per view (px; None: no tip seen)."""

    distance_m: float
    touching: bool
    shift_px_simulated: list
    shift_px_predicted: list
    shift_error_px: float | None    # the worst view's; None if a view lost the tip


def _images(rig, state, pred, supersample) -> np.ndarray:
    r = rig.render_inputs(state, size=pred.image_size, gray=pred.channels == 1,
                          supersample=supersample, cameras=pred.views)
    return np.stack([r[v] for v in pred.views])


def _bend(rig, lim, pairs) -> tuple[np.ndarray, float]:
    """Return the chamber ``pairs`` at 80 % and the bearing (deg) of the free tip they give."""
    p = np.zeros(6)
    for k in pairs:
        p[k], p[k + 3] = 0.8 * lim[k], 0.8 * lim[k + 3]
    rig.set_scene(None)
    tip = rig.solve(p).tip_pose[:3, 3]
    return p, float(np.degrees(np.arctan2(tip[1], tip[0])))


def setups(rig, lim) -> list[Setup]:
    """
    Return Fig. 4(c)'s setup first, then the same geometry turned about the robot's axis.

    Fig. 4(c): the chamber pair whose free tip swings furthest towards +x, the cylinder moved
    along +x (30 deg beside the bend). The rest: each of the six bends (one chamber pair, or
    two, at 80 %: bearings 60 deg apart) with the cylinder 30 deg to either side of it. The
    robot is symmetric, so every setup is the same contact seen from another angle: the
    simulated push is the same, only the cameras see it differently.
    """
    bends = [_bend(rig, lim, pairs) for pairs in ((0,), (1,), (2,), (0, 1), (1, 2), (2, 0))]
    main = max(bends[:3], key=lambda b: np.cos(np.radians(b[1])))
    out = [Setup(main[1], 0.0, main[0])]
    for p, deg in bends:
        for side in (-30.0, 30.0):
            cyl = (deg + side + 180.0) % 360.0 - 180.0
            if not (p is main[0] and abs(cyl) < 1e-6):
                out.append(Setup(deg, round(cyl, 6), p))
    return out


class SweepImages(NamedTuple):
    """One setup's images, a row per distance (N x V x C x S x S), and the simulator's contact."""

    initial: np.ndarray
    target: np.ndarray
    predicted: np.ndarray
    free: np.ndarray                # the free robot under the same actuation, repeated
    touching: list


def _sweep(rig, pred, setup: Setup, distances, supersample) -> SweepImages:
    """Simulate and predict one setup at every distance."""
    rig.set_scene(None)
    free = _images(rig, rig.solve(setup.actuation), pred, supersample)
    initial, target, touching = [], [], []
    c, s = np.cos(np.radians(setup.cylinder_deg)), np.sin(np.radians(setup.cylinder_deg))
    for i, d in enumerate(distances):
        rig.set_scene(Scene(id=1000 + i, object='cylinder',
                            position_m=(round(d * c, 9), round(d * s, 9), 0.02),
                            dims=dict(CYLINDER)))
        initial.append(_images(rig, rig.solve(np.zeros(6)), pred, supersample))
        st = rig.solve(setup.actuation)
        target.append(_images(rig, st, pred, supersample))
        touching.append(any(k.gap_m < 0 and not k.ridge for k in st.contacts))
    initial, target = np.stack(initial), np.stack(target)
    predicted = pred.predict_batch(initial, [setup.actuation] * len(distances))
    return SweepImages(initial, target, predicted, np.repeat(free[None], len(target), 0),
                       touching)


def _shifts(sil, target, predicted, free) -> tuple[np.ndarray, np.ndarray]:
    """N x V tip pushes from the free shape's tip (px), simulated and predicted (NaN: none)."""
    t, p, f = sil.tips(target), sil.tips(predicted), sil.tips(free)
    return np.linalg.norm(t - f, axis=-1), np.linalg.norm(p - f, axis=-1)


def _px(v) -> float | None:
    return None if not np.isfinite(v) else round(float(v), 3)


def distance_sweep(checkpoint, path=None, distances=DISTANCES_M,
                   supersample: int = SUPERSAMPLE, turned: bool = True,
                   placement_head=None) -> dict:
    """
    Run the sweep for ``checkpoint``; draw the panels to ``path`` (PNG) if given.

    ``supersample``: how the images are rendered (``SimRig.render_inputs``; 0: the camera's
    own pixels). A model should not care; one that learned a rendering's edges does.
    ``turned``: also run the same contact turned about the robot (:func:`setups`; one
    actuation is a thin check: a model's answer there swings by a pixel or two between
    recipes), with a second figure beside ``path`` (``*_turned.png``).
    ``placement_head``: predict by the placement path instead (the checkpoint draws what the
    head predicts for each rest image's fitted placement; ``experiments/placement_predictor``).

    Returns the actuation, one :class:`SweepRow` per distance (as dicts) and the worst
    shift error over the distances (Fig. 4(c), main view); with ``turned`` also
    ``turned``: every setup's :class:`SetupRow` per distance (every view), and per distance
    the mean and worst shift error over setups and views and the share within tolerance.
    """
    from softshape_ros.sim.rig import SimRig

    cfg = load_rig_config()
    if placement_head is None:
        pred = Predictor.from_checkpoint(checkpoint)
    else:
        from softshape_ros.experiments.placement_predictor import PlacementPredictor
        pred = PlacementPredictor.from_paths(checkpoint, placement_head, cfg)
    rig = SimRig(cfg)
    lim = np.asarray(pred.max_pressure_pa)
    plan = setups(rig, lim)[:None if turned else 1]
    runs = [_sweep(rig, pred, s, distances, supersample) for s in plan]
    initial, target, predicted, free, touching = runs[0]
    sil = RobotSilhouette.fit(initial)
    sim, got = (a[:, 0] for a in _shifts(sil, target, predicted, free))
    objects = sil.object_mask(initial)
    rows = []
    for i, d in enumerate(distances):
        p_sil, t_sil = sil.mask(predicted[i:i + 1]), sil.mask(target[i:i + 1])
        rows.append(SweepRow(d, bool(touching[i]), float(sim[i]), float(got[i]),
                             abs(float(got[i] - sim[i])), rmse(predicted[i], target[i]),
                             iou(p_sil, t_sil), intrusion(p_sil, t_sil, objects[i:i + 1])))
    act = plan[0].actuation
    if path is not None:
        prediction_panels(initial, target, predicted, pred.views, path,
                          title=f'same actuation {np.round(act / 1000).astype(int).tolist()} '
                                'kPa, cylinder moved away (simulator vs model)',
                          row_labels=[f'x = {r.distance_m * 1000:.0f} mm, sim push '
                                      f'{r.tip_shift_px_simulated:.0f} px, model '
                                      f'{r.tip_shift_px_predicted:.0f}' for r in rows])
    worst = max(r.shift_error_px for r in rows)
    res = {'checkpoint': str(checkpoint), 'supersample': supersample,
           'placement_head': None if placement_head is None else str(placement_head),
           'actuation_pa': act.tolist(),
           'rows': [asdict(r) for r in rows], 'worst_shift_error_px': worst,
           'within_tolerance': bool(worst <= SHIFT_TOLERANCE_PX),
           'tolerance_px': SHIFT_TOLERANCE_PX,
           'figure': None if path is None else str(path)}
    if turned:
        res['turned'] = _turned(plan, runs, distances, pred.views, path)
    return res


def _turned(plan, runs, distances, views, path) -> dict:
    """Score every setup (each with its own segmentation, as Fig. 4(c)'s); summarise."""
    out, errors, pushes = [], [], []         # errors: setups x distances x views
    for setup, run in zip(plan, runs):
        sim, got = _shifts(RobotSilhouette.fit(run.initial), run.target, run.predicted,
                           run.free)
        touching = run.touching
        pushes.append((sim, got))
        err = np.abs(got - sim)              # N x V; NaN where a tip was not found
        errors.append(err)
        out.append({'bend_deg': round(setup.bend_deg, 3),
                    'cylinder_deg': round(setup.cylinder_deg, 3),
                    'actuation_pa': setup.actuation.tolist(),
                    'rows': [asdict(SetupRow(d, bool(touching[i]),
                                             [_px(v) for v in sim[i]],
                                             [_px(v) for v in got[i]],
                                             _px(np.max(err[i]))))
                             for i, d in enumerate(distances)]})
    err = np.stack(errors)                   # setups x distances x views
    ok = np.isfinite(err) & (err <= SHIFT_TOLERANCE_PX)
    touch = np.array([[r['touching'] for r in s['rows']] for s in out])
    per = [{'distance_m': d, 'touching_share': float(touch[:, i].mean()),
            'mean_shift_error_px': _px(np.nanmean(err[:, i])),
            'worst_shift_error_px': _px(np.nanmax(err[:, i])),
            'within_tolerance_share': round(float(ok[:, i].mean()), 4),
            'tips_missing': int((~np.isfinite(err[:, i])).sum())}
           for i, d in enumerate(distances)]
    figure = None
    if path is not None:
        figure = Path(path).with_name(Path(path).stem + '_turned.png')
        _turned_figure(pushes, distances, views, figure)
    return {'setups': out, 'per_distance': per,
            'mean_shift_error_px': _px(np.nanmean(err)),
            'within_tolerance_share': round(float(ok.mean()), 4),
            'figure': None if figure is None else str(figure)}


def _turned_figure(pushes, distances, views, path) -> None:
    """Predicted against simulated push, a point per setup and view, coloured by distance."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(views), figsize=(4.2 * len(views), 4), squeeze=False)
    colours = plt.cm.viridis(np.linspace(0, 0.9, len(distances)))
    sims = pushes
    top = max(2.0, np.nanmax([np.nanmax(np.r_[s, g]) for s, g in sims]) + 1)
    for j, view in enumerate(views):
        ax = axes[0, j]
        ax.fill_between([0, top], [-SHIFT_TOLERANCE_PX, top - SHIFT_TOLERANCE_PX],
                        [SHIFT_TOLERANCE_PX, top + SHIFT_TOLERANCE_PX], color='0.9',
                        label=f'within {SHIFT_TOLERANCE_PX} px')
        ax.plot([0, top], [0, top], color='0.5', lw=0.8)
        for i, d in enumerate(distances):
            ax.scatter([s[i, j] for s, _ in sims], [g[i, j] for _, g in sims], s=14,
                       color=colours[i], label=f'{d * 1000:.0f} mm')
        ax.set_xlim(0, top)
        ax.set_ylim(0, top)
        ax.set_xlabel('simulated tip push (px)')
        ax.set_ylabel('predicted tip push (px)')
        ax.set_title(f'{view} view', fontsize=9)
        ax.legend(fontsize=7, loc='upper left')
    fig.suptitle(f'Fig. 4(c) turned about the robot: {len(pushes)} setups '
                 '(bend, cylinder 30 deg beside it)', fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run(checkpoint, out, supersample: int = SUPERSAMPLE, placement_head=None) -> dict:
    """Write ``distance_sweep.json`` and ``distance_sweep.png`` to ``out``; return the result."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    res = distance_sweep(checkpoint, out / 'distance_sweep.png', supersample=supersample,
                         placement_head=placement_head)
    (out / 'distance_sweep.json').write_text(json.dumps(res, indent=2))
    return res
