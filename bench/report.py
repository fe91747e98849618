"""Turn the harness's raw results into docs/benchmarks.md and the docs/images/bench-*.png plots.

Every number in the document comes from the results dict (bench/results/benchmarks.json) or from
bench/paper_table1.csv (the paper's own figures, with their source); nothing is typed here.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

from bench.pose_bench import STAGES

ROOT = Path(__file__).resolve().parent.parent
PAPER_TABLE = Path(__file__).resolve().parent / "paper_table1.csv"
#: Targets of the issue (seconds / counts) and where they apply.
#: Requested demo sizes the targets refer to: paper scale (the paper's model had ~19,000 solids)
#: and one million elements.
PAPER_SCALE, MILLION = 20_000, 1_000_000
TARGETS = {
    "pose_paper_s": 0.050,
    "pose_1m_s": 1.0,
    "precompute_paper_s": 2.0,
    "inverted_120": 0,
}
#: Columns of the comparison tables: (key, header, format).
METRIC_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("worst_jacobian", "worst J", "{:.3f}"),
    ("inverted", "inverted", "{:d}"),
    ("worst_aspect", "worst aspect", "{:.2f}"),
    ("worst_warpage", "worst warpage°", "{:.1f}"),
    ("worst_skew", "worst skew°", "{:.1f}"),
    ("worse_than_initial_aspect", "> initial worst aspect", "{:d}"),
    ("max_volume_change_pct", "max element vol. change %", "{:+.1f}"),
    ("bone_rigidity_error", "bone rigidity error", "{:.1e}"),
)


def load_paper_table(path: Path = PAPER_TABLE) -> list[dict[str, str]]:
    """The paper's Table I figures (and a few from its text), one dict per row, with sources."""
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


# ------------------------------------------------------------------------------------ formatting
def fmt_seconds(seconds: float | None) -> str:
    """A duration in the unit that reads best (µs, ms or s)."""
    if seconds is None:
        return "n/a"
    if seconds < 1e-3:
        return f"{seconds * 1e6:.0f} µs"
    if seconds < 1.0:
        return f"{seconds * 1e3:.1f} ms"
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds:.2f} s"


def _fmt(value: Any, pattern: str) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, str):  # "inf" stored as text
        return value
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if "d}" in pattern:
        return pattern.format(int(value))
    return pattern.format(value)


def verdict(measured: float | None, target: float, why_missing: str = "not measured") -> str:
    """``met`` / ``**missed**`` against an upper-bound target (``missed`` when not measured)."""
    if measured is None:
        return f"**missed** ({why_missing})"
    return "met" if measured <= target else "**missed**"


# ------------------------------------------------------------------------------------ lookups
def _pick(d: dict, *keys: str) -> Any:
    for k in keys:
        if d.get(k) is not None:
            return d[k]
    return None


def gui_summary(gui: dict) -> dict | None:
    """Frame time and rate from bench/gui_bench.py's JSON (None if it has no frame time)."""
    res = gui.get("results") or {}
    parts, heat = res.get("part_colours") or {}, res.get("jacobian_heatmap") or {}
    frame_keys = ("stepwise_median_update_ms", "median_frame_ms")
    frame = _pick(parts, *frame_keys)
    if frame is None:
        return None
    return {
        "frame_ms": float(frame),
        "heatmap_frame_ms": _pick(heat, *frame_keys),
        "steps": _pick(parts, "slider_positions", "updates"),
        "stepwise_updates_per_s": _pick(parts, "stepwise_updates_per_s", "updates_per_s"),
        "drag_updates_per_s": _pick(parts, "drag_updates_per_s"),
        "target_updates_per_s": gui.get("target_updates_per_s"),
        "elements": (gui.get("model") or {}).get("elements"),
    }


def size_record(results: dict, requested: int) -> dict | None:
    """The per-size record of the demo requested with ``requested`` elements."""
    for rec in results.get("sizes", []):
        if rec.get("requested_elements") == requested:
            return rec
    return None


def stage_seconds(rec: dict | None, stage: str) -> float | None:
    """Median seconds of a stage of a size record (None if it did not run or finish)."""
    if not rec:
        return None
    entry = rec.get("stages", {}).get(stage)
    return None if not entry or "seconds" not in entry else float(entry["seconds"])


