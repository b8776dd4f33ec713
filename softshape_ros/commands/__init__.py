"""Subcommands of ``softshape``: one module per area, each with ``register(subparsers)``."""
