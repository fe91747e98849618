"""The export at scale: precompute and one export at 90 degrees per demo size, split by stage.

``python -m bench.export_bench DECK_DIR [DECK_DIR ...]`` measures, for each folder holding a
``demo_leg.k`` and ``demo_leg.setup.json`` (``kneegui demo OUT --elements N``), in a fresh
process per size: the precompute (``Repositioner``) and one ``export_pose`` at 90 degrees (pose,
relaxation, smoothing, quality, write), the export's time split into region finding,
relaxation, smoothing, quality and write, the size of the relaxed region beside the model's,
the final worst Jacobian and inverted count, and the process's peak resident memory. Wall and
CPU seconds are both recorded (the solvers' kernels use up to 4 threads, so on an idle machine
the CPU time exceeds the wall time). Results: bench/results/export_scaling.json, the
table in docs/benchmarks.md (between its ``export-scaling`` markers, also rendered by
:mod:`bench.report`) and docs/images/export-scaling.png.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results" / "export_scaling.json"
#: ``--restore-volume`` runs (the opt-in step), kept apart from the default's table
RESTORE_RESULTS = ROOT / "bench" / "results" / "export_restore_volume.json"
ANGLE = 90.0
#: The default demo's variant label: hexahedral soft solids, no element locked between bones.
DEFAULT_VARIANT = "hex8"
#: The row of the export's time outside its timed stages (wall time less their sum).
UNSTAGED = "the rest (pose, pre-flight, checks, report; not timed apart)"
BEGIN, END = "<!-- export-scaling:begin -->", "<!-- export-scaling:end -->"

_CHILD = r"""
import json, os, resource, sys, tempfile, time
from kneegui.io.lsdyna import read_deck
from kneegui.reposition import Repositioner
from kneegui.reposition.pipeline import export_pose
from kneegui.reposition.repositioner import SOFT_ROLES
from kneegui.setup import load_setup
from kneegui.topology import SOLID_TYPES

from kneegui.meshopt.volume_correction import VolumeCorrectionOptions
from kneegui.reposition import RepositionOptions

folder, angle = sys.argv[1], float(sys.argv[2])
restore = len(sys.argv) > 3 and sys.argv[3] == "restore-volume"
deck = os.path.join(folder, "demo_leg.k")
model = read_deck(deck)
setup = load_setup(os.path.join(folder, "demo_leg.setup.json"), model)

def clock():
    return time.perf_counter(), time.process_time()

w, c = clock()
volume = VolumeCorrectionOptions() if restore else None
rep = Repositioner(model, setup, RepositionOptions(volume_correction=volume))
pre = {"wall_s": time.perf_counter() - w, "cpu_s": time.process_time() - c,
       "breakdown_s": dict(rep.timings_s)}
# how long a cancel would wait: the longest time between two of the export's cancel checks
# (from its start to the first and from the last to its end included)
longest, last = 0.0, 0.0

def cancel():
    global longest, last
    now = time.perf_counter()
    longest, last = max(longest, now - last), now
    return False

with tempfile.TemporaryDirectory() as tmp:
    w, c = clock()
    last = w
    posed = export_pose(
        rep, angle, os.path.join(tmp, "posed.k"), model_path=deck, force=True, cancel=cancel
    )
    wall, cpu = time.perf_counter() - w, time.process_time() - c
    longest = max(longest, time.perf_counter() - last)
r = posed.report
t = r["timings_s"]
relax = r["relaxation"] or {}
quality_opt = relax.get("quality") or {}
smooth = r["smoothing"] or {}
region = t.get("relax_region", 0.0)
split = {
    "relaxation setup (first export)": rep.timings_s.get("relaxation", 0.0)
    + rep.timings_s.get("relaxation contact", 0.0),
    "volume correction": t.get("volume_correction", 0.0)
    + rep.timings_s.get("volume correction", 0.0),
    "region finding": region,
    "relaxation": t.get("pose_relax", 0.0) - region,
    "smoothing": t.get("smoothing", 0.0),
    "quality": t.get("quality_initial", 0.0) + t.get("quality_posed", 0.0)
    + t.get("quality_smoothed", 0.0),
    "write": t.get("write", 0.0),
}
split["relaxation"] -= split["relaxation setup (first export)"]
final = r["quality"].get("smoothed", r["quality"]["posed"])
soft = set(setup.parts_of(*SOFT_ROLES))
types = sorted(k for k, b in model.blocks.items()
               if k in SOLID_TYPES and len(b) and soft & set(b.part_ids.tolist()))
