"""
``softshape train | evaluate | export | reproduce | pretrain | distance-sweep``: the model's tools.

``train`` runs unchanged under ``torchrun --nproc_per_node N .venv/bin/softshape train ...``
(DDP: gloo on CPU, NCCL on GPUs).
"""

from __future__ import annotations

import argparse
import json
import sys

from softshape_ros.commands.sim import supersample_arg

OUTLINE_HELP = ("tube: learn how far out of the keypoints' radius the drawn outline lies, "
                'per view (off in the shipped recipe; docs/model.md, "The outline")')
DEPTH_TEST_HELP = ('tube: hide the robot where a learned map of the object puts it nearer than '
                   'the tube (docs/model.md, "A depth test")')
ENCODER_BF16_HELP = ("tube: train the scene encoder's convolutions in bfloat16 (a reader step "
                     'in about 0.6 of the time on a CPU with AVX-512 BF16; the checkpoint '
                     'stays float32; docs/model.md, "The encoder in bfloat16")')
SCENE_NETS_BF16_HELP = ("tube, the full loss: ObjectNet's and BackgroundNet's convolutions in "
                        'bfloat16 too, but for their heads (a full step in about 0.77 of the '
                        'time; docs/model.md, "The scene nets in bfloat16")')
COMPILE_RENDERER_HELP = ('tube, the full loss: compile the renderer with torch.compile (needs a '
                         'C++ compiler; about 20 s to build; docs/model.md, "A compiled '
                         'renderer")')
FUSED_ADAM_HELP = ("Adam's update fused into one kernel over all parameters (the same rule, "
                   'rounded differently; docs/model.md, "The 30 minutes")')


def tube_options(args, command: str) -> dict:
    """Return the tube-only flags as arch_params; any of them on another arch exits."""
    params = {k: True for k in ('outline', 'depth_test') if getattr(args, k, None)}
    if params and args.arch != 'tube':
        flag = '--' + next(iter(params)).replace('_', '-')
        raise SystemExit(f'softshape {command}: {flag} is a tube model option, not '
                         f'{args.arch!r}')
    return params


def _train(args) -> int:
    from softshape_ros.data import load_dataset
    from softshape_ros.experiments.object_depths import object_depths
    from softshape_ros.model.train import TrainConfig, train
    arch_params = tube_options(args, 'train')
    ds = load_dataset(args.dataset)
    rows = None if args.rows is None else range(min(args.rows, len(ds)))
    cfg = TrainConfig(arch=args.arch, seed=args.seed, split=args.split,
                      batch_size=args.batch_size, lr=args.lr, max_steps=args.max_steps,
                      eval_every=args.eval_every, patience=args.patience,
                      threads=args.threads, loss=args.loss, init=args.init,
                      min_steps=args.min_steps, scene_batch=args.scene_batch,
                      freeze_scene=args.freeze_scene, warmup=args.warmup,
                      val_fraction=args.val_fraction,
                      encoder_bf16=args.encoder_bf16, scene_nets_bf16=args.scene_nets_bf16,
                      compile_renderer=args.compile_renderer, fused_adam=args.fused_adam,
                      arch_params=arch_params)
    res = train(ds, cfg, out=args.out, indices=rows, progress=not args.quiet,
                object_depths=object_depths)
    summary = {'checkpoint': args.out, 'steps': res.steps,
               'val_rmse_255': res.val_rmse_255, 'copy_val_rmse_255': res.copy_val_rmse_255}
    if res.config['training']['world_size'] == 1 or _rank() == 0:
        print(json.dumps(summary))
    return 0


def _rank() -> int:
    import os
    return int(os.environ.get('RANK', '0'))


def _evaluate(args) -> int:
    import numpy as np

    from softshape_ros.data import load_dataset
    from softshape_ros.model.checkpoint import read_config
    from softshape_ros.model.evaluate import evaluate
    ds = load_dataset(args.dataset)
    idx = None
    if args.validation:
        rows = read_config(args.checkpoint).get('dataset', {}).get('val_rows')
        if not isinstance(rows, list) or not rows:
            raise ValueError(f'{args.checkpoint}: config.json records no validation rows')
        if max(rows) >= len(ds):
            raise ValueError(f'{args.checkpoint}: validation rows do not fit {ds.path}')
        idx = np.asarray(rows, dtype=np.int64)
    res = evaluate(args.checkpoint, ds, indices=idx, out_dir=args.out)
    print(json.dumps(res, indent=2))
    return 0


