"""The ``softshape`` command: each run registers only the module of its subcommand."""

import argparse
import subprocess
import sys

from softshape_ros.cli import build_parser, command_modules


def choices(parser) -> dict:
    """Return the subcommands a parser holds, by name."""
    return parser._subparsers._group_actions[0].choices


def added(module) -> set:
    parser = argparse.ArgumentParser()
    module.register(parser.add_subparsers())
    return set(choices(parser))


def test_every_module_names_the_subcommands_it_adds_and_no_two_share_one():
    seen = []
    for module in command_modules():
        assert set(module.COMMANDS) == added(module), module.__name__
        seen += module.COMMANDS
    assert len(seen) == len(set(seen)), seen
    # With no command (``softshape -h``) or an unknown one, the help lists every one.
    for command in (None, 'no-such-tool'):
        assert set(choices(build_parser(command))) == set(seen)
    assert set(choices(build_parser('bag'))) == {'bag', 'build-dataset'}


def test_a_bag_tool_does_not_import_torch(tmp_path):
    code = ('import sys; from softshape_ros.cli import main; '
            f'rc = main(["bag", "info", {str(tmp_path / "none")!r}]); '
            'print(rc, "torch" in sys.modules)')
    r = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                       timeout=60)
    assert r.stdout.split() == ['2', 'False'], (r.stdout, r.stderr)
    assert 'no such bag directory' in r.stderr
    # ... while a model tool still gets its whole parser.
    train = choices(build_parser('train'))['train']
    assert '--arch {paper,ours,tube}' in train.format_help()