def _why_missing(rec: dict | None, stage: str) -> str:
    if rec is None:
        return "size not run"
    if rec.get("stages", {}).get(stage, {}).get("skipped"):
        return rec["stages"][stage]["skipped"]
    if rec.get("status") == "budget":
        return f"not finished within this size's {rec['budget_s']:.0f} s budget"
    if rec.get("status") == "failed":
        return "failed: " + rec.get("error", "").splitlines()[-1] if rec.get("error") else "failed"
    return "not measured"


def _rows(results: dict, angle: float, label: str | None = None) -> list[dict]:
    rows = results.get("baselines", {}).get("rows", [])
    return [r for r in rows if r["angle"] == angle and (label is None or r["label"] == label)]


def default_rows(results: dict, angle: float) -> tuple[dict | None, dict | None]:
    """kneegui's default method at ``angle``: (without smoothing, with smoothing)."""
    base = results.get("baselines", {})
    method = base.get("default_method")
    raw = smoothed = None
    for r in _rows(results, angle):
        if r["method"] == method:
            if r.get("smoothed"):
                smoothed = r
            else:
                raw = r
    return raw, smoothed


def baseline_row(results: dict, angle: float, method: str) -> dict | None:
    """The row of baseline ``method`` (``rigid`` / ``rbf``) at ``angle``."""
    for r in _rows(results, angle):
        if r["method"] == method:
            return r
    return None


# ------------------------------------------------------------------------------------ sections
def headline(results: dict) -> list[str]:
    """The lines the README quotes."""
    paper = size_record(results, PAPER_SCALE)
    big = size_record(results, MILLION)
    lines = ["## Headline", ""]
    pose_p = stage_seconds(paper, "pose")
    pre_p = stage_seconds(paper, "precompute")
    pose_b = stage_seconds(big, "pose")

    def solids(rec: dict | None, requested: int) -> str:
        return f"{rec['solids']:,} solids" if rec and rec.get("solids") else f"~{requested:,}"

    lines.append(
        f"- One `pose()` (a slider step) at paper scale ({solids(paper, PAPER_SCALE)}): "
        f"**{fmt_seconds(pose_p)}** (target ≤ 50 ms: "
        f"{verdict(pose_p, TARGETS['pose_paper_s'], _why_missing(paper, 'pose'))}); setup "
        f"precompute {fmt_seconds(pre_p)} (target ≤ 2 s: "
        f"{verdict(pre_p, TARGETS['precompute_paper_s'], _why_missing(paper, 'precompute'))})."
    )
    lines.append(
        f"- One `pose()` at {solids(big, MILLION)}: **{fmt_seconds(pose_b)}** "
        f"(target ≤ 1 s: {verdict(pose_b, TARGETS['pose_1m_s'], _why_missing(big, 'pose'))});"
        f" setup precompute {fmt_seconds(stage_seconds(big, 'precompute'))}."
    )
    base = results.get("baselines", {})
    for angle in (90.0, 120.0):
        raw, smoothed = default_rows(results, angle)
        rigid, rbf = baseline_row(results, angle, "rigid"), baseline_row(results, angle, "rbf")
        if not (raw or rigid):
            continue

        def q(row: dict | None) -> str:
            if row is None:
                return "not measured"
            return f"worst J {_fmt(row['worst_jacobian'], '{:.2f}')}, {row['inverted']} inverted"

        lines.append(
            f"- At {angle:g}° on the {base.get('solids', 0):,}-solid demo: kneegui "
            f"(`{base.get('default_method')}`) slider pose {q(raw)}; exported (relaxation + "
            f"smoothing) {q(smoothed)}; "
            f"rigid segment rotation {q(rigid)}; RBF morph {q(rbf)}."
        )
    raw90, smooth90 = default_rows(results, 90.0)
    rigid90, rbf90 = baseline_row(results, 90.0, "rigid"), baseline_row(results, 90.0, "rbf")
    if raw90 and rigid90 and rbf90:
        lines.append(
            f"- Same run, 90°: kneegui's `pose()` took {fmt_seconds(raw90['seconds'])}, "
            f"{rbf90['seconds'] / raw90['seconds']:.0f}x less than the RBF morph "
            f"({fmt_seconds(rbf90['seconds'])}) and {raw90['seconds'] / rigid90['seconds']:.0f}x "
            f"more than the rigid rotation ({fmt_seconds(rigid90['seconds'])})."
        )
    paper_time = next(
        (r for r in load_paper_table() if r["metric"] == "time_s" and r["paper"]), None
    )
    if paper_time and raw90:
        pose_and_smooth = (
            f"; pose + relaxation + smoothing {fmt_seconds(smooth90['seconds'])}"
            if smooth90
            else ""
        )
        lines.append(
            f"- The paper: {float(paper_time['paper']):g} s per pose (bones, skin contours and "
            f"soft-tissue mapping) for its ≈ 19,000-solid model on a Core2 Q6600. kneegui here, at "
            f"90° on the {base.get('solids', 0):,}-solid demo: `pose()` "
            f"{fmt_seconds(raw90['seconds'])}{pose_and_smooth} (different model and machine, so "
            "no ratio is given)."
        )
    lines.append("")
    return lines


