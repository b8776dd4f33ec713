"""
Training: Adam, batch 256, held-out validation, early stopping, seeded, DDP-ready.

Run as one process or under ``torchrun --nproc_per_node N`` with no change: the global
batch is split across ranks (same seeded order on every rank), DDP averages gradients
(gloo on CPU, NCCL on GPUs), validation error is summed over ranks, so every rank takes
the same early-stopping decision and ends with the same weights. Rank 0 writes the
checkpoint. ``TrainConfig.init`` starts from a checkpoint's weights instead (fine-tuning a
model pre-trained on simulation on recorded bags).
"""

from __future__ import annotations

import copy
import hashlib
import math
import os
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from tqdm import tqdm

from softshape_ros.data import load_dataset
from softshape_ros.model import data as model_data
from softshape_ros.model import layers, losses, networks, tube_net, tube_render
from softshape_ros.model.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from softshape_ros.model.data import (
    scene_targets, shape_tensors, split_indices, to_float, to_tensors)
from softshape_ros.model.losses import ImageLoss, PixelLoss, TubeLoss
from softshape_ros.model.metrics import RobotSilhouette
from softshape_ros.model.networks import build_network
from softshape_ros.model.tube_net import (
    TubeNet, check_renderer_compiles, compiled_renderer, encoder_bf16, rest_template,
    scene_nets_bf16, scenes_shared)


# Adam learning rates, each network's best on the simulated stereo sets of the design
# studies (docs/model.md), so the comparison is fair.
DEFAULT_LR = {'paper': 1e-3, 'ours': 4e-3, 'tube': 2e-3}
# The paper trains on MSE; so does ours (the silhouette term and Huber lost at a fixed
# budget, docs/model.md); the tube model on keypoints and images (losses.TubeLoss).
DEFAULT_LOSS = {'paper': 'mse', 'ours': 'mse', 'tube': 'tube'}


def code_stamp() -> str:
    """Hash of the network, data and training code: results of other code are never reused."""
    files = (networks.__file__, layers.__file__, tube_net.__file__, tube_render.__file__,
             model_data.__file__, losses.__file__, __file__,
             *(Path(model_data.__file__).parents[1] / f for f in (
                 'sim/object_depth.py', 'experiments/object_depths.py')))
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
    loss: str | None = None         # None: the architecture's default (DEFAULT_LOSS)
    silhouette_weight: float = 0.05
    max_steps: int = 600
    min_steps: int = 0               # never stop early before this many steps
    eval_every: int = 10             # steps between validations (early stopping rounds)
    patience: int = 8                # rounds without improvement before stopping
    threads: int = 0                 # torch threads per process (0 = leave as is)
    init: str | None = None          # checkpoint to start from (fine-tuning); None: seeded
    # > 0: every batch is this many whole placements, all their training rows, instead of
    # batch_size rows. The tube model encodes each placement's rest images once per batch,
    # so its keypoint phase sees ten actuations for the cost of about one (docs/model.md).
    scene_batch: int = 0
    # tube, keypoint loss: the scene encoder frozen, each placement encoded once before the
    # steps, which then train only the keypoint heads (MLPs: fast, so many more rows a
    # second; docs/model.md, "A reader first").
    freeze_scene: bool = False
    # Share of max_steps over which the rate rises linearly to lr before its cosine (0: none).
    warmup: float = 0.0
    # tube: the scene encoder's convolutions in bfloat16 during training steps (autocast;
    # validation and the checkpoint's use stay float32): a reader step in about 0.6 of the
    # time on a CPU with AVX-512 BF16 (docs/model.md, "The encoder in bfloat16").
    encoder_bf16: bool = False
    # tube, full loss: ObjectNet's and BackgroundNet's convolutions in bfloat16 too (but for
    # their heads; docs/model.md, "The scene nets in bfloat16").
    scene_nets_bf16: bool = False
    # tube, full loss: the renderer's field compiled (torch.compile; needs a C++ compiler)
    # in training steps, fused where it made some thirty passes through memory
    # (docs/model.md, "A compiled renderer").
    compile_renderer: bool = False
    # Adam's update as one fused kernel over all parameters (torch.optim.Adam(fused=True)),
    # not a loop of about ten small operations per tensor: the same rule, rounded
    # differently; a tube keypoint step in about 0.85 of the time (docs/model.md, "The 30
    # minutes").
    fused_adam: bool = False
    arch_params: dict = field(default_factory=dict)

    def __post_init__(self):
        # Here, not in train(): a recipe that simulates its data first fails before that.
        if not 0.0 < self.val_fraction < 1.0:
            raise ValueError(f'val_fraction {self.val_fraction}: the held-out share of the '
                             'rows or placements, in (0, 1)')


