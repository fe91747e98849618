"""Mid-side nodes of 10-node tets in a pose: on their edges as at rest, out of the bones at right
angles to their edges, no deeper than the deck put them."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.geometry.transforms import RigidTransform
from kneegui.model import ElementBlock
from kneegui.reposition.contact import BoneSurfaceDistance
from kneegui.reposition.midside import TET10_MIDSIDE, MidsideNodes
from kneegui.reposition.relax import ElasticRelaxation
from kneegui.topology import corner_tetrahedra

EDGES = list(TET10_MIDSIDE.values())
BLOCK = ElementBlock("tet10", np.array([1]), np.array([1]), np.arange(10)[None, :])


def _tet10(corners) -> np.ndarray:
    corners = np.asarray(corners, dtype=float)
    return np.vstack([corners, [(corners[a] + corners[b]) / 2 for a, b in EDGES]])


def _offsets(x: np.ndarray, node: int) -> tuple[float, float]:
    """(normal, tangent) offset of mid-side node ``node`` from its edge, in edge lengths."""
    a, b = TET10_MIDSIDE[node]
    edge = x[b] - x[a]
    length = np.linalg.norm(edge)
    d = x[node] - 0.5 * (x[a] + x[b])
    tangent = d @ edge / length
    return float(np.sqrt(max(d @ d - tangent**2, 0.0)) / length), abs(tangent) / length


def _relaxation(rest: np.ndarray, bone: np.ndarray) -> ElasticRelaxation:
    """The relaxation of one free 10-node tet beside bone ``femur``."""
    tets = corner_tetrahedra({"tet10": BLOCK})
    return ElasticRelaxation(
        rest, tets, np.arange(10), bones={"femur": bone}, blocks={"tet10": BLOCK}
    )


def test_straighten_puts_each_movable_mid_side_node_back_on_its_edge():
    rest = _tet10([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    rest[4] += [0.0, -1.0, 0.0]  # a bowed edge keeps its bow
    movable = np.ones(10, dtype=bool)
    movable[9] = False  # e.g. a node of a fixed part: left alone
    mid = MidsideNodes.of_block(BLOCK, movable, rest)
    assert mid.nodes.tolist() == [4, 5, 6, 7, 8]
    mapped = rest.copy()
    mapped[1] += [2.0, 0.0, 0.0]
    mapped[4:] += 0.7  # every mid-side node placed off its edge
    out = mid.straighten(mapped)
    np.testing.assert_allclose(out[4], (mapped[0] + mapped[1]) / 2 + [0.0, -1.0, 0.0])
    for node in (5, 6, 7, 8):
        assert max(_offsets(out, node)) < 1e-12
    np.testing.assert_array_equal(out[9], mapped[9])
    np.testing.assert_array_equal(out[:4], mapped[:4])
    assert len(MidsideNodes.of_block(None, movable, rest)) == 0


def test_a_mid_side_node_leaves_a_bone_at_right_angles_to_its_edge(box_surface):
    """The bone is the quadrant x < 0, y < 0: an edge from one of its faces round its rim to the
    other cuts into it. The mid-side node goes out across its edge only, so it stays centred
    on it (a push to the closest surface point slid it along the edge); within the tolerance,
    and no deeper than at rest, a node stays."""
    bone = BoneSurfaceDistance(box_surface((-20.0, -20.0, -20.0), (0.0, 0.0, 20.0)))
    rest = _tet10([[1.0, -2, 0], [1.0, 2, 0], [3, 0, 0], [2, 0, 2]])  # outside the bone
    mid = MidsideNodes.of_block(BLOCK, np.ones(10, dtype=bool), rest)
    posed = rest.copy()
    posed[0] = [0.0, -2.0, 0.0]  # on the face x = 0
    posed[1] = [-3.0, 0.0, 0.0]  # on the face y = 0: the edge cuts the rim
    posed = mid.straighten(posed)
    identity = {"femur": RigidTransform.identity()}
    depth_before = bone.query(posed[4:5])[0][0]
    assert depth_before < -0.5
    out = mid.out_of_bones(posed, {"femur": bone}, identity, tolerance=0.1)
    depth = bone.query(out[4:5])[0][0]
    assert -0.1 < depth <= 0.0  # out to half the tolerance, within a pass's rounding
    normal, tangent = _offsets(out, 4)
    assert tangent < 1e-9
    assert normal > 0.1  # the edge bends round the rim
    np.testing.assert_array_equal(np.delete(out, 4, axis=0), np.delete(posed, 4, axis=0))
    # within the tolerance: left as it is
    assert mid.out_of_bones(posed, {"femur": bone}, identity, tolerance=2.0) is posed
    # the same edge round the rim in the deck itself: no deeper than at rest, it stays
    at_rest = MidsideNodes.of_block(BLOCK, np.ones(10, dtype=bool), posed)
    assert at_rest.out_of_bones(posed, {"femur": bone}, identity, tolerance=0.1) is posed


def test_the_relaxation_holds_an_edge_of_a_10_node_tet_out_of_a_bone(box_surface):
    """The contact planes of a 10-node tet's corners include its edges: an edge whose middle
    lies inside a bone asks each corner out by the depth the middle must gain, so that the
    edge's mid-side node, carried with it, ends out of the bone too. An edge inside the bone at
    rest may stay as deep."""
    tris = box_surface((-20.0, -20.0, -20.0), (0.0, 0.0, 20.0))
    rest = _tet10([[1.0, -2, 0], [1.0, 2, 0], [3, 0, 0], [2, 0, 2]])
    relax = _relaxation(rest, tris)
    posed = rest.copy()
    posed[0] = [0.0, -2.0, 0.0]
    posed[1] = [-3.0, 0.0, 0.0]
    identity = RigidTransform.identity()
    nodes = np.arange(4)
    rows, normals, offsets = relax._chord_planes(posed, nodes, "femur", identity, band=1.0)
    bone = relax.bones["femur"]
    depth = bone.query(((posed[0] + posed[1]) / 2)[None])[0][0]
    assert depth < -0.5
    violated = np.einsum("ij,ij->i", normals, posed[nodes[rows]]) - offsets < -1e-9
    assert sorted(rows[violated].tolist()) == [0, 1]  # both corners of edge 4, and no other
    k = np.flatnonzero(violated)
    moved = posed.copy()
    for r in k:  # each corner onto its plane
        gap = normals[r] @ moved[r] - offsets[r]
        moved[rows[r]] -= gap * normals[r]
    assert bone.query(((moved[0] + moved[1]) / 2)[None])[0][0] > -1e-9
    # the deck with that edge round the rim at rest: its middle may stay as deep
    posed[4] = (posed[0] + posed[1]) / 2
    at_rest = _relaxation(posed, tris)
    rows, normals, offsets = at_rest._chord_planes(posed, nodes, "femur", identity, band=1.0)
    gaps = np.einsum("ij,ij->i", normals, posed[nodes[rows]]) - offsets
    assert gaps.min() == pytest.approx(0.0, abs=1e-9)
