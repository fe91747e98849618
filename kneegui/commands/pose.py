"""``kneegui pose``: deck in, posed deck(s) out, with a quality report per angle."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TextIO

from kneegui.errors import SetupError
from kneegui.io.atomic import atomic_write_text
from kneegui.io.lsdyna import read_deck
from kneegui.io.output_plan import check_distinct_targets
from kneegui.meshopt.volume_correction import VolumeCorrectionOptions
from kneegui.reposition import METHODS, Repositioner, RepositionOptions
from kneegui.reposition.pipeline import angle_tag, export_pose
from kneegui.setup import load_setup

NAME = "pose"
HELP = "Re-pose the knee of a deck to one or more flexion angles and write the posed deck(s)."

EXIT_QUALITY_GATE = 3


class ProgressBar:
    """A one-line progress bar on a terminal (``[#####     ]  45% relaxing soft tissue``),
    redrawn at most every ``interval`` seconds; silent when the stream is not a terminal, so
    pipes and logs get only the result lines.

    Parameters
    ----------
    label : str
        Printed before the bar (e.g. the angle).
    stream : text stream, optional
        Default: standard error.
    interval : float
        Smallest time between redraws (seconds).
    """

    WIDTH = 24

    def __init__(self, label: str, stream: TextIO | None = None, interval: float = 0.1) -> None:
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.interval = interval
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last = float("-inf")
        self._shown = 0

    def __call__(self, fraction: float, message: str) -> None:
        """Draw ``fraction`` (0..1) and ``message`` (a ``progress`` callback)."""
        now = time.monotonic()
        if not self.enabled or (now - self._last < self.interval and fraction < 1.0):
            return
        self._last = now
        fraction = min(max(float(fraction), 0.0), 1.0)
        filled = round(self.WIDTH * fraction)
        line = (
            f"{self.label} [{'#' * filled}{' ' * (self.WIDTH - filled)}] "
            f"{100 * fraction:3.0f}% {message}"
        )
        self.stream.write("\r" + line.ljust(self._shown))
        self.stream.flush()
        self._shown = len(line)

    def close(self) -> None:
        """Erase the bar (the result line is printed in its place)."""
        if self.enabled and self._shown:
            self.stream.write("\r" + " " * self._shown + "\r")
            self.stream.flush()
            self._shown = 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="LS-DYNA keyword deck")
    parser.add_argument("--setup", required=True, help="joint setup JSON (docs/setup-format.md)")
    parser.add_argument(
        "--flexion",
        required=True,
        type=float,
        nargs="+",
        metavar="DEG",
        help="target flexion angle(s), degrees",
    )
    parser.add_argument(
        "--out",
        required=True,
        help="output deck (one angle) or output folder (several angles: "
        "OUT/flex_<deg>/<deck name>)",
    )
    parser.add_argument("--report", help="report JSON path (several angles: _<deg> is added)")
    parser.add_argument("--no-smooth", action="store_true", help="skip mesh smoothing")
    parser.add_argument(
        "--force",
        action="store_true",
        help="write the deck even if it fails the quality gate, and overwrite existing include "
        "files beside the output (another deck's, maybe)",
    )
    parser.add_argument("--flatten", action="store_true", help="inline every *INCLUDE")
    parser.add_argument("--method", choices=METHODS, help="soft-tissue method (default: best)")
    parser.add_argument(
        "--restore-volume",
        action="store_true",
        help="before the relaxation, one smoothed step that gives the soft solids back their "
        "rest volumes (for fine meshes whose volume change the quality stage cannot remove; "
        "docs/repositioning.md)",
    )


def run(args: argparse.Namespace) -> int:
    t = time.perf_counter()
    model = read_deck(args.model)
    t_read = time.perf_counter() - t
    t = time.perf_counter()
    setup = load_setup(args.setup, model)
    options = RepositionOptions(
        **({"method": args.method} if args.method else {}),
        volume_correction=VolumeCorrectionOptions() if args.restore_volume else None,
    )
    t_setup = time.perf_counter() - t
    t = time.perf_counter()
    bar = ProgressBar("precompute")
    try:
        repositioner = Repositioner(model, setup, options, progress=bar)
    finally:
        bar.close()
    t_pre = time.perf_counter() - t
    deck_name = Path(args.model).name
    several = len(args.flexion) > 1
    for deg in args.flexion:
        repositioner.bone_pose(deg)  # validates the angle before any work or output
    jobs = []
    for deg in args.flexion:
        if several:
            folder = Path(args.out) / f"flex_{angle_tag(deg)}"
            out = folder / deck_name
            report_path = (
                Path(args.report).with_name(
                    f"{Path(args.report).stem}_{angle_tag(deg)}{Path(args.report).suffix}"
                )
                if args.report
                else folder / "report.json"
            )
        else:
            out = Path(args.out)
            if out.is_dir():
                raise SetupError(
                    f"--out {out} is a folder; give the output deck's file name", key="--out"
                )
            report_path = Path(args.report) if args.report else None
        jobs.append((deg, out, report_path))
    check_distinct_targets([p for _, o, r in jobs for p in (o, r) if p])
    context_timings = {
        "read": t_read,
        "setup": t_setup,
        "precompute": t_pre,
        **{f"precompute_{k}": v for k, v in repositioner.timings_s.items()},
    }
    status = 0
    for deg, out, report_path in jobs:
        bar = ProgressBar(f"{deg:g} deg")
        try:
            posed = export_pose(
                repositioner,
                deg,
                out,
                model_path=args.model,
                smooth=not args.no_smooth,
                force=args.force,
                flatten=args.flatten,
                overwrite=args.force,
                context_timings=context_timings,
                progress=bar,
            )
        finally:
            bar.close()
        report = posed.report
        written = report["written"]
        if report_path is not None:
            atomic_write_text(report_path, json.dumps(report, indent=2) + "\n")
        q = report["quality"]
        final = q.get("smoothed", q["posed"])
        line = (
            f"{deg:g} deg: achieved {report['achieved_flexion']:.2f} deg, worst Jacobian "
            f"{final['jacobian']['worst']:.3f} (initial {q['initial']['jacobian']['worst']:.3f})"
            f", inverted {final['inverted']}"
        )
        if final.get("tet_collapse", {}).get("worst") is not None:
            line += (
                f", worst tet collapse {final['tet_collapse']['worst']:.3f} "
                f"(initial {q['initial']['tet_collapse']['worst']:.3f})"
            )
        for warning in report["warnings"]:
            print(f"kneegui: warning: {deg:g} deg: {warning}", file=sys.stderr)
        if not posed.passes_gate:
            status = EXIT_QUALITY_GATE
        if written:
            forced = "" if posed.passes_gate else " (fails the quality gate; written with --force)"
            print(f"{line} -> {written[0]}{forced}")
        else:
            reasons = list(posed.gate_reasons)
            out_of_reach = (report.get("smoothing") or {}).get("inverted_out_of_reach")
            if out_of_reach:
                reasons.append(
                    f"{out_of_reach} inverted element(s) have no node the smoother may move"
                )
            print(
                f"{line}: fails the quality gate ({'; '.join(reasons)}); "
                "not written (use --force to write it anyway)"
            )
    return status