locked = r["preflight"]["locked"]["count"]
variant = "+".join(types) + (f", {locked:,} locked" if locked else "")
print(json.dumps({
    "variant": variant,
    "nodes": model.n_nodes, "elements": model.n_elements,
    "solids": int(sum(len(b) for k, b in model.blocks.items() if k in SOLID_TYPES)),
    "precompute": pre,
    "export": {"wall_s": wall, "cpu_s": cpu, "split_s": split},
    "region": {"relaxed_nodes": relax.get("free_nodes", 0),
               "relaxed_corners": relax.get("corners", 0),
               "optimised_nodes": quality_opt.get("free_nodes", 0),
               "optimised_elements": quality_opt.get("elements", 0),
               "smoothed_nodes": smooth.get("free_nodes", 0)},
    "worst_jacobian": final["jacobian"]["worst"], "inverted": final["inverted"],
    "tissue_in_bones": {k: r["tissue_in_bones"][k] for k in ("nodes", "deepest", "tolerance")},
    "p95_volume_change_pct": r["volume_change"]["soft_element_p95_abs_pct"],
    "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    "cancel_gap_s": longest,
}))
"""


def _in_bones(run: dict[str, Any]) -> str:
    """The export's soft-tissue nodes in a bone, as the pose report counts them (runs saved
    before the field was recorded say so)."""
    found = run.get("tissue_in_bones")
    if found is None:
        return "not recorded"
    return f"{found['nodes']:,} ({found['deepest']:.2f} mm)"


def _p95(run: dict[str, Any]) -> str:
    """The 95th percentile of the soft solids' |volume change| after the export (runs saved
    before the field was recorded say so)."""
    value = run.get("p95_volume_change_pct")
    return "not recorded" if value is None else f"{value:.1f} %"


def measure(
    folder: Path,
    angle: float = ANGLE,
    timeout_s: float | None = None,
    restore_volume: bool = False,
) -> dict[str, Any]:
    """One size in a fresh process (see the module docstring); ``restore_volume``: with the
    opt-in volume step (``kneegui pose --restore-volume``)."""
    flag = ["restore-volume"] if restore_volume else []
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD, str(folder), str(angle), *flag],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=timeout_s,
    )
    if proc.returncode:
        return {"folder": str(folder), "error": proc.stderr.strip().splitlines()[-1:]}
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["folder"] = str(folder)
    return out


def measure_repeated(
    folder: Path, angle: float = ANGLE, repeats: int = 1, restore_volume: bool = False
) -> dict[str, Any]:
    """``repeats`` fresh-process runs of :func:`measure`; the run with the median export time
    (its stage split with it), and every run's export and precompute wall time."""
    runs = [measure(folder, angle, restore_volume=restore_volume) for _ in range(max(1, repeats))]
    ok = [r for r in runs if "error" not in r]
    if not ok:
        return runs[-1]
    ok.sort(key=lambda r: r["export"]["wall_s"])
    out = ok[(len(ok) - 1) // 2]  # the lower median for an even count
    out["repeats"] = len(ok)
    out["export_runs_s"] = [r["export"]["wall_s"] for r in ok]
    out["precompute_runs_s"] = sorted(r["precompute"]["wall_s"] for r in ok)
    return out


def _column(run: dict[str, Any]) -> str:
    """A run's column heading: its solids, and its soft solids' element types and locked
    elements (the pre-flight check's) where it recorded them."""
    variant = run.get("variant")
    return f"{run['solids']:,} solids" + (f" ({variant})" if variant else "")


def _is_default(run: dict[str, Any]) -> bool:
    """Whether a run is of the default demo (hexahedral flesh, nothing locked)."""
    return run.get("variant", DEFAULT_VARIANT) == DEFAULT_VARIANT


def _s(value: float) -> str:
    return f"{value:.2f} s" if value >= 1 else f"{1000 * value:.0f} ms"


def markdown(results: dict[str, Any]) -> list[str]:
    """The section of docs/benchmarks.md (between the markers)."""
    runs = sorted(
        (r for r in results.get("runs", []) if "error" not in r), key=lambda r: r["elements"]
    )
    lines = [
        BEGIN,
        "## The export at scale (`python -m bench.export_bench`)",
        "",
        f"One export at {results.get('angle', ANGLE):g}° (`export_pose`: pose, relaxation, "
        "smoothing, quality, write) per demo size, each in a fresh process; the run with the "
        "median export time where there were several (their count in brackets after the "
        "time; the range of their export times below the table); "
        "wall time with the CPU time in brackets (the solvers' kernels run on up to 4 threads, "
        "so the CPU time exceeds the wall time on an idle machine; on a shared one the wall "
        "time grows with the other load). "
        "![export time against model size](images/export-scaling.png)",
        "",
    ]
    if not runs:
        return [*lines, "Not measured.", END]
    head = "| | " + " | ".join(_column(r) for r in runs) + " |"
    lines += [head, "|---" * (len(runs) + 1) + "|"]

    def row(label: str, cells: list[str]) -> None:
        lines.append(f"| {label} | " + " | ".join(cells) + " |")

    row("nodes / elements", [f"{r['nodes']:,} / {r['elements']:,}" for r in runs])
    row(
        "precompute (`Repositioner`)",
        [f"{_s(r['precompute']['wall_s'])} ({_s(r['precompute']['cpu_s'])})" for r in runs],
    )
    row(
        "**export at 90°**",
        [
            f"**{_s(r['export']['wall_s'])}** ({_s(r['export']['cpu_s'])})"
            + (f" [{r['repeats']} runs]" if r.get("repeats", 1) > 1 else "")
            for r in runs
        ],
    )
    for stage in runs[0]["export"]["split_s"]:
        row(f"— {stage}", [_s(r["export"]["split_s"][stage]) for r in runs])
    # what the stages' own clocks do not cover, so that the split adds up to the export
    row(
        f"— {UNSTAGED}",
        [_s(max(0.0, r["export"]["wall_s"] - sum(r["export"]["split_s"].values()))) for r in runs],
    )
    row(
        "relaxed region: nodes / corner tets",
        [f"{r['region']['relaxed_nodes']:,} / {r['region']['relaxed_corners']:,}" for r in runs],
    )
    row(
        "quality-optimised: nodes / elements",
        [
            f"{r['region']['optimised_nodes']:,} / {r['region']['optimised_elements']:,}"
            for r in runs
        ],
    )
    row("smoothed nodes", [f"{r['region']['smoothed_nodes']:,}" for r in runs])
    row(
        "after export: worst J / inverted",
        [f"{r['worst_jacobian']:.3f} / {r['inverted']}" for r in runs],
    )
    row(
        "after export: soft-tissue nodes in a bone (deeper than 0.02 condyle radii; deepest)",
        [_in_bones(r) for r in runs],
    )
    row(
        "after export: 95th percentile of the soft solids' \\|volume change\\|",
        [_p95(r) for r in runs],
    )
    row("peak memory (process)", [f"{r['peak_rss_mb']:,.0f} MB" for r in runs])
    row(
        "longest wait for a cancel (time between two cancel checks)",
        [_s(r["cancel_gap_s"]) if "cancel_gap_s" in r else "not recorded" for r in runs],
    )
    lines += [
        "",
        "Where the export's time goes (the stage taking most of it, and the share of the "
        "model's nodes the relaxation moved):",
        "",
    ]
    for r in runs:
        split = r["export"]["split_s"]
        stage = max(split, key=split.get)
        total = sum(split.values())
        lines.append(
            f"- {_column(r)}: {stage} {100 * split[stage] / max(total, 1e-12):.0f} % "
            f"of the staged time; relaxed region {r['region']['relaxed_nodes']:,} of "
            f"{r['nodes']:,} nodes ({100 * r['region']['relaxed_nodes'] / r['nodes']:.1f} %)."
        )
    repeated = [r for r in runs if r.get("repeats", 1) > 1]
    if repeated:
        lines += ["", "Export times of the repeated sizes (every run, fresh processes):", ""]
        lines += [
            f"- {_column(r)}: "
            + ", ".join(_s(t) for t in r["export_runs_s"])
            + f" (median {_s(r['export']['wall_s'])})."
            for r in repeated
        ]
    failed = [r for r in results.get("runs", []) if "error" in r]
    for r in failed:
        lines += ["", f"{r['folder']}: failed ({' '.join(r['error'])})."]
    machine = results.get("machine")
    if machine:
        lines += [
            "",
            f"Machine: {machine.get('cpu')}, {machine.get('cores')} cores, "
            f"{machine.get('memory_gb')} GB; load average (1 / 5 / 15 min) at start "
            f"{results.get('load', '?')}.",
        ]
    return [*lines, END]


def plot(results: dict[str, Any], path: Path) -> Path | None:
    """Export time (and its stages) against model size, log-log."""
    runs = sorted(
        (r for r in results.get("runs", []) if "error" not in r), key=lambda r: r["elements"]
    )
    if not runs:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    others = [r for r in runs if not _is_default(r)]
    runs = [r for r in runs if _is_default(r)]
    x = [r["elements"] for r in runs]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ax.loglog(x, [r["export"]["wall_s"] for r in runs], "o-", label="export, wall")
    ax.loglog(x, [r["export"]["cpu_s"] for r in runs], "o--", label="export, CPU")
    for stage in ("relaxation", "smoothing", "quality", "write"):
        values = [max(r["export"]["split_s"][stage], 1e-3) for r in runs]
        ax.loglog(x, values, ".:", label=stage)
    ax.loglog(x, [r["precompute"]["wall_s"] for r in runs], "s-", label="precompute, wall")
    for marker, r in zip("^vDP*X", others, strict=False):
        ax.loglog(
            [r["elements"]],
            [r["export"]["wall_s"]],
            marker,
            color="black",
            label=f"export, wall: {r['variant']}",
        )
    ax.set_xlabel("model elements")
    ax.set_ylabel("seconds")
    ax.set_title("kneegui export at 90° against model size (demo leg; lines: default)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_docs(results: dict[str, Any], root: Path = ROOT) -> None:
    """Put the section into docs/benchmarks.md (replacing the previous one) and draw the plot."""
    doc = root / "docs" / "benchmarks.md"
    text = doc.read_text() if doc.exists() else ""
    section = "\n".join(markdown(results))
    if BEGIN in text and END in text:
        before, rest = text.split(BEGIN, 1)
        text = before + section + rest.split(END, 1)[1]
    else:
        marker = "## How it is measured"
        text = (
            text.replace(marker, section + "\n\n" + marker, 1)
            if marker in text
            else text + "\n" + section + "\n"
        )
    doc.write_text(text)
    plot(results, root / "docs" / "images" / "export-scaling.png")


def _same_deck(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Whether two runs measured the same deck: the same folder, or the same variant with
    the same node and element counts (a deck regenerated in another folder replaces its
    earlier run instead of adding a second column)."""
    if a.get("folder") == b.get("folder"):
        return True
    keys = ("variant", "nodes", "elements")
    return all(k in a and k in b for k in keys) and all(a[k] == b[k] for k in keys)


def main(argv: list[str] | None = None) -> int:
    import os

    from bench.machine import machine_description

    parser = argparse.ArgumentParser(prog="python -m bench.export_bench", description=__doc__)
    parser.add_argument("folders", nargs="+", type=Path, help="folders from `kneegui demo`")
    parser.add_argument("--angle", type=float, default=ANGLE)
    parser.add_argument("--merge", action="store_true", help="add to the saved results")
    parser.add_argument(
        "--repeats", type=int, default=1, help="fresh-process runs per size (median kept)"
    )
    parser.add_argument(
        "--restore-volume",
        action="store_true",
        help="with the opt-in volume step; results to "
        f"{RESTORE_RESULTS.relative_to(ROOT)}, not into the benchmark's table",
    )
    args = parser.parse_args(argv)
    out_file = RESTORE_RESULTS if args.restore_volume else RESULTS
    results: dict[str, Any] = {"angle": args.angle, "runs": []}
    if args.merge and out_file.exists():
        results = json.loads(out_file.read_text())
    results["machine"] = machine_description()
    results["load"] = " / ".join(f"{v:.1f}" for v in os.getloadavg())
    for folder in args.folders:
        run = measure_repeated(folder, args.angle, args.repeats, args.restore_volume)
        results["runs"] = [r for r in results["runs"] if not _same_deck(r, run)] + [run]
        print(json.dumps(run), flush=True)
        out_file.parent.mkdir(parents=True, exist_ok=True)
        out_file.write_text(json.dumps(results, indent=2) + "\n")
    if not args.restore_volume:
        write_docs(results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