def targets_table(results: dict) -> list[str]:
    paper = size_record(results, PAPER_SCALE)
    big = size_record(results, MILLION)
    raw120, smooth120 = default_rows(results, 120.0)
    rigid120 = baseline_row(results, 120.0, "rigid")
    rbf120 = baseline_row(results, 120.0, "rbf")
    lines = ["## Targets", "", "| target | measured | verdict |", "|---|---|---|"]
    for label, rec, stage, key in (
        ("one `pose()` ≤ 50 ms at paper scale", paper, "pose", "pose_paper_s"),
        ("setup precompute ≤ 2 s at paper scale", paper, "precompute", "precompute_paper_s"),
        ("one `pose()` ≤ 1 s at 1M elements", big, "pose", "pose_1m_s"),
    ):
        value = stage_seconds(rec, stage)
        size = f" ({rec.get('solids', 0):,} solids)" if rec else ""
        lines.append(
            f"| {label} | {fmt_seconds(value)}{size} | "
            f"{verdict(value, TARGETS[key], _why_missing(rec, stage))} |"
        )
    if smooth120 or raw120:
        best = smooth120 or raw120
        others = ", ".join(
            f"{name} {row['inverted']}"
            for name, row in (("rigid", rigid120), ("RBF", rbf120))
            if row is not None
        )
        lines.append(
            f"| zero inverted elements at 120° (baselines: {others}) | {best['inverted']} "
            f"({best['label']}) | {verdict(best['inverted'], TARGETS['inverted_120'])} |"
        )
    else:
        lines.append("| zero inverted elements at 120° | not measured | **missed** |")
    lines.append("")
    return lines


def scaling_table(results: dict) -> list[str]:
    sizes = results.get("sizes", [])
    if not sizes:
        return []
    head = (
        "| stage | "
        + " | ".join(
            f"{r['solids']:,} solids" if r.get("solids") else f"~{r['requested_elements']:,} wanted"
            for r in sizes
        )
        + " |"
    )
    lines = [
        "## Stages by model size",
        "",
        "Demo leg at each size (`kneegui.demo.generate_demo_leg`); median of the repeats given in "
        "brackets; the default repositioning method; posed to "
        f"{results['config']['slider_angle']:g}°. ![scaling](images/bench-scaling.png)",
        "",
        head,
        "|---" * (len(sizes) + 1) + "|",
        "| nodes / elements | "
        + " | ".join(f"{r.get('nodes', 0):,} / {r.get('elements', 0):,}" for r in sizes)
        + " |",
    ]
    for stage, label in STAGES.items():
        cells = []
        for rec in sizes:
            entry = rec.get("stages", {}).get(stage)
            if entry and "seconds" in entry:
                cells.append(f"{fmt_seconds(entry['seconds'])} ({entry['repeats']})")
            elif entry and entry.get("skipped"):
                cells.append(f"skipped: {entry['skipped']}")
            else:
                cells.append(_why_missing(rec, stage))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append(
        "| peak memory of the run | "
        + " | ".join(f"{r.get('peak_rss_mb', 0):,.0f} MB" for r in sizes)
        + " |"
    )
    lines.append(
        "| status (wall time / budget) | "
        + " | ".join(f"{r['status']} ({r['wall_s']:.0f} s / {r['budget_s']:.0f} s)" for r in sizes)
        + " |"
    )
    extra = []
    for rec in sizes:
        sm = rec.get("stages", {}).get("smoothing")
        if sm and "inverted_before" in sm:
            extra.append(
                f"{rec.get('solids', 0):,} solids: {sm['inverted_before']} → {sm['inverted_after']}"
            )
    if extra:
        lines += [
            "",
            "Inverted elements at the slider angle before → after smoothing: "
            + "; ".join(extra)
            + ".",
        ]
    gui = results.get("gui", {})
    if gui.get("skipped"):
        lines += ["", f"GUI frame time: skipped ({gui['skipped']})."]
    elif gui_summary(gui):
        g = gui_summary(gui)
        rate = g["drag_updates_per_s"] or g["stepwise_updates_per_s"] or 0.0
        target = g["target_updates_per_s"]
        heat = g["heatmap_frame_ms"]
        elements = f"{g['elements']:,}-element" if g["elements"] else "default"
        lines += [
            "",
            f"GUI (bench/gui_bench.py, {elements} demo, {g['steps']} slider positions, software "
            f"OpenGL under Xvfb): median update {g['frame_ms']:.1f} ms in part colours"
            + (
                f", {heat:.1f} ms with the Jacobian heat map (quality recomputed each step)"
                if heat is not None
                else ""
            )
            + f"; {rate:.1f} updates/s"
            + (
                f" (GUI target ≥ {target:g}: {'met' if rate >= target else '**missed**'})."
                if target
                else "."
            ),
        ]
    lines.append("")
    return lines


