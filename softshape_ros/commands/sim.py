"""``softshape sim-solve`` (one equilibrium as JSON) and ``softshape simulate`` (a dataset)."""

from __future__ import annotations

import json
import sys

from softshape_ros.config import load_rig_config
from softshape_ros.scene import Scene, load_session


def supersample_arg(text: str):
    """Parse ``--supersample``: one int >= 0, or several comma-separated (a tuple: a mix)."""
    import argparse
    try:
        values = tuple(int(v) for v in text.split(','))
    except ValueError:
        values = ()
    if not values or min(values) < 0:
        raise argparse.ArgumentTypeError(
            f'expected integers >= 0, comma-separated (3, or 0,3), got {text!r}')
    return values[0] if len(values) == 1 else values


def _onoff(text: str) -> bool:
    t = text.lower()
    if t in ('on', 'true', '1', 'yes'):
        return True
    if t in ('off', 'false', '0', 'no'):
        return False
    raise ValueError(f'expected on or off, got {text!r}')


def _scene(args):
    if args.object and args.session:
        raise ValueError('give --object or --session, not both')
    if args.object:
        return Scene.from_json(args.object)
    if args.session:
        scenes = load_session(args.session)
        if args.scene_id is None:
            raise ValueError('--session needs --scene-id')
        for s in scenes:
            if s.id == args.scene_id:
                return s
        raise ValueError(f'{args.session}: no scene with id {args.scene_id}')
    return None


def _solve(args) -> int:
    from softshape_ros.sim.equilibrium import solve_equilibrium
    from softshape_ros.sim.statics import PointLoad
    cfg = load_rig_config(args.config)
    total = cfg.robot.total_length_m
    loads = []
    if args.tip_force or args.tip_moment:
        loads.append(PointLoad(total, tuple(args.tip_force or (0, 0, 0)),
                               tuple(args.tip_moment or (0, 0, 0))))
    for pl in args.point_load or []:
        loads.append(PointLoad(pl[0], tuple(pl[1:4]), tuple(pl[4:7])))
    out = solve_equilibrium(
        cfg, pressures_pa=args.pressures, tensions_n=args.tensions, loads=loads,
        gravity=_onoff(args.gravity), order=args.order,
        shear=None if args.shear is None else _onoff(args.shear),
        stretch=None if args.stretch is None else _onoff(args.stretch),
        scene=_scene(args), samples=args.samples)
    json.dump(out, sys.stdout, indent=None if args.compact else 2)
    print()
    return 0


def _simulate(args) -> int:
    from softshape_ros.sim.generate import generate, make_plan
    if args.workers < 0:
        raise ValueError(f'--workers must be >= 0 (0: all cores), got {args.workers}')
    cfg = load_rig_config(args.config)
    views = ['main'] if args.views == 'mono' else list(cfg.cameras)[:2]
    if args.views == 'stereo' and len(views) < 2:
        raise ValueError('--views stereo needs two cameras in the config')
    scenes = load_session(args.session) if args.session else args.scenes
    plan = make_plan(cfg, args.samples, scenes, args.seed, toward_share=args.toward_share,
                     sparse_share=args.sparse_share, far_share=args.far_share)
    ds, summary = generate(cfg, plan, args.out, views, size=args.size or cfg.dataset.image_size,
                           gray=not args.rgb and cfg.dataset.gray, workers=args.workers,
                           supersample=args.supersample,
                           noise=(args.image_noise, args.pressure_noise),
                           overwrite=args.overwrite,
                           source=f'softshape simulate (seed {args.seed})')
    print(json.dumps({'out': str(ds.path), **summary}))
    return 0


#: The subcommands :func:`register` adds; ``softshape NAME`` registers only NAME's module.
COMMANDS = ('sim-solve', 'simulate')