def _export(args) -> int:
    from softshape_ros.model.export import export_onnx
    info = export_onnx(args.checkpoint, args.out)
    print(json.dumps({k: info[k] for k in ('onnx', 'max_abs_diff', 'batch_checked')}))
    return 0


def _ensemble(args) -> int:
    from softshape_ros.model.ensemble import ensemble
    out = ensemble(args.checkpoints, args.out)
    print(json.dumps({'checkpoint': str(out), 'members': len(args.checkpoints)}))
    return 0


def _reproduce(args) -> int:
    from softshape_ros.experiments.reproduction import reproduce_with_sweep
    from softshape_ros.model.reproduce import ReproConfig
    sizes = [int(s) for s in args.sizes.split(',')]
    cfg = ReproConfig(sizes=sizes, test_fraction=args.test_fraction, seed=args.seed,
                      max_steps=args.max_steps, patience=args.patience,
                      eval_every=args.eval_every, threads=args.threads,
                      tube_depth_test=args.depth_test)
    table = reproduce_with_sweep(args.dataset, args.out, cfg, work=args.work,
                                 sweep=not args.no_fig4c, splits=args.splits.split(','),
                                 views=args.views.split(','), archs=args.archs.split(','))
    sys.stdout.write(table)
    return 0


def _pretrain(args) -> int:
    from softshape_ros.experiments.pretrain import PretrainSettings, pretrain
    s = PretrainSettings.for_arch(args.arch, args.as_shipped, **{k: getattr(args, k) for k in (
        'samples', 'scenes', 'seed', 'max_steps', 'batch_size', 'scene_batch', 'lr', 'eval_every',
        'patience', 'threads', 'workers', 'keypoint_steps', 'keypoint_scene_batch',
        'reader_steps', 'head_steps', 'head_batch', 'val_fraction',
        'toward_share', 'sparse_share', 'far_share', 'outline', 'depth_test',
        'encoder_bf16', 'scene_nets_bf16', 'compile_renderer', 'fused_adam', 'supersample',
        'members')})
    out = args.out or f'models/{args.arch}_stereo_gray'
    print(json.dumps(pretrain(s, out, args.work, progress=not args.quiet)))
    return 0


def _distance_sweep(args) -> int:
    from softshape_ros.experiments.distance_sweep import run
    if args.supersample < 0:
        raise ValueError(f'--supersample must be >= 0 (0: the camera\'s pixels), got '
                         f'{args.supersample}')
    print(json.dumps(run(args.checkpoint, args.out, args.supersample, args.placement_head),
                     indent=2))
    return 0


def _placement_head(args) -> int:
    from softshape_ros.experiments.placement_study import run
    print(json.dumps(run(args.train, args.test, args.checkpoint, args.out, args.steps,
                         args.workers, args.limit, progress=not args.quiet,
                         head=args.head), indent=2))
    return 0


#: The subcommands :func:`register` adds; ``softshape NAME`` registers only NAME's module.
COMMANDS = ('train', 'evaluate', 'export', 'ensemble', 'reproduce', 'pretrain', 'distance-sweep',
            'placement-head')


