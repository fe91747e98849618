"""CLI subcommands: each module defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and
``run(args) -> int``. :mod:`kneegui.cli` discovers them, so a new command is one new module."""
