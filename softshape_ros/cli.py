"""
The ``softshape`` command: offline tools (simulate, datasets, training, bags, demo).

Each area registers its subcommands from its own module in ``softshape_ros/commands/``
(a ``register(subparsers)`` function and the ``COMMANDS`` it adds), so adding a tool never
touches this file. A run registers only the module of the subcommand it names: registering
pulls in what the help texts quote (the model's architectures import torch, 1.5 s here),
and ``softshape bag info`` should not wait for that.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import softshape_ros.commands as commands


def command_modules() -> list:
    """Return the modules of ``softshape_ros/commands/`` (cheap: they import on use)."""
    return [importlib.import_module(f'{commands.__name__}.{info.name}')
            for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name)
            if not info.name.startswith('_')]


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """
    Return the parser; with ``command``, only the module that adds it registers.

    An unknown or missing ``command`` registers every module, so the help lists them all.
    """
    parser = argparse.ArgumentParser(
        prog='softshape',
        description='softshape_ros: simulate, record, learn and predict soft-robot '
                    'interaction shapes.')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    sub.required = True
    modules = command_modules()
    owners = [m for m in modules if command in m.COMMANDS]
    for module in owners or modules:
        module.register(sub)
    return parser


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv[0] if argv and not argv[0].startswith('-') else None)
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
