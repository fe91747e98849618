"""The batch summary: one row per posture (CSV and Markdown) and quality-vs-flexion plots.

Every number is read from the posture's pose report; a column whose value the report does not
carry stays empty (``inverted_locked`` / ``inverted_movable`` come from the report's
``inverted`` split, :meth:`kneegui.reposition.preflight.Preflight.split_inverted`; a report
written before the pre-flight check existed has none).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from kneegui.batch.plan import Posture
from kneegui.io.atomic import atomic_write_bytes, atomic_write_text

#: Summary columns, in order, with their Markdown headers.
COLUMNS: dict[str, str] = {
    "posture": "posture",
    "status": "status",
    "flexion": "target (deg)",
    "achieved_flexion": "achieved (deg)",
    "inverted": "inverted",
    "inverted_locked": "inverted locked",
    "inverted_movable": "inverted movable",
    "worst_jacobian": "worst Jacobian",
    "initial_worst_jacobian": "initial worst Jacobian",
    "worst_aspect": "worst aspect",
    "worst_warpage": "worst warpage (deg)",
    "worst_skew": "worst skew (deg)",
    "tissue_in_bones": "tissue nodes in bones",
    "tissue_in_bones_deepest": "deepest in bone",
    "seconds": "time (s)",
    "reason": "reason",
}


def _locked_movable(report: dict[str, Any], final: dict[str, Any]) -> tuple[Any, Any]:
    """Inverted elements split into locked / movable, where the report has them."""
    for source in (
        final,
        report.get("inverted") if isinstance(report.get("inverted"), dict) else {},
    ):
        locked = source.get("inverted_locked", source.get("locked"))
        movable = source.get("inverted_movable", source.get("movable"))
        if locked is not None or movable is not None:
            return locked, movable
    return None, None


def summary_row(posture: Posture, report: dict[str, Any]) -> dict[str, Any]:
    """The summary fields of one posture, from its pose report (final = smoothed if smoothed)."""
    q = report["quality"]
    final = q.get("smoothed", q["posed"])
    locked, movable = _locked_movable(report, final)
    in_bones = report.get("tissue_in_bones") or {}
    timings = report.get("timings_s", {})
    return {
        "deck": posture.deck_name,
        "tables": posture.tables_tag,
        "achieved_flexion": report["achieved_flexion"],
        "inverted": final["inverted"],
        "inverted_locked": locked,
        "inverted_movable": movable,
        "worst_jacobian": final["jacobian"]["worst"],
        "initial_worst_jacobian": q["initial"]["jacobian"]["worst"],
        "worst_aspect": final["aspect"]["worst"],
        "worst_warpage": final["warpage"]["worst"],
        "worst_skew": final["skew"]["worst"],
        "tissue_in_bones": in_bones.get("nodes"),
        "tissue_in_bones_deepest": in_bones.get("deepest"),
        "pose_seconds": sum(
            v for k, v in timings.items() if k in ("pose", "smoothing", "write", "tissue_in_bones")
        ),
    }


def _cells(entry: dict[str, Any]) -> dict[str, Any]:
    row = entry.get("row") or {}
    seconds = entry.get("seconds")
    if seconds is None:  # resumed: the posing time its report recorded
        seconds = row.get("pose_seconds")
    values = {
        "posture": entry["id"],
        "status": entry["status"] + (" (resumed)" if entry.get("skipped") else ""),
        "flexion": entry["flexion"],
        "seconds": seconds,
        "reason": entry.get("reason", ""),
    }
    values.update({k: row.get(k) for k in COLUMNS if k not in values})
    return values


def _fmt(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def write_summary(out: Path, entries: Sequence[dict[str, Any]]) -> list[Path]:
    """``OUT/summary.csv`` and ``OUT/summary.md`` (one row per posture, plan order)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(COLUMNS)
    md = [
        "| " + " | ".join(COLUMNS.values()) + " |",
        "|" + "|".join("---" for _ in COLUMNS) + "|",
    ]
    for entry in entries:
        cells = _cells(entry)
        writer.writerow(["" if cells[k] is None else cells[k] for k in COLUMNS])
        md.append("| " + " | ".join(_fmt(cells[k]).replace("|", "\\|") for k in COLUMNS) + " |")
    return [
        atomic_write_text(out / "summary.csv", buf.getvalue()),
        atomic_write_text(out / "summary.md", "\n".join(md) + "\n"),
    ]


def write_plots(out: Path, entries: Sequence[dict[str, Any]]) -> tuple[list[Path], list[str]]:
    """``OUT/<deck>/quality_vs_flexion.png`` per deck: worst Jacobian and inverted elements
    against target flexion, one line per kinematic-table choice.

    Returns the files written and warnings (matplotlib missing: no plot).
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return [], ["no plots: matplotlib is not installed (pip install 'kneegui[gui]')"]
    decks: dict[str, dict[str, list[tuple[float, float, float]]]] = {}
    for entry in entries:
        row = entry.get("row")
        if not row:
            continue
        series = decks.setdefault(row["deck"], {}).setdefault(row["tables"], [])
        series.append((entry["flexion"], row["worst_jacobian"], row["inverted"]))
    written = []
    for deck, by_tables in decks.items():
        fig = Figure(figsize=(8, 3.4), dpi=100)
        FigureCanvasAgg(fig)
        ax_j, ax_i = fig.subplots(1, 2)
        for tables, points in sorted(by_tables.items()):
            points.sort()
            x = [p[0] for p in points]
            ax_j.plot(x, [p[1] for p in points], "o-", label=tables)
            ax_i.plot(x, [p[2] for p in points], "o-", label=tables)
        ax_j.set(xlabel="flexion (deg)", ylabel="worst corner Jacobian", title=deck)
        ax_i.set(xlabel="flexion (deg)", ylabel="inverted elements", title=deck)
        ax_j.legend(fontsize="small", title="tables")
        for ax in (ax_j, ax_i):
            ax.grid(alpha=0.3)
        fig.tight_layout()
        png = io.BytesIO()
        fig.savefig(png, format="png", metadata={"Software": None})
        written.append(atomic_write_bytes(out / deck / "quality_vs_flexion.png", png.getvalue()))
    return written, []
