"""Where a pose's worst elements are and why: the diagnosis behind docs/repositioning.md.

``python scripts/worst_elements.py 90`` poses the default demo (mapping + relaxation, what the
export writes) and prints the worst corner Jacobian of every soft-tissue part, the span between
each ligament's femoral and tibial attachments at rest and posed, and how deep each meniscus
would be inside the femur if it moved rigidly with the tibia, and how many pairs of neighbouring
skin contours cross and how many interior tissue nodes are deeper than 0.5 mm in each bone
(the numbers in the strict-xfail reasons of tests/engine/reposition use
``--elements 2000``, the tests' small demo).
"""

from __future__ import annotations

import kneegui.reproducible  # noqa: F401  (before numpy: the same kernels on every machine)

import argparse

import numpy as np

from kneegui.demo import generate_demo_leg
from kneegui.quality import compute_quality
from kneegui.reposition import Repositioner
from kneegui.reposition.checks import penetrating, surface_triangles
from kneegui.reposition.contact import BoneSurfaceDistance
from kneegui.reposition.skin_contours import build_skin_contours, count_contour_crossings
from kneegui.setup import load_setup

SOFT = ("flesh", "capsule", "skin", "ligament", "meniscus", "tendon")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("flexion", type=float)
    parser.add_argument("--elements", type=int, default=20000)
    args = parser.parse_args()
    leg = generate_demo_leg(args.elements)
    model = leg.model
    setup = load_setup(leg.setup, model)
    rep = Repositioner(model, setup)
    result = rep.pose_detailed(args.flexion)
    x0, x = model.coords, result.coords
    q0 = compute_quality(x0, model.blocks)
    q = compute_quality(x, model.blocks)
    print(
        f"{args.flexion:g} deg: initial worst {q0.worst_jacobian():.3f}, posed worst "
        f"{q.worst_jacobian():.3f}, inverted {q.n_inverted}"
    )
    print("worst corner Jacobian per soft-tissue part (posed):")
    for role in SOFT:
        for pid in setup.parts_of(role):
            worst = [
                float(q[e].jacobian_corner[model.blocks[e].part_ids[q[e].rows] == pid].min())
                for e in q
                if np.any(model.blocks[e].part_ids[q[e].rows] == pid)
            ]
            if worst:
                print(f"  {role:9s} {model.parts[pid].title:28s} {min(worst):.3f}")
    segment = np.full(model.n_nodes, "", dtype=object)
    for name, idx in rep.groups.segment.items():
        segment[idx] = name
    print("ligament attachments (centroid of the nodes moving with each bone):")
    for pid in setup.parts_of("ligament"):
        nodes = np.unique(
            np.concatenate([b.conn[b.part_ids == pid].ravel() for b in model.blocks.values()])
        )
        fem, tib = nodes[segment[nodes] == "femur"], nodes[segment[nodes] == "tibia"]
        if len(fem) and len(tib):
            rest = np.linalg.norm(x0[fem].mean(0) - x0[tib].mean(0))
            posed = np.linalg.norm(x[fem].mean(0) - x[tib].mean(0))
            offset = x0[fem].mean(0) - rep.axes.fe_axis.point
            radial = np.linalg.norm(
                offset - (offset @ rep.axes.fe_axis.direction) * rep.axes.fe_axis.direction
            )
            print(
                f"  {model.parts[pid].title:28s} span {rest:5.1f} -> {posed:5.1f} mm "
                f"({100 * (posed / rest - 1):+.0f} %), femoral attachment {radial:4.1f} mm "
                "from the F-E axis"
            )
    femur = BoneSurfaceDistance(x0[rep._bone_triangles()["femur"]])
    bone = rep.bone_pose(args.flexion)
    to_femur = bone.transforms["femur"].inverse()
    print("menisci moved rigidly with the tibia: deepest point inside the femur")
    for pid in setup.parts_of("meniscus"):
        nodes = np.unique(
            np.concatenate([b.conn[b.part_ids == pid].ravel() for b in model.blocks.values()])
        )
        depth = femur.query(to_femur.apply(bone.transforms["tibia"].apply(x0[nodes])))[0]
        print(f"  {model.parts[pid].title:28s} {max(0.0, -depth.min()):.1f} mm")
    contours = build_skin_contours(
        x0,
        rep.groups.skin,
        rep.axes.knee_center,
        rep.axes.superior,
        rep.axes.tibia_axis.direction,
        setup.skin_contours,
        rep.options.zone_factor,
        rep.groups.bone_surface,
    )
    print(f"skin contour crossings: {count_contour_crossings(contours, x, reference=x0)}")
    interior = np.concatenate([rep.groups.flesh, rep.groups.band])
    inside = {
        role: int(
            penetrating(
                x[interior],
                x,
                surface_triangles(model, setup.parts_of(role), shells=False),
                rep.axes.fe_axis.direction,
                tolerance=0.5,
            ).sum()
        )
        for role in ("femur", "tibia", "fibula", "patella")
    }
    print(f"interior nodes deeper than 0.5 mm in a bone: {inside}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
