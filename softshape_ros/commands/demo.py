"""``softshape demo``: the whole pipeline on the simulated rig (what ``make demo`` runs)."""

from __future__ import annotations

from softshape_ros.demo.pipeline import DemoSettings


def _run(args) -> int:
    from softshape_ros.demo.pipeline import main_args
    return main_args(args)


#: The subcommands :func:`register` adds; ``softshape NAME`` registers only NAME's module.
COMMANDS = ('demo',)


def register(sub) -> None:
    d = DemoSettings()
    p = sub.add_parser('demo', help='record on the simulated rig, build a dataset, train, '
                                    'evaluate, predict live; writes <out>/report.md')
    p.add_argument('--out', default=d.out, help='output folder (default: %(default)s)')
    p.add_argument('--scenes', type=int, default=d.scenes, help='object placements recorded')
    p.add_argument('--actuations', type=int, default=d.actuations, help='samples per scene')
    p.add_argument('--rate-hz', type=float, default=d.rate_hz, help='actuation rate (paper: 2)')
    p.add_argument('--max-steps', type=int, default=d.max_steps,
                   help='training steps at most (from scratch)')
    p.add_argument('--pretrained', default=d.pretrained,
                   help="checkpoint to fine-tune ('' = train ours from scratch; default: "
                        "the shipped models/tube_stereo_gray, rebuilt by make pretrain "
                        "ARGS='--arch tube --as-shipped'; an ensemble fine-tunes whole)")
    p.add_argument('--finetune-lr', type=float, default=d.finetune_lr,
                   help='Adam learning rate when fine-tuning the pre-trained checkpoint '
                        '(default: 3e-4 for tube, 1e-3 for ours and paper)')
    p.add_argument('--finetune-steps', type=int, default=d.finetune_steps,
                   help='fine-tuning steps (batch 64) when starting from the checkpoint')
    p.add_argument('--threads', type=int, default=d.threads, help='torch threads')
    p.add_argument('--live-scenes', type=int, default=d.live_scenes,
                   help='unseen placements in the live stage')
    p.add_argument('--live-commands', type=int, default=d.live_commands,
                   help='commands per live placement')
    p.add_argument('--control-goals', type=int, default=d.control_goals,
                   help='control stage: goals for control-eval (model, random, oracle)')
    p.add_argument('--control-live', type=int, default=d.control_live,
                   help='control stage: goals closed over DDS by shape_controller (0: none)')
    p.add_argument('--control-bank', type=int, default=d.control_bank,
                   help='control stage: predictions per scene the planner starts from')
    p.add_argument('--seed', type=int, default=d.seed)
    p.add_argument('--fresh', action='store_true', help='redo every stage')
    p.set_defaults(func=_run)
