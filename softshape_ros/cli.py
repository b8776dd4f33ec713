"""
The ``softshape`` command: offline tools (simulate, datasets, training, bags, demo).

Each area registers its subcommands from its own module in ``softshape_ros/commands/``
(a ``register(subparsers)`` function), so adding a tool never touches this file.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import softshape_ros.commands as commands


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='softshape',
        description='softshape_ros: simulate, record, learn and predict soft-robot '
                    'interaction shapes.')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    sub.required = True
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith('_'):
            continue
        module = importlib.import_module(f'{commands.__name__}.{info.name}')
        module.register(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print('softshape: interrupted', file=sys.stderr)
        return 130
    except (ValueError, OSError, RuntimeError) as exc:
        # Known failure kinds (bad config, bad file, solver did not converge): one clear line.
        print(f'softshape {args.command}: error: {exc}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