@dataclass
class TrainResult:
    """The trained (best-validation) model and what happened."""

    model: torch.nn.Module
    config: dict
    history: list
    best_val_mse: float | None      # None: a keypoint-only objective (nothing drawn)
    copy_val_mse: float
    steps: int
    rows_seen: int = 0              # training rows over all steps (placement batches vary)

    @property
    def val_rmse_255(self) -> float | None:
        """Return the best validation RMSE on the 0-255 scale (None: nothing drawn)."""
        return None if self.best_val_mse is None else 255 * self.best_val_mse ** 0.5

    @property
    def copy_val_rmse_255(self) -> float:
        """Return the RMSE of copying the initial images, on the 0-255 scale."""
        return 255 * self.copy_val_mse ** 0.5


@dataclass
class Rows:
    """One rank's training rows and validation slice, as uint8 / float tensors."""

    train_idx: np.ndarray
    val_idx: np.ndarray
    train: tuple            # (initial uint8, target uint8, pressure float) N x VC x S x S
    val: tuple
    # (keypoints N x V x K x 4, free N bool, scene N x 17, object depths: data.ObjectDepths
    # for a depth_test model), each None where not recorded
    train_shape: tuple = (None, None, None, None)
    val_shape: tuple = (None, None, None, None)
    train_scene: np.ndarray | None = None   # N placement ids of the training rows, in order


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


def _batches(n: int, batch: int, world: int, gen: torch.Generator, scenes=None):
    """
    Global batches of a seeded permutation; a tail too small to share is merged.

    ``scenes`` (N placement ids): ``batch`` whole placements per batch, in a seeded order.
    """
    if scenes is None:
        perm = torch.randperm(n, generator=gen)
        out = [perm[i:i + batch] for i in range(0, n, batch)]
    else:
        ids = np.asarray(scenes)
        order = np.argsort(ids, kind='stable')                       # rows by placement
        groups = [torch.from_numpy(g) for g in
                  np.split(order, np.flatnonzero(np.diff(ids[order])) + 1)]
        perm = torch.randperm(len(groups), generator=gen).tolist()
        out = [torch.cat([groups[g] for g in perm[i:i + batch]])
               for i in range(0, len(perm), batch)]
    if len(out) > 1 and len(out[-1]) < world:
        out[-2] = torch.cat([out[-2], out.pop()])
    return out


def _all_sum(world: int, *vals) -> list:
    t = torch.tensor(vals, dtype=torch.float64)
    if world > 1:
        dist.all_reduce(t)
    return t.tolist()


def renderer_compiles() -> None:
    """Raise ValueError, naming the way out, where ``compile_renderer`` cannot work."""
    try:
        check_renderer_compiles()
    except RuntimeError as e:
        raise ValueError(f'compile_renderer: {e}. The same training without it: '
                         '--no-compile-renderer (softshape pretrain), or leave out '
                         '--compile-renderer (softshape train)') from e