def _metric_cells(row: dict) -> str:
    return " | ".join(_fmt(row.get(k), f) for k, _, f in METRIC_COLUMNS)


def comparison_tables(results: dict) -> list[str]:
    base = results.get("baselines", {})
    if not base.get("rows") and not base.get("initial"):
        return ["## Baselines", "", f"Not measured ({base.get('status', 'not run')}).", ""]
    ctl = base.get("rbf_control", {})
    per_seg = ", ".join(f"{k} {v}" for k, v in ctl.get("per_segment", {}).items())
    lines = [
        "## Against the baselines",
        "",
        f"Same model (demo leg, {base['solids']:,} solids, {base['elements']:,} elements), same "
        "bone transforms at every angle. Time: median of the repeats in brackets (posing only for "
        "the baselines and kneegui's slider `pose()`; pose + relaxation (default method only) + "
        "smoothing for the smoothed rows). RBF control points: "
        f"{ctl.get('count', 0)} ({per_seg}). Quality over every solid and shell element. "
        "![inverted elements](images/bench-inverted.png)",
        "",
    ]
    pre = base.get("precompute", {})
    if pre:
        lines.append(
            "One-off precompute per model: "
            + "; ".join(
                f"{'RBF control points' if k == 'rbf' else 'kneegui ' + k} "
                f"{fmt_seconds(v['seconds'])}"
                for k, v in pre.items()
            )
            + "."
        )
        lines.append("")
    header = "| method | time | " + " | ".join(h for _, h, _ in METRIC_COLUMNS) + " |"
    rule = "|---" * (len(METRIC_COLUMNS) + 2) + "|"
    paper_rows = {r["metric"]: r for r in load_paper_table() if r["angle_deg"] == "90"}
    for angle in base["angles"]:
        rows = _rows(results, angle)
        if not rows:
            lines += [f"### {angle:g}°", "", f"Not measured ({base.get('status')}).", ""]
            continue
        lines += [f"### {angle:g}°", "", header, rule]
        if angle == base["angles"][0]:
            lines.append(f"| initial model | | {_metric_cells(base['initial'])} |")
        for r in rows:
            lines.append(
                f"| {r['label']} | {fmt_seconds(r['seconds'])} ({r['repeats']}) | "
                f"{_metric_cells(r)} |"
            )
        if angle == 90.0 and paper_rows:
            for col, label in (
                ("initial", "paper: initial model"),
                ("paper", "paper: repositioned"),
                ("paper_smoothed", "paper: repositioned + smoothing"),
                ("fe_simulation", "paper: FE-simulation positioning"),
            ):
                cells = []
                for key, _, pattern in METRIC_COLUMNS:
                    value = paper_rows.get(key, {}).get(col, "")
                    cells.append(_fmt(float(value), pattern.replace("d}", "g}")) if value else "")
                t = paper_rows.get("time_s", {}).get(col, "")
                lines.append(
                    f"| *{label}* | {fmt_seconds(float(t)) if t else ''} | "
                    + " | ".join(cells)
                    + " |"
                )
        lines.append("")
    if paper_rows:
        lines += [
            "Rows in italics are the paper's own figures (Jani et al. 2012, Table I and text: "
            "GM/UVA 50th male lower extremity, ≈ 19,000 solids, Intel Core2 Q6600), copied from "
            "bench/paper_table1.csv with their source; they were not measured here. The paper "
            "also reports "
            + "; ".join(
                f"{r['paper']} elements above the initial worst aspect ratio at {r['angle_deg']}°"
                for r in load_paper_table()
                if r["metric"] == "worse_than_initial_aspect"
            )
            + ".",
            "",
        ]
    lines += summary_matrix(results, "inverted", "Inverted elements by angle", "{:d}")
    lines += summary_matrix(results, "worst_jacobian", "Worst Jacobian by angle", "{:.3f}")
    return lines


