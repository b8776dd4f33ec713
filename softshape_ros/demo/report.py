"""Write ``report.md``: what ran, the numbers, the figures and where every artefact is."""

from __future__ import annotations

import json
from pathlib import Path

METRICS = (('rmse', 'RMSE (0-255)'), ('rmse_changed', 'RMSE in the changed region'),
           ('yellow_fraction', 'yellow-mask fraction (>10/255)'), ('ssim', 'SSIM'),
           ('psnr_db', 'PSNR (dB)'), ('silhouette_iou', 'robot-silhouette IoU'),
           ('tip_error_px', 'tip error (px), mean'),
           ('tip_error_median_px', 'tip error (px), median'),
           ('intrusion', "intrusion (share of the object's pixels)"))


def _fmt(v, nd=2):
    return f'{v:.{nd}f}' if isinstance(v, float) else str(v)


def metric_table(sections: dict) -> list[str]:
    """Return markdown rows: one metric per row, one column per (name, metrics dict)."""
    names = list(sections)
    lines = ['| metric | ' + ' | '.join(names) + ' |', '|---' * (len(names) + 1) + '|']
    for key, label in METRICS:
        if any(key in m for m in sections.values()):
            lines.append(f'| {label} | '
                         + ' | '.join(_fmt(m.get(key, '-'), 3) for m in sections.values())
                         + ' |')
    return lines


def _evaluation(ev: dict) -> list[str]:
    sections = {'model': ev.get('model', {}), 'copy initial': ev.get('copy', {})}
    for part in ('touching', 'free'):
        if ev.get(part, {}).get('samples'):
            sections[f'model, {part} ({ev[part]["samples"]})'] = ev[part]['model']
            sections[f'copy, {part}'] = ev[part]['copy']
    lines = metric_table(sections)
    lines += ['', f'{ev.get("samples")} validation samples; split: {ev.get("split", "-")}.']
    return lines


def _live(settings, lv: dict) -> list[str]:
    lines = [f'{lv["samples"]} commands on {len(lv["scenes"])} placements not seen in '
             'training: the predicted image published on `/softshape/predicted/{view}/image_raw`'
             ' for each `/rig/pressure/command`, against the mock rig\'s camera images after '
             'settling (both preprocessed like the dataset).', '']
    if 'model' in lv:
        lines += metric_table({'inference node': lv['model'], 'copy initial': lv['copy']})
        t, met = lv['targets'], lv['targets_met']
        lines += ['', '| target | wanted | got | met |', '|---|---|---|---|',
                  f'| silhouette IoU | >= {t["silhouette_iou"]} | '
                  f'{_fmt(lv["model"]["silhouette_iou"], 3)} | {met["silhouette_iou"]} |',
                  f'| tip error (px) | <= {t["tip_error_px"]} | '
                  f'{_fmt(lv["model"]["tip_error_px"], 2)} | {met["tip_error_px"]} |',
                  f'| yellow mask vs copy | <= {t["yellow_vs_copy"]} | '
                  f'{_fmt(lv["yellow_vs_copy"], 3)} | {met["yellow_vs_copy"]} |']
    ms = lv['command_to_prediction_ms']
    lines += ['', f'Command -> predicted image over DDS, median / p99: {_fmt(ms["median"])} / '
              f'{_fmt(ms["p99"])} ms.']
    return lines


def write_report(root: Path, settings, results: dict, wall_s: float | None = None) -> Path:
    """Write ``<root>/report.md`` from every stage's result; return its path."""
    rec, ds, tr = results['record'], results['dataset'], results['train']
    ev, lv = results['evaluate'], results['live']
    topics = rec.get('bag_info', {}).get('topics', [])
    arch = tr.get('arch', 'ours')       # results written before the tube demo: ours
    start = (f'fine-tuned from the checkpoint pre-trained on simulation `{tr["pretrained"]}`'
             if tr.get('pretrained') else 'trained from scratch')
    lines = [
        '# softshape_ros demo report', '',
        'The whole pipeline on the simulated rig: mock_hardware (Cosserat simulator + renderer),',
        'collector and recorder as separate ROS 2 processes -> rosbag2 bag -> dataset -> '
        f'`{arch}`',
        'model -> evaluation -> the inference node live against the mock rig.', '',
        f'Settings: `{json.dumps({k: getattr(settings, k) for k in vars(settings)})}`', '',
        '## Stages', '',
        f'Wall time of this run: {wall_s} s (stages reused from an earlier run count 0).', '',
        '| stage | seconds (0 = reused) | output |', '|---|---|---|',
        f'| record | {rec.get("seconds")} | `{rec["bag"]}` |',
        f'| dataset | {ds.get("seconds")} | `{ds["dataset"]}` |',
        f'| train | {tr.get("seconds")} | `{tr.get("checkpoint")}` |',
        f'| evaluate | {ev.get("seconds")} | `{root / "eval"}` |',
        f'| live | {lv.get("seconds")} | `{lv.get("figure")}` |', '',
        '## Recording', '',
        f'{rec["triggers"]} triggers ({settings.scenes} scenes x (1 rest + {settings.actuations}'
        f' actuations) at {settings.rate_hz} Hz); session `{rec["session"]}`.', '',
        '| topic | type | messages |', '|---|---|---|',
    ]
    lines += [f'| {t["name"]} | {t["type"]} | {t["count"]} |' for t in topics]
    lines += [
        '', '## Dataset', '',
        f'{ds.get("count")} samples, views {ds.get("views")}; dropped: '
        f'`{json.dumps(ds.get("dropped"))}`.', '',
        f'## Training (`{arch}`, random 80/20 split as the paper)', '',
        f'{start}; {tr.get("steps")} steps; validation RMSE {_fmt(tr.get("val_rmse_255"))} '
        f'(0-255 scale) vs {_fmt(tr.get("copy_val_rmse_255"))} for copying the initial image.',
        '', '## Evaluation on the validation rows', '']
    lines += _evaluation(ev)
    lines += ['', '![validation panels](eval/panels.png)', '',
              '## Live: the inference node against the mock rig', '']
    lines += _live(settings, lv)
    lines += ['', '![live panels](live_panels.png)', '', f'Node logs: `{root / "logs"}`.', '']
    path = root / 'report.md'
    path.write_text('\n'.join(lines))
    from softshape_ros.demo.control_stage import append_report   # the control stage
    append_report(path, results.get('control'))
    return path
