"""``kneegui quality MODEL``: mesh-quality table (worst (mean ± σ)) or JSON, per model/role/part."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from kneegui.io.atomic import atomic_write_text
from kneegui.quality import (
    compute_quality,
    format_quality_table,
    jsonable,
    load_thresholds,
    quality_gate,
    summarize_quality,
)
from kneegui.topology import SOLID_TYPES

NAME = "quality"
HELP = (
    "Print the mesh quality of a deck (Jacobian, aspect ratio, warpage, skew; on tetrahedra also "
    "tet collapse, dihedral angles, volumetric skew) like Table I."
)

EXIT_QUALITY_GATE = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="LS-DYNA keyword deck")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--out", help="also write the JSON summary to this file")
    parser.add_argument(
        "--initial", help="the initial (unposed) deck: adds change vs. initial and volume change"
    )
    parser.add_argument("--setup", help="joint setup JSON: adds per-role statistics")
    parser.add_argument(
        "--thresholds", help="warn/fail table CSV (default resources/quality_thresholds.csv)"
    )
    parser.add_argument("--parts", action="store_true", help="add one line per part")
    parser.add_argument("--solids", action="store_true", help="solid elements only (no shells)")
    parser.add_argument(
        "--gate",
        action="store_true",
        help="exit with code 3 if an element is inverted or (with --initial) the worst "
        "Jacobian, or on tetrahedra a worst tet measure, is worse than the initial model's",
    )


def _part_lines(summary: dict) -> list[str]:
    tets = "tet_collapse" in summary["metrics"]
    header = "Per part: worst J | worst aspect | worst warpage | worst skew | inverted"
    lines = ["", header + (" | worst tet collapse | min / max dihedral" if tets else "")]
    for pid, g in sorted(summary["parts"].items(), key=lambda kv: int(kv[0])):
        if not g["elements"]:
            continue

        def w(metric: str, digits: int = 2, g: dict = g) -> str:
            value = g[metric]["worst"]
            return "n/a" if value is None else f"{value:.{digits}f}"

        line = (
            f"  {pid:>10} {g['title'][:32]:<32} {g['elements']:>8} el  J {w('jacobian', 3)}"
            f"  AR {w('aspect')}  W {w('warpage', 1)}  S {w('skew', 1)}  inv {g['inverted']}"
        )
        if tets and g["tet_collapse"]["worst"] is not None:
            line += (
                f"  TC {w('tet_collapse', 3)}  DA {w('dihedral_min', 1)} / {w('dihedral_max', 1)}"
            )
        lines.append(line)
    return lines


def run(args: argparse.Namespace) -> int:
    from kneegui.io.lsdyna import read_deck

    model = read_deck(args.model)
    thresholds = load_thresholds(args.thresholds) if args.thresholds else None
    roles = None
    if args.setup:
        from kneegui.setup import load_setup

        setup = load_setup(args.setup, model)
        roles = {r: list(p) for r, p in setup.roles.items() if len(p)}
    etypes = SOLID_TYPES if args.solids else None
    result = compute_quality(model.coords, model.blocks)
    initial_result = None
    initial_summary = None
    if args.initial:
        initial_model = read_deck(args.initial)
        initial_result = compute_quality(initial_model.coords, initial_model.blocks)
        initial_summary = summarize_quality(
            initial_model, initial_result, roles, thresholds, etypes=etypes
        )
    summary = summarize_quality(model, result, roles, thresholds, initial_result, etypes)
    reasons = quality_gate(summary)
    summary["gate"] = {"passed": not reasons, "reasons": reasons}
    payload = jsonable(summary)
    if args.out:
        atomic_write_text(args.out, json.dumps(payload, indent=2) + "\n")
    if args.json:
        print(json.dumps(payload, indent=2))
    else:
        columns = {}
        if initial_summary is not None:
            columns["initial"] = initial_summary["model"]
        columns[Path(args.model).name] = summary["model"]
        for role, group in summary["roles"].items():
            if group["elements"]:
                columns[role] = group
        print(format_quality_table(columns))
        if args.parts:
            print("\n".join(_part_lines(summary)))
        if reasons:
            print(f"\nquality gate: {'; '.join(reasons)}")
    if args.gate and reasons:
        return EXIT_QUALITY_GATE
    return 0
