"""``kneegui axes MODEL --setup S.json``: condyle circle fits, joint axes and initial flexion.

``kneegui axes MODEL --suggest OUT.json --side left`` first writes a setup suggested from the part
titles and the bone geometry (roles, condyle node sets, axis points), then reports on it.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

NAME = "axes"
HELP = "Fit the condyle circles and print the radii, F-E and L-R axes and the initial flexion."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", help="LS-DYNA keyword deck (.k/.key/.dyn)")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--setup", help="joint setup file (kneegui-setup JSON)")
    source.add_argument(
        "--suggest",
        metavar="OUT_JSON",
        help="write a setup suggested from part titles and bone geometry to OUT_JSON, then use it",
    )
    parser.add_argument(
        "--side", choices=("right", "left"), help="knee to set up (required with --suggest)"
    )
    parser.add_argument(
        "--moving-segment",
        choices=("tibia", "femur"),
        default="tibia",
        help="segment that moves (with --suggest; default tibia)",
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")


def _vec(v: Any) -> str:
    return "(" + ", ".join(f"{float(x):9.3f}" for x in v) + ")"


def format_sensitivity(spread: dict[str, Any] | None) -> str:
    """One line of :meth:`AxisSensitivity.to_dict` (None: not measured)."""
    if spread is None:
        return "F-E axis spread: not measured (too few condyle nodes to leave a fifth out)"
    how = (
        f"{spread['percentile']:g}th percentile over {spread['n_subsets']} fits each leaving out "
        f"{100 * spread['leave_out_fraction']:g} % of each condyle's nodes"
    )
    failed = spread.get("failed_subsets", 0)
    if failed:
        how += f"; {failed} gave no determined circle"
    if spread["direction_spread_deg"] is None:
        return f"F-E axis spread: unstable ({how})"
    return (
        f"F-E axis spread: {spread['direction_spread_deg']:.2f} deg, centres "
        f"{spread['lateral_center_spread_mm']:.2f} / {spread['medial_center_spread_mm']:.2f} mm, "
        f"radii {spread['lateral_radius_spread_mm']:.2f} / "
        f"{spread['medial_radius_spread_mm']:.2f} mm (lateral / medial; {how})"
    )


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
    lines.append(format_sensitivity(result.get("sensitivity")))
    lines.append(f"initial flexion: {result['initial_flexion']:.2f} deg")
    for w in result["warnings"]:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from kneegui.errors import SetupError
    from kneegui.geometry.axes import compute_joint_axes
    from kneegui.io.lsdyna import read_deck
    from kneegui.setup.format import load_setup, save_setup
    from kneegui.setup.landmarks import suggest_setup

    if args.suggest and not args.side:
        raise SetupError("--suggest needs --side right or --side left", key="side")
    model = read_deck(args.model)
    if args.suggest:
        data = suggest_setup(model, args.side, moving_segment=args.moving_segment)
        setup = load_setup(data, model)
        save_setup(setup, args.suggest)
    else:
        setup = load_setup(args.setup, model)
    axes = compute_joint_axes(model.coords, setup)
    result = axes.to_dict()
    result["warnings"] = [*setup.warnings, *axes.warnings]
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(format_axes(result))
    return 0
