"""
Training: Adam, batch 256, held-out validation, early stopping, seeded, DDP-ready.

Run as one process or under ``torchrun --nproc_per_node N`` with no change: the global
batch is split across ranks (same seeded order on every rank), DDP averages gradients
(gloo on CPU, NCCL on GPUs), validation error is summed over ranks, so every rank takes
the same early-stopping decision and ends with the same weights. Rank 0 writes the
checkpoint.
"""

from __future__ import annotations

import copy
import hashlib
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from tqdm import tqdm

from softshape_ros.data import load_dataset
from softshape_ros.model.checkpoint import save_checkpoint
from softshape_ros.model.data import split_indices, to_tensors
from softshape_ros.model import data as model_data
from softshape_ros.model import networks
from softshape_ros.model.networks import build_network


# Adam learning rates, each network's best of three on the simulated 1000-sample stereo set
# at 300 steps (docs/model.md, "Design study"), so the comparison is fair.
DEFAULT_LR = {'paper': 1e-3, 'ours': 4e-3}


def code_stamp() -> str:
    """Hash of the network, data and training code: results of other code are never reused."""
    files = (networks.__file__, model_data.__file__, __file__)
    return hashlib.sha256(b''.join(Path(f).read_bytes() for f in files)).hexdigest()[:12]


@dataclass
class TrainConfig:
    """What a training run needs; stored in the checkpoint's config.json."""

    arch: str = 'ours'
    seed: int = 0
    split: str = 'random'           # 'random' (paper, 80/20) or 'scene'
    val_fraction: float = 0.2
    batch_size: int = 256
    lr: float | None = None         # None: the architecture's default (DEFAULT_LR)
    max_steps: int = 600
    min_steps: int = 0               # never stop early before this many steps
    eval_every: int = 10             # steps between validations (early stopping rounds)
    patience: int = 8                # rounds without improvement before stopping
    threads: int = 0                 # torch threads per process (0 = leave as is)
    arch_params: dict = field(default_factory=dict)


@dataclass
class TrainResult:
    """The trained (best-validation) model and what happened."""

    model: torch.nn.Module
    config: dict
    history: list
    best_val_mse: float
    copy_val_mse: float
    steps: int


def _dist():
    """(rank, world, started_here): join the torchrun process group if there is one."""
    world = int(os.environ.get('WORLD_SIZE', '1'))
    if world <= 1:
        return 0, 1, False
    if dist.is_initialized():
        return dist.get_rank(), dist.get_world_size(), False
    backend = 'nccl' if torch.cuda.is_available() else 'gloo'
    dist.init_process_group(backend)
    return dist.get_rank(), dist.get_world_size(), True


def _batches(n: int, batch: int, world: int, gen: torch.Generator):
    """Global batches of a seeded permutation; a tail too small to share is merged."""
    perm = torch.randperm(n, generator=gen)
    out = [perm[i:i + batch] for i in range(0, n, batch)]
    if len(out) > 1 and len(out[-1]) < world:
        out[-2] = torch.cat([out[-2], out.pop()])
    return out


def _sse(model, x, t, p, chunk=256) -> float:
    with torch.no_grad():
        return float(sum(((model(x[i:i + chunk], p[i:i + chunk]) - t[i:i + chunk]) ** 2)
                         .sum() for i in range(0, len(x), chunk)))


def train(dataset, config: TrainConfig, out=None, indices=None, progress: bool = True,
          desc: str = 'train') -> TrainResult:
    """
    Train on ``dataset`` (a path or loaded Dataset), rows ``indices`` (default all).

    The rows are split ``config.split`` into train/validation; the best-validation
    weights are kept, and written to ``out`` (a checkpoint folder) if given.
    """
    rank, world, started = _dist()
    try:
        return _train(dataset, config, out, indices, progress and rank == 0, desc, rank, world)
    finally:
        if started:
            dist.destroy_process_group()


