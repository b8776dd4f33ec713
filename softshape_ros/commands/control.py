"""``softshape control-eval``: the shape controller's closed loop on the simulated rig."""

from __future__ import annotations

import json


def _control_eval(args) -> int:
    from softshape_ros.config import load_rig_config
    from softshape_ros.control.evaluate import METHODS, EvalSettings, evaluate_control
    from softshape_ros.control.loop import Tolerance
    from softshape_ros.control.planner import PlannerConfig
    from softshape_ros.model import Predictor
    if args.goals < 1:
        raise ValueError(f'--goals must be >= 1, got {args.goals}')
    methods = tuple(m for m in args.methods.split(',') if m)
    unknown = sorted(set(methods) - set(METHODS))
    if unknown or not methods:
        raise ValueError(f'--methods: choose from {",".join(METHODS)}, got {args.methods!r}')
    if 'random' in methods and 'model' not in methods:
        raise ValueError('--methods: random search takes its budget from the model planner: '
                         'add "model"')
    settings = EvalSettings(
        goals=args.goals, seed=args.seed, max_iterations=args.iterations,
        tolerance=Tolerance(args.tip_px, args.iou), methods=methods, threads=args.threads,
        contact_goals=args.contact_goals,
        planner=PlannerConfig(bank_size=args.bank_size, lm_iterations=args.lm_iterations))
    summary = evaluate_control(Predictor.from_checkpoint(args.model),
                               load_rig_config(args.config), settings, out_dir=args.out,
                               progress=not args.quiet)
    print(json.dumps(summary, indent=2))
    return 0


#: The subcommands :func:`register` adds; ``softshape NAME`` registers only NAME's module.
COMMANDS = ('control-eval',)


def register(sub) -> None:
    p = sub.add_parser('control-eval',
                       help='close the loop through a model on the simulated rig: success, '
                            'iterations, planning time, against random search and the oracle')
    p.add_argument('--model', required=True, help='checkpoint folder')
    p.add_argument('--goals', type=int, default=20, help='goals (half touching the object)')
    p.add_argument('--seed', type=int, default=0, help='draws the held-out scenes and goals')
    p.add_argument('--out', required=True, help='folder for control.json and control.png')
    p.add_argument('--config', default=None, help='rig YAML (default: the package rig.yaml)')
    p.add_argument('--methods', default='model,random,oracle',
                   help='model (the planner through the model), random (random search, same '
                        'budget), oracle (the planner through the simulator)')
    p.add_argument('--iterations', type=int, default=3, help='closed-loop iterations at most')
    p.add_argument('--tip-px', type=float, default=2.0, help='tip tolerance in every view')
    p.add_argument('--iou', type=float, default=0.9, help='silhouette IoU tolerance')
    p.add_argument('--bank-size', type=int, default=384, help='predictions per scene')
    p.add_argument('--lm-iterations', type=int, default=4, help='LM steps per plan at most')
    p.add_argument('--contact-goals', action='store_true',
                   help='ask touching goals to touch the object and free ones to stay clear')
    p.add_argument('--threads', type=int, default=1, help='torch threads (planning: one core)')
    p.add_argument('--quiet', action='store_true', help='no progress bars')
    p.set_defaults(func=_control_eval)