def train(dataset, config: TrainConfig, out=None, indices=None, progress: bool = True,
          desc: str = 'train', object_depths=None) -> TrainResult:
    """
    Train on ``dataset`` (a path or loaded Dataset), rows ``indices`` (default all).

    The rows are split ``config.split`` into train/validation; the best-validation
    weights are kept, and written to ``out`` (a checkpoint folder) if given.
    ``object_depths(ds, idx) -> data.ObjectDepths | None``: a depth-test tube model's
    object targets (:func:`softshape_ros.experiments.object_depths.object_depths`; None:
    its ObjectNet learns from the images alone).
    """
    rank, world, started = _dist()
    try:
        return _train(dataset, config, out, indices, progress and rank == 0, desc, rank, world,
                      object_depths)
    finally:
        if started:
            dist.destroy_process_group()


#: Rows a batch of the heads phase (:func:`train_in_phases`): the heads alone are cheap.
HEAD_BATCH = 128
#: The reader phase's warm-up (a share of its steps, :func:`_rate`).
READER_WARMUP = 0.3


def train_in_phases(dataset, config: TrainConfig, keypoint_steps: int, first, out=None,
                    keypoint_scene_batch: int = 0, indices=None, progress: bool = True,
                    desc: str = 'train', reader_steps: int = 0, head_steps: int = 0,
                    head_batch: int = HEAD_BATCH, phase_val_fraction: float | None = None,
                    object_depths=None) -> tuple[dict, TrainResult]:
    """
    Train the tube model's recipe: up to three phases that draw nothing, then ``config``.

    1. ``reader_steps`` of the scene term alone (``loss='scene'``, the rate warmed up over
       :data:`READER_WARMUP` of them): the encoder learns to read the placement before
       anything reads its code.
    2. ``keypoint_steps`` of the keypoint and scene terms (``keypoint_scene_batch`` whole
       placements a batch): what the keypoint phase has always been.
    3. ``head_steps`` of the keypoint heads alone on the frozen encoder's codes
       (``freeze_scene``), ``head_batch`` rows a batch.

    Then ``config``'s loss from the last of them. A phase of 0 steps is skipped; each
    starts from the one before and is written to its own folder: the keypoint phase to
    ``first``, the others beside it (``first`` + ``_reader``, ``_heads``). Returns the
    earlier phases' results by name (``reader``, ``keypoints``, ``heads``) and the last one.
    ``phase_val_fraction``: the held-out share of the phases before the last (None:
    ``config``'s); the split being seeded, a smaller last share holds out a subset of theirs.
    ``object_depths``: as :func:`train` (only the last phase draws).
    """
    plan = (('reader', reader_steps, {'loss': 'scene', 'scene_batch': 0,
                                      'warmup': READER_WARMUP}),
            ('keypoints', keypoint_steps, {'loss': 'keypoints',
                                           'scene_batch': keypoint_scene_batch}),
            ('heads', head_steps, {'loss': 'keypoints', 'freeze_scene': True,
                                   'batch_size': head_batch, 'scene_batch': 0}))
    done = {}
    early = {} if phase_val_fraction is None else {'val_fraction': phase_val_fraction}
    for name, steps, change in plan:
        if not steps:
            continue
        change = {**early, **change}
        folder = Path(first) if name == 'keypoints' else Path(f'{first}_{name}')
        done[name] = train(dataset, replace(config, max_steps=steps, **change), out=folder,
                           indices=indices, progress=progress, desc=f'{desc} {name}')
        config = replace(config, init=str(folder))
    return done, train(dataset, config, out=out, indices=indices, progress=progress, desc=desc,
                       object_depths=object_depths)


