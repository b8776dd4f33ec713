"""``softshape config``: validate and show the rig configuration."""

from __future__ import annotations

import dataclasses
import json

from softshape_ros.config import load_rig_config


def _show(args) -> int:
    cfg = load_rig_config(args.config)
    print(json.dumps(dataclasses.asdict(cfg), indent=2))
    return 0


#: The subcommands :func:`register` adds; ``softshape NAME`` registers only NAME's module.
COMMANDS = ('config',)


def register(sub) -> None:
    p = sub.add_parser('config', help='validate and print the rig configuration as JSON')
    p.add_argument('--config', default=None, help='rig YAML (default: the package rig.yaml)')
    p.set_defaults(func=_show)