def register(sub) -> None:
    from softshape_ros.model.losses import LOSSES
    from softshape_ros.model.networks import ARCHS
    p = sub.add_parser('train', help='train a forward model on a dataset (DDP under torchrun)')
    p.add_argument('--dataset', required=True, help='dataset folder')
    p.add_argument('--out', required=True, help='checkpoint folder to write')
    p.add_argument('--arch', choices=ARCHS, default='ours')
    p.add_argument('--split', choices=('random', 'scene'), default='random',
                   help='validation rows: random ones (the paper: 20%%) or whole held-out '
                        'scenes; --val-fraction gives the share')
    p.add_argument('--val-fraction', type=float, default=0.2,
                   help='the held-out share of the rows (random) or scenes (scene)')
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--rows', type=int, default=None, help='use only the first N rows')
    p.add_argument('--batch-size', type=int, default=256)
    p.add_argument('--scene-batch', type=int, default=0,
                   help='N > 0: batches of N whole placements (all their rows) instead of '
                        '--batch-size rows; tube encodes each placement once a batch')
    p.add_argument('--freeze-scene', action='store_true',
                   help='tube, --loss keypoints: the scene encoder frozen, each placement '
                        'encoded once; only the keypoint heads train (fast)')
    p.add_argument('--outline', action='store_true', help=OUTLINE_HELP)
    p.add_argument('--depth-test', action='store_true', help=DEPTH_TEST_HELP)
    p.add_argument('--encoder-bf16', action='store_true', help=ENCODER_BF16_HELP)
    p.add_argument('--scene-nets-bf16', action='store_true', help=SCENE_NETS_BF16_HELP)
    p.add_argument('--compile-renderer', action='store_true', help=COMPILE_RENDERER_HELP)
    p.add_argument('--fused-adam', action='store_true', help=FUSED_ADAM_HELP)
    p.add_argument('--warmup', type=float, default=0.0,
                   help='share of --max-steps over which the rate rises to --lr before '
                        'its cosine (0: none)')
    p.add_argument('--lr', type=float, default=None,
                   help="Adam learning rate (default: the architecture's own, "
                        'DEFAULT_LR in softshape_ros/model/train.py)')
    p.add_argument('--max-steps', type=int, default=600)
    p.add_argument('--eval-every', type=int, default=10, help='steps between validations')
    p.add_argument('--patience', type=int, default=8,
                   help='validations without improvement before stopping early')
    p.add_argument('--min-steps', type=int, default=0, help='never stop early before this')
    p.add_argument('--loss', choices=LOSSES, default=None,
                   help="training loss (default: the architecture's own, DEFAULT_LOSS)")
    p.add_argument('--init', default=None,
                   help='start from this checkpoint (fine-tuning; same arch, views, channels)')
    p.add_argument('--threads', type=int, default=0, help='torch threads (0: default)')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    p.set_defaults(func=_train)

    p = sub.add_parser('evaluate', help='metrics and prediction panels of a checkpoint')
    p.add_argument('--checkpoint', required=True)
    p.add_argument('--dataset', required=True)
    p.add_argument('--validation', action='store_true',
                   help="only the checkpoint's own validation rows of this dataset")
    p.add_argument('--out', default=None, help='folder for metrics.json and panels.png')
    p.set_defaults(func=_evaluate)

    p = sub.add_parser('export', help='export a checkpoint to ONNX (checked within 1e-4)')
    p.add_argument('--checkpoint', required=True)
    p.add_argument('--out', required=True, help='.onnx file to write')
    p.set_defaults(func=_export)

    p = sub.add_parser('ensemble', help='average tube trainings: one checkpoint drawing '
                                        'the mean of their keypoints with the first\'s '
                                        'renderer (docs/model.md, "Trainings averaged")')
    p.add_argument('checkpoints', nargs='+', help='two or more tube checkpoints, the '
                                                  'drawing one first')
    p.add_argument('--out', required=True, help='checkpoint folder to write')
    p.set_defaults(func=_ensemble)

    p = sub.add_parser('reproduce', help="the paper's RMSE-vs-size study, paper vs ours")
    p.add_argument('--dataset', required=True, help='stereo dataset (mono uses its 1st view)')
    p.add_argument('--out', default='benchmarks/reproduction', help='table + figures folder')
    p.add_argument('--work', default=None, help='checkpoints folder (default: a temp dir)')
    p.add_argument('--sizes', default='100,200,500,1000')
    p.add_argument('--test-fraction', type=float, default=0.2)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--max-steps', type=int, default=400)
    p.add_argument('--eval-every', type=int, default=10)
    p.add_argument('--patience', type=int, default=8)
    p.add_argument('--threads', type=int, default=0)
    p.add_argument('--splits', default='random,scene',
                   help='train only these splits here (the table uses all cached runs)')
    p.add_argument('--views', default='mono,stereo', help='train only these views here')
    p.add_argument('--archs', default='paper,ours',
                   help='train only these networks here (paper, ours, tube)')
    p.add_argument('--no-fig4c', action='store_true', help='skip the object-distance sweep')
    p.add_argument('--depth-test', action=argparse.BooleanOptionalAction, default=True,
                   help='tube: hide the robot by a depth test, as the shipped recipe '
                        '(docs/model.md, "A depth test"); --no-depth-test: the recipe before')
    p.set_defaults(func=_reproduce)

    from softshape_ros.experiments.distance_sweep import SUPERSAMPLE
    from softshape_ros.experiments.pretrain import TUBE, TUBE_AS_SHIPPED, PretrainSettings
    d = PretrainSettings()
    p = sub.add_parser('pretrain', help='simulate a dataset and pre-train ours on it '
                                        '(the checkpoint the demo fine-tunes)')
    p.add_argument('--arch', choices=('ours', 'tube'), default='ours',
                   help='ours (the demo\'s model) or tube (two phases, its own defaults: '
                        + ', '.join(f'{k} {v}' for k, v in TUBE.items()) + ')')
    p.add_argument('--out', default=None,
                   help='checkpoint folder (default models/ARCH_stereo_gray)')
    p.add_argument('--work', default='/tmp/softshape_pretrain',
                   help='where the simulated dataset is kept (reused when unchanged)')
    for flag, typ in (('samples', int), ('scenes', int), ('seed', int), ('max-steps', int),
                      ('keypoint-steps', int), ('keypoint-scene-batch', int),
                      ('reader-steps', int), ('head-steps', int), ('head-batch', int),
                      ('batch-size', int), ('scene-batch', int), ('lr', float),
                      ('eval-every', int), ('patience', int), ('threads', int),
                      ('val-fraction', float), ('toward-share', float), ('sparse-share', float),
                      ('far-share', float), ('supersample', supersample_arg)):
        p.add_argument(f'--{flag}', type=typ, default=None,
                       help=f'default {getattr(d, flag.replace("-", "_"))} (ours)')
    p.add_argument('--workers', type=int, default=None,
                   help='simulation processes (0: one per core)')
    p.add_argument('--members', type=int, default=None,
                   help='tube: N trainings, seeds SEED to SEED+N-1 (each in WORK/member_seedS), '
                        'averaged into one checkpoint (softshape ensemble; default 1)')
    p.add_argument('--outline', action='store_true', default=None, help=OUTLINE_HELP)
    p.add_argument('--depth-test', action=argparse.BooleanOptionalAction, default=None,
                   help=DEPTH_TEST_HELP + '; default on for tube (the shipped recipe)')
    p.add_argument('--encoder-bf16', action=argparse.BooleanOptionalAction, default=None,
                   help=ENCODER_BF16_HELP + '; default on for tube (the shipped recipe), '
                   '--no-encoder-bf16: float32')
    p.add_argument('--scene-nets-bf16', action=argparse.BooleanOptionalAction, default=None,
                   help=SCENE_NETS_BF16_HELP + '; default on for tube, --no-scene-nets-bf16: '
                   'float32')
    p.add_argument('--compile-renderer', action=argparse.BooleanOptionalAction, default=None,
                   help=COMPILE_RENDERER_HELP + '; default on for tube, '
                   '--no-compile-renderer: eager PyTorch')
    p.add_argument('--fused-adam', action=argparse.BooleanOptionalAction, default=None,
                   help=FUSED_ADAM_HELP + '; default on for tube, --no-fused-adam: '
                   'PyTorch\'s loop')
    p.add_argument('--as-shipped', action='store_true',
                   help='tube: the settings models/tube_stereo_gray was made with (the '
                        'recipe\'s, and ' + ', '.join(
                            f'{k} {v}' for k, v in TUBE_AS_SHIPPED.items()
                            if TUBE.get(k) != v) + '); other flags still override them')
    p.add_argument('--quiet', action='store_true', help='no progress bars')
    p.set_defaults(func=_pretrain)

    p = sub.add_parser('distance-sweep', help="Fig. 4(c): a cylinder moved away, the "
                                              "simulator's push vs the model's")
    p.add_argument('--checkpoint', required=True)
    p.add_argument('--out', required=True, help='folder for distance_sweep.json and .png')
    p.add_argument('--supersample', type=int, default=SUPERSAMPLE,
                   help=f'render the images at this many samples a pixel a side (default '
                        f"{SUPERSAMPLE}; 0: the camera's own pixels)")
    p.add_argument('--placement-head', default=None,
                   help='predict by the placement path: this head (softshape placement-head), '
                        'drawn by the checkpoint for each fitted placement')
    p.set_defaults(func=_distance_sweep)

    p = sub.add_parser('placement-head', help='train the folded placement head, fit the test '
                                              "placements, and score what the tube model draws")
    p.add_argument('--train', required=True, help='simulated dataset the head learns from')
    p.add_argument('--test', required=True, help='simulated dataset of held-out placements')
    p.add_argument('--checkpoint', required=True, help='tube checkpoint: reads and draws')
    p.add_argument('--out', required=True, help='folder for head/ and placement_head.json')
    p.add_argument('--steps', type=int, default=20000, help='head training steps (batch 512)')
    p.add_argument('--workers', type=int, default=2, help='processes fitting placements')
    p.add_argument('--limit', type=int, default=None, help='fit only the first N placements')
    p.add_argument('--head', default=None, help='use this saved head instead of training one')
    p.add_argument('--quiet', action='store_true', help='no progress bars')
    p.set_defaults(func=_placement_head)