def _train(dataset, config, out, indices, progress, desc, rank, world,
           object_depths=None) -> TrainResult:
    ds = load_dataset(dataset) if isinstance(dataset, (str, os.PathLike)) else dataset
    if config.threads:
        torch.set_num_threads(config.threads)
    if config.batch_size < world:
        raise ValueError(f'batch size {config.batch_size} < {world} processes')
    if not 0.0 <= config.warmup < 1.0:
        raise ValueError(f'warmup {config.warmup} is a share of the steps in [0, 1)')
    if config.scene_batch < 0:
        raise ValueError(f'scene_batch {config.scene_batch} < 0')
    rows = _rows(ds, config, indices, rank, world)
    sil = RobotSilhouette.fit(rows.train[0][:2000].numpy().reshape(
        -1, len(ds.views), ds.channels, *rows.train[0].shape[-2:]))
    net, arch_params, init_from = _network(ds, config, rows, sil)
    loss_kind = config.loss or DEFAULT_LOSS.get(config.arch, 'mse')
    if loss_kind in ('tube', 'keypoints', 'scene'):
        if not isinstance(net, TubeNet):
            raise ValueError(f'the {loss_kind} loss trains tube, not {config.arch!r}')
        objective = TubeLoss(keypoints_only=loss_kind == 'keypoints',
                             scene_only=loss_kind == 'scene',
                             threshold=sil.threshold / 255, channels=ds.channels)
    else:
        objective = PixelLoss(ImageLoss(loss_kind, ds.channels, sil.threshold / 255,
                                        config.silhouette_weight))
    for flag, what in (('encoder_bf16', 'scene encoder'),
                       ('scene_nets_bf16', 'ObjectNet and BackgroundNet'),
                       ('compile_renderer', 'renderer')):
        if getattr(config, flag) and not isinstance(net, TubeNet):
            raise ValueError(f'{flag} trains the tube model\'s {what}; '
                             f'{config.arch!r} has none')
    if config.compile_renderer and _draws(objective):
        renderer_compiles()
    if config.freeze_scene and loss_kind != 'keypoints':
        raise ValueError(f'freeze_scene trains the tube keypoint heads on the keypoint loss, '
                         f'not {config.arch!r} on {loss_kind!r}')
    lr = _learning_rate(config)
    copy_mse = _copy_mse(rows, world)
    if getattr(net, 'depth_test', False) and _draws(objective) and object_depths is not None:
        rows = _with_object_depths(ds, rows, rank, world, progress, object_depths)
    if config.freeze_scene:
        rows = _encoded(net, rows)
    fit = _fit(net, rows, objective, config, lr, rank, world, progress, desc, copy_mse)
    net.load_state_dict(fit['best_state'])
    net.eval()
    cfg = {
        'arch': config.arch,
        'arch_params': arch_params,
        'views': ds.views,
        'channels': ds.channels,
        'image_size': int(ds.meta.get('image_size', 64)),
        'max_pressure_pa': [float(v) for v in ds.max_pressure_pa],
        'normalisation': {'image': 'uint8 / 255, views stacked as channels',
                          'pressure': 'Pa / max_pressure_pa, clamped to [0, max]'},
        'silhouette': sil.to_json(),
        'dataset': {'path': str(ds.path), 'count': len(ds), 'rows_used': int(
                        len(rows.train_idx) + len(rows.val_idx)),
                    'train': int(len(rows.train_idx)), 'val': int(len(rows.val_idx)),
                    'val_rows': [int(i) for i in rows.val_idx],
                    'provenance': ds.meta.get('provenance'),
                    'touching_share': ds.meta.get('touching_share'),
                    'shape_record': getattr(ds, 'shape', None) is not None},
        'training': dict(asdict(config), lr=lr, loss=loss_kind, world_size=world,
                         steps=fit['steps'], best_val_mse=fit['best_mse'],
                         best_val_loss=fit['best_loss'], copy_val_mse=fit['copy_mse'],
                         init_from=init_from),
    }
    if out is not None and rank == 0:
        save_checkpoint(out, net, cfg)
    if world > 1:
        dist.barrier()
    return TrainResult(net, cfg, fit['history'], fit['best_mse'], fit['copy_mse'],
                       fit['steps'], fit['rows_seen'])


