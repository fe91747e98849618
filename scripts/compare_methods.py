"""Compare the soft-tissue methods on the demo leg, and the export on every demo variant, at the
same angles; write the docs tables.

``python scripts/compare_methods.py [--elements 20000]`` writes the methods section of
docs/repositioning-comparison.md and bench/results/methods.json;
``python scripts/compare_methods.py --variants [--elements 20000]`` writes its variants section
(one table per demo variant: what ``kneegui pose`` writes) and bench/results/variants.json.
Each run replaces only its own section. Every number is measured here.
"""

from __future__ import annotations

import kneegui.reproducible  # noqa: F401  (before numpy: the same kernels on every machine)

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np

from kneegui.demo import generate_demo_leg
from kneegui.quality import compute_quality
from kneegui.reposition import METHODS, Repositioner, RepositionOptions, classify_nodes
from kneegui.reposition.checks import penetrating, surface_triangles
from kneegui.reposition.pipeline import pose_model
from kneegui.reposition.preflight import preflight_of
from kneegui.reposition.skin_contours import build_skin_contours, count_contour_crossings
from kneegui.setup import load_setup
from kneegui.topology import SOLID_TYPES

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


#: Demo variants of the variants table: name -> ``generate_demo_leg`` keywords, each changed
#: alone from the default leg. The engine is told nothing of them; the unit only scales this
#: script's in-bone tolerance.
DEMO_VARIANTS: dict[str, dict] = {
    "hex, sliding, right, mm (default)": {},
    "hex, left": {"side": "left"},
    "hex, m": {"unit": "m"},
    "hex, built at 0°": {"initial_flexion": 0.0},
    "hex, built at 20°": {"initial_flexion": 20.0},
    "hex, welded": {"joint": "welded"},
    "tet": {"element_type": "tet"},
    "mixed": {"element_type": "mixed"},
    "tet10": {"element_type": "tet10"},
}
TET_TYPES = ("tet4", "tet10")
#: Variants with no coarse grid that meets the demo's quality bounds (the leg built at 20 deg:
#: docs/demo-leg.md), built at this many solids instead (as the variant test matrix does).
SMALLEST_ELEMENTS = {"hex, built at 20°": 20_000}


def _worst(q, types: tuple[str, ...], metric: str, worst=max):
    values = [getattr(q[t], metric) for t in types if t in q and len(q[t])]
    return float(worst(v.max() if worst is max else v.min() for v in values)) if values else None


