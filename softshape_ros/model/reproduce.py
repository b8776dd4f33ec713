"""
The paper's simulation study (III-B/C, Fig. 4 and 5), with our network beside the paper's.

One stereo dataset; mono runs use its first view (``main``). A test set is held out once
per split (random rows, or whole scenes) and never trained on; training sets of 100, 200,
500, 1000 rows are nested draws from the rest, each split 80/20 into train/validation as in
the paper. Every run's metrics are cached as JSON beside the table, so an interrupted
reproduction resumes where it stopped. ``tube`` (our structured model) joins the grid when
asked for (``archs``): its two-phase recipe (:func:`~softshape_ros.model.train.train_in_phases`)
costs several times a ``paper`` or ``ours`` run, so the default grid is the paper's pair.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import matplotlib
import numpy as np
from tqdm import tqdm

from softshape_ros.data import Dataset, load_dataset
from softshape_ros.model.data import no_contact_why, split_indices, touching_flags
from softshape_ros.model.evaluate import predict_rows, prediction_panels
from softshape_ros.model.metrics import RobotSilhouette, evaluate_arrays
from softshape_ros.model.predictor import Predictor
from softshape_ros.model.train import TrainConfig, code_stamp, train, train_in_phases

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402

ARCHS = ('paper', 'ours', 'tube')
DEFAULT_ARCHS = ('paper', 'ours')   # what is trained unless asked
COLOURS = {'paper': 'tab:orange', 'ours': 'tab:blue', 'tube': 'tab:green'}
VIEWS = ('mono', 'stereo')
SPLITS = ('random', 'scene')


@dataclass
class ReproConfig:
    """The study grid and the training budget of each run."""

    sizes: list = field(default_factory=lambda: [100, 200, 500, 1000])
    test_fraction: float = 0.2
    seed: int = 0
    max_steps: int = 400
    eval_every: int = 10
    patience: int = 8
    threads: int = 0
    # tube: the keypoint phase (whole placements a batch, nothing drawn; skipped on data
    # without a shape record), then the full loss for max_steps at its own batch size, both
    # validated every tube_eval_every steps (a validation draws every validation row)
    tube_keypoint_steps: int = 3000
    tube_scene_batch: int = 16
    tube_batch_size: int = 64
    tube_eval_every: int = 50
    # tube: hide the robot by a depth test against a learned object map, as the shipped
    # recipe's composite does (docs/model.md, "A depth test"); False: the learned
    # visibility before it. The grid runs no reader phases (its budget, above).
    tube_depth_test: bool = True


def select_views(ds: Dataset, n: int) -> Dataset:
    """Keep the first ``n`` views of a dataset (mono = the main camera only)."""
    meta = dict(ds.meta, views=list(ds.meta['views'])[:n])
    return dataclasses.replace(ds, initial=ds.initial[:, :n], target=ds.target[:, :n],
                               meta=meta)


def plan(ds: Dataset, cfg: ReproConfig) -> dict:
    """Per split: (test rows, nested training rows per size). Sizes above the pool fail."""
    out = {}
    for split in SPLITS:
        pool, test = split_indices(ds.scene, np.arange(len(ds)), split, cfg.test_fraction,
                                   cfg.seed)
        order = np.random.default_rng(cfg.seed + 1).permutation(pool)
        too_big = [s for s in cfg.sizes if s > len(order)]
        if too_big:
            raise ValueError(f'{ds.path}: {len(order)} rows left for training after the '
                             f'{split} test split, sizes {too_big} need more '
                             '(simulate more samples or pass --sizes)')
        out[split] = (test, {s: np.sort(order[:s]) for s in cfg.sizes})
    return out


def _key(split, views, arch, size) -> str:
    return f'{split}_{views}_{arch}_{size}'


def _fit_and_score(ds, rows, test, tc, ckpt, sil, desc, cfg: ReproConfig,
                   object_depths=None) -> dict:
    t0 = time.perf_counter()
    phases = {}
    if tc.arch == 'tube':
        kp = cfg.tube_keypoint_steps if getattr(ds, 'shape', None) is not None else 0
        params = {'depth_test': True} if cfg.tube_depth_test else {}
        phases, res = train_in_phases(
            ds, replace(tc, batch_size=cfg.tube_batch_size, eval_every=cfg.tube_eval_every,
                        arch_params=params),
            kp, ckpt.with_name(ckpt.name + '_keypoints'), out=ckpt,
            keypoint_scene_batch=cfg.tube_scene_batch, indices=rows, desc=desc,
            object_depths=object_depths)
    else:
        res = train(ds, tc, out=ckpt, indices=rows, desc=desc)
    secs = time.perf_counter() - t0
    pred = Predictor.from_checkpoint(ckpt)
    p = predict_rows(pred, ds, test)
    m = evaluate_arrays(np.asarray(ds.initial[test]), np.asarray(ds.target[test]), p, sil,
                        touching_flags(ds, test), no_contact_why(ds))
    m.update(train_seconds=secs, steps=res.steps, val_rmse=res.val_rmse_255,
             keypoint_steps=phases['keypoints'].steps if 'keypoints' in phases else 0)
    return m


def reproduce(dataset, out, cfg: ReproConfig | None = None, work=None,
              splits=SPLITS, views=VIEWS, archs=DEFAULT_ARCHS, object_depths=None) -> str:
    """
    Run (or resume) the grid; write table.md, results.json and figures to ``out``.

    Only ``splits`` x ``views`` x ``archs`` are trained here (two processes can share the
    grid, one split each); the table and figures use every cached run of this dataset and
    budget. ``object_depths``: the depth-test tube's object targets, as ``train`` takes
    them (:func:`softshape_ros.experiments.object_depths.object_depths`).
    """
    cfg = cfg or ReproConfig()
    for name, given, known in (('split', splits, SPLITS), ('views', views, VIEWS),
                               ('architecture', archs, ARCHS)):
        bad = sorted(set(given) - set(known))
        if bad:
            raise ValueError(f'unknown {name} {", ".join(bad)} (choose from {", ".join(known)})')
    full = load_dataset(dataset)
    if len(full.views) < 2:
        raise ValueError(f'{full.path}: reproduce needs a stereo dataset (mono = its 1st view)')
    out = Path(out)
    (out / 'runs').mkdir(parents=True, exist_ok=True)
    work = Path(work or tempfile.mkdtemp(prefix='softshape_repro_'))
    sets = {'mono': select_views(full, 1), 'stereo': full}
    sils = {'stereo': RobotSilhouette.fit(np.asarray(full.initial))}
    sils['mono'] = sils['stereo'].views(1)
    planned = plan(full, cfg)
    grid = [(sp, v, a, s) for sp in SPLITS for s in cfg.sizes for v in VIEWS for a in ARCHS]
    wanted = set(splits) | set(views) | set(archs)
    grid.sort(key=lambda g: not {g[0], g[1], g[2]} <= wanted)
    # Cached runs count only for the same grid, data, networks and training code.
    stamp = hashlib.sha256(json.dumps([dataclasses.asdict(cfg), str(full.path), len(full),
                                       code_stamp()]).encode()).hexdigest()[:12]
    results = {}
    bar = tqdm(grid, desc='reproduce', dynamic_ncols=True)
    for split, view, arch, size in bar:
        key = _key(split, view, arch, size)
        cache = out / 'runs' / f'{key}.json'
        if cache.exists():
            cached = json.loads(cache.read_text())
            if cached.get('stamp') == stamp:
                results[key] = cached
                continue
        if not {split, view, arch} <= wanted:
            continue
        bar.set_postfix_str(key)
        test, train_rows = planned[split]
        tc = TrainConfig(arch=arch, seed=cfg.seed, split=split, max_steps=cfg.max_steps,
                         eval_every=cfg.eval_every, patience=cfg.patience,
                         threads=cfg.threads)
        m = _fit_and_score(sets[view], train_rows[size], test, tc, work / key,
                           sils[view], key, cfg, object_depths)
        m.update(stamp=stamp, split=split, views=view, arch=arch, size=size,
                 test_rows=int(len(test)), checkpoint=str(work / key))
        cache.write_text(json.dumps(m, indent=2))
        results[key] = m
    bar.close()
    summary = {'dataset': str(full.path), 'dataset_count': len(full),
               'provenance': full.meta.get('provenance'), 'config': dataclasses.asdict(cfg),
               'runs': results}
    summary['work'] = str(work)
    (out / 'results.json').write_text(json.dumps(summary, indent=2))
    table = write_table(results, cfg, out / 'table.md', full)
    rmse_figure(results, cfg, out / 'rmse_vs_size.png')
    biggest = max(cfg.sizes)
    for view in VIEWS:
        # Unseen scenes if that split was trained here, else the random split's test rows.
        split = next((sp for sp in ('scene', 'random')
                      if (work / _key(sp, view, 'ours', biggest) / 'config.json').exists()),
                     None)
        if split is None:
            continue
        test = planned[split][0]
        pick = test[np.linspace(0, len(test) - 1, 4).astype(int)]
        panels_figure(sets[view], pick, work, biggest, view, split,
                      out / f'panels_{view}.png')
    return table


def write_table(results, cfg, path, ds) -> str:
    """Markdown: RMSE (0-255) per split/size/views/arch, with the copy baseline and gains."""
    lines = [f'Dataset: `{Path(ds.path).name}` ({len(ds)} samples, '
             f'{len(np.unique(ds.scene))} scenes). Test RMSE on the 0-255 scale, '
             'lower is better; "gain" = how much lower `ours` is than `paper`.', '']
    for split in SPLITS:
        lines += [f'**Split: {split}** '
                  + ('(held-out random rows)' if split == 'random'
                     else '(held-out scenes: unseen object placements)'), '',
                  '| size | views | copy | paper | ours | gain | ours RMSE changed | '
                  'yellow % ours / copy | ours IoU all / touching | ours tip px all / touching '
                  '| ours SSIM | ours intrusion % | ours train s |',
                  '|---|---|---|---|---|---|---|---|---|---|---|---|---|']
        for size in cfg.sizes:
            for views in VIEWS:
                p = results.get(_key(split, views, 'paper', size))
                o = results.get(_key(split, views, 'ours', size))
                if not (p and o):
                    lines.append(f'| {size} | {views} | missing run | | | | | | | | | | |')
                    continue
                om, touch = o['model'], o.get('touching', {}).get('model', {})
                gain = 100 * (1 - om['rmse'] / p['model']['rmse'])
                lines.append(
                    f'| {size} | {views} | {o["copy"]["rmse"]:.2f} | {p["model"]["rmse"]:.2f} '
                    f'| {om["rmse"]:.2f} | {gain:.0f}% | {om["rmse_changed"]:.1f} '
                    f'| {100 * om["yellow_fraction"]:.2f} / '
                    f'{100 * o["copy"]["yellow_fraction"]:.2f} '
                    f'| {om["silhouette_iou"]:.3f} / {_num(touch.get("silhouette_iou"), 3)} '
                    f'| {om["tip_error_px"]:.2f} / {_num(touch.get("tip_error_px"), 2)} '
                    f'| {_num(om.get("ssim"), 3)} | {_num(100 * om.get("intrusion", np.nan), 2)} '
                    f'| {o["train_seconds"]:.0f} |')
        lines.append('')
        lines += _tube_rows(results, cfg, split)
    text = '\n'.join(lines) + '\n'
    Path(path).write_text(text)
    return text


def _tube_rows(results, cfg, split) -> list:
    """Tabulate the tube model's rows of one split (none if not run), beside paper's RMSE."""
    keys = [(size, views) for size in cfg.sizes for views in VIEWS
            if _key(split, views, 'tube', size) in results]
    if not keys:
        return []
    lines = [f'`tube` on the same test rows ({split} split):', '',
             '| size | views | copy | paper | tube | gain | tube RMSE changed | '
             'yellow % tube / copy | tube IoU all / touching | tube tip px all / touching '
             '| tube SSIM | tube intrusion % | tube train s |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|---|']
    for size, views in keys:
        t = results[_key(split, views, 'tube', size)]
        p = results.get(_key(split, views, 'paper', size))
        tm, touch = t['model'], t.get('touching', {}).get('model', {})
        paper = p['model']['rmse'] if p else np.nan
        lines.append(
            f'| {size} | {views} | {t["copy"]["rmse"]:.2f} | {_num(paper, 2)} '
            f'| {tm["rmse"]:.2f} | {_num(100 * (1 - tm["rmse"] / paper), 0)}% '
            f'| {tm["rmse_changed"]:.1f} | {100 * tm["yellow_fraction"]:.2f} / '
            f'{100 * t["copy"]["yellow_fraction"]:.2f} '
            f'| {tm["silhouette_iou"]:.3f} / {_num(touch.get("silhouette_iou"), 3)} '
            f'| {tm["tip_error_px"]:.2f} / {_num(touch.get("tip_error_px"), 2)} '
            f'| {_num(tm.get("ssim"), 3)} | {_num(100 * tm.get("intrusion", np.nan), 2)} '
            f'| {t["train_seconds"]:.0f} |')
    return lines + ['']


def _num(v, nd) -> str:
    return '-' if v is None or not np.isfinite(v) else f'{v:.{nd}f}'


def rmse_figure(results, cfg, path) -> None:
    """Fig. 5: test RMSE against training-set size, one panel per split."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, split in zip(axes, SPLITS):
        for views, ls in zip(VIEWS, ('--', '-')):
            for arch, colour in COLOURS.items():
                pts = [(s, results[_key(split, views, arch, s)]['model']['rmse'])
                       for s in cfg.sizes if _key(split, views, arch, s) in results]
                if pts:
                    ax.plot(*zip(*pts), ls, marker='o', color=colour, label=f'{arch} {views}')
        copies = [(s, results[_key(split, 'stereo', 'ours', s)]['copy']['rmse'])
                  for s in cfg.sizes if _key(split, 'stereo', 'ours', s) in results]
        if copies:
            ax.plot(*zip(*copies), ':', color='gray', label='copy initial image')
        ax.set_xscale('log')
        ax.set_xticks(cfg.sizes)
        ax.set_xticklabels([str(s) for s in cfg.sizes])
        ax.set_xlabel('training samples')
        ax.set_title(f'split: {split}')
        ax.grid(alpha=0.3)
    axes[0].set_ylabel('test RMSE (0-255)')
    for ax in axes:
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def panels_figure(ds, rows, work, size, views, split, path) -> None:
    """Fig. 4(a)/(b): test-set predictions of paper, ours (and tube, if run), largest size."""
    initial, target = np.asarray(ds.initial[rows]), np.asarray(ds.target[rows])
    cks = {a: work / _key(split, views, a, size) for a in ARCHS}
    archs = [a for a in ARCHS if (cks[a] / 'config.json').exists()]
    if not set(DEFAULT_ARCHS) <= set(archs):
        return
    preds, labels = [], []
    for arch in archs:
        preds.append(predict_rows(Predictor.from_checkpoint(cks[arch]), ds, rows))
        labels += [f'{arch} #{r}' for r in rows]
    n, k = len(rows), len(archs)
    where = 'unseen scenes' if split == 'scene' else 'held-out rows'
    prediction_panels(np.concatenate([initial] * k), np.concatenate([target] * k),
                      np.concatenate(preds), list(ds.views), path,
                      title=f'{views}, {size} training samples, {where} '
                            f'({n} rows each: {", ".join(archs)})', row_labels=labels)
