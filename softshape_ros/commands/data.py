"""``softshape bag info|recover`` and ``softshape build-dataset``: bags in, datasets out."""

from __future__ import annotations

import json


def _info(args) -> int:
    from softshape_ros.data.bag_tools import bag_info, format_info
    info = bag_info(args.path)
    print(json.dumps(info, indent=2) if args.json else format_info(info))
    return 0


def _recover(args) -> int:
    from softshape_ros.data.bag_tools import recover_bag
    report = recover_bag(args.path)
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    for f in report['files']:
        state = 'finished, untouched' if f['was_finished'] else \
            f'unfinished: finalised, {f["cut_bytes"]} torn bytes dropped'
        print(f'{f["file"]}: {f["messages"]} messages ({state})')
    print(f'{report["bag"]}: metadata.yaml rebuilt, {report["messages"]} messages')
    return 0


def _build(args) -> int:
    from softshape_ros.config import load_rig_config
    from softshape_ros.data.builder import build_dataset
    cfg = load_rig_config(args.config)
    ds, report = build_dataset(args.bags, args.out, cfg, gray=None if not args.rgb else False,
                               overwrite=args.overwrite, progress=not args.quiet)
    print(f'{args.out}: {len(ds)} samples from {report["triggers"]} triggers; dropped '
          + (', '.join(f'{k}={v}' for k, v in sorted(report['dropped'].items())) or 'none'))
    return 0


#: The subcommands :func:`register` adds; ``softshape NAME`` registers only NAME's module.
COMMANDS = ('bag', 'build-dataset')


def register(sub) -> None:
    bag = sub.add_parser('bag', help='inspect or repair rosbag2 bags (MCAP or sqlite3)')
    bsub = bag.add_subparsers(dest='bag_command', metavar='BAG_COMMAND')
    bsub.required = True
    p = bsub.add_parser('info', help='topics, types, counts and duration (like ros2 bag info)')
    p.add_argument('path', help='bag directory')
    p.add_argument('--json', action='store_true', help='print JSON instead of text')
    p.set_defaults(func=_info)
    p = bsub.add_parser('recover', help='make a bag from a crashed recording readable again')
    p.add_argument('path', help='bag directory')
    p.add_argument('--json', action='store_true', help='print the report as JSON')
    p.set_defaults(func=_recover)

    p = sub.add_parser('build-dataset', help='turn recorded bags into a training dataset')
    p.add_argument('bags', nargs='+', metavar='BAG', help='bag directories')
    p.add_argument('--out', required=True, help='dataset folder to write')
    p.add_argument('--config', default=None, help='rig YAML (default: the package rig.yaml)')
    p.add_argument('--rgb', action='store_true', help='keep RGB (default: rig.yaml dataset.gray)')
    p.add_argument('--overwrite', action='store_true', help='replace an existing dataset')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    p.set_defaults(func=_build)
