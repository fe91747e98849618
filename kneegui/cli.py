"""The ``kneegui`` command line: one entry, subcommands discovered in :mod:`kneegui.commands`.

Errors the engine raises on purpose (:class:`kneegui.errors.KneeguiError`) are printed as one line
on stderr and exit with code 2; nothing else is printed and no traceback is shown.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Sequence

from kneegui import __version__, commands
from kneegui.errors import KneeguiError

#: Exit codes shared by every subcommand.
EXIT_OK, EXIT_BAD_INPUT, EXIT_QUALITY_GATE = 0, 2, 3


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every discovered subcommand."""
    parser = argparse.ArgumentParser(
        prog="kneegui", description="Re-pose the knee of a human-body FE model."
    )
    parser.add_argument("--version", action="version", version=f"kneegui {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        if not hasattr(module, "run"):
            continue
        p = sub.add_parser(module.NAME, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except KneeguiError as exc:
        print(f"kneegui: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (OSError, MemoryError) as exc:
        print(f"kneegui: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("kneegui: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
