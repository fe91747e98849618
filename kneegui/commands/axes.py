"""``kneegui axes MODEL --setup S.json``: condyle circle fits, joint axes and initial flexion."""

from __future__ import annotations

import argparse
import json
from typing import Any

NAME = "axes"
HELP = "Fit the condyle circles and print the radii, F-E and L-R axes and the initial flexion."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="LS-DYNA keyword deck (.k/.key/.dyn)")
    parser.add_argument("--setup", required=True, help="joint setup file (kneegui-setup JSON)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")


def _vec(v: Any) -> str:
    return "(" + ", ".join(f"{float(x):9.3f}" for x in v) + ")"


def format_axes(result: dict[str, Any]) -> str:
    """Human-readable text of :meth:`JointAxes.to_dict` (plus setup warnings)."""
    lines = [
        f"side: {result['side']}",
        f"lateral condyle: radius {result['lateral_radius']:.2f} mm, "
        f"RMS {result['lateral_rms']:.3f} mm, arc {result['lateral_arc_span_deg']:.0f} deg, "
        f"centre {_vec(result['lateral_center'])}",
        f"medial condyle:  radius {result['medial_radius']:.2f} mm, "
        f"RMS {result['medial_rms']:.3f} mm, arc {result['medial_arc_span_deg']:.0f} deg, "
        f"centre {_vec(result['medial_center'])}",
    ]
    for key, label in (
        ("fe_axis", "F-E axis (GCA)"),
        ("lr_axis", "L-R axis"),
        ("femur_axis", "femoral axis"),
        ("tibia_axis", "tibial axis"),
    ):
        ax = result[key]
        lines.append(f"{label:15s} point {_vec(ax['point'])}  direction {_vec(ax['direction'])}")
    lines.append(f"initial flexion: {result['initial_flexion']:.2f} deg")
    for w in result["warnings"]:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from kneegui.geometry.axes import compute_joint_axes
    from kneegui.io.lsdyna import read_deck
    from kneegui.setup.format import load_setup

    model = read_deck(args.model)
    setup = load_setup(args.setup, model)
    axes = compute_joint_axes(model.coords, setup)
    result = axes.to_dict()
    result["warnings"] = [*setup.warnings, *axes.warnings]
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(format_axes(result))
    return 0
