"""
Design study behind ``ours``: train variants for a fixed number of steps, score on held-out rows.

Not part of ``make bench`` (minutes per variant). Each variant is JSON: ``{"arch": "ours",
...OursNet params}``, ``{"arch": "paper"}``, or ``{"arch": "variant", ...}`` for the
alternatives that lost (kept so docs/model.md's design study can be re-run); an ``"lr"`` key
sets its learning rate (default: the network's own, ``ours``' for variants)::

    python -m benchmarks.model_ablation --dataset D --steps 300
        '{"arch": "ours", "coords": false}' '{"arch": "variant", "spatial": true}'

(one command line).

Rows: the reproduction's random-split plan (1000 training rows, the 320 test rows).
Prints one JSON line per variant (test RMSE, silhouette IoU, copy baseline, seconds).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
from torch import nn

import softshape_ros.model.train as train_module
from softshape_ros.data import load_dataset
from softshape_ros.model.data import to_tensors
from softshape_ros.model.metrics import RobotSilhouette, evaluate_arrays
from softshape_ros.model.networks import OursNet, build_network, coordinate_planes
from softshape_ros.model.reproduce import ReproConfig, plan, select_views


class VariantNet(OursNet):
    """``ours`` with options that were tried and lost: a pressure map, coords in the decoder."""

    def __init__(self, image_channels, widths=(16, 32, 64, 64), cond=64, coords=True,
                 spatial=False, decoder_coords=False):
        super().__init__(image_channels, widths, cond, coords)
        self.spatial, self.decoder_coords = spatial, decoder_coords
        if spatial:     # the actuation drawn straight into the 4x4 bottleneck
            self.smap = nn.Linear(cond, widths[-1] * 16)
        if decoder_coords:
            for m in self.merge:
                m.conv = nn.Conv2d(m.conv.in_channels + 2, m.channels, 3, 1, 1)

    def forward(self, image, pressure):
        c = self.cond(pressure)
        films = self.films(c)
        x = self.inputs(image, pressure)
        skips = []
        for stage in self.down:
            x = stage(x, *next(films))
            skips.append(x)
        skips.pop()
        if self.spatial:
            x = torch.relu(x + self.smap(c).view(len(x), -1, 4, 4))
        for up, merge in zip(self.up, self.merge):
            x = up(x, *next(films))
            m = torch.cat([x, skips.pop()], 1)
            if self.decoder_coords:
                m = torch.cat([m, coordinate_planes(len(m), *m.shape[2:], m)], 1)
            x = merge(m, *next(films))
        return image + self.head(x)


def _build(arch, views, channels, **params):
    if arch == 'variant':
        return VariantNet(views * channels, **params)
    return build_network(arch, views, channels, **params)


def run_variant(ds, full, rows, test, variant: dict, steps: int, lr, seed: int) -> dict:
    params = dict(variant)
    arch = params.pop('arch', 'ours')
    # Each at its own best unless told: variants of ours at ours' rate.
    lr = params.pop('lr', lr) or train_module.DEFAULT_LR.get(arch, train_module.DEFAULT_LR['ours'])
    train_module.build_network = _build     # the study's variants next to the real ones
    cfg = train_module.TrainConfig(arch=arch, max_steps=steps, eval_every=10, patience=10 ** 6,
                                   lr=lr, seed=seed, arch_params=params)
    t0 = time.perf_counter()
    res = train_module.train(ds, cfg, indices=rows, progress=False)
    secs = time.perf_counter() - t0
    x, _, p = to_tensors(ds, test, ds.max_pressure_pa)
    with torch.no_grad():
        y = torch.cat([res.model(x[i:i + 256], p[i:i + 256]) for i in range(0, len(x), 256)])
    v = len(ds.views)
    pred = (y.clamp(0, 1) * 255).round().numpy().astype(np.uint8)
    pred = pred.reshape(len(test), v, ds.channels, *pred.shape[-2:])
    sil = RobotSilhouette.fit(np.asarray(full.initial))
    sil = RobotSilhouette(sil.threshold, sil.base_rc[:v])
    m = evaluate_arrays(np.asarray(ds.initial[test]), np.asarray(ds.target[test]), pred, sil)
    return {'variant': variant, 'steps': steps, 'lr': res.config['training']['lr'],
            'seconds': round(secs), 'test_rmse': round(m['model']['rmse'], 2),
            'silhouette_iou': round(m['model']['silhouette_iou'], 3),
            'copy_rmse': round(m['copy']['rmse'], 2)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='python -m benchmarks.model_ablation')
    ap.add_argument('variants', nargs='+', help='JSON per variant')
    ap.add_argument('--dataset', required=True, help='stereo dataset (as for reproduce)')
    ap.add_argument('--steps', type=int, default=300)
    ap.add_argument('--size', type=int, default=1000)
    ap.add_argument('--views', choices=('mono', 'stereo'), default='stereo')
    ap.add_argument('--lr', type=float, default=None,
                    help="every variant's rate (default: each network's own)")
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--threads', type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    full = load_dataset(args.dataset)
    ds = full if args.views == 'stereo' else select_views(full, 1)
    test, rows = plan(full, ReproConfig(sizes=[args.size]))['random']
    for v in args.variants:
        print(json.dumps(run_variant(ds, full, rows[args.size], test, json.loads(v), args.steps,
                                     args.lr, args.seed)), flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