def _rows(ds, config, indices, rank, world) -> Rows:
    """Split the rows into train / validation and load them; each rank validates a slice."""
    idx = np.arange(len(ds)) if indices is None else np.asarray(indices)
    tr_idx, va_idx = split_indices(ds.scene, idx, config.split, config.val_fraction,
                                   config.seed)
    if len(tr_idx) < world or len(va_idx) < 1:
        raise ValueError(f'too few samples to train: {len(tr_idx)} train, {len(va_idx)} val')
    maxp = ds.max_pressure_pa
    val = to_tensors(ds, va_idx, maxp, as_uint8=True)
    vs = slice(rank * len(va_idx) // world, (rank + 1) * len(va_idx) // world)
    val_shape = tuple(None if t is None else t[vs] for t in (
        *shape_tensors(ds, va_idx), scene_targets(ds, va_idx)))
    return Rows(tr_idx, va_idx, to_tensors(ds, tr_idx, maxp, as_uint8=True),
                tuple(t[vs] for t in val),
                (*shape_tensors(ds, tr_idx), scene_targets(ds, tr_idx), None),
                (*val_shape, None), np.asarray(ds.scene)[np.sort(tr_idx)])


def _with_object_depths(ds, rows, rank, world, progress, object_depths) -> Rows:
    """
    Add the rows' object depth maps (a depth_test model's ObjectNet learns them).

    Cast once for training and validation rows together: under a random split they share
    placements, and each placement's map is cast once.
    """
    every = np.sort(np.concatenate([rows.train_idx, rows.val_idx]))
    maps = object_depths(ds, every, progress=progress and rank == 0)
    if maps is None:
        return rows

    def at(idx):                    # positions of rows ``idx`` (sorted) among ``every``
        return torch.from_numpy(np.searchsorted(every, np.sort(idx)))

    vs = slice(rank * len(rows.val_idx) // world, (rank + 1) * len(rows.val_idx) // world)
    return replace(rows, train_shape=(*rows.train_shape[:3], maps.rows(at(rows.train_idx))),
                   val_shape=(*rows.val_shape[:3], maps.rows(at(rows.val_idx)[vs])))


def _network(ds, config, rows, sil):
    """Return (network, its arch_params, the checkpoint it starts from or None)."""
    torch.manual_seed(config.seed)
    if config.init is None:
        params = dict(config.arch_params)
        if params.get('members', 1) != 1:
            raise ValueError(f'members {params["members"]}: an ensemble is made of trained '
                             'checkpoints (softshape ensemble), not trained as one')
        truth = rows.train_shape[0]
        if config.arch == 'tube':
            params.setdefault('scene_visibility', True)
            if truth is not None:
                params.setdefault('keypoints', int(truth.shape[2]))
        net = build_network(config.arch, len(ds.views), ds.channels, **params)
        if isinstance(net, TubeNet):
            # The heads start from the mean shape of the record, else the resting robot.
            with torch.no_grad():
                net.set_template(truth.mean(0) if truth is not None else rest_template(
                    rows.train[0][:256].numpy(), sil, len(ds.views), net.keypoints.k))
                net.keypoints.scene.set_stats(to_float(rows.train[0][:2000]),
                                              rows.train_shape[2])
        return net, params, None
    net, cfg = load_checkpoint(config.init)
    if cfg['arch_params'].get('members', 1) > 1 and config.freeze_scene:
        # Fine-tuned whole, an ensemble trains its members through their mean; the heads
        # on one frozen encoder's codes would leave the other members' unread.
        raise CheckpointError(f'{config.init}: an ensemble of {cfg["arch_params"]["members"]} '
                              'trainings: each member has its own scene encoder, so its heads '
                              'do not train on frozen codes (freeze_scene)')
    want = {'arch': config.arch, 'views': ds.views, 'channels': ds.channels,
            'image_size': int(ds.meta.get('image_size', 64)),
            'max_pressure_pa': [float(v) for v in ds.max_pressure_pa]}
    bad = [f'{k} {cfg[k]!r} (dataset/config: {v!r})' for k, v in want.items()
           if (cfg[k] != v if k != 'max_pressure_pa'
               else not np.allclose(cfg[k], v, rtol=1e-6))]
    # The checkpoint's architecture is what it is: parameters asked for must agree with it.
    bad += [f'arch_params {k}={cfg["arch_params"].get(k)!r} (config: {v!r})'
            for k, v in config.arch_params.items() if cfg['arch_params'].get(k) != v]
    if bad:
        raise CheckpointError(f'{config.init}: cannot fine-tune on {ds.path}: the checkpoint '
                              f'has {"; ".join(bad)}')
    net.train()
    return net, dict(cfg['arch_params']), str(config.init)


def _learning_rate(config) -> float:
    if config.lr is None and config.arch not in DEFAULT_LR:
        raise ValueError(f'no default learning rate for architecture {config.arch!r}: give lr')
    lr = DEFAULT_LR[config.arch] if config.lr is None else config.lr
    if not (lr > 0 and math.isfinite(lr)):
        raise ValueError(f'learning rate must be a positive number, got {lr}')
    return lr


def _take(extra, idx):
    """Rows ``idx`` of the optional (keypoints, free, scene, object depths) tensors."""
    return tuple(None if t is None else t[idx] for t in extra)


def _draws(objective) -> bool:
    """Whether ``objective`` draws images (keypoint- or scene-only ones do not: no image error)."""
    return not (getattr(objective, 'keypoints_only', False)
                or getattr(objective, 'scene_only', False))


def _rate(step: int, config) -> float:
    """
    Return the learning rate's factor at ``step``: a cosine from 1 to 0 over ``max_steps``.

    With ``warmup`` (a share of the steps): a linear rise from 1/25 over those steps, then
    the cosine over the rest (the shape of a one-cycle rate; the reader phase reads the
    placement to 0.73 mm in x without it, 0.50 with it: docs/model.md, "A reader first").
    """
    n = config.max_steps
    w = int(round(config.warmup * n))
    if step < w:
        return 0.04 + 0.96 * step / w
    return 0.5 * (1 + math.cos(math.pi * min(step - w, n - w) / max(n - w, 1)))


def _copy_mse(rows, world: int) -> float:
    """Return the validation MSE of copying the initial images (all ranks' slices)."""
    xv, tv, _ = rows.val
    copy_sse, n_pix = _all_sum(world, float(((to_float(xv) - to_float(tv)) ** 2).sum()),
                               tv.numel())
    return copy_sse / n_pix


def _encoded(net, rows, chunk: int = 512):
    """
    Return ``rows`` with each rest image replaced by its scene code (N x code), encoder frozen.

    Each distinct rest image (a placement) is encoded once; the steps then run the keypoint
    heads alone, about 10 ms a batch of 128 rows where encoding them cost 20 times that.
    """
    enc = net.keypoints.scene
    enc.requires_grad_(False)

    def codes(x8):
        unique, inverse = torch.unique(x8.flatten(1), dim=0, return_inverse=True)
        with torch.no_grad():
            z = torch.cat([enc(to_float(unique[i:i + chunk].view(-1, *x8.shape[1:])))[0]
                           for i in range(0, len(unique), chunk)])
        return z[inverse]                                             # N x code

    return replace(rows, train=(codes(rows.train[0]), *rows.train[1:]),
                   val=(codes(rows.val[0]), *rows.val[1:]))


def _validate(net, val, extra, objective, chunk=256):
    """
    Return (sum of squared errors, sum of per-chunk losses x rows) over the val slice.

    A keypoint-only objective draws nothing, and nothing is drawn for it here either: the
    squared error is then 0 (``_fit`` reports no ``val_mse``); drawing every validation row
    cost more than the keypoint steps between two validations.
    """
    x8, t8, p = val
    sse = loss = 0.0
    with torch.no_grad(), scenes_shared():       # a placement's rows: its scene parts once
        for i in range(0, len(x8), chunk):
            x, t = to_float(x8[i:i + chunk]), to_float(t8[i:i + chunk])
            lo, y = objective(net, x, p[i:i + chunk], t, *_take(extra, slice(i, i + chunk)))
            if y is not None:
                sse += float(((y - t) ** 2).sum())
            loss += float(lo) * len(x)
    return sse, loss


def _fit(net, rows, objective, config, lr, rank, world, progress, desc, copy_mse) -> dict:
    """Run the optimisation: seeded batches, validation rounds, early stopping."""
    # The keypoint phase of the tube model leaves its drawing parts without gradients, and
    # data without recorded placements its scene description.
    unused = isinstance(objective, TubeLoss)
    model = (torch.nn.parallel.DistributedDataParallel(net, find_unused_parameters=unused)
             if world > 1 else net)
    opt = torch.optim.Adam(net.parameters(), lr=lr, fused=config.fused_adam or None)  # None: loop
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: _rate(s, config))
    gen = torch.Generator().manual_seed(config.seed)
    xt, tt, pt = rows.train
    xv, tv, _ = rows.val
    n_pix, n_val = _all_sum(world, tv.numel(), len(tv))
    draws = _draws(objective)       # else no image error (val_mse None)
    best, best_mse, best_state, bad, step, history = math.inf, math.inf, None, 0, 0, []
    if not draws:
        best_mse = None
    if config.init is not None:     # fine-tuning never ends worse than where it started
        net.eval()
        sse, vloss = _all_sum(world, *(_validate(net, rows.val, rows.val_shape, objective)
                                       if len(xv) else (0.0, 0.0)))
        best, best_mse = vloss / n_val, sse / n_pix if draws else None
        best_state = copy.deepcopy(net.state_dict())
        history.append({'step': 0, 'train_loss': None, 'val_loss': best, 'val_mse': best_mse})
    bar = tqdm(total=config.max_steps, desc=desc, disable=not progress, leave=False,
               dynamic_ncols=True)
    run_loss, run_n, seen = 0.0, 0, 0
    while True:
        for gb in _batches(len(xt), config.scene_batch or config.batch_size, world, gen,
                           rows.train_scene if config.scene_batch else None):
            b = gb[rank * len(gb) // world:(rank + 1) * len(gb) // world]
            net.train()
            with (encoder_bf16(config.encoder_bf16), scene_nets_bf16(config.scene_nets_bf16),
                  compiled_renderer(config.compile_renderer)):
                loss, _ = objective(model, to_float(xt[b]), pt[b], to_float(tt[b]),
                                    *_take(rows.train_shape, b))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            step, seen = step + 1, seen + len(gb)
            run_loss, run_n = run_loss + float(loss.detach()), run_n + 1
            bar.update(1)
            if step % config.eval_every and step < config.max_steps:
                continue
            net.eval()
            sse, vloss = _all_sum(world, *(_validate(net, rows.val, rows.val_shape, objective)
                                           if len(xv) else (0.0, 0.0)))
            val, vloss = sse / n_pix if draws else None, vloss / n_val
            (tl,) = _all_sum(world, run_loss / run_n)
            history.append({'step': step, 'train_loss': tl / world, 'val_loss': vloss,
                            'val_mse': val})
            run_loss, run_n = 0.0, 0
            if vloss < best:
                best, best_mse, bad = vloss, val, 0
                best_state = copy.deepcopy(net.state_dict())
            else:
                bad += 1
            bar.set_postfix(train=f'{tl / world:.5f}', val=f'{vloss:.5f}',
                            mse='-' if val is None else f'{val:.5f}', copy=f'{copy_mse:.5f}')
            if step >= config.max_steps or (bad >= config.patience
                                            and step >= config.min_steps):
                bar.close()
                return {'best_state': best_state, 'best_loss': best, 'best_mse': best_mse,
                        'copy_mse': copy_mse, 'steps': step, 'rows_seen': seen,
                        'history': history}
