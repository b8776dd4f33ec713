"""Experiments over both the simulator and the model: the Fig. 4(c) distance sweep."""

import json
from dataclasses import asdict

import numpy as np
import pytest
import torch

from softshape_ros.config import load_rig_config
from softshape_ros.experiments.distance_sweep import distance_sweep
from softshape_ros.model import build_network, save_checkpoint


def test_distance_sweep_reports_the_objects_push(tmp_path):
    """The sweep's simulated side must show contact near and none far, whatever the model."""
    cfg = load_rig_config()
    torch.manual_seed(0)
    ck = save_checkpoint(tmp_path / 'ck', build_network('ours', 2, 1), {
        'arch': 'ours', 'arch_params': {}, 'views': ['main', 'side'], 'channels': 1,
        'image_size': 64, 'max_pressure_pa': list(cfg.max_pressures_pa)})
    res = distance_sweep(ck, tmp_path / 'fig4c.png')
    rows = res['rows']
    assert [r['touching'] for r in rows][0] and not rows[-1]['touching']
    # Far away the simulated tip is where the free shape puts it; near, the cylinder pushes it.
    assert rows[-1]['tip_shift_px_simulated'] < 1.0
    assert rows[0]['tip_shift_px_simulated'] > 2.0
    # An untrained "ours" returns (about) the initial image: its tip never leaves the rest
    # pose, so it is far from the free shape and from the simulated push alike.
    assert all(r['tip_shift_px_predicted'] > 2.0 for r in rows)
    assert res['worst_shift_error_px'] == max(r['shift_error_px'] for r in rows)
    assert not res['within_tolerance']
    assert all(np.isfinite(r['rmse']) and 0 <= r['intrusion'] <= 1 for r in rows)
    assert (tmp_path / 'fig4c.png').stat().st_size > 1000
    # The same contact turned about the robot: 12 setups, Fig. 4(c)'s first, each bend
    # with the cylinder 30 deg beside it. The robot is symmetric, so every setup touches
    # where Fig. 4(c) does, and its main view is Fig. 4(c)'s rows.
    t = res['turned']
    assert len(t['setups']) == 12
    first = t['setups'][0]
    assert (first['bend_deg'], first['cylinder_deg']) == (30.0, 0.0)
    assert [r['shift_px_simulated'][0] for r in first['rows']] == \
        [round(r['tip_shift_px_simulated'], 3) for r in rows]
    bends = sorted({round(s['bend_deg']) for s in t['setups']})
    assert bends == [-150, -90, -30, 30, 90, 150]
    for s in t['setups']:
        assert abs((s['cylinder_deg'] - s['bend_deg'] + 180) % 360 - 180) == 30.0
        assert [r['touching'] for r in s['rows']] == [r['touching'] for r in rows]
    assert [p['touching_share'] for p in t['per_distance']] == \
        [float(r['touching']) for r in rows]
    errors = [r['shift_error_px'] for s in t['setups'] for r in s['rows']]
    assert all(e is None or e >= 0 for e in errors)
    assert t['within_tolerance_share'] < 1.0
    assert max(p['worst_shift_error_px'] for p in t['per_distance']) == \
        max(e for e in errors if e is not None)
    assert (tmp_path / 'fig4c_turned.png').stat().st_size > 1000


def test_distance_sweep_cli_writes_numbers_and_figure(tmp_path, capsys):
    from softshape_ros.cli import main as cli
    cfg = load_rig_config()
    ck = save_checkpoint(tmp_path / 'ck', build_network('paper', 1, 1), {
        'arch': 'paper', 'arch_params': {}, 'views': ['main'], 'channels': 1,
        'image_size': 64, 'max_pressure_pa': list(cfg.max_pressures_pa)})
    assert cli(['distance-sweep', '--checkpoint', str(ck), '--out', str(tmp_path / 'o')]) == 0
    printed = json.loads(capsys.readouterr().out)
    saved = json.loads((tmp_path / 'o' / 'distance_sweep.json').read_text())
    assert printed == saved and len(saved['rows']) == 5
    assert (tmp_path / 'o' / 'distance_sweep.png').is_file()
    # The same sweep on images made at the camera's own pixels: the same pushes to a pixel.
    assert cli(['distance-sweep', '--checkpoint', str(ck), '--out', str(tmp_path / 'c'),
                '--supersample', '0']) == 0
    camera = json.loads(capsys.readouterr().out)
    assert saved['supersample'] == 4 and camera['supersample'] == 0
    for a, b in zip(saved['rows'], camera['rows']):
        assert abs(a['tip_shift_px_simulated'] - b['tip_shift_px_simulated']) < 1.0
    assert cli(['distance-sweep', '--checkpoint', str(ck), '--out', str(tmp_path / 'n'),
                '--supersample', '-1']) == 2
    assert '--supersample must be >= 0' in capsys.readouterr().err
    assert not (tmp_path / 'n').exists()


