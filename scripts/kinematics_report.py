"""Measure the bone kinematics on the demo leg: ``python scripts/kinematics_report.py``.

Prints the condyle fits, the initial flexion, and for each target flexion the re-measured
flexion, the applied coupled rotations, the worst relative change of intra-bone distances and the
time taken. docs/kinematics.md quotes its output.
"""

from __future__ import annotations

import kneegui.reproducible  # noqa: F401  (before numpy: the same kernels on every machine)

import argparse
import json
import time
from typing import Any

import numpy as np

from kneegui.demo import generate_demo_leg
from kneegui.geometry.axes import compute_joint_axes, measure_flexion
from kneegui.kinematics.posing import apply_bone_transforms, solve_bone_pose
from kneegui.setup.format import load_setup
from kneegui.setup.kinematic_tables import VALIDATED_FLEXION_DEG
from kneegui.setup.landmarks import suggest_setup

TARGETS = (VALIDATED_FLEXION_DEG[0], 0.0, 30.0, 60.0, 90.0, 120.0, VALIDATED_FLEXION_DEG[1])


def _max_relative_distance_change(a: np.ndarray, b: np.ndarray, sample: int = 400) -> float:
    idx = np.linspace(0, len(a) - 1, min(sample, len(a))).astype(int)
    d0 = np.linalg.norm(a[idx][:, None] - a[idx][None], axis=-1)
    d1 = np.linalg.norm(b[idx][:, None] - b[idx][None], axis=-1)
    mask = d0 > 0
    return float(np.max(np.abs(d1[mask] - d0[mask]) / d0[mask]))


def kinematics_report(elements: int = 20000, side: str = "right") -> dict[str, Any]:
    """Pose the demo leg at :data:`TARGETS` and collect the figures."""
    leg = generate_demo_leg(elements=elements, side=side)
    t0 = time.perf_counter()
    setup = load_setup(leg.setup, leg.model)
    t1 = time.perf_counter()
    axes = compute_joint_axes(leg.model.coords, setup)
    t2 = time.perf_counter()
    rows = []
    for target in TARGETS:
        s0 = time.perf_counter()
        pose = solve_bone_pose(axes, setup, target)
        coords = apply_bone_transforms(leg.model.coords, setup, pose.transforms)
        s1 = time.perf_counter()
        rigid = max(
            _max_relative_distance_change(leg.model.coords[idx], coords[idx])
            for idx in setup.segment_nodes.values()
            if len(idx)
        )
        rows.append(
            {
                "target": target,
                "measured": measure_flexion(coords, setup),
                "fe_rotation": pose.fe_rotation_deg,
                "tibial_rotation": pose.tibial_rotation_deg,
                "patellar_flexion": pose.patellar_flexion_deg,
                "patellar_tilt": pose.patellar_tilt_deg,
                "max_rel_distance_change": rigid,
                "pose_seconds": s1 - s0,
            }
        )
    s0 = time.perf_counter()
    suggested_setup = load_setup(suggest_setup(leg.model, side), leg.model)
    suggested = compute_joint_axes(leg.model.coords, suggested_setup)
    s1 = time.perf_counter()
    return {
        "suggested": {
            "lateral_radius": suggested.lateral_fit.radius,
            "medial_radius": suggested.medial_fit.radius,
            "initial_flexion": suggested.initial_flexion_deg,
            "lateral_nodes": len(suggested_setup.lateral_condyle_ids),
            "medial_nodes": len(suggested_setup.medial_condyle_ids),
            "seconds": s1 - s0,
        },
        "side": side,
        "nodes": leg.model.n_nodes,
        "elements": leg.model.n_elements,
        "load_setup_seconds": t1 - t0,
        "axes_seconds": t2 - t1,
        "axes": {k: v for k, v in axes.to_dict().items() if k != "warnings"},
        "warnings": [*setup.warnings, *axes.warnings],
        "poses": rows,
    }


def main(argv: list[str] | None = None) -> None:
    """Print the report (text, or JSON with ``--json``)."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--elements", type=int, default=20000)
    parser.add_argument("--side", default="right")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    rep = kinematics_report(args.elements, args.side)
    if args.json:
        print(json.dumps(rep, indent=2))
        return
    ax = rep["axes"]
    print(f"demo leg, {args.side}: {rep['nodes']} nodes, {rep['elements']} elements")
    print(
        f"lateral radius {ax['lateral_radius']:.3f} mm (RMS {ax['lateral_rms']:.4f}), "
        f"medial radius {ax['medial_radius']:.3f} mm (RMS {ax['medial_rms']:.4f}), "
        f"initial flexion {ax['initial_flexion']:.3f} deg"
    )
    ms_setup, ms_axes = rep["load_setup_seconds"] * 1e3, rep["axes_seconds"] * 1e3
    print(f"load_setup {ms_setup:.1f} ms, axes {ms_axes:.1f} ms")
    for w in rep["warnings"]:
        print(f"warning: {w}")
    sug = rep["suggested"]
    print(
        f"suggest_setup: lateral {sug['lateral_radius']:.3f} mm ({sug['lateral_nodes']} nodes), "
        f"medial {sug['medial_radius']:.3f} mm ({sug['medial_nodes']} nodes), initial flexion "
        f"{sug['initial_flexion']:.3f} deg, {sug['seconds']:.2f} s"
    )
    print(
        "target | measured | F-E rot | tibial int. rot | patellar flex | tilt "
        "| max rel dist change | ms"
    )
    for r in rep["poses"]:
        print(
            f"{r['target']:6.1f} | {r['measured']:8.4f} | {r['fe_rotation']:7.3f} | "
            f"{r['tibial_rotation']:15.3f} | {r['patellar_flexion']:13.3f} | "
            f"{r['patellar_tilt']:5.2f} | {r['max_rel_distance_change']:.1e} | "
            f"{r['pose_seconds'] * 1e3:.1f}"
        )


if __name__ == "__main__":
    main()
