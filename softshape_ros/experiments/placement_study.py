"""
The placement path, measured: fitted placement + folded placement head, drawn by the tube model.

On the held-out placements of a test dataset: the tube model reads each placement from its
rest images (its scene description), ``sim/placement_fit`` fits it to those images, and
the placement head (trained on the training dataset, ``experiments/placement_head``) predicts
every actuation's keypoints, which the tube model draws. The placement path is that, with
the tube model's own prediction where the fitted object is hidden in a view or beyond the
head's reach (``placement_predictor.alone_because``, as ``PlacementPredictor`` serves it).
Reported beside the tube model's own prediction and the head given the true, the unfitted
read or the fitted placement everywhere: silhouette IoU all / touching / free, the gap,
tip error, intrusion, and how far the placements were read.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from softshape_ros.config import load_rig_config
from softshape_ros.data.dataset import load_dataset
from softshape_ros.model.checkpoint import load_checkpoint
from softshape_ros.model.data import placements, scene_from_vector, to_tensors, touching_flags
from softshape_ros.model.metrics import RobotSilhouette, evaluate_arrays
from softshape_ros.model.predictor import to_uint8
from softshape_ros.experiments.placement_head import (ShapePredictor, drawing_offset,
                                                      read_facing_out, train_shape_predictor)

OFFSET_ROWS = 4000          # training rows the drawing offset is averaged over (free ones)
_FIT = {}


def _init_fit(cfg, views):
    from softshape_ros.sim.placement_fit import PlacementFit
    torch.set_num_threads(1)
    _FIT['fit'] = PlacementFit(cfg, views)


def _fit_one(job):
    sid, image, reading = job
    r = _FIT['fit'].fit(image, reading, seed=sid)
    return sid, r


def _draw(model, ini, p, kp, batch: int = 250) -> np.ndarray:
    with torch.inference_mode():
        out = [model(ini[i:i + batch], p[i:i + batch], truth=None if kp is None else
                     kp[i:i + batch], parts=True) for i in range(0, len(ini), batch)]
    img = torch.cat([o.image if kp is None else o.teacher for o in out])
    return to_uint8(img)


def _errors(read: dict, truth: dict) -> dict:
    kinds = [read[s].object == truth[s].object for s in truth]
    same = [s for s in truth if read[s].object == truth[s].object]
    e = np.array([np.subtract(read[s].position_m, truth[s].position_m) for s in same]) * 1e3
    return {'kind_right': float(np.mean(kinds)),
            'position_mae_mm': np.abs(e).mean(0).round(4).tolist(),
            'position_median_mm': np.median(np.abs(e), 0).round(4).tolist()}


def run(train, test, checkpoint, out, steps: int = 20000, workers: int = 2,
        limit: int | None = None, progress: bool = True, head=None) -> dict:
    """
    Train the head on ``train``, fit and predict ``test``; write ``out``/placement_head.json.

    ``head``: a saved head to use instead of training one (``train`` is then not read).
    Every fitted placement goes to ``out``/fitted_placements.json.
    """
    t_start = time.monotonic()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = load_rig_config(None)
    model, ccfg = load_checkpoint(checkpoint)
    model.eval()
    views, pmax = list(ccfg['views']), ccfg['max_pressure_pa']
    te = load_dataset(test)
    if list(te.meta.get('cameras', views)) != views:
        raise ValueError(f'{test}: views {te.meta.get("cameras")}, the checkpoint {views}')
    if head is None:
        tr = load_dataset(train)
        rows = np.sort(np.random.default_rng(0).permutation(len(tr))[:OFFSET_ROWS])
        offset = drawing_offset(model, tr, rows, pmax)
        head, report = train_shape_predictor(tr, cfg, views, steps=steps, offset_px=offset,
                                             progress=progress)
        head.save(out / 'head')
        trained = {'steps': report.steps, 'train_s': round(report.seconds, 1),
                   'final_l1_mm': report.final_l1_mm, 'rows': report.rows,
                   'placements': report.placements}
    else:
        trained = {'loaded': str(head)}
        head = ShapePredictor.load(head, cfg)

    scenes = np.asarray(te.scene)
    ids = np.unique(scenes)[:limit]
    idx = np.nonzero(np.isin(scenes, ids))[0]
    table = placements(te, idx)
    truth = {int(s): table[int(s)] for s in ids}
    first = {int(s): int(np.nonzero(scenes == s)[0][0]) for s in ids}
    ini1, _, p1 = to_tensors(te, [first[int(s)] for s in ids], pmax)
    with torch.inference_mode():
        described = model(ini1, p1, parts='keypoints')[2]
    read = {int(s): read_facing_out(scene_from_vector(d, int(s)), head.sym)
            for s, d in zip(ids, described.numpy())}
    jobs = [(int(s), np.asarray(te.initial[first[int(s)]]), read[int(s)]) for s in ids]
    t0 = time.monotonic()
    fitted = {}
    ctx = mp.get_context('spawn')
    with ctx.Pool(workers, initializer=_init_fit, initargs=(cfg, views)) as pool:
        for sid, r in tqdm(pool.imap_unordered(_fit_one, jobs), total=len(jobs),
                           desc='placement fits', disable=not progress, leave=False):
            fitted[sid] = r
    fit_s = time.monotonic() - t0
    (out / 'fitted_placements.json').write_text(json.dumps(
        {str(s): {'fitted': json.loads(r.scene.to_json()), 'mse': r.mse,
                  'evaluations': r.evaluations, 'starts': r.starts, 'hidden': list(r.hidden),
                  'read': json.loads(read[s].to_json()),
                  'truth': json.loads(truth[s].to_json())} for s, r in sorted(fitted.items())}))

    ini, _, p = to_tensors(te, idx, pmax)
    init_np, tgt_np = np.asarray(te.initial[idx]), np.asarray(te.target[idx])
    touching = touching_flags(te, idx)
    sil = RobotSilhouette.fit(np.asarray(te.initial))
    pa = np.asarray(te.pressure[idx], dtype=float)
    rows_of = scenes[idx]
    results = {}

    def score(name, pred):
        r = evaluate_arrays(init_np, tgt_np, pred, sil, touching)
        row = {k: r[k]['model'] for k in ('touching', 'free')}
        row['all'] = r['model']
        iou = [row[k]['silhouette_iou'] for k in ('all', 'touching', 'free')]
        results[name] = {'iou_all_touching_free': iou, 'gap': iou[2] - iou[1],
                         'yellow_vs_copy': row['all']['yellow_fraction'] / max(
                             r['copy']['yellow_fraction'], 1e-12),
                         'tip_px_touching_mean': row['touching']['tip_error_px'],
                         'tip_px_median': row['all']['tip_error_median_px'],
                         'intrusion': row['all'].get('intrusion'), 'metrics': row}

    alone = _draw(model, ini, p, None).reshape(tgt_np.shape)
    score('tube model alone', alone)
    for name, table in (('head, true placement', truth),
                        ('head, read placement (unfitted)', read),
                        ('head, fitted placement', {s: r.scene for s, r in fitted.items()})):
        pred = _draw(model, ini, p, head.keypoints([table[int(s)] for s in rows_of], pa))
        score(name, pred.reshape(tgt_np.shape))
    drawn = pred.reshape(tgt_np.shape)                 # the head's, for the fitted placements
    from softshape_ros.experiments.placement_predictor import alone_because
    from softshape_ros.sim.placement_fit import PlacementFit
    fit = PlacementFit(cfg, views)
    why = {s: alone_because(fit, head, r.scene, r.hidden) for s, r in fitted.items()}
    own = np.array([bool(why[int(s)]) for s in rows_of])             # per test row
    score('placement path', np.where(own[:, None, None, None, None], alone, drawn))
    summary = {
        'train': str(train), 'test': str(test), 'checkpoint': str(checkpoint),
        'test_rows': int(len(idx)), 'test_placements': int(len(ids)),
        'head': trained,
        'fit': {'seconds': round(fit_s, 1), 'workers': workers,
                'seconds_per_placement_per_worker': round(fit_s * workers / len(ids), 2),
                'mse_median': float(np.median([r.mse for r in fitted.values()])),
                'hidden_placements': sum(bool(r.hidden) for r in fitted.values()),
                'tube_model_alone_placements': sum(bool(w) for w in why.values()),
                'evaluations_mean': float(np.mean([r.evaluations for r in fitted.values()]))},
        'read': _errors(read, truth),
        'fitted': _errors({s: r.scene for s, r in fitted.items()}, truth),
        'predictions': results,
        'wall_s': round(time.monotonic() - t_start, 1)}
    (out / 'placement_head.json').write_text(json.dumps(summary, indent=1))
    return summary
