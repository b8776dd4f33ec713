"""Write ``report.md``: what ran, the numbers, the figures and where every artefact is."""

from __future__ import annotations

import json
from pathlib import Path


def _fmt(v, nd=2):
    return f'{v:.{nd}f}' if isinstance(v, float) else str(v)


def write_report(root: Path, settings, results: dict) -> Path:
    rec, ds, tr = results['record'], results['dataset'], results['train']
    ev, lv = results['evaluate'], results['live']
    topics = rec.get('bag_info', {}).get('topics', [])
    lines = [
        '# softshape_ros demo report', '',
        'The whole pipeline on the simulated rig: mock_hardware (Cosserat simulator + renderer),',
        'collector and recorder as separate ROS 2 processes -> rosbag2 bag -> dataset -> `ours`',
        'model -> evaluation -> the inference node live against the mock rig.', '',
        f'Settings: `{json.dumps({k: getattr(settings, k) for k in vars(settings)})}`', '',
        '## Stages', '',
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
        '## Training (`ours`, random 80/20 split as the paper)', '',
        f'{tr.get("steps")} steps; validation RMSE {_fmt(tr.get("val_rmse_255"))} (0-255 scale) '
        f'vs {_fmt(tr.get("copy_val_rmse_255"))} for copying the initial image.', '',
        '## Evaluation on the validation rows', '',
        '| metric | model | copy-initial baseline |', '|---|---|---|',
    ]
    model, copy = ev.get('model', {}), ev.get('copy', {})
    for key, label in (('rmse', 'RMSE (0-255)'), ('rmse_changed', 'RMSE in the changed region'),
                       ('yellow_fraction', 'yellow-mask fraction (>10/255)'),
                       ('silhouette_iou', 'robot-silhouette IoU'),
                       ('tip_error_px', 'tip error (px)')):
        if key in model:
            lines.append(f'| {label} | {_fmt(model[key], 3)} | {_fmt(copy.get(key), 3)} |')
    lines += ['', f'{ev.get("samples")} validation samples.', '',
              '![validation panels](eval/panels.png)', '',
              '## Live: the inference node against the mock rig', '',
              f'{lv["samples"]} commands on {len(lv["scenes"])} placements not seen in training: '
              'the predicted image published on `/softshape/predicted/{view}/image_raw` for each '
              '`/rig/pressure/command`, against the mock rig\'s camera images after settling '
              '(both preprocessed like the dataset).', '',
              '| metric | value |', '|---|---|',
              f'| RMSE (0-255) | {_fmt(lv["rmse_255"])} |',
              f'| copy-initial RMSE | {_fmt(lv["copy_initial_rmse_255"])} |',
              f'| yellow-mask fraction | {_fmt(lv["yellow_mask_fraction"], 4)} |',
              f'| command -> predicted image over DDS, median / p99 (ms) | '
              f'{_fmt(lv["command_to_prediction_ms"]["median"])} / '
              f'{_fmt(lv["command_to_prediction_ms"]["p99"])} |', '',
              '![live panels](live_panels.png)', '',
              f'Node logs: `{root / "logs"}`.', '']
    path = root / 'report.md'
    path.write_text('\n'.join(lines))
    from softshape_ros.demo.control_stage import append_report   # the control stage
    append_report(path, results.get('control'))
    return path
