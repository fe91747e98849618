"""``python -m bench``: the whole benchmark, written to docs/benchmarks.md plus a JSON of raw data.

Runs, each in a fresh process with a wall-clock budget: the pipeline stages on the demo leg at
≈2k, ≈20k (paper scale), ≈200k and ≈1M solids (:func:`bench.pose_bench.measure_size`); the
baseline comparison at paper scale (:func:`bench.pose_bench.measure_baselines`); the GUI frame
time under Xvfb (``bench/gui_bench.py``, skipped with a message when it is absent or no display
can be made). Then writes bench/results/benchmarks.json, docs/benchmarks.md and
docs/images/bench-scaling.png / bench-inverted.png (:mod:`bench.report`).

The whole run keeps within :data:`TOTAL_BUDGET_S` (14.5 minutes): each process has a cap, and the
largest model, measured last, gets what is left.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
PAPER_SCALE = 20_000
#: Wall-clock budget of the whole run (s): 14.5 minutes, under the 15 the issue allows.
TOTAL_BUDGET_S = 870.0
#: Requested demo sizes and the most wall-clock time (s) each one's process may take. The
#: largest runs last and gets whatever the total budget has left (at most its own cap).
SIZE_BUDGETS: dict[int, float] = {2_000: 30, 20_000: 60, 200_000: 150, 1_000_000: 600}
BASELINE_BUDGET_S = 300.0
GUI_BUDGET_S = 75.0
#: Kept back from the last process for writing the report (s).
REPORT_RESERVE_S = 15.0
GUI_STEPS = 40
QUICK_SIZE = 2_000


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """Options of ``python -m bench``."""
    parser = parser or argparse.ArgumentParser(prog="python -m bench", description=__doc__)
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"smoke test: the ~{QUICK_SIZE:,}-element demo only, one repeat, 120 deg only, "
        "default method, no GUI (writes to bench/results/quick/ unless --out-dir is given)",
    )
    parser.add_argument("--repeats", type=int, default=None, help="runs per cheap stage (5)")
    parser.add_argument(
        "--heavy-repeats", type=int, default=None, help="runs per precompute and smoothing (1)"
    )
    parser.add_argument(
        "--budget-scale",
        type=float,
        default=1.0,
        help="multiply every process's wall-clock budget (default budgets total < 15 min)",
    )
    parser.add_argument("--no-gui", action="store_true", help="skip the GUI frame-time stage")
    parser.add_argument(
        "--report-only",
        type=Path,
        metavar="JSON",
        help="measure nothing: regenerate the markdown and plots from a saved benchmarks.json",
    )
    parser.add_argument(
        "--out-dir",
        type=Path,
        default=None,
        help="write docs/benchmarks.md, docs/images/ and bench/results/ under this directory "
        "(default: the repository)",
    )
    return parser


def _display_command() -> list[str] | None:
    """Prefix that gives the GUI child a display, or None if none can be made."""
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return []
    if shutil.which("xvfb-run"):
        return ["xvfb-run", "-a", "-s", "-screen 0 1600x1000x24"]
    return None


def run_gui(elements: int, budget_s: float, steps: int = GUI_STEPS) -> dict[str, Any]:
    """GUI frame time of a slider step on the demo of ``elements`` (or why it was skipped)."""
    if not (ROOT / "bench" / "gui_bench.py").exists():
        return {"skipped": "bench/gui_bench.py is not in this checkout"}
    prefix = _display_command()
    if prefix is None:
        return {"skipped": "no display and no xvfb-run to make one"}
    with tempfile.TemporaryDirectory(prefix="kneegui-bench-gui-") as tmp:
        out = Path(tmp) / "gui.json"
        cmd = [
            *prefix,
            sys.executable,
            "-m",
            "bench.gui_bench",
            "--elements",
            str(elements),
            "--steps",
            str(steps),
            "--out",
            str(out),
            "--markdown",
            str(Path(tmp) / "gui.md"),
        ]
        # own process group: on timeout, xvfb-run, Xvfb and the window all go
        proc = subprocess.Popen(
            cmd,
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        try:
            _, stderr = proc.communicate(timeout=budget_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            return {"skipped": f"the GUI did not finish within its {budget_s:.0f} s budget"}
        if proc.returncode != 0 or not out.exists():
            last = (stderr.strip().splitlines() or ["no output"])[-1]
            return {"skipped": f"the GUI benchmark failed: {last[:200]}"}
        return json.loads(out.read_text(encoding="utf-8"))


def _attach_gui(results: dict[str, Any], gui: dict[str, Any], elements: int) -> None:
    """Put the GUI frame time into the size records as the ``gui_frame`` stage."""
    from bench.report import gui_summary

    summary = None if gui.get("skipped") else gui_summary(gui)
    if summary is None and not gui.get("skipped"):
        gui["skipped"] = "bench/gui_bench.py's output has no frame time this harness knows"
    for rec in results["sizes"]:
        stages = rec.setdefault("stages", {})
        if summary is None:
            stages["gui_frame"] = {"skipped": gui["skipped"]}
        elif rec.get("requested_elements") != elements:
            stages["gui_frame"] = {"skipped": "measured at paper scale only"}
        else:
            stages["gui_frame"] = {
                "seconds": summary["frame_ms"] / 1e3,
                "repeats": summary["steps"],
                "heatmap_seconds": None
                if summary["heatmap_frame_ms"] is None
                else summary["heatmap_frame_ms"] / 1e3,
            }


def run_benchmarks(args: argparse.Namespace, log=print) -> dict[str, Any]:
    """Run every measurement and return the results dict (nothing written)."""
    from bench.machine import machine_description
    from bench.pose_bench import ANGLES, SLIDER_ANGLE, run_child

    quick = bool(args.quick)
    repeats = args.repeats or (1 if quick else 5)
    heavy = args.heavy_repeats or 1
    scale = args.budget_scale
    sizes = {QUICK_SIZE: 120.0} if quick else dict(SIZE_BUDGETS)
    largest = max(sizes)
    deadline = time.monotonic() + TOTAL_BUDGET_S * scale - REPORT_RESERVE_S
    paper_scale = QUICK_SIZE if quick else PAPER_SCALE
    angles = (120.0,) if quick else ANGLES
    started = time.time()
    results: dict[str, Any] = {
        "started_utc": dt.datetime.fromtimestamp(started, dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "load_average_start": " / ".join(f"{x:.1f}" for x in os.getloadavg()),
        "machine": machine_description(),
        "config": {
            "command": "python -m bench --quick" if quick else "python -m bench",
            "json_name": "benchmarks.json" if quick else "bench/results/benchmarks.json",
            "quick": quick,
            "repeats": repeats,
            "heavy_repeats": heavy,
            "total_budget_s": TOTAL_BUDGET_S * scale,
            "size_budget_caps_s": {str(k): v * scale for k, v in sizes.items()},
            "baseline_budget_s": (120.0 if quick else BASELINE_BUDGET_S) * scale,
            "paper_scale": paper_scale,
            "largest": largest,
            "angles": list(angles),
            "slider_angle": SLIDER_ANGLE,
        },
        "sizes": [],
    }

    def measure(elements: int) -> None:
        budget = sizes[elements] * scale
        if elements == largest:
            budget = max(0.0, min(budget, deadline - time.monotonic()))
        log(f"[bench] demo ~{elements:,} elements: stages (budget {budget:.0f} s)")
        reps = repeats if elements < 1_000_000 else min(repeats, 3)
        rec = run_child("size", elements, reps, heavy, budget)
        log(f"[bench]   {rec['status']} in {rec['wall_s']:.0f} s")
        results["sizes"].append(rec)

    for elements in sorted(sizes):
        if elements != largest:
            measure(elements)
    log(f"[bench] baselines on ~{paper_scale:,} elements at {', '.join(f'{a:g}' for a in angles)}")
    results["baselines"] = run_child(
        "baselines",
        paper_scale,
        repeats,
        heavy,
        results["config"]["baseline_budget_s"],
        angles=angles,
        methods=() if quick else None,
    )
    log(f"[bench]   {results['baselines']['status']} in {results['baselines']['wall_s']:.0f} s")
    if quick or args.no_gui:
        gui = {"skipped": "--quick" if quick else "--no-gui"}
    else:
        log("[bench] GUI frame time")
        try:
            gui = run_gui(paper_scale, GUI_BUDGET_S * scale)
        except (OSError, ValueError) as exc:  # a broken GUI run must not lose the other figures
            gui = {"skipped": f"the GUI benchmark could not be run: {exc}"}
    results["gui"] = gui
    measure(largest)  # last: it gets what the total budget has left
    results["sizes"].sort(key=lambda rec: rec["requested_elements"])
    _attach_gui(results, gui, paper_scale)
    results["duration_s"] = time.time() - started
    return results


def write_outputs(results: dict[str, Any], out_dir: Path, quick: bool) -> dict[str, Path]:
    """Write the JSON, the markdown and the plots; return their paths."""
    from bench import report

    if quick:
        paths = {
            "json": out_dir / "benchmarks.json",
            "markdown": out_dir / "benchmarks.md",
            "scaling": out_dir / "images" / "bench-scaling.png",
            "inverted": out_dir / "images" / "bench-inverted.png",
        }
    else:
        paths = {
            "json": out_dir / "bench" / "results" / "benchmarks.json",
            "markdown": out_dir / "docs" / "benchmarks.md",
            "scaling": out_dir / "docs" / "images" / "bench-scaling.png",
            "inverted": out_dir / "docs" / "images" / "bench-inverted.png",
        }
    for p in paths.values():
        p.parent.mkdir(parents=True, exist_ok=True)
    paths["json"].write_text(json.dumps(results, indent=1) + "\n", encoding="utf-8")
    report.plot_scaling(results, paths["scaling"])
    report.plot_inverted(results, paths["inverted"])
    paths["markdown"].write_text(report.to_markdown(results), encoding="utf-8")
    return paths


def run_from_args(args: argparse.Namespace, log=print) -> int:
    """Run and write; the entry of ``python -m bench``."""
    out_dir = args.out_dir
    if out_dir is None:
        out_dir = ROOT / "bench" / "results" / "quick" if args.quick else ROOT
    if args.report_only:
        results = json.loads(Path(args.report_only).read_text(encoding="utf-8"))
    else:
        results = run_benchmarks(args, log)
    paths = write_outputs(results, Path(out_dir), bool(results["config"]["quick"]))
    done = "report regenerated" if args.report_only else f"done in {results['duration_s']:.0f} s"
    log(f"[bench] {done}; wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_from_args(args)


if __name__ == "__main__":
    raise SystemExit(main())
