"""
Pre-training on simulation: simulate a dataset, train a network on it, write the checkpoint.

The demo fine-tunes a shipped result (``models/tube_stereo_gray``) on the bags it records,
so it starts from thousands of simulated interactions instead of its few hundred recorded
ones. One command rebuilds it (``make pretrain`` = ``softshape pretrain``); the simulated
dataset is kept in ``work`` and reused when its settings did not change. Same settings and
thread count, same weights. ``softshape pretrain --arch tube`` builds the tube model the
same way, in phases that draw nothing (fast: the scene term alone, the keypoint and scene
terms, the keypoint heads on frozen codes; :func:`~softshape_ros.model.train.train_in_phases`),
then the full loss from there (:data:`TUBE`).
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from softshape_ros.config import load_rig_config
from softshape_ros.experiments.object_depths import object_depths
from softshape_ros.model.train import HEAD_BATCH, TrainConfig, renderer_compiles, train_in_phases
from softshape_ros.model.tube_net import cpu_bf16_native
from softshape_ros.sim.generate import SPARSE_SHARE, TOWARD_SHARE


@dataclass
class PretrainSettings:
    """The simulated data and the training budget of the shipped checkpoint."""

    samples: int = 3000
    scenes: int = 100
    views: tuple = ('main', 'side')
    seed: int = 0
    max_steps: int = 700
    batch_size: int = 64            # more updates per sample than 256 at this budget
    # > 0: the last phase's batches are this many whole placements (TrainConfig.scene_batch;
    # 0: batch_size rows): the tube model then encodes each placement once a batch.
    scene_batch: int = 0
    lr: float = 2e-3
    eval_every: int = 100
    patience: int = 10
    # Placements held out to validate the last phase (tube: the phases before it hold out
    # PHASE_VAL_FRACTION; the same seeded permutation, so theirs include these).
    val_fraction: float = 0.2
    threads: int = 2
    workers: int = 0
    arch: str = 'ours'
    keypoint_steps: int = 0         # tube: steps of the keypoint phase before the full loss
    keypoint_scene_batch: int = 0   # tube: whole placements per keypoint batch (0: rows)
    reader_steps: int = 0           # tube: steps of the scene term alone, first
    head_steps: int = 0             # tube: steps of the keypoint heads on frozen codes, last
    head_batch: int = HEAD_BATCH    # tube: rows per batch of the heads phase
    toward_share: float = TOWARD_SHARE  # the simulated actuations (sim.generate.make_plan)
    sparse_share: float = SPARSE_SHARE
    far_share: float = 0.0          # placements beyond reach (make_plan)
    outline: bool = False           # tube: the learned outline (TubeNet(outline=True))
    depth_test: bool = False        # tube: the robot hidden by a depth test (TubeNet)
    encoder_bf16: bool = False      # tube: the scene encoder's convolutions in bfloat16
    scene_nets_bf16: bool = False   # tube: ObjectNet's and BackgroundNet's too (full loss)
    compile_renderer: bool = False  # tube: the renderer compiled (full loss; torch.compile)
    fused_adam: bool = False        # every phase: Adam's update fused (TrainConfig.fused_adam)
    # The simulated images' samples per pixel a side (0: the camera's own pixels; several:
    # a mix, each placement rendered with one).
    supersample: int | tuple = 3
    # > 1: that many trainings, seeds ``seed``, ``seed + 1``, ..., averaged into one
    # checkpoint (tube; model.ensemble, docs/model.md "Trainings averaged").
    members: int = 1

    @classmethod
    def for_arch(cls, arch: str, as_shipped: bool = False, **given) -> 'PretrainSettings':
        """
        Return ``arch``'s defaults (:data:`TUBE` for tube), overridden by ``given`` not None.

        ``as_shipped``: tube's as its shipped checkpoint was made (:data:`TUBE_AS_SHIPPED`).
        """
        if as_shipped and arch != 'tube':
            raise ValueError(f'as_shipped: the tube checkpoint\'s settings, not {arch!r}\'s')
        d = asdict(cls())
        if arch == 'tube':
            d.update(TUBE_AS_SHIPPED if as_shipped else TUBE)
        d.update({k: v for k, v in given.items() if v is not None}, arch=arch)
        return cls(**d)


#: The tube model's defaults: it needs many placements to learn to see the object
#: (docs/model.md: 1000 samples over 100 placements overfit them; 2000 placements for
#: 20 000 samples still leave a gap between seen and unseen ones, 10 000 narrow it), and
#: data is cheap. The keypoint phase takes 16 whole placements a batch, each encoded once.
#: A reader phase first (the scene encoder alone against the placement) and a heads phase
#: after it (the keypoint heads on frozen codes): seeing the placement and fitting the push
#: each get their own budget (docs/model.md, "A reader first, with the depth test").
#: The scene encoder's convolutions train in bfloat16: the same figures in 0.85 of the time
#: (docs/model.md, "The encoder in bfloat16"). The full phase is 2400 steps: its validation
#: loss still fell at 1200, and the 1200 more made every test-set figure better on two
#: seeds, for about 13 min more (docs/model.md, "A longer full phase"). The full phase holds
#: out 5 % of the placements, not 20 %: on 9500 placements instead of 8000, RMSE, IoU, the
#: touching tip and intrusion were better on two seeds, at no cost (docs/model.md, "The full
#: phase on more placements"). The full phase draws with a compiled renderer and runs
#: ObjectNet and BackgroundNet in bfloat16: the same figures on two seeds in 0.62-0.68 of
#: the time (docs/model.md, "A compiled renderer"). Adam's update is fused, and the reader
#: and heads phases take 4000 and 10 000 steps (6000 and 20 000 before): 28.7 and 29.5 min
#: on two seeds, the test set level but for IoU, 0.0005-0.001 lower (docs/model.md, "The
#: 30 minutes"). The keypoint phase takes 8000 steps (10 000 before): 28.0 and 28.1 min on
#: two seeds, the test set level with 10 000 (docs/model.md, "A shorter keypoint phase").
#: The shipped checkpoint is two of these trainings averaged: :data:`TUBE_AS_SHIPPED`.
TUBE = {'samples': 20000, 'scenes': 10000, 'reader_steps': 4000, 'keypoint_steps': 8000,
        'keypoint_scene_batch': 16, 'head_steps': 10000, 'max_steps': 2400, 'eval_every': 400,
        'patience': 100, 'depth_test': True, 'encoder_bf16': True, 'val_fraction': 0.05,
        'scene_nets_bf16': True, 'compile_renderer': True, 'fused_adam': True}
#: The settings ``models/tube_stereo_gray`` was made with (``softshape pretrain --arch tube
#: --as-shipped``; ``make pretrain ARGS="--arch tube --as-shipped"``): the recipe on seeds 0
#: and 1, averaged (docs/model.md, "Trainings averaged"; 56 min here).
TUBE_AS_SHIPPED = {**TUBE, 'members': 2}
#: The held-out share of the tube recipe's phases before the full one (as they were measured).
PHASE_VAL_FRACTION = 0.2


def simulated_dataset(settings: PretrainSettings, work, progress: bool = True):
    """
    Return the simulated dataset of ``settings`` in ``work`` (made once, then reused).

    Reused only if made with the same data settings, the plan's shares included
    (``pretrain_key.json``); otherwise it is simulated again in its place.
    """
    from softshape_ros.data import load_dataset
    from softshape_ros.sim.generate import generate, make_plan
    cfg = load_rig_config()
    key = {k: v for k, v in asdict(settings).items()
           if k in ('samples', 'scenes', 'views', 'seed', 'toward_share', 'sparse_share',
                    'far_share', 'supersample')}
    key['views'] = list(key['views'])
    if isinstance(key['supersample'], (tuple, list)):
        key['supersample'] = list(key['supersample'])
    path = Path(work) / f'sim_{settings.samples}_{settings.scenes}_{settings.seed}'
    marker = path / 'pretrain_key.json'
    if marker.is_file() and json.loads(marker.read_text()) == key:
        return load_dataset(path)
    plan = make_plan(cfg, settings.samples, settings.scenes, settings.seed,
                     toward_share=settings.toward_share, sparse_share=settings.sparse_share,
                     far_share=settings.far_share)
    generate(cfg, plan, path, views=list(settings.views), workers=settings.workers,
             supersample=settings.supersample,
             overwrite=True, progress=progress, source='softshape pretrain')
    marker.write_text(json.dumps(key))
    return load_dataset(path)


def pretrain(settings: PretrainSettings, out, work, progress: bool = True,
             phase_dir=None) -> dict:
    """
    Simulate (or reuse) the data, train ``settings.arch``, write the checkpoint to ``out``.

    ``phase_dir``: the folder of the phases before the last (default ``work``). With
    ``settings.members`` > 1, each member's seed is trained in ``work``/``member_seed<N>``
    (its data in ``work`` as any seed's) and the ensemble written to ``out``.
    """
    if settings.members != 1:
        return _pretrain_members(settings, out, work, progress)
    low = [k for k in ('encoder_bf16', 'scene_nets_bf16') if getattr(settings, k)]
    tube_params = {k: True for k in ('outline', 'depth_test') if getattr(settings, k)}
    compiled = ['compile_renderer'] if settings.compile_renderer else []
    tube_only = [*tube_params, *low, *compiled]             # the network's, then training's
    if tube_only and settings.arch != 'tube':
        raise ValueError(f'{", ".join(tube_only)}: tube model options, not {settings.arch!r}')
    if compiled:
        renderer_compiles()         # before the data and the phases, not at the full one
    if low and not cpu_bf16_native():
        flags = ' '.join(f'--no-{k.replace("_", "-")}' for k in low)
        warnings.warn(f'{", ".join(low)}: this CPU has no native bfloat16 (AVX-512 BF16 or '
                      f'AMX); its convolutions may run slower than in float32. {flags} '
                      'trains in float32 (not the shipped checkpoint\'s recipe)', stacklevel=2)
    cfg = TrainConfig(arch=settings.arch, seed=settings.seed, split='scene',
                      batch_size=settings.batch_size, lr=settings.lr,
                      max_steps=settings.max_steps, eval_every=settings.eval_every,
                      patience=settings.patience, threads=settings.threads,
                      val_fraction=settings.val_fraction,
                      scene_batch=settings.scene_batch, arch_params=tube_params,
                      encoder_bf16=settings.encoder_bf16,
                      scene_nets_bf16=settings.scene_nets_bf16,
                      compile_renderer=settings.compile_renderer,
                      fused_adam=settings.fused_adam)
    ds = simulated_dataset(settings, work, progress)
    t0 = time.perf_counter()
    phases, res = train_in_phases(ds, cfg, settings.keypoint_steps,
                                  Path(phase_dir or work) / f'{settings.arch}_keypoints', out=out,
                                  keypoint_scene_batch=settings.keypoint_scene_batch,
                                  progress=progress, desc='pretrain',
                                  reader_steps=settings.reader_steps,
                                  head_steps=settings.head_steps,
                                  head_batch=settings.head_batch,
                                  phase_val_fraction=PHASE_VAL_FRACTION,
                                  object_depths=object_depths)
    seen = sum(r.rows_seen for r in phases.values())
    steps = {name: r.steps for name, r in phases.items()}
    secs = time.perf_counter() - t0
    return {'checkpoint': str(out), 'dataset': str(ds.path), 'samples': len(ds),
            'reader_steps': steps.get('reader', 0), 'keypoint_steps': steps.get('keypoints', 0),
            'head_steps': steps.get('heads', 0), 'steps': res.steps,
            'val_rmse_255': res.val_rmse_255, 'copy_val_rmse_255': res.copy_val_rmse_255,
            'train_seconds': round(secs),
            'train_samples_per_s': round((seen + res.rows_seen) / secs, 1),
            'settings': asdict(settings)}


def _pretrain_members(settings: PretrainSettings, out, work, progress: bool) -> dict:
    """Train ``settings.members`` seeds one after the other, then write their ensemble."""
    from softshape_ros.model.ensemble import ensemble
    if settings.members < 1:
        raise ValueError(f'members {settings.members}: at least one training')
    if settings.arch != 'tube':
        raise ValueError(f'members {settings.members}: ensembles average the tube model\'s '
                         f'keypoints, not {settings.arch!r}\'s')
    runs = []
    for seed in range(settings.seed, settings.seed + settings.members):
        folder = Path(work) / f'member_seed{seed}'
        runs.append(pretrain(replace(settings, seed=seed, members=1), folder / 'checkpoint',
                             work, progress, phase_dir=folder))
    path = ensemble([r['checkpoint'] for r in runs], out)
    return {'checkpoint': str(path), 'members': runs,
            'train_seconds': sum(r['train_seconds'] for r in runs), 'settings': asdict(settings)}
