"""Skin-contour order: the crossing count and the constraints that keep contours apart."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kneegui.meshopt.foldover import RelaxOptions
from kneegui.reposition.skin_contours import (
    ContourOrder,
    SkinContours,
    count_contour_crossings,
    neighbour_planes,
)


def ring_stack(levels=(10.0, 20.0, 30.0), nodes_per_ring: int = 8):
    """Thigh rings at z = +levels and calf rings at z = -levels (radius 5), numbered from the
    joint outwards on each side."""
    angles = np.linspace(0.0, 2 * np.pi, nodes_per_ring, endpoint=False)
    ring = np.stack([5 * np.cos(angles), 5 * np.sin(angles), np.zeros_like(angles)], axis=1)
    coords, contour, sides, ranks = [], [], [], []
    for side, sign in ((0, 1.0), (1, -1.0)):
        for rank, z in enumerate(levels):
            coords.append(ring + np.array([0.0, 0.0, sign * z]))
            contour += [len(ranks)] * nodes_per_ring
            sides.append(side)
            ranks.append(rank)
    coords = np.vstack(coords)
    n_c = len(ranks)
    contours = SkinContours(
        nodes=np.arange(len(coords)),
        side=np.repeat(np.array(sides, dtype=np.int8), nodes_per_ring),
        contour=np.array(contour),
        n_contours=n_c,
        contour_side=np.array(sides, dtype=np.int8),
        contour_rank=np.array(ranks),
        centers=np.zeros((n_c, 3)),
        zone_length=np.array([30.0, 30.0]),
        clearance=np.full(len(coords), 5.0),
    )
    return coords, contours


def test_neighbour_planes_face_away_from_the_joint():
    coords, contours = ring_stack()
    rows, normals, offsets = neighbour_planes(contours, coords)
    # every contour but the two joint ones (the first calf ring is checked against the first
    # thigh ring), each node against the plane of the ring nearer the joint
    assert len(rows) == len(coords) - 8
    gaps = np.einsum("ij,ij->i", normals, coords[contours.nodes[rows]]) - offsets
    np.testing.assert_allclose(np.sort(np.unique(np.round(gaps, 9))), [10.0, 20.0])


def test_contour_order_flags_and_constrains_a_node_pushed_past_its_neighbour():
    coords, contours = ring_stack()
    order = ContourOrder(contours, coords, margin=0.5)
    assert len(order.crossing(coords)) == 0
    moved = coords.copy()
    node = 8 * 2 + 3  # a node of the third thigh ring, pushed below the second one
    moved[node, 2] = 19.8
    assert count_contour_crossings(contours, moved, reference=coords) == 1
    assert list(order.crossing(moved)) == [node]
    nodes, normals, offsets = order.constraints(moved)
    k = int(np.flatnonzero(nodes == node)[0])
    # the plane of the second ring (z = 20) plus the margin
    assert normals[k] @ [0.0, 0.0, 1.0] == pytest.approx(1.0)
    assert offsets[k] == pytest.approx(20.5)
    # a node only 0.3 beyond its neighbour's plane still keeps the margin
    moved[node, 2] = 20.3
    assert list(order.crossing(moved)) == [node]
    assert count_contour_crossings(contours, moved, reference=coords) == 0


def test_a_node_beyond_its_neighbour_at_rest_is_left_alone():
    coords, contours = ring_stack()
    rough = coords.copy()
    rough[8 * 2 + 1, 2] = 19.9  # the initial mesh already has it beyond the z = 20 ring
    order = ContourOrder(contours, rough, margin=0.5)
    assert len(order.crossing(rough)) == 0
    nodes, _, _ = order.constraints(rough)
    assert 8 * 2 + 1 not in set(nodes)


@pytest.mark.parametrize(("outward", "bound"), [(False, 1.5), (True, 6.0)])
def test_the_untangling_puts_the_skin_contours_back_in_order(
    small_repositioner, small_posed, outward, bound
):
    """The mapping crosses the contours behind a flexed knee (12 mm at 90 deg on the coarse
    demo). The untangling energy holds them in order as it untangles, so its shape terms, not
    the quality optimiser's penalties, carry the skin back: before, it handed over contours
    still 7 mm crossed and the optimiser pressed the elements between them flat (tet
    collapse 0.014 against 0.108 on the tetrahedral demo; 0.107 now). With the skin sliding in
    its tangent planes it hands over 1.2 mm; free to bulge outwards (``skin_outward``, the
    default), 3.2 mm, which the quality stage takes to 0.02 mm (the tet demo's collapse at 90
    deg the same, 0.109)."""
    rep = small_repositioner
    if not outward:
        relax = replace(rep.options.improvement.relax or RelaxOptions(), skin_outward=False)
        rep = rep.with_options(improvement=replace(rep.options.improvement, relax=relax))
    pose = rep.pose_detailed(90.0, remeasure=False, relax=False)
    relaxation = rep._elastic_relaxation()
    order = relaxation.contour_order
    assert order is not None

    def deepest(x):
        nodes, normals, offsets = order.constraints(x)
        return float(-(np.einsum("ij,ij->i", normals, x[nodes]) - offsets).min())

    assert deepest(pose.coords) > 10.0
    untangled, report, ok = relaxation.untangle(
        pose.coords, pose.bone_pose.transforms, True, lambda f, m: None, lambda: False
    )
    assert ok and report.inverted_corners_after == 0
    assert deepest(untangled) < bound
    if outward:  # what the export writes: in order
        assert deepest(small_posed(90.0).coords) < 0.2