def summary_matrix(results: dict, key: str, title: str, pattern: str) -> list[str]:
    base = results["baselines"]
    labels = list(dict.fromkeys(r["label"] for r in base["rows"]))
    angles = base["angles"]
    lines = [f"### {title}", "", "| method | " + " | ".join(f"{a:g}°" for a in angles) + " |"]
    lines.append("|---" * (len(angles) + 1) + "|")
    for label in labels:
        cells = []
        for a in angles:
            rows = _rows(results, a, label)
            cells.append(_fmt(rows[0][key], pattern) if rows else "n/a")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append("")
    return lines


METHOD_NOTES = """## How it is measured

- **Command.** `python -m bench` (from the source tree) regenerates this file,
  bench/results/benchmarks.json (every raw run time, the configuration and the machine) and the
  plots. Each size and the baseline comparison run in a fresh Python process with a wall-clock
  budget (the whole run stays under 14.5 minutes; the largest model runs last with the time
  left); a stage that had not finished when its budget ran out is reported as such, never
  estimated. `--quick` runs the ~2k demo only, with one repeat, for the smoke test.
- **Figures.** Every time is the median of its repeats (the count is in brackets). Comparisons
  are made within one run on one machine; the paper's figures are printed beside ours,
  labelled, never divided into ours.
- **Stages.** precompute = constructing `Repositioner(model, setup)` with the default
  `RepositionOptions()` (at least 3 runs up to paper scale, 1 above); `pose()` = one call at a
  new angle (0.5° slider steps after a warm-up);
  full pose with quality = `pose_model(..., smooth=True)` less its smoothing stage (mapping,
  relaxation, initial and posed quality, volume change, gate, report); quality alone =
  `compute_quality` of the posed coordinates; deck read = `read_deck` of a deck written by
  `write_model`; deck write = `write_deck` of the read model with the posed coordinates;
  smoothing = the smoothing stage of that `pose_model` run;
  GUI frame = `bench/gui_bench.py` (slider move to end of render in the real window under Xvfb,
  part colours and Jacobian heat map).
- **Baselines** (bench/baselines.py), driven by kneegui's own bone transforms at each angle so
  that only the soft-tissue treatment differs. *Rigid segment rotation*: the moving segment's
  bone nodes and every soft-tissue node on its side of the knee's bisector plane (through the
  knee centre, containing the flexion axis, halving the thigh-leg angle of the initial pose)
  move with that segment's rigid transform; femur and patella nodes follow their own bone.
  *RBF morph* (the approach of PIPER's kriging module): `scipy.interpolate.RBFInterpolator`
  with `kernel="thin_plate_spline"` (degree-1 polynomial, no smoothing) fitted to the
  displacements of a farthest-point subsample of each bone's surface nodes (1,000 in total,
  shared among femur, tibia + fibula and patella in proportion to their surface-node counts, at
  least 50 each), evaluated at every soft-tissue node; bone nodes move rigidly. Its time per
  pose includes fitting the interpolant (the displacements change with the angle); choosing the
  control points is the one-off precompute.
- **Quality** (docs/quality-table.md, QUALITY.md): corner Jacobian ratio (≤ 0 = inverted),
  aspect ratio, warpage and skew as crash pre-processors define them, over every solid and shell;
  "> initial worst aspect" counts elements whose aspect ratio exceeds the initial model's worst
  (the paper's measure); max element volume change = the signed change of the solid whose
  relative volume change is largest (an inverted element shows below -100 %).
- **Bone rigidity error** = max over bones (femur, tibia, fibula, patella) of
  max |d − d₀| / d₀ over 5,000 random node pairs of the bone (fixed seed); 0 for a rigid motion,
  ~1e-15 is round-off.
"""