def test_pretrain_tube_runs_its_two_phases_and_reuses_the_data(tmp_path, capsys, monkeypatch):
    """`softshape pretrain --arch tube`: the keypoint phase, then the full loss from it."""
    from softshape_ros.cli import main as cli
    from softshape_ros.experiments.pretrain import PretrainSettings
    from softshape_ros.model import load_checkpoint
    args = ['pretrain', '--arch', 'tube', '--out', str(tmp_path / 'ck'), '--work',
            str(tmp_path / 'work'), '--samples', '40', '--scenes', '4', '--keypoint-steps', '3',
            '--max-steps', '2', '--batch-size', '8', '--eval-every', '1', '--threads', '1',
            '--workers', '1', '--quiet', '--reader-steps', '0', '--head-steps', '0',
            '--no-compile-renderer']
    # The recipe's phases: reader, keypoints, heads, full (docs/model.md).
    recipe = PretrainSettings.for_arch('tube')
    assert (recipe.reader_steps, recipe.keypoint_steps, recipe.head_steps, recipe.max_steps,
            recipe.depth_test, recipe.encoder_bf16) == (4000, 8000, 10000, 2400, True, True)
    # "A compiled renderer" (the renderer compiled: off in these runs), "The 30 minutes".
    assert recipe.scene_nets_bf16 and recipe.compile_renderer and recipe.fused_adam
    assert recipe.val_fraction == 0.05          # the full phase's held-out placements
    # How the shipped checkpoint was made: two trainings of the recipe, averaged.
    shipped = PretrainSettings.for_arch('tube', as_shipped=True, head_steps=None, seed=3)
    assert (shipped.members, shipped.seed, recipe.members) == (2, 3, 1)
    changed = {'members', 'seed'}

    def kept(settings):
        return {k: v for k, v in asdict(settings).items() if k not in changed}
    assert kept(shipped) == kept(recipe)
    assert cli(['pretrain', '--as-shipped', '--out', str(tmp_path / 'o')]) != 0
    assert "as_shipped: the tube checkpoint's settings, not 'ours'" in capsys.readouterr().err
    assert cli(args + ['--val-fraction', '0']) != 0          # refused before simulating
    assert 'val_fraction 0.0: the held-out share' in capsys.readouterr().err
    assert not (tmp_path / 'work').exists()
    assert cli(args) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out['keypoint_steps'] == 3 and out['steps'] == 2
    assert out['settings']['arch'] == 'tube' and out['settings']['samples'] == 40
    model, cfg = load_checkpoint(tmp_path / 'ck')
    assert cfg['arch'] == 'tube' and cfg['training']['loss'] == 'tube'
    assert cfg['training']['init_from'] == str(tmp_path / 'work' / 'tube_keypoints')
    # The shipped recipe hides the robot by its depth test (docs/model.md, "A depth test").
    assert out['settings']['depth_test'] is True and cfg['arch_params']['depth_test'] is True
    assert model.depth_test and model.visibility is None
    assert cfg['training']['encoder_bf16'] is True          # the recipe's default
    assert cfg['training']['scene_nets_bf16'] and cfg['training']['fused_adam']
    assert cfg['training']['compile_renderer'] is False       # --no-compile-renderer
    _, first = load_checkpoint(tmp_path / 'work' / 'tube_keypoints')
    assert first['training']['loss'] == 'keypoints' and first['training']['steps'] == 3
    # The full phase holds out fewer placements than the phases before it.
    assert (first['training']['val_fraction'], cfg['training']['val_fraction']) == (0.2, 0.05)
    assert first['training']['best_val_mse'] is None          # the keypoint phase draws nothing
    assert out['val_rmse_255'] > 0
    data = next((tmp_path / 'work').glob('sim_40_4_0'))
    stamp = (data / 'meta.json').stat().st_mtime_ns
    assert cli(args) == 0                   # the simulated data is reused, not remade
    assert (data / 'meta.json').stat().st_mtime_ns == stamp
    meta = json.loads((data / 'meta.json').read_text())
    assert meta['simulator']['sparse_share'] > 0
    # --members 2: seeds 0 and 1 trained one after the other, each in its own folder (seed
    # 0's data reused, seed 1's simulated), then averaged into one checkpoint.
    assert cli(args[:-1] + ['--arch', 'ours', '--members', '2']) != 0
    assert "ensembles average the tube model's keypoints, not 'ours'" in \
        capsys.readouterr().err
    both = args + ['--out', str(tmp_path / 'both'), '--members', '2']     # the last --out
    assert cli(both) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert [m['settings']['seed'] for m in out['members']] == [0, 1]
    assert (data / 'meta.json').stat().st_mtime_ns == stamp
    model, cfg = load_checkpoint(tmp_path / 'both')
    assert cfg['arch_params']['members'] == 2 and len(model.members) == 1
    work = tmp_path / 'work'
    assert [m['checkpoint'] for m in cfg['ensemble']] == [
        str(work / f'member_seed{s}' / 'checkpoint') for s in (0, 1)]
    _, member = load_checkpoint(work / 'member_seed1' / 'checkpoint')
    assert member['dataset']['path'].endswith('sim_40_4_1')
    assert member['training']['init_from'] == str(work / 'member_seed1' / 'tube_keypoints')
    # Other plan settings: the data is simulated again, not taken from the cache.
    assert cli(args + ['--sparse-share', '0', '--max-steps', '1', '--keypoint-steps', '1',
                       '--no-depth-test', '--no-encoder-bf16']) == 0
    _, cfg = load_checkpoint(tmp_path / 'ck')
    assert cfg['arch_params'].get('depth_test') is None
    assert cfg['training']['encoder_bf16'] is False
    meta = json.loads((data / 'meta.json').read_text())
    assert (data / 'meta.json').stat().st_mtime_ns != stamp
    assert meta['simulator']['sparse_share'] == 0
    # A mix of renderings is a data setting too: simulated again, each placement one of them.
    stamp = (data / 'meta.json').stat().st_mtime_ns
    assert cli(args + ['--sparse-share', '0', '--max-steps', '1', '--keypoint-steps', '1',
                       '--supersample', '0,3']) == 0
    meta = json.loads((data / 'meta.json').read_text())
    assert (data / 'meta.json').stat().st_mtime_ns != stamp
    assert meta['rendering']['supersample'] == [0, 3]
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])[
        'settings']['supersample'] == [0, 3]
    # A reader phase first and a heads phase last: each starts from the one before. On a
    # CPU without bfloat16 instructions the recipe says it may be slower, and trains anyway.
    import softshape_ros.experiments.pretrain as pretrain_module
    monkeypatch.setattr(pretrain_module, 'cpu_bf16_native', lambda: False)
    # --compile-renderer: checked before anything else, then every phase records it. (Here
    # the check passes and the "compiled" field is the plain one: test_model_tube compiles.)
    from softshape_ros.model import train as train_module, tube_net
    checked = []
    monkeypatch.setattr(train_module, 'check_renderer_compiles', lambda: checked.append(1))
    monkeypatch.setattr(tube_net, '_compiled_field', lambda: tube_net.tube_field)
    with pytest.warns(UserWarning, match='no native bfloat16.*--no-encoder-bf16 '
                                         '--no-scene-nets-bf16 trains in float32'):
        assert cli(args + ['--reader-steps', '2', '--head-steps', '3', '--head-batch', '8',
                           '--scene-batch', '2', '--encoder-bf16', '--scene-nets-bf16',
                           '--compile-renderer']) == 0
    assert len(checked) == 2                # up front, and at the full phase (it draws)
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (out['reader_steps'], out['keypoint_steps'], out['head_steps']) == (2, 3, 3)
    work = tmp_path / 'work'
    chain = [load_checkpoint(work / f)[1]['training'] for f in (
        'tube_keypoints_reader', 'tube_keypoints', 'tube_keypoints_heads')]
    assert [c['loss'] for c in chain] == ['scene', 'keypoints', 'keypoints']
    assert [c['freeze_scene'] for c in chain] == [False, False, True]
    assert [c['warmup'] for c in chain] == [0.3, 0.0, 0.0]       # the reader's warm-up
    assert chain[2]['batch_size'] == 8
    assert [c['init_from'] for c in chain[1:]] == [str(work / 'tube_keypoints_reader'),
                                                   str(work / 'tube_keypoints')]
    _, cfg = load_checkpoint(tmp_path / 'ck')
    assert cfg['training']['init_from'] == str(work / 'tube_keypoints_heads')
    # --scene-batch is the full phase's alone: whole placements, each encoded once a batch.
    assert [c['scene_batch'] for c in chain] == [0, 16, 0]
    assert cfg['training']['scene_batch'] == 2
    # --encoder-bf16: every phase's steps (the heads' frozen codes are made in float32).
    assert [c['encoder_bf16'] for c in chain] == [True] * 3
    assert cfg['training']['encoder_bf16'] and out['settings']['encoder_bf16']
    assert cfg['training']['scene_nets_bf16'] and out['settings']['scene_nets_bf16']
    assert cfg['training']['compile_renderer'] and out['settings']['compile_renderer']
    assert [c['compile_renderer'] for c in chain] == [True] * 3
    assert [c['fused_adam'] for c in chain] == [True] * 3 and cfg['training']['fused_adam']
    # A machine where it cannot compile: refused before simulating, the way out named.

    def cannot():
        raise RuntimeError('torch.compile could not build the renderer here (...)')
    monkeypatch.setattr(train_module, 'check_renderer_compiles', cannot)
    assert cli(args + ['--compile-renderer', '--work', str(tmp_path / 'work2')]) != 0
    assert ('compile_renderer: torch.compile could not build the renderer here (...). The same '
            'training without it: --no-compile-renderer') in capsys.readouterr().err
    assert not (tmp_path / 'work2').exists()
