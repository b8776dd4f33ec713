"""
Design study behind ``ours``: train variants for a fixed number of steps, score on held-out rows.

Not part of ``make bench`` (minutes per variant). Each variant is JSON: the architecture
(``"arch": "ours"`` or ``"paper"``), any network parameters (e.g. ``"output": "residual"``,
``"coords": false``) and any training settings (``"lr"``, ``"loss"``,
``"silhouette_weight"``); what is left out is the network's default::

    python -m benchmarks.model_ablation --dataset D --steps 300 --split scene
        '{"arch": "ours", "output": "residual", "loss": "mse"}' '{"arch": "ours"}'

(one command line). Rows: the reproduction's plan for ``--split`` (``--size`` training rows,
its test rows). Prints one JSON line per variant: every metric of ``softshape evaluate``
on the test rows (all, touching and free where the dataset records contact), seconds.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from softshape_ros.data import load_dataset
from softshape_ros.model.data import to_tensors, touching_flags
from softshape_ros.model.metrics import RobotSilhouette, evaluate_arrays
from softshape_ros.model.reproduce import ReproConfig, plan, select_views
from softshape_ros.model.train import TrainConfig, train

TRAIN_KEYS = ('lr', 'loss', 'silhouette_weight', 'batch_size')


def _short(m: dict) -> dict:
    keys = ('rmse', 'yellow_fraction', 'ssim', 'psnr_db', 'silhouette_iou', 'tip_error_px',
            'tip_error_median_px', 'intrusion')
    return {k: round(m[k], 4) for k in keys if k in m}


def run_variant(ds, full, rows, test, variant: dict, steps: int, split: str, seed: int) -> dict:
    """Train one variant on ``rows`` for ``steps`` and score it on ``test``."""
    params = dict(variant)
    arch = params.pop('arch', 'ours')
    train_kw = {k: params.pop(k) for k in TRAIN_KEYS if k in params}
    cfg = TrainConfig(arch=arch, max_steps=steps, eval_every=20, patience=10 ** 6, seed=seed,
                      split=split, arch_params=params, **train_kw)
    t0 = time.perf_counter()
    res = train(ds, cfg, indices=rows, progress=False)
    secs = time.perf_counter() - t0
    x, _, p = to_tensors(ds, test, ds.max_pressure_pa)
    with torch.no_grad():
        y = torch.cat([res.model(x[i:i + 256], p[i:i + 256]) for i in range(0, len(x), 256)])
    v = len(ds.views)
    pred = torch.clamp(y * 255 + 0.5, 0, 255).to(torch.uint8).numpy()
    pred = pred.reshape(len(test), v, ds.channels, *pred.shape[-2:])
    sil = RobotSilhouette.fit(np.asarray(full.initial)).views(v)
    m = evaluate_arrays(np.asarray(ds.initial[test]), np.asarray(ds.target[test]), pred, sil,
                        touching_flags(ds, test))
    out = {'variant': variant, 'steps': res.steps, 'lr': res.config['training']['lr'],
           'loss': res.config['training']['loss'], 'seconds': round(secs),
           'params': sum(q.numel() for q in res.model.parameters()),
           'model': _short(m['model']), 'copy': _short(m['copy'])}
    for part in ('touching', 'free'):
        if m.get(part, {}).get('samples'):
            out[part] = dict(_short(m[part]['model']), samples=m[part]['samples'])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='python -m benchmarks.model_ablation')
    ap.add_argument('variants', nargs='+', help='JSON per variant')
    ap.add_argument('--dataset', required=True, help='stereo dataset (as for reproduce)')
    ap.add_argument('--steps', type=int, default=300)
    ap.add_argument('--size', type=int, default=1000)
    ap.add_argument('--split', choices=('random', 'scene'), default='scene')
    ap.add_argument('--views', choices=('mono', 'stereo'), default='stereo')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--threads', type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    full = load_dataset(args.dataset)
    ds = full if args.views == 'stereo' else select_views(full, 1)
    test, rows = plan(full, ReproConfig(sizes=[args.size]))[args.split]
    for v in args.variants:
        print(json.dumps(run_variant(ds, full, rows[args.size], test, json.loads(v), args.steps,
                                     args.split, args.seed)), flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