def measure_variants(
    elements: int, names: tuple[str, ...], angles: tuple[float, ...] = ANGLES
) -> dict:
    """The export (``pose_model``, smoothing on) on each demo variant at ``angles``."""
    out = {}
    for name in names:
        kwargs = DEMO_VARIANTS[name]
        unit = 1e-3 if kwargs.get("unit") == "m" else 1.0
        leg = generate_demo_leg(max(elements, SMALLEST_ELEMENTS.get(name, 0)), **kwargs)
        model = leg.model
        setup = load_setup(leg.setup, model)
        t = time.perf_counter()
        rep = Repositioner(model, setup, RepositionOptions())
        pre = time.perf_counter() - t
        q0 = compute_quality(model.coords, model.blocks)
        preflight = preflight_of(rep)
        triangles = [
            surface_triangles(model, setup.parts_of(role), shells=False)
            for role in ("femur", "tibia", "fibula", "patella")
        ]
        hexes = tuple(t for t in SOLID_TYPES if t not in TET_TYPES)
        entry = {
            "requested": max(elements, SMALLEST_ELEMENTS.get(name, 0)),
            "elements": model.n_elements,
            "unit_mm": unit,
            "precompute_s": pre,
            "locked": len(preflight.locked),
            "locked_with_free_nodes": int(np.count_nonzero(preflight.locked.free_nodes)),
            "load_1min": os.getloadavg()[0],
            "initial": {
                "worst_hex_jacobian": _worst(q0, hexes, "jacobian_corner", min),
                "worst_tet_aspect": _worst(q0, TET_TYPES, "tet_aspect"),
                "worst_tet_vol_skew": _worst(q0, TET_TYPES, "vol_skew"),
                "worst_tet_collapse": _worst(q0, TET_TYPES, "tet_collapse", min),
                "worst_tet_dihedral_min": _worst(q0, TET_TYPES, "dihedral_min", min),
                "worst_tet_dihedral_max": _worst(q0, TET_TYPES, "dihedral_max"),
                "inverted": q0.n_inverted,
            },
            "angles": [],
        }
        for deg in angles:
            t = time.perf_counter()
            posed = pose_model(rep, deg)
            seconds = time.perf_counter() - t
            coords = posed.model.coords
            q = compute_quality(coords, model.blocks)
            inverted = preflight.split_inverted(posed.model, q)
            inv_locked, inv_movable = inverted["locked"], inverted["movable"] + inverted["other"]
            interior = np.concatenate([rep.groups.flesh, rep.groups.band])
            inside = np.zeros(len(interior), dtype=bool)
            for tris in triangles:
                if len(tris):
                    inside |= penetrating(
                        coords[interior],
                        coords,
                        tris,
                        rep.axes.fe_axis.direction,
                        PENETRATION_TOLERANCE * unit,
                    )
            v = posed.report["volume_change"]
            entry["angles"].append(
                {
                    "angle": deg,
                    "inverted_locked": inv_locked,
                    "inverted_movable": inv_movable,
                    "worst_hex_jacobian": _worst(q, hexes, "jacobian_corner", min),
                    "worst_tet_aspect": _worst(q, TET_TYPES, "tet_aspect"),
                    "worst_tet_vol_skew": _worst(q, TET_TYPES, "vol_skew"),
                    "worst_tet_collapse": _worst(q, TET_TYPES, "tet_collapse", min),
                    "worst_tet_dihedral_min": _worst(q, TET_TYPES, "dihedral_min", min),
                    "worst_tet_dihedral_max": _worst(q, TET_TYPES, "dihedral_max"),
                    "nodes_inside_bones": int(inside.sum()),
                    "p95_element_volume_change_pct": v["soft_element_p95_abs_pct"],
                    "elements_volume_change_over_25_pct": v["soft_elements_over_pct"]["25"],
                    "gate_passed": posed.passes_gate,
                    "gate_reasons": posed.gate_reasons,
                    "seconds": seconds,
                }
            )
            print(name, entry["angles"][-1], flush=True)
        out[name] = entry
    return out


def _fmt(value, spec: str) -> str:
    return "–" if value is None else format(value, spec)


def _measured(entry: dict, key: str, spec: str) -> str:
    # an entry saved before the tet measures were added: "not measured", never "no tets" (–)
    return "not measured" if key not in entry else _fmt(entry[key], spec)


def _dihedrals(entry: dict) -> str:
    if "worst_tet_dihedral_min" not in entry:
        return "not measured"
    lo, hi = entry["worst_tet_dihedral_min"], entry["worst_tet_dihedral_max"]
    return "–" if lo is None else f"{lo:.1f} / {hi:.1f}"


