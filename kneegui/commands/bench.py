"""``kneegui bench``: run the benchmark harness (``python -m bench``) and write docs/benchmarks.md.

The harness lives in the repository's ``bench`` package (not in the engine); this command only
forwards to it, so both entries take the same options.
"""

from __future__ import annotations

import argparse

from kneegui.errors import KneeguiError

NAME = "bench"
HELP = (
    "Benchmark speed, scale and quality against the paper and the baselines; "
    "writes docs/benchmarks.md and bench/results/benchmarks.json."
)


def _harness():
    try:
        import bench.__main__ as harness
    except ImportError as exc:
        raise KneeguiError(
            f"the benchmark harness (the repository's bench/ package) is not importable: {exc}"
        ) from exc
    return harness


def add_arguments(parser: argparse.ArgumentParser) -> None:
    try:
        harness = _harness()
    except KneeguiError:
        return
    harness.build_parser(parser)


def run(args: argparse.Namespace) -> int:
    return _harness().run_from_args(args)
