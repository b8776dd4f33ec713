"""
The demo pipeline end to end at a tiny size: bag -> dataset -> model -> live predictions.

Runs exactly what ``make demo`` runs (nodes as separate processes, the ``softshape`` tools),
then checks the artefacts with independent readers, and that a second run reuses them.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from softshape_ros.demo.pipeline import STAGES, DemoSettings, run_demo

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_tiny_demo_end_to_end_and_reuse(tmp_path):
    s = DemoSettings(out=str(tmp_path / 'demo'), scenes=2, actuations=4, rate_hz=4.0,
                     max_steps=20, finetune_steps=10, threads=1, live_scenes=1,
                     live_commands=3, seed=5)
    s.control_goals, s.control_live, s.control_bank = 2, 1, 48     # the control stage
    report = run_demo(s)
    root = Path(s.out)
    text = report.read_text()
    for section in ('## Recording', '## Dataset', '## Training', '## Evaluation', '## Live',
                    '## Control'):
        assert section in text

    # The bag, read with the independent mcap reader: one image per camera per trigger.
    from mcap.reader import make_reader
    counts = {}
    for f in sorted((root / 'bag').glob('*.mcap')):
        with open(f, 'rb') as fh:
            for _, channel, _ in make_reader(fh).iter_messages():
                counts[channel.topic] = counts.get(channel.topic, 0) + 1
    triggers = s.scenes * (s.actuations + 1)
    assert counts['/rig/trigger'] == triggers
    assert counts['/rig/camera_main/image_raw'] == triggers
    assert counts['/rig/camera_side/image_raw'] == triggers

    # The dataset: every actuation became a sample, nothing dropped.
    from softshape_ros.data import load_dataset
    ds = load_dataset(root / 'dataset')
    assert len(ds) == s.scenes * s.actuations
    assert ds.views == ['main', 'side']
    assert not any(ds.meta['dropped'].values())

    # The model and the live stage: predictions came back for every command.
    assert (root / 'model' / 'model.safetensors').is_file()
    from softshape_ros.model.checkpoint import read_config
    trained = read_config(root / 'model')['training']
    assert trained['init_from'] == (s.pretrained or None)     # the shipped checkpoint, if any
    # ... of its own architecture (the shipped tube model; ours when trained from scratch)
    want = read_config(s.pretrained)['arch'] if s.pretrained else 'ours'
    assert read_config(root / 'model')['arch'] == want
    assert f'## Training (`{want}`' in text
    live = json.loads((root / '.live.done.json').read_text())['result']
    assert live['samples'] == s.live_scenes * s.live_commands
    assert np.isfinite(live['rmse_255']) and 0 <= live['rmse_255'] < 255
    # Scored like `softshape evaluate`, beside the copy baseline, with the targets.
    assert set(live['model']) == set(live['copy']) and 'silhouette_iou' in live['model']
    assert set(live['targets_met']) == {'silhouette_iou', 'tip_error_px', 'yellow_vs_copy'}
    assert '| target | wanted | got | met |' in text
    assert all(code == 0 for code in live['exit_codes'].values()), live['exit_codes']
    assert (root / 'live_panels.png').stat().st_size > 10_000

    # The control stage: the evaluation ran all three methods on both goals, and the live
    # loop over DDS gave a result for its goal (a 20-step model need not reach it).
    ctl = json.loads((root / '.control.done.json').read_text())['result']
    for m in ('model', 'random', 'oracle'):
        assert 0.0 <= ctl['eval'][m]['success_rate'] <= 1.0
    assert ctl['eval']['goals'] == 2
    assert [r['state'] for r in ctl['live']['results']][0] in ('reached', 'not_reached')
    assert all(code == 0 for code in ctl['live']['exit_codes'].values()), ctl['live']
    for fig in ('control/control.png', 'control_live.png'):
        assert (root / fig).stat().st_size > 10_000

    # A second run with the same settings reuses every stage.
    before = {n: (root / f'.{n}.done.json').stat().st_mtime_ns for n in STAGES + ('control',)}
    run_demo(s)
    after = {n: (root / f'.{n}.done.json').stat().st_mtime_ns for n in STAGES + ('control',)}
    assert before == after