def machine_lines(results: dict) -> list[str]:
    m = results["machine"]
    cfg = results["config"]
    return [
        "## Machine and run",
        "",
        f"{m['cpu']}, {m['cores']} cores, {m['memory_gb']} GB; {m['os']}; Python {m['python']}, "
        f"numpy {m['numpy']}, scipy {m['scipy']}. Run started {results['started_utc']}, took "
        f"{results['duration_s']:.0f} s; repeats {cfg['repeats']} (cheap stages), "
        f"{cfg['heavy_repeats']} (smoothing, and precompute above paper scale); load average at "
        "start "
        f"{results.get('load_average_start', 'n/a')} (other processes may share the CPU).",
        "",
    ]


def export_scaling_lines() -> list[str]:
    """The export-at-scale section (:mod:`bench.export_bench`), from its saved results."""
    from bench.export_bench import RESULTS, markdown

    if not RESULTS.exists():
        return []
    return [*markdown(json.loads(RESULTS.read_text())), ""]


def to_markdown(results: dict) -> str:
    """The whole docs/benchmarks.md text from the results dict."""
    cfg = results["config"]
    lines = [
        "# Benchmarks: speed, scale and quality against the paper and the baselines",
        "",
        f"Generated by `{cfg['command']}`; do not edit by hand. Raw figures: {cfg['json_name']}.",
        "",
    ]
    if cfg.get("quick"):
        lines += [
            "**Quick run (smoke test): one small model, one repeat; not the published figures.**",
            "",
        ]
    lines += headline(results)
    lines += targets_table(results)
    lines += scaling_table(results)
    lines += comparison_tables(results)
    lines += export_scaling_lines()
    lines += [*METHOD_NOTES.splitlines(), ""]
    lines += machine_lines(results)
    return "\n".join(lines)


# ------------------------------------------------------------------------------------ plots
def plot_scaling(results: dict, path: Path) -> Path | None:
    """Log-log plot of each stage's median time against the solid-element count."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = [r for r in results.get("sizes", []) if r.get("solids")]
    if not sizes:
        return None
    fig, ax = plt.subplots(figsize=(8, 5.5), dpi=110)
    for stage, label in STAGES.items():
        pts = [(r["solids"], stage_seconds(r, stage)) for r in sizes]
        pts = [(x, y) for x, y in pts if y is not None and y > 0]
        if pts:
            xs, ys = zip(*pts, strict=True)
            ax.plot(xs, ys, marker="o", label=label.replace("`", ""))
    ax.axhline(TARGETS["pose_paper_s"], color="grey", ls=":", lw=1)
    ax.axhline(TARGETS["pose_1m_s"], color="grey", ls="--", lw=1)
    ax.text(
        sizes[0]["solids"],
        TARGETS["pose_paper_s"] * 1.1,
        "pose target, paper scale",
        fontsize=7,
        color="grey",
    )
    ax.text(
        sizes[0]["solids"], TARGETS["pose_1m_s"] * 1.1, "pose target, 1M", fontsize=7, color="grey"
    )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("solid elements")
    ax.set_ylabel("median time (s)")
    ax.set_title("kneegui stages vs model size (demo leg)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_inverted(results: dict, path: Path) -> Path | None:
    """Inverted elements against flexion angle, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    base = results.get("baselines", {})
    if not base.get("rows"):
        return None
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=110)
    methods = list(dict.fromkeys(r["method"] for r in base["rows"]))
    colours = {m: f"C{i}" for i, m in enumerate(methods)}
    for label in dict.fromkeys(r["label"] for r in base["rows"]):
        rows = [r for r in base["rows"] if r["label"] == label]
        xs = [r["angle"] for r in rows]
        ys = [r["inverted"] for r in rows]
        smoothed = bool(rows[0].get("smoothed"))
        ax.plot(
            xs,
            ys,
            marker="s" if smoothed else "o",
            label=label,
            ls="--" if smoothed else "-",
            color=colours[rows[0]["method"]],
        )
    ax.set_xlabel("target flexion (deg)")
    ax.set_ylabel("inverted elements")
    ax.set_yscale("symlog", linthresh=1)
    ax.set_title(f"Inverted elements, demo leg {base.get('solids', 0):,} solids")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
