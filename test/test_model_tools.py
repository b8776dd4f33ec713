"""The forward model's tools: metrics, `softshape train/evaluate/export`, ONNX parity."""

import json

import numpy as np
import pytest
import torch

from softshape_ros.cli import main as cli
from softshape_ros.model import build_network, save_checkpoint
from softshape_ros.model.export import export_onnx, run_onnx
from softshape_ros.model.metrics import (RobotSilhouette, changed_mask, evaluate_arrays, rmse,
                                         yellow_mask)
from softshape_ros.model.synthetic import make_dataset, make_samples


def test_metrics_on_known_images():
    a = np.zeros((1, 1, 3, 4, 4), np.uint8)
    b = a.copy()
    b[0, 0, :, 0, 0] = 30                # one pixel off by 30 in all channels
    b[0, 0, 0, 1, 1] = 30                # one pixel off in one channel only
    assert rmse(a, b) == pytest.approx(np.sqrt((3 * 900 + 900) / 48))
    assert yellow_mask(a, b).sum() == 1  # the paper's mask needs every channel off
    assert changed_mask(a, b).sum() == 2
    assert rmse(a, b, changed_mask(a, b)) == pytest.approx(np.sqrt(4 * 900 / 6))


def test_silhouette_iou_and_tip_separate_good_from_copy():
    initial, target, _, _ = make_samples(40, 5, views=('main', 'side'), seed=2)
    sil = RobotSilhouette.fit(initial)
    perfect = evaluate_arrays(initial, target, target, sil)['model']
    copy = evaluate_arrays(initial, target, initial, sil)['copy']
    assert perfect['rmse'] == 0 and perfect['silhouette_iou'] == 1.0
    assert perfect['tip_error_px'] == 0 and perfect['tip_missing'] == 0
    assert copy['silhouette_iou'] < 0.6 and copy['tip_error_px'] > 5
    # The base is at the top of the image where the rod hangs from.
    assert np.all(sil.base_rc[:, 0] < 10) and np.all(np.abs(sil.base_rc[:, 1] - 32) < 3)


@pytest.mark.parametrize('arch, params', [
    ('paper', {}), ('ours', {}), ('tube', {'scene_visibility': True}),   # what training builds
    # ... and what pretrain ships: an ensemble of depth-tested members (its graph holds the
    # single depth-tested network's, so that one is not exported on its own: 10 s each)
    ('tube', {'scene_visibility': True, 'depth_test': True, 'members': 2})])
def test_onnx_export_matches_pytorch(arch, params, tmp_path):
    torch.manual_seed(1)
    net = build_network(arch, 2, 3, **params)
    with torch.no_grad():                # ours starts as the identity: make it non-trivial
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    ck = save_checkpoint(tmp_path / arch, net, {
        'arch': arch, 'arch_params': params, 'views': ['main', 'side'], 'channels': 3,
        'image_size': 64, 'max_pressure_pa': [1e5] * 6})
    info = export_onnx(ck, tmp_path / f'{arch}.onnx', batch=3)
    assert info['max_abs_diff'] <= 1e-4
    # Dynamic batch: another batch size through the exported graph still matches.
    x, p = torch.rand(5, 6, 64, 64), torch.rand(5, 6)
    with torch.no_grad():
        ref = net(x, p).numpy()
    got = run_onnx(tmp_path / f'{arch}.onnx', x.numpy(), p.numpy())
    assert got.shape == ref.shape
    assert np.abs(got - ref).max() <= 1e-4
    assert np.abs(ref - x.numpy()).max() > 1e-2     # the check compares a real mapping


