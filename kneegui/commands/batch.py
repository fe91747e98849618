"""``kneegui batch PLAN``: pose a family of postures (decks x angles x tables) in parallel."""

from __future__ import annotations

import argparse
import sys
from typing import TextIO

from kneegui.batch import BatchError, BatchProgress, load_plan, run_plan

NAME = "batch"
HELP = (
    "Pose every deck x angle x kinematic-table choice of a TOML plan in worker processes or on "
    "a Dask cluster; one deck + report per posture, a summary table and plots (docs/batch.md)."
)

EXIT_QUALITY_GATE = 3
#: Some postures failed with an error (bad input, a worker died): see OUT/manifest.json.
EXIT_POSTURES_FAILED = 4


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("plan", help="plan file (TOML, docs/batch.md)")
    parser.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="local worker processes (default: the number of CPUs)",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run on an existing Dask cluster, e.g. tcp://host:8786 (needs kneegui[batch])",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue a run: skip postures whose outputs are complete and valid",
    )


def _duration(seconds: float) -> str:
    seconds = round(seconds)
    if seconds >= 3600:
        return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m"
    return f"{seconds // 60}m{seconds % 60:02d}s" if seconds >= 60 else f"{seconds}s"


class ProgressBar:
    """One line redrawn in place on a terminal; silent elsewhere (the summary line says it all)."""

    def __init__(self, stream: TextIO, width: int = 30):
        self.stream, self.width = stream, width
        self.tty = stream.isatty()

    def __call__(self, p: BatchProgress) -> None:
        if not self.tty or not p.total:
            return
        filled = round(self.width * (p.done + p.failed) / p.total)
        eta = "" if p.eta_s is None else f", about {_duration(p.eta_s)} left"
        line = (
            f"[{'#' * filled}{'.' * (self.width - filled)}] {p.done} done, {p.failed} failed, "
            f"{p.remaining} remaining{eta}"
        )
        self.stream.write(f"\r{line}\x1b[K")
        self.stream.flush()

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")


def run(args: argparse.Namespace) -> int:
    if args.workers is not None and args.workers < 1:
        raise BatchError(f"--workers must be at least 1, got {args.workers}")
    plan = load_plan(args.plan)
    bar = ProgressBar(sys.stderr)
    try:
        outcome = run_plan(
            plan,
            workers=args.workers,
            scheduler=args.scheduler,
            resume=args.resume,
            progress=bar,
        )
    finally:
        bar.close()
    for warning in outcome.warnings:
        print(f"kneegui: warning: {warning}", file=sys.stderr)
    total = outcome.ok + outcome.gate_failed + outcome.errors
    resumed = f", {outcome.skipped} already complete" if outcome.skipped else ""
    print(
        f"{total} postures: {outcome.ok} ok, {outcome.gate_failed} failed the quality gate, "
        f"{outcome.errors} failed{resumed} in {_duration(outcome.seconds)}; "
        f"summary: {plan.out / 'summary.md'}"
    )
    if outcome.errors:
        return EXIT_POSTURES_FAILED
    return EXIT_QUALITY_GATE if outcome.gate_failed else 0
