"""DDP: the training code under torchrun with 2 CPU processes (gloo) ends with equal weights."""

import json
import os
import subprocess
import sys
from pathlib import Path

import torch
from safetensors.torch import load_file

from softshape_ros.model import build_network, load_checkpoint
from softshape_ros.model.synthetic import make_dataset
from softshape_ros.model.train import TrainConfig, train

TORCHRUN = Path(sys.executable).with_name('torchrun')

SCRIPT = '''
import os, sys
from safetensors.torch import save_file
from softshape_ros.model.train import TrainConfig, train
cfg = TrainConfig(arch='ours', batch_size=16, max_steps=12, eval_every=4, threads=1, seed=2,
                  lr=1e-3)
res = train(sys.argv[1], cfg, out=sys.argv[2], progress=False)
sd = {k: v.contiguous() for k, v in res.model.state_dict().items()}
save_file(sd, os.path.join(sys.argv[3], 'rank%s.safetensors' % os.environ['RANK']))
'''


def test_ddp_two_processes_end_with_identical_weights(tmp_path):
    ds = make_dataset(tmp_path / 'ds', 60, 4, views=('main', 'side'), seed=4)
    script = tmp_path / 'ddp_train.py'
    script.write_text(SCRIPT)
    env = dict(os.environ, OMP_NUM_THREADS='1')
    proc = subprocess.run(
        [str(TORCHRUN), '--standalone', '--nnodes', '1', '--nproc_per_node', '2',
         str(script), str(ds.path), str(tmp_path / 'ckpt'), str(tmp_path)],
        env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r0 = load_file(str(tmp_path / 'rank0.safetensors'))
    r1 = load_file(str(tmp_path / 'rank1.safetensors'))
    assert r0.keys() == r1.keys()
    assert all(torch.equal(r0[k], r1[k]) for k in r0)
    model, cfg = load_checkpoint(tmp_path / 'ckpt')
    assert cfg['training']['world_size'] == 2
    assert all(torch.equal(model.state_dict()[k], r0[k]) for k in r0)
    # Splitting each global batch over two ranks is the same optimisation as one process
    # taking the whole batch, up to float summation order (which Adam can amplify for
    # near-zero gradients by at most ~lr per step: the rate is fixed, not the default).
    single = train(ds, TrainConfig(arch='ours', batch_size=16, max_steps=12, eval_every=4,
                                   threads=1, seed=2, lr=1e-3), progress=False)
    sd = single.model.state_dict()
    worst = max(float((sd[k] - r0[k]).abs().max()) for k in r0)
    print('largest weight difference DDP vs one process:', worst)
    assert worst < 1e-5, worst
    assert json.loads((tmp_path / 'ckpt' / 'config.json').read_text())['training']['steps'] == 12
    # ... and it did train: the weights moved from their seeded start.
    torch.manual_seed(2)
    start = build_network('ours', 2, 1).state_dict()
    assert max(float((start[k] - r0[k]).abs().max()) for k in r0) > 1e-3


def test_softshape_train_cli_runs_unchanged_under_torchrun(tmp_path):
    ds = make_dataset(tmp_path / 'ds', 40, 4, views=('main',), seed=5)
    softshape = Path(sys.executable).with_name('softshape')
    proc = subprocess.run(
        [str(TORCHRUN), '--standalone', '--nnodes', '1', '--nproc_per_node', '2',
         str(softshape), 'train', '--dataset', str(ds.path), '--out', str(tmp_path / 'ck'),
         '--max-steps', '4', '--eval-every', '2', '--batch-size', '8', '--threads', '1',
         '--quiet'],
        env=dict(os.environ, OMP_NUM_THREADS='1'), capture_output=True, text=True,
        timeout=240)
    # On a failure: what the ranks said before the launcher's traceback (the start of stderr)
    assert proc.returncode == 0, (f'stdout:\n{proc.stdout[-2000:]}\nstderr start:\n'
                                  f'{proc.stderr[:3000]}\nstderr end:\n{proc.stderr[-1500:]}')
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith('{')]
    assert len(lines) == 1                      # rank 0 reports, rank 1 stays quiet
    assert json.loads(lines[0])['steps'] == 4
    _, cfg = load_checkpoint(tmp_path / 'ck')
    assert cfg['training']['world_size'] == 2