def test_cli_train_evaluate_export(tmp_path, capsys):
    ds = make_dataset(tmp_path / 'ds', 60, 6, views=('main', 'side'), seed=7)
    ck = tmp_path / 'ck'
    assert cli(['train', '--dataset', str(ds.path), '--out', str(ck), '--arch', 'ours',
                '--split', 'scene', '--val-fraction', '0.5', '--batch-size', '16',
                '--max-steps', '20', '--eval-every', '5', '--threads', '1', '--quiet',
                '--fused-adam']) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary['steps'] <= 20 and summary['val_rmse_255'] > 0
    assert json.loads((ck / 'config.json').read_text())['training']['fused_adam'] is True
    with pytest.raises(SystemExit, match='--outline is a tube model option'):
        cli(['train', '--dataset', str(ds.path), '--out', str(ck), '--arch', 'ours',
             '--outline'])
    assert cli(['train', '--dataset', str(ds.path), '--out', str(tmp_path / 'no'), '--arch',
                'ours', '--encoder-bf16', '--max-steps', '1']) == 2
    assert "encoder_bf16 trains the tube model's scene encoder; 'ours' has none" in \
        capsys.readouterr().err
    assert cli(['train', '--dataset', str(ds.path), '--out', str(tmp_path / 'no'), '--arch',
                'ours', '--scene-nets-bf16', '--max-steps', '1']) == 2
    assert ("scene_nets_bf16 trains the tube model's ObjectNet and BackgroundNet; 'ours' has "
            "none") in capsys.readouterr().err
    assert cli(['train', '--dataset', str(ds.path), '--out', str(tmp_path / 'no'), '--arch',
                'ours', '--compile-renderer', '--max-steps', '1']) == 2
    assert "compile_renderer trains the tube model's renderer; 'ours' has none" in \
        capsys.readouterr().err
    assert not (tmp_path / 'no').exists()
    assert cli(['evaluate', '--checkpoint', str(ck), '--dataset', str(ds.path),
                '--validation', '--out', str(tmp_path / 'ev')]) == 0
    res = json.loads(capsys.readouterr().out)
    # --val-fraction 0.5: half the six placements (ten rows each) held out.
    assert res['samples'] == 30 and set(res['model']) == set(res['copy'])
    # No contact record in this dataset: unsplit metrics, and metrics.json says why.
    saved = json.loads((tmp_path / 'ev' / 'metrics.json').read_text())
    assert saved['split'].startswith('none') and 'touching' not in saved
    assert {'ssim', 'psnr_db', 'intrusion', 'tip_error_median_px'} <= set(saved['model'])
    assert (tmp_path / 'ev' / 'panels.png').stat().st_size > 1000
    assert cli(['export', '--checkpoint', str(ck), '--out', str(tmp_path / 'm.onnx')]) == 0
    assert json.loads(capsys.readouterr().out)['max_abs_diff'] <= 1e-4
    # A broken checkpoint or a mismatched dataset: one clear line, exit code 2.
    (ck / 'model.safetensors').write_bytes(b'not safetensors')
    assert cli(['evaluate', '--checkpoint', str(ck), '--dataset', str(ds.path)]) == 2
    assert 'model.safetensors' in capsys.readouterr().err
    mono = make_dataset(tmp_path / 'mono', 10, 2, views=('main',), seed=1)
    net = build_network('paper', 2, 1)
    ck2 = save_checkpoint(tmp_path / 'ck2', net, {
        'arch': 'paper', 'arch_params': {}, 'views': ['main', 'side'], 'channels': 1,
        'image_size': 64, 'max_pressure_pa': [1e5] * 6})
    assert cli(['evaluate', '--checkpoint', str(ck2), '--dataset', str(mono.path)]) == 2
    assert 'expects' in capsys.readouterr().err


def test_reproduce_writes_table_and_figures_and_resumes(tmp_path):
    from softshape_ros.model.reproduce import ReproConfig, reproduce
    ds = make_dataset(tmp_path / 'ds', 80, 10, views=('main', 'side'), seed=3)
    cfg = ReproConfig(sizes=[20, 40], max_steps=3, eval_every=3, patience=1, threads=1)
    out = tmp_path / 'repro'
    table = reproduce(ds.path, out, cfg, work=tmp_path / 'work', splits=['random'])
    assert table.count('missing run') == 4           # the scene split was left to another run
    assert len(list((out / 'runs').glob('random_*.json'))) == 8
    table = reproduce(ds.path, out, cfg, work=tmp_path / 'work')
    assert 'missing run' not in table and '| 40 | stereo |' in table
    for f in ('table.md', 'results.json', 'rmse_vs_size.png', 'panels_mono.png',
              'panels_stereo.png'):
        assert (out / f).stat().st_size > 100, f
    res = json.loads((out / 'results.json').read_text())['runs']
    assert len(res) == 16 and res['scene_stereo_ours_40']['test_rows'] > 0
    # Sizes beyond what the split leaves for training are refused, not silently shrunk.
    with pytest.raises(ValueError, match='need more'):
        reproduce(ds.path, out, ReproConfig(sizes=[500]))