def _train(dataset, config, out, indices, progress, desc, rank, world) -> TrainResult:
    ds = load_dataset(dataset) if isinstance(dataset, (str, os.PathLike)) else dataset
    if config.threads:
        torch.set_num_threads(config.threads)
    if config.batch_size < world:
        raise ValueError(f'batch size {config.batch_size} < {world} processes')
    idx = np.arange(len(ds)) if indices is None else np.asarray(indices)
    tr_idx, va_idx = split_indices(ds.scene, idx, config.split, config.val_fraction,
                                   config.seed)
    if len(tr_idx) < world or len(va_idx) < 1:
        raise ValueError(f'too few samples to train: {len(tr_idx)} train, {len(va_idx)} val')
    maxp = ds.max_pressure_pa
    xt, tt, pt = to_tensors(ds, tr_idx, maxp)
    xv, tv, pv = to_tensors(ds, va_idx, maxp)
    # Each rank validates its own slice; sums are all-reduced.
    vs = slice(rank * len(xv) // world, (rank + 1) * len(xv) // world)
    xv, tv, pv = xv[vs], tv[vs], pv[vs]

    torch.manual_seed(config.seed)
    net = build_network(config.arch, len(ds.views), ds.channels, **config.arch_params)
    model = torch.nn.parallel.DistributedDataParallel(net) if world > 1 else net
    if config.lr is None and config.arch not in DEFAULT_LR:
        raise ValueError(f'no default learning rate for architecture {config.arch!r}: give lr')
    lr = DEFAULT_LR[config.arch] if config.lr is None else config.lr
    if not (lr > 0 and math.isfinite(lr)):
        raise ValueError(f'learning rate must be a positive number, got {lr}')
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.5 * (1 + math.cos(math.pi * min(s, config.max_steps)
                                           / config.max_steps)))
    gen = torch.Generator().manual_seed(config.seed)

    def all_sum(*vals):
        t = torch.tensor(vals, dtype=torch.float64)
        if world > 1:
            dist.all_reduce(t)
        return t.tolist()

    nval_pix = tv.numel()
    copy_sse, n_pix = all_sum(float(((xv - tv) ** 2).sum()), nval_pix)
    copy_mse = copy_sse / n_pix
    best, best_state, bad, step, history = math.inf, None, 0, 0, []
    bar = tqdm(total=config.max_steps, desc=desc, disable=not progress, leave=False,
               dynamic_ncols=True)
    run_loss, run_n = 0.0, 0
    stop = False
    while not stop:
        for gb in _batches(len(xt), config.batch_size, world, gen):
            b = gb[rank * len(gb) // world:(rank + 1) * len(gb) // world]
            net.train()
            loss = torch.mean((model(xt[b], pt[b]) - tt[b]) ** 2)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            step += 1
            run_loss, run_n = run_loss + float(loss.detach()), run_n + 1
            bar.update(1)
            if step % config.eval_every == 0 or step >= config.max_steps:
                net.eval()
                (sse,) = all_sum(_sse(net, xv, tv, pv) if len(xv) else 0.0)
                val = sse / n_pix
                (tl,) = all_sum(run_loss / run_n)
                history.append({'step': step, 'train_mse': tl / world, 'val_mse': val})
                run_loss, run_n = 0.0, 0
                if val < best:
                    best, bad = val, 0
                    best_state = copy.deepcopy(net.state_dict())
                else:
                    bad += 1
                bar.set_postfix(train=f'{tl / world:.5f}', val=f'{val:.5f}',
                                copy=f'{copy_mse:.5f}')
                patient = bad >= config.patience and step >= config.min_steps
                if step >= config.max_steps or patient:
                    stop = True
                    break
    bar.close()
    net.load_state_dict(best_state)
    net.eval()
    cfg = {
        'arch': config.arch,
        'arch_params': dict(config.arch_params),
        'views': ds.views,
        'channels': ds.channels,
        'image_size': int(ds.meta.get('image_size', 64)),
        'max_pressure_pa': [float(v) for v in maxp],
        'normalisation': {'image': 'uint8 / 255, views stacked as channels',
                          'pressure': 'Pa / max_pressure_pa, clamped to [0, max]'},
        'dataset': {'path': str(ds.path), 'count': len(ds), 'rows_used': int(len(idx)),
                    'train': int(len(tr_idx)), 'val': int(len(va_idx)),
                    'val_rows': [int(i) for i in va_idx],
                    'provenance': ds.meta.get('provenance')},
        'training': dict(asdict(config), lr=lr, world_size=world, steps=step,
                         best_val_mse=best, copy_val_mse=copy_mse),
    }
    if out is not None and rank == 0:
        save_checkpoint(out, net, cfg)
    if world > 1:
        dist.barrier()
    return TrainResult(net, cfg, history, best, copy_mse, step)
