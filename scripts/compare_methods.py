"""Compare the soft-tissue methods on the demo leg at the same angles; write the docs table.

``python scripts/compare_methods.py [--elements 20000]`` writes
docs/repositioning-comparison.md and bench/results/methods.json. Every number is measured here.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from kneegui.demo import generate_demo_leg
from kneegui.quality import compute_quality
from kneegui.reposition import METHODS, Repositioner, RepositionOptions, classify_nodes
from kneegui.reposition.checks import penetrating, surface_triangles
from kneegui.reposition.pipeline import pose_model
from kneegui.reposition.skin_contours import build_skin_contours, count_contour_crossings
from kneegui.setup import load_setup

ROOT = Path(__file__).resolve().parent.parent
ANGLES = (0, 30, 60, 90, 120)
#: Variants beyond the plain methods: name -> options.
VARIANTS = {
    "blend, live slider (no relaxation)": RepositionOptions(relax=False),
    "blend + bone contact, no relaxation": RepositionOptions(contact_reach=0.25, relax=False),
}
#: A soft-tissue node counts as inside a bone when deeper than this (model units): nodes of a
#: sliding interface lie on the bone surface itself.
PENETRATION_TOLERANCE = 0.5
SHAPE_METRICS = ("aspect", "warpage", "skew")


def nodes_inside_bones(rep: Repositioner, coords, triangles) -> int:
    """Interior soft-tissue nodes deeper than the tolerance inside any bone."""
    interior = np.concatenate([rep.groups.flesh, rep.groups.band])
    ml = rep.axes.fe_axis.direction
    inside = np.zeros(len(interior), dtype=bool)
    for tris in triangles:
        inside |= penetrating(coords[interior], coords, tris, ml, PENETRATION_TOLERANCE)
    return int(inside.sum())


def measure(elements: int, methods: tuple[str, ...], smooth: bool) -> dict:
    leg = generate_demo_leg(elements)
    setup = load_setup(leg.setup, leg.model)
    q0 = compute_quality(leg.model.coords, leg.model.blocks)
    groups = classify_nodes(leg.model, setup)
    out = {
        "elements": leg.model.n_elements,
        "initial": {
            "worst_jacobian": q0.worst_jacobian(),
            "inverted": q0.n_inverted,
            **{f"worst_{m}": float(q0.concatenated(m).max()) for m in SHAPE_METRICS},
        },
        "interior_nodes": int(len(groups.flesh) + len(groups.band)),
        "methods": {},
    }
    triangles = [
        surface_triangles(leg.model, setup.parts_of(role), shells=False)
        for role in ("femur", "tibia", "fibula", "patella")
    ]
    axes_rep = Repositioner(leg.model, setup, RepositionOptions(relax=False))
    contours = build_skin_contours(
        leg.model.coords,
        groups.skin,
        axes_rep.axes.knee_center,
        axes_rep.axes.superior,
        axes_rep.axes.tibia_axis.direction,
        setup.skin_contours,
        axes_rep.options.zone_factor,
        groups.bone_surface,
    )
    variants = {m: RepositionOptions(method=m) for m in methods}
    variants.update(VARIANTS)
    for method, options in variants.items():
        t = time.perf_counter()
        rep = Repositioner(leg.model, setup, options)
        pre = time.perf_counter() - t
        pose_times = []
        rows = []
        for deg in ANGLES:
            for _ in range(3):
                t = time.perf_counter()
                rep.pose(deg)
                pose_times.append(time.perf_counter() - t)
            posed = pose_model(rep, deg, smooth=smooth)
            inside = nodes_inside_bones(rep, posed.model.coords, triangles)
            r = posed.report
            row = {
                "angle": deg,
                "achieved": r["achieved_flexion"],
                "posed_worst_jacobian": r["quality"]["posed"]["jacobian"]["worst"],
                "posed_inverted": r["quality"]["posed"]["inverted"],
                "posed_worst_aspect": r["quality"]["posed"]["aspect"]["worst"],
                "posed_worst_warpage": r["quality"]["posed"]["warpage"]["worst"],
                "posed_worst_skew": r["quality"]["posed"]["skew"]["worst"],
                "max_element_volume_change_pct": r["volume_change"]["max_element_pct"],
                "soft_tissue_volume_change_pct": r["volume_change"]["soft_tissue_total_pct"],
                "p95_element_volume_change_pct": r["volume_change"]["soft_element_p95_abs_pct"],
                "elements_volume_change_over_25_pct": r["volume_change"]["soft_elements_over_pct"][
                    "25"
                ],
                "nodes_inside_bones": inside,
                "contour_crossings": count_contour_crossings(
                    contours, posed.model.coords, reference=leg.model.coords
                ),
                "relax_s": r["timings_s"].get("pose_relax"),
            }
            if smooth:
                row["smoothed_worst_jacobian"] = r["quality"]["smoothed"]["jacobian"]["worst"]
                row["smoothed_inverted"] = r["quality"]["smoothed"]["inverted"]
                row["smoothing_s"] = r["timings_s"].get("smoothing")
            rows.append(row)
        out["methods"][method] = {
            "precompute_s": pre,
            "pose_median_ms": 1000 * statistics.median(pose_times),
            "angles": rows,
        }
    return out


def to_markdown(res: dict, smooth: bool) -> str:
    lines = [
        "# Soft-tissue methods compared",
        "",
        "Generated by `python scripts/compare_methods.py`; do not edit by hand.",
        "",
        f"Demo leg, {res['elements']:,} elements; initial worst corner Jacobian "
        f"{res['initial']['worst_jacobian']:.3f}, aspect {res['initial']['worst_aspect']:.2f}, "
        f"warpage {res['initial']['worst_warpage']:.1f}°, "
        f"skew {res['initial']['worst_skew']:.1f}°, {res['initial']['inverted']} inverted. "
        "Pose time = median of 15 `pose()` calls (3 per angle: the live slider, never relaxed). "
        "The other columns are measured on what `kneegui pose` writes: worst J, inverted, "
        "aspect, warpage and skew after the mapping and the relaxation (relax s = its time), "
        "ΔV (element volume change: the largest of any solid, the 95th percentile of the soft "
        "solids' and how many of them changed by more than 25 %), "
        '"in bone" and "crossing" after smoothing too. "In bone" = interior soft-tissue '
        f"nodes (of {res['interior_nodes']:,}) deeper than {PENETRATION_TOLERANCE} mm inside a "
        'bone; "crossing" = skin nodes beyond the plane of the neighbouring skin contour nearer '
        "the joint (the paper's kink-free condition; `count_contour_crossings`).",
        "",
    ]
    for method, m in res["methods"].items():
        lines += [
            f"## `{method}`: precompute {m['precompute_s']:.2f} s, one pose "
            f"{m['pose_median_ms']:.1f} ms",
            "",
            "| angle | achieved | worst J | inverted | worst aspect | worst warpage ° | "
            "worst skew ° | max element ΔV % | p95 \\|ΔV\\| % | ΔV > 25 % | soft-tissue ΔV % | "
            "in bone | crossing | relax s |"
            + (" smoothed worst J | smoothed inverted |" if smooth else ""),
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
            + ("---|---|" if smooth else ""),
        ]
        for r in m["angles"]:
            row = (
                f"| {r['angle']}° | {r['achieved']:.2f}° | {r['posed_worst_jacobian']:.3f} | "
                f"{r['posed_inverted']} | {r['posed_worst_aspect']:.2f} | "
                f"{r['posed_worst_warpage']:.1f} | {r['posed_worst_skew']:.1f} | "
                f"{r['max_element_volume_change_pct']:.1f} | "
                f"{r['p95_element_volume_change_pct']:.1f} | "
                f"{r['elements_volume_change_over_25_pct']} | "
                f"{r['soft_tissue_volume_change_pct']:.2f} | {r['nodes_inside_bones']} | "
                f"{r['contour_crossings']} | "
                + ("–" if r["relax_s"] is None else f"{r['relax_s']:.1f}")
                + " |"
            )
            if smooth:
                row += f" {r['smoothed_worst_jacobian']:.3f} | {r['smoothed_inverted']} |"
            lines.append(row)
        lines.append("")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--elements", type=int, default=20000)
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--no-smooth", action="store_true")
    args = parser.parse_args()
    res = measure(args.elements, tuple(args.methods.split(",")), not args.no_smooth)
    (ROOT / "bench" / "results").mkdir(parents=True, exist_ok=True)
    (ROOT / "bench" / "results" / "methods.json").write_text(
        json.dumps(res, indent=2, default=float) + "\n"
    )
    text = to_markdown(res, not args.no_smooth)
    (ROOT / "docs" / "repositioning-comparison.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    raise SystemExit(main())