def variants_markdown(res: dict) -> str:
    lines = [
        "## The export on every demo variant",
        "",
        "Generated by `python scripts/compare_methods.py --variants`. What `kneegui pose` writes "
        "(mapping, relaxation, smoothing; default options, the engine told nothing of the "
        "variant) at each angle. Inverted elements are split as the pre-flight check "
        "(`kneegui check`) splits them into *locked* (bone nodes on two segments that move "
        "apart, and either every node on a bone or the bone nodes alone proven to leave the "
        "free ones no valid position at that flexion: no repositioner can save them) and "
        '*movable* (the repositioner\'s failure). "in bone" = interior soft-tissue nodes '
        f"deeper than {PENETRATION_TOLERANCE} mm (in the model's unit) inside a bone; p95 "
        "\\|ΔV\\| = 95th percentile of the soft solids' volume change; tet aspect (longest "
        "edge / shortest altitude), tet collapse, volumetric skew and dihedral angles as "
        "docs/quality.md defines them (worst of the tets; – without tets); "
        "s = seconds per export (read, setup and precompute excluded) on the machine's two "
        "cores, with the 1-minute load average when the variant started.",
        "",
    ]
    for name, e in res.items():
        i0 = e["initial"]
        lines += [
            f"### {name}: {e['elements']:,} elements ({e['requested']:,} requested), "
            f"{e['locked']} locked"
            + (
                f" ({e['locked_with_free_nodes']} of them with free nodes, locked beyond a flexion)"
                if e.get("locked_with_free_nodes")
                else ""
            ),
            "",
            f"Initial worst hex corner Jacobian {_fmt(i0['worst_hex_jacobian'], '.3f')}, worst "
            f"tet aspect {_fmt(i0['worst_tet_aspect'], '.3g')}, collapse "
            f"{_measured(i0, 'worst_tet_collapse', '.3f')}, vol skew "
            f"{_fmt(i0.get('worst_tet_vol_skew'), '.4f')}, dihedral "
            f"{_dihedrals(i0)}, {i0['inverted']} inverted; precompute "
            f"{e['precompute_s']:.1f} s"
            + (f"; load {e['load_1min']:.1f}" if "load_1min" in e else "")
            + ".",
            "",
            "| angle | inverted (locked / movable) | worst hex J | worst tet aspect | "
            "worst tet collapse | worst tet vol skew | tet dihedral min / max ° | in bone | "
            "p95 \\|ΔV\\| % | ΔV > 25 % | gate | s |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in e["angles"]:
            lines.append(
                f"| {r['angle']}° | {r['inverted_locked']} / {r['inverted_movable']} | "
                f"{_fmt(r['worst_hex_jacobian'], '.3f')} | {_fmt(r['worst_tet_aspect'], '.3g')} | "
                f"{_measured(r, 'worst_tet_collapse', '.3f')} | "
                f"{_fmt(r.get('worst_tet_vol_skew'), '.4f')} | {_dihedrals(r)} | "
                f"{r['nodes_inside_bones']} | {r['p95_element_volume_change_pct']:.1f} | "
                f"{r['elements_volume_change_over_25_pct']} | "
                f"{'pass' if r['gate_passed'] else 'fail'} | {r['seconds']:.0f} |"
            )
        lines.append("")
    return "\n".join(lines)


VARIANTS_MARK = "<!-- variants: written by compare_methods.py --variants -->"


def write_section(text: str, variants: bool) -> str:
    """The comparison doc with one section replaced: the methods (everything before the
    variants mark) or the variants (everything after it)."""
    path = ROOT / "docs" / "repositioning-comparison.md"
    old = path.read_text() if path.exists() else ""
    methods, _, old_variants = old.partition(VARIANTS_MARK)
    if variants:
        methods = methods.rstrip("\n") + "\n\n"
        new = methods + VARIANTS_MARK + "\n\n" + text
    else:
        new = text.rstrip("\n") + "\n\n" + VARIANTS_MARK + old_variants
    path.write_text(new.rstrip("\n") + "\n")
    return new


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
    parser.add_argument(
        "--variants",
        nargs="*",
        metavar="NAME",
        help=f"the export on demo variants instead of the methods (default: all of "
        f"{', '.join(DEMO_VARIANTS)})",
    )
    parser.add_argument(
        "--angles", type=float, nargs="+", default=ANGLES, help="with --variants: the angles"
    )
    args = parser.parse_args()
    (ROOT / "bench" / "results").mkdir(parents=True, exist_ok=True)
    if args.variants is not None:
        names = tuple(args.variants) or tuple(DEMO_VARIANTS)
        res = measure_variants(args.elements, names, tuple(args.angles))
        # the variants not measured now keep their last figures
        saved = ROOT / "bench" / "results" / "variants.json"
        kept = json.loads(saved.read_text()) if saved.exists() and args.variants else {}
        res = {
            name: res.get(name, kept.get(name)) for name in DEMO_VARIANTS if name in {*res, *kept}
        }
        saved.write_text(json.dumps(res, indent=2, default=float) + "\n")
        text = variants_markdown(res)
    else:
        res = measure(args.elements, tuple(args.methods.split(",")), not args.no_smooth)
        (ROOT / "bench" / "results" / "methods.json").write_text(
            json.dumps(res, indent=2, default=float) + "\n"
        )
        text = to_markdown(res, not args.no_smooth)
    write_section(text, args.variants is not None)
    print(text)
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    raise SystemExit(main())
