"""Measure the demo leg at several sizes and write docs/demo-leg-numbers.md.

    python scripts/demo_leg_numbers.py [--sizes 2000,8000,12000,20000,100000,1000000]

Every number quoted in docs/demo-leg.md comes from this script: element counts, generation time,
quality (kneegui.quality, QUALITY.md definitions), the circle fits of the posterior condyle node
sets, the flexion measured from the setup's landmarks, knee width and skin girths.
"""

from __future__ import annotations

import kneegui.reproducible  # noqa: F401  (before numpy: the same kernels on every machine)

import argparse
import time
from pathlib import Path

import numpy as np

from kneegui.demo import PARTS, DemoDesign, generate_demo_leg
from kneegui.demo import grid as demo_grid
from kneegui.demo.generator import _assemble, quality_problems, repair_grid
from kneegui.demo.grid import rotate_about_y
from kneegui.demo.layout import make_layout
from kneegui.geometry.axes import compute_joint_axes, measure_flexion
from kneegui.quality import compute_quality
from kneegui.setup.format import load_setup


def girth(leg, z, frame_angle=0.0):
    """Perimeter (mm) of the skin cut by the plane at height z of a frame rotated about y."""
    m = leg.model
    pids = [s.pid for s in PARTS if s.role == "skin"]
    skin = m.blocks["quad4"].conn[np.isin(m.blocks["quad4"].part_ids, pids)]
    pts = rotate_about_y(m.coords, -frame_angle)
    edges = np.concatenate([skin[:, [0, 1]], skin[:, [1, 2]], skin[:, [2, 3]], skin[:, [3, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    za, zb = pts[edges[:, 0], 2] - z, pts[edges[:, 1], 2] - z
    cut = za * zb < 0
    t = za[cut] / (za[cut] - zb[cut])
    ring = (pts[edges[cut, 0]] + t[:, None] * (pts[edges[cut, 1]] - pts[edges[cut, 0]]))[:, :2]
    c = ring.mean(axis=0)
    ring = ring[np.argsort(np.arctan2(ring[:, 1] - c[1], ring[:, 0] - c[0]))]
    return float(np.linalg.norm(np.diff(np.vstack([ring, ring[:1]]), axis=0), axis=1).sum())


def measure(elements: int) -> dict:
    t0 = time.perf_counter()
    leg = generate_demo_leg(elements)
    seconds = time.perf_counter() - t0
    m = leg.model
    q = compute_quality(m.coords, m.blocks)
    hexq, quadq = q.by_type["hex8"], q.by_type["quad4"]
    setup = load_setup(leg.setup, m)
    axes = compute_joint_axes(m.coords, setup)
    femur = m.part_node_indices([s.pid for s in PARTS if s.role == "femur"])
    phi = leg.design.flexion_rad
    return {
        "requested": elements,
        "solids": len(m.blocks["hex8"]),
        "shells": len(m.blocks["quad4"]),
        "nodes": m.n_nodes,
        "repaired": leg.stats["repaired_nodes"],
        "seconds": seconds,
        "inverted": q.n_inverted,
        "jac_hex": hexq.metric("jacobian_corner").min(),
        "jac_quad": quadq.metric("jacobian_corner").min(),
        "aspect": max(hexq.metric("aspect").max(), quadq.metric("aspect").max()),
        "warpage": max(hexq.metric("warpage").max(), quadq.metric("warpage").max()),
        "r_lat": axes.lateral_fit.radius,
        "r_med": axes.medial_fit.radius,
        "rms_lat": axes.lateral_fit.rms,
        "arc_lat": axes.lateral_fit.arc_span_deg,
        "arc_med": axes.medial_fit.arc_span_deg,
        "flexion": measure_flexion(m.coords, setup),
        "knee_width": float(np.ptp(m.coords[femur, 1])),
        "girth_thigh_top": girth(leg, 399.0),
        "girth_above_knee": girth(leg, 60.0),
        "girth_knee": girth(leg, 0.0),
        "girth_calf": max(girth(leg, z, phi) for z in (-200.0, -170.0, -140.0, -110.0)),
        "girth_ankle": girth(leg, -399.0, phi),
    }


def sweep(max_factor: float) -> list[dict]:
    """Every distinct block structure from the coarsest up to ``max_factor``: solids, whether it
    met the bounds as built, how many free flesh nodes the repair moved and how far, and the
    final worst quality."""
    design = DemoDesign()
    seen, rows = set(), []
    factors = [0.05]
    while factors[-1] * 1.02 < max_factor:
        factors.append(factors[-1] * 1.02)
    for factor in [*factors, max_factor]:
        layout = make_layout(factor)
        key = (layout.rows.counts, layout.cols.counts, layout.rings.counts, layout.slabs.counts)
        if key in seen:
            continue
        seen.add(key)
        grid = demo_grid.build_grid(design, layout)
        as_built = quality_problems(_assemble(grid, design, "right").model)
        repaired, moved = repair_grid(grid) if as_built else (grid, 0)
        leg = _assemble(repaired, design, "right")
        q = compute_quality(leg.model.coords, leg.model.blocks)
        rows.append(
            {
                "solids": leg.stats["solids"],
                "as_built": "; ".join(as_built) or "meets all",
                "moved": moved,
                "displacement": float(np.linalg.norm(repaired.coords - grid.coords, axis=1).max()),
                "final": "; ".join(quality_problems(leg.model)) or "meets all",
                "jac": min(e.metric("jacobian_corner").min() for e in q.by_type.values()),
                "aspect": max(e.metric("aspect").max() for e in q.by_type.values()),
                "warpage": max(e.metric("warpage").max() for e in q.by_type.values()),
            }
        )
    return rows


#: One block fewer than the coarsest layout: (what, direction, block, new count).
COARSER_VARIANTS = (
    ("one row for the condylar wall", "rows", "wall", 1),
    ("no rim columns", "cols", "lat_rim", 0),
    ("5 tibial metaphysis slabs", "slabs", "tibmeta", 5),
    ("3 patella slabs", "slabs", "pat", 3),
    ("14 calf slabs", "slabs", "calf", 14),
    ("13 calf slabs", "slabs", "calf", 13),
    ("15 thigh slabs", "slabs", "thigh", 15),
    ("14 thigh slabs", "slabs", "thigh", 14),
)


def coarser_variants() -> list[tuple[str, int, str]]:
    """The coarsest layout with one block made smaller: solids and what the final mesh misses."""
    from dataclasses import replace

    from kneegui.demo.generator import build_demo_leg
    from kneegui.demo.layout import Blocks

    base = make_layout(0.05)
    out = []
    for what, direction, block, count in (("coarsest layout", "", "", None), *COARSER_VARIANTS):
        layout = base
        if count is not None:
            blocks: Blocks = getattr(base, direction)
            counts = list(blocks.counts)
            if block == "lat_rim":
                counts[blocks.names.index("lat_rim")] = counts[blocks.names.index("med_rim")] = 0
            else:
                counts[blocks.names.index(block)] = count
            layout = replace(base, **{direction: Blocks(blocks.names, tuple(counts))})
        leg, problems = build_demo_leg(layout, DemoDesign())
        out.append((what, leg.stats["solids"], "; ".join(problems) or "meets all"))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="2000,8000,12000,20000,100000,1000000")
    ap.add_argument(
        "--out", default=str(Path(__file__).resolve().parent.parent / "docs/demo-leg-numbers.md")
    )
    args = ap.parse_args()
    rows = [measure(int(s)) for s in args.sizes.split(",")]
    lines = [
        "# Demo leg: measured numbers",
        "",
        "Written by `python scripts/demo_leg_numbers.py`; see docs/demo-leg.md for what they mean.",
        "",
        "| requested | solids | shells | nodes | repaired nodes | time s | inverted | worst J hex "
        "| worst J quad | worst aspect | worst warpage ° | R lat | R med | arc lat/med ° "
        "| flexion ° |",
        "|---" * 15 + "|",
    ]
    for r in rows:
        lines.append(
            f"| {r['requested']:,} | {r['solids']:,} | {r['shells']:,} | {r['nodes']:,} "
            f"| {r['repaired']} | {r['seconds']:.2f} | {r['inverted']} "
            f"| {r['jac_hex']:.3f} | {r['jac_quad']:.3f} "
            f"| {r['aspect']:.2f} | {r['warpage']:.1f} | {r['r_lat']:.3f} | {r['r_med']:.3f} "
            f"| {r['arc_lat']:.0f}/{r['arc_med']:.0f} | {r['flexion']:.3f} |"
        )
    lines += [
        "",
        "| requested | knee width mm | girth upper thigh | above knee (z=60) | knee (z=0) "
        "| calf max | ankle |",
        "|---" * 7 + "|",
    ]
    for r in rows:
        lines.append(
            f"| {r['requested']:,} | {r['knee_width']:.1f} | {r['girth_thigh_top']:.0f} "
            f"| {r['girth_above_knee']:.0f} | {r['girth_knee']:.0f} | {r['girth_calf']:.0f} "
            f"| {r['girth_ankle']:.0f} |"
        )
    default_factor = generate_demo_leg().layout.factor
    lines += [
        "",
        "## Every block structure from the coarsest to the default",
        "",
        "Each distinct layout (`make_layout`) between the coarsest and the default one, as "
        "`build_demo_leg` makes it: the bounds the grid misses as built, the free flesh nodes "
        "the repair moved (and the largest move, mm), and the final mesh.",
        "",
        "| solids | as built | nodes moved | largest move mm | final | worst J | worst aspect "
        "| worst warpage ° |",
        "|---" * 8 + "|",
    ]
    for r in sweep(default_factor):
        lines.append(
            f"| {r['solids']:,} | {r['as_built']} | {r['moved']} | {r['displacement']:.2f} "
            f"| {r['final']} | {r['jac']:.3f} | {r['aspect']:.2f} | {r['warpage']:.1f} |"
        )
    lines += [
        "",
        "## The coarsest layout with one block fewer",
        "",
        "What the final mesh (after the repair) misses when one block of the coarsest layout is "
        "made smaller; docs/demo-leg.md explains the minimum counts.",
        "",
        "| variant | solids | final mesh |",
        "|---|---|---|",
    ]
    for what, solids, final in coarser_variants():
        lines.append(f"| {what} | {solids:,} | {final} |")
    text = "\n".join(lines) + "\n"
    Path(args.out).write_text(text, encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main()
