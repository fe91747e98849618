"""Measure the relaxation's volume aims: what ``kneegui pose`` writes with other settings.

``python scripts/volume_aims.py [--elements 20000] [--volume-change 0.1]
[--contact-stiffness 100] [--reach 5] 90 120`` prints, per angle, the worst corner Jacobian
(posed and smoothed), inverted elements, interior soft-tissue nodes deeper than 0.5 mm inside
a bone, and the report's volume-change figures. The "measured, not kept" settings in
docs/repositioning.md (known limits, element volume) come from this script.
"""

from __future__ import annotations

import kneegui.reproducible  # noqa: F401  (before numpy: the same kernels on every machine)

import argparse
import dataclasses
import time

import numpy as np
from compare_methods import nodes_inside_bones

from kneegui.demo import generate_demo_leg
from kneegui.reposition import Repositioner, RepositionOptions
from kneegui.reposition.checks import surface_triangles
from kneegui.reposition.pipeline import pose_model
from kneegui.setup import load_setup


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("angles", type=float, nargs="+")
    parser.add_argument("--elements", type=int, default=20000)
    defaults = RepositionOptions()
    parser.add_argument("--volume-change", type=float, default=defaults.volume_change)
    parser.add_argument(
        "--contact-stiffness",
        type=float,
        default=defaults.improvement.quality.constraint_stiffness,
    )
    parser.add_argument("--reach", type=float, default=defaults.relax_reach)
    args = parser.parse_args()
    leg = generate_demo_leg(args.elements)
    setup = load_setup(leg.setup, leg.model)
    improvement = dataclasses.replace(
        defaults.improvement,
        quality=dataclasses.replace(
            defaults.improvement.quality, constraint_stiffness=args.contact_stiffness
        ),
    )
    options = dataclasses.replace(
        defaults,
        improvement=improvement,
        volume_change=args.volume_change,
        relax_reach=args.reach,
    )
    rep = Repositioner(leg.model, setup, options)
    triangles = [
        surface_triangles(leg.model, setup.parts_of(role), shells=False)
        for role in ("femur", "tibia", "fibula", "patella")
    ]
    for angle in args.angles:
        t = time.perf_counter()
        posed = pose_model(rep, angle, smooth=True)
        r, q = posed.report, posed.report["quality"]
        v = r["volume_change"]
        print(
            f"{angle:g} deg ({time.perf_counter() - t:.0f} s): worst J "
            f"{q['posed']['jacobian']['worst']:.3f} (smoothed "
            f"{q['smoothed']['jacobian']['worst']:.3f}), inverted {q['smoothed']['inverted']}, "
            f"in bone {nodes_inside_bones(rep, posed.model.coords, triangles)}, "
            f"max element dV {v['max_element_pct']:+.1f} %, p95 "
            f"{v['soft_element_p95_abs_pct']:.1f} %, over {v['soft_elements_over_pct']} "
            f"of {v['soft_elements']}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    raise SystemExit(main())