def register(sub) -> None:
    from softshape_ros.sim.generate import SPARSE_SHARE, TOWARD_SHARE
    p = sub.add_parser('sim-solve', help='solve one simulator equilibrium and print JSON')
    p.add_argument('--config', default=None, help='rig YAML (default: the package rig.yaml)')
    act = p.add_mutually_exclusive_group()
    act.add_argument('--pressures', type=float, nargs=6, metavar='PA',
                     help='six chamber pressures in Pa (positive inflates)')
    act.add_argument('--tensions', type=float, nargs=6, metavar='N',
                     help='six tendon tensions in N at the chamber positions (positive pulls)')
    p.add_argument('--tip-force', type=float, nargs=3, metavar=('FX', 'FY', 'FZ'),
                   help='dead world force at the tip, N')
    p.add_argument('--tip-moment', type=float, nargs=3, metavar=('MX', 'MY', 'MZ'),
                   help='world moment at the tip, N m')
    p.add_argument('--point-load', type=float, nargs=7, action='append',
                   metavar=('S', 'FX', 'FY', 'FZ', 'MX', 'MY', 'MZ'),
                   help='world wrench at arc length S (m); repeatable')
    p.add_argument('--gravity', default='on', help='on|off (default on)')
    p.add_argument('--order', type=int, default=None, help='Legendre order per strain')
    p.add_argument('--shear', default=None, help='on|off (default: config)')
    p.add_argument('--stretch', default=None, help='on|off (default: config)')
    p.add_argument('--object', default=None,
                   help='scene JSON, e.g. \'{"id": 0, "object": "sphere", "position_m": '
                        '[0.02, 0, 0.03], "dims": {"radius_m": 0.01}}\'')
    p.add_argument('--session', default=None, help='session YAML to take the object from')
    p.add_argument('--scene-id', type=int, default=None, help='scene id in --session')
    p.add_argument('--samples', type=int, default=21, help='backbone samples in the output')
    p.add_argument('--compact', action='store_true', help='one-line JSON')
    p.set_defaults(func=_solve)

    p = sub.add_parser('simulate', help='write a simulated training dataset')
    p.add_argument('--config', default=None, help='rig YAML (default: the package rig.yaml)')
    p.add_argument('--samples', type=int, required=True, help='number of samples N')
    p.add_argument('--scenes', type=int, default=12,
                   help='random object placements S (cylinder, ring, prism in turn)')
    p.add_argument('--session', default=None, help='use this session YAML\'s scenes instead')
    p.add_argument('--views', choices=('mono', 'stereo'), default='stereo')
    p.add_argument('--out', required=True, help='dataset folder to create')
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--toward-share', type=float, default=TOWARD_SHARE,
                   help='share of actuations drawn to bend towards the object (0: all '
                        f'uniform, as the recorded rig; default {TOWARD_SHARE})')
    p.add_argument('--sparse-share', type=float, default=SPARSE_SHARE,
                   help='share of sparse actuations: one chamber on, or one per segment, the '
                        f'rest at zero (0: none; default {SPARSE_SHARE})')
    p.add_argument('--far-share', type=float, default=0.0,
                   help='share of random placements beyond reach (gap 10-25 mm instead of '
                        '1-10 mm; default 0)')
    p.add_argument('--workers', type=int, default=0,
                   help='processes (default 0: all cores; 1: no worker processes)')
    p.add_argument('--size', type=int, default=0, help='image size (default: config)')
    p.add_argument('--rgb', action='store_true', help='keep colour (default: config gray)')
    p.add_argument('--supersample', type=supersample_arg, default=3,
                   help='render the crop at size x this, then area-resize (default 3; 0: '
                        "at the camera's own pixels, as the rig's camera nodes see it); "
                        'several, comma-separated (0,3): each placement drawn with one')
    p.add_argument('--image-noise', type=float, default=0.0, help='gray levels (std)')
    p.add_argument('--pressure-noise', type=float, default=0.0, help='Pa (std)')
    p.add_argument('--overwrite', action='store_true')
    p.set_defaults(func=_simulate)
