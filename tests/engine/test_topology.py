"""The element tables of kneegui.topology: one convention, checked on reference elements."""

from __future__ import annotations

import numpy as np
import pytest

import kneegui.topology as topology
from kneegui.errors import Cancelled
from kneegui.model import ElementBlock
from kneegui.quality.kernels import (
    HEX_FACES,
    corner_determinants,
    corner_determinants_cm,
    corner_jacobian,
    ratio_of_determinants,
)
from kneegui.topology import (
    CORNER_NODES,
    CORNER_TRIPLES,
    ELEMENT_EDGES,
    ELEMENT_FACES,
    ELEMENT_TYPES,
    HEX_REFERENCE_COORDS,
    LINE_TYPES,
    MIRRORED_NODE_ORDER,
    NODES_PER_ELEMENT,
    SHELL_TYPES,
    SOLID_FACES,
    SOLID_TYPES,
    block_offsets,
    boundary_faces,
    corner_tetrahedra,
    hex_faces_parametric,
    split_degenerate_solids,
)

#: A positive reference element of each type (corner nodes; tet10 adds its mid-edge nodes).
UNIT: dict[str, list[tuple[float, float, float]]] = {
    "hex8": [tuple(map(float, c)) for c in HEX_REFERENCE_COORDS],
    "wedge6": [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (0, 1, 1)],
    "pyramid5": [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0.5, 0.5, 1)],
    "tet4": [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)],
    "quad4": [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)],
    "tri3": [(0, 0, 0), (1, 0, 0), (0, 1, 0)],
}
_TET = np.array(UNIT["tet4"])
UNIT["tet10"] = [
    *UNIT["tet4"],
    *(
        tuple(0.5 * (_TET[a] + _TET[b]))
        for a, b in ((0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3))
    ),
]


def test_type_groups_partition_the_element_types():
    groups = SOLID_TYPES + SHELL_TYPES + LINE_TYPES
    assert sorted(groups) == sorted(ELEMENT_TYPES) and len(set(groups)) == len(groups)
    assert set(ELEMENT_EDGES) == set(ELEMENT_TYPES)
    assert set(SOLID_FACES) == set(SOLID_TYPES)
    assert set(ELEMENT_FACES) == set(SOLID_TYPES + SHELL_TYPES)
    for etype, k in CORNER_NODES.items():
        assert k <= NODES_PER_ELEMENT[etype]


@pytest.mark.parametrize("etype", SOLID_TYPES)
def test_solid_faces_point_outward_and_close_the_element(etype):
    x = np.array(UNIT[etype])
    centre = x[: CORNER_NODES[etype]].mean(axis=0)
    area = np.zeros(3)
    for face in SOLID_FACES[etype]:
        p = x[list(face)]
        normal = np.cross(p[1] - p[0], p[2] - p[0])
        if len(face) == 4:
            normal = np.cross(p[2] - p[0], p[3] - p[1])
        assert normal @ (p.mean(axis=0) - centre) > 0, face
        area += 0.5 * normal
    np.testing.assert_allclose(area, 0.0, atol=1e-12)  # a closed surface
    # every edge of a face is used by exactly two face sides, once each way
    sides = [(f[i], f[(i + 1) % len(f)]) for f in SOLID_FACES[etype] for i in range(len(f))]
    assert len(set(sides)) == len(sides)
    assert {(b, a) for a, b in sides} == set(sides)


@pytest.mark.parametrize("etype", [t for t in ELEMENT_TYPES if t in ELEMENT_FACES])
def test_edges_are_the_face_sides(etype):
    """Each undirected edge is a side of some face and every face side is an edge (tet10's
    edges pass through its mid-edge nodes; its faces list the corners)."""
    edges = {frozenset(e) for e in ELEMENT_EDGES[etype]}
    assert len(edges) == len(ELEMENT_EDGES[etype])
    sides = {
        frozenset((f[i], f[(i + 1) % len(f)])) for f in ELEMENT_FACES[etype] for i in range(len(f))
    }
    if etype == "tet10":
        mids = {frozenset(e) for e in ELEMENT_EDGES["tet4"]}
        assert sides == mids and len(edges) == 2 * len(mids)
        return
    assert sides == edges


@pytest.mark.parametrize("etype", list(CORNER_TRIPLES))
def test_corner_triples_are_positive_on_a_reference_element(etype):
    x = np.array(UNIT[etype])
    k = CORNER_NODES[etype]
    assert {t[0] for t in CORNER_TRIPLES[etype]} <= set(range(k))
    dets = corner_determinants(x[None, :k], etype)
    assert dets.shape == (1, len(CORNER_TRIPLES[etype]))
    assert np.all(dets > 0)
    mirrored = x[:k] * np.array([1.0, 1.0, -1.0])
    if etype != "quad4":  # a quad's own normal flips with it
        assert np.all(corner_determinants(mirrored[None], etype) < 0)
    # each corner's three edges are element edges (or the normal, for a shell)
    edges = {frozenset(e) for e in ELEMENT_EDGES["tet4" if etype == "tet10" else etype]}
    for i, *others in CORNER_TRIPLES[etype]:
        for j in others:
            assert j == -1 or frozenset((i, j)) in edges


def test_corner_jacobian_of_the_reference_cases():
    """QUALITY.md's reference table (corner column) through the one corner kernel."""
    cube = np.array(UNIT["hex8"])
    raised = cube.copy()
    raised[7, 2] += 0.25
    cases = {"unit": (cube, 1.0), "node 7 raised": (raised, 0.8)}
    frustum = cube.copy()
    frustum[4:, :2] = 0.25 + 0.5 * frustum[4:, :2]
    cases["frustum"] = (frustum, 0.25)
    cases["mirrored"] = (cube[[4, 5, 6, 7, 0, 1, 2, 3]], -1.0)
    for name, (x, expected) in cases.items():
        assert corner_jacobian(x[None], "hex8")[0] == pytest.approx(expected), name


def test_kernel_hex_faces_follow_the_parametric_rule():
    faces = hex_faces_parametric()
    assert faces == HEX_FACES
    assert [frozenset(f) for f in faces] == [frozenset(f) for f in SOLID_FACES["hex8"]]
    ref = np.array(HEX_REFERENCE_COORDS)
    for face in faces:
        p = ref[list(face)]
        assert p[0].sum() == p.sum(axis=1).min()  # starts at the face's origin corner
        step = p[1] - p[0]
        assert step.sum() == 1 and np.flatnonzero(step)[0] < np.flatnonzero(p[3] - p[0])[0]


def _two_hexes() -> dict[str, ElementBlock]:
    """Two unit hexes side by side in x (nodes 0-11), parts 1 and 2, and a quad shell."""
    conn = np.array([[0, 1, 4, 3, 6, 7, 10, 9], [1, 2, 5, 4, 7, 8, 11, 10]])
    return {
        "quad4": ElementBlock("quad4", np.array([9]), np.array([3]), np.array([[6, 7, 10, 9]])),
        "hex8": ElementBlock("hex8", np.array([1, 2]), np.array([1, 2]), conn),
    }


def test_boundary_faces_of_two_elements():
    blocks = _two_hexes()
    quads, tris, cells, _ = boundary_faces(blocks, with_cells=True)
    assert len(tris) == 0 and len(quads) == 10  # 12 faces, the shared one dropped
    shared = {1, 4, 7, 10}
    assert not any(set(f) == shared for f in quads.tolist())
    assert set(cells.tolist()) == {1, 2}  # global cells: the quad shell block comes first
    one, _ = boundary_faces(blocks, [1])
    assert len(one) == 6 and any(set(f) == shared for f in one.tolist())
    assert block_offsets(blocks) == {"quad4": 0, "hex8": 1}


def test_boundary_faces_of_mixed_solids_are_outward():
    """A wedge on a hex: their shared quad is interior; the triangles are outward."""
    coords = np.array([*UNIT["hex8"], (0, 0, 2), (1, 0, 2)], dtype=float)
    hexes = ElementBlock("hex8", [1], [1], [[0, 1, 2, 3, 4, 5, 6, 7]])
    wedge = ElementBlock("wedge6", [2], [1], [[4, 7, 8, 5, 6, 9]])
    quads, tris = boundary_faces({"hex8": hexes, "wedge6": wedge})
    assert len(quads) == 5 + 3 - 1 and len(tris) == 2
    centre = coords.mean(axis=0)
    for f in [*quads.tolist(), *tris.tolist()]:
        p = coords[f]
        n = np.cross(p[1] - p[0], p[2] - p[0])
        assert n @ (p.mean(axis=0) - centre) > 0


def test_corner_tetrahedra_carry_the_corner_determinants():
    blocks = _two_hexes()
    coords = np.array([(x, y, z) for z in (0, 1) for y in (0, 1) for x in (0, 1, 2)], float)
    tets = corner_tetrahedra(blocks)
    assert tets.shape == (16, 4)
    p = coords[tets]
    dets = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    expected = corner_determinants(coords[blocks["hex8"].conn], "hex8").reshape(-1)
    np.testing.assert_allclose(dets, expected)
    assert np.all(dets > 0)


def test_degenerate_hexes_become_positive_wedges_and_tets():
    cube = np.array(UNIT["hex8"])
    wedge_as_hex = np.array([[0, 1, 2, 3, 4, 4, 7, 7]])  # top edge 4-5 / 7-6 merged
    split = split_degenerate_solids(wedge_as_hex)
    rows, conn = split["wedge6"]
    assert rows.tolist() == [0]
    assert np.all(corner_determinants(cube[conn], "wedge6") > 0)
    tet = split_degenerate_solids(np.array([[0, 1, 3, 3, 4, 4, 4, 4]]))["tet4"][1]
    assert np.all(corner_determinants(cube[tet], "tet4") > 0)


@pytest.mark.parametrize("etype", list(MIRRORED_NODE_ORDER))
def test_mirrored_node_order_turns_a_mirrored_element_positive(etype):
    x = np.array(UNIT[etype]) * np.array([1.0, -1.0, 1.0])
    order = MIRRORED_NODE_ORDER[etype]
    assert sorted(order) == list(range(NODES_PER_ELEMENT[etype]))
    y = x[list(order)]
    if etype == "tet10":  # the mid-edge nodes still sit on their edges
        half = ELEMENT_EDGES[etype]
        for (a, m), (_, b) in zip(half[::2], half[1::2], strict=True):
            assert np.allclose(y[m], 0.5 * (y[a] + y[b]))
    if etype in CORNER_TRIPLES and etype != "quad4":
        k = CORNER_NODES[etype]
        assert np.all(corner_determinants(x[None, :k], etype) < 0)
        assert np.all(corner_determinants(y[None, :k], etype) > 0)


@pytest.mark.parametrize("etype", list(CORNER_TRIPLES))
def test_node_major_corner_determinants_match_the_kernels(etype):
    """The node-major (einsum) layout agrees with the kernels' component-major reference."""
    k = CORNER_NODES[etype]
    x = np.array(UNIT[etype])[:k] * 7.0
    pts = x + np.random.default_rng(2).uniform(-2.5, 2.5, (5000, k, 3))
    fast = corner_determinants(pts, etype)
    reference = np.stack(corner_determinants_cm(list(np.moveaxis(pts, (1, 2), (0, 1))), etype), 1)
    np.testing.assert_allclose(fast, reference, rtol=0, atol=1e-15 * np.abs(reference).max())
    np.testing.assert_array_equal(corner_jacobian(pts, etype), ratio_of_determinants(fast.T))


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.uint16, np.bool_, np.float64])
def test_sorted_unique_is_np_unique(dtype):
    from kneegui.topology import sorted_unique

    rng = np.random.default_rng(5)
    for values in (
        rng.integers(0, 50, size=(300, 4)),  # 2-D: flattened, as np.unique does
        rng.integers(0, 2**15, size=10_000),
        np.zeros(0),
        np.array([7]),
    ):
        a = np.asarray(values).astype(dtype)
        got = sorted_unique(a)
        expected = np.unique(a)
        assert got.dtype == expected.dtype
        np.testing.assert_array_equal(got, expected)


def test_corner_tetrahedra_in_chunks_are_the_same_and_ask_cancel(monkeypatch):
    """A whole-body model's knee has millions of corners: the table is filled a chunk of
    elements at a time, asking ``cancel`` before each, and comes out the same."""
    rng = np.random.default_rng(5)
    blocks = {
        "hex8": ElementBlock("hex8", np.arange(10), np.ones(10, int), rng.integers(0, 99, (10, 8))),
        "tet4": ElementBlock("tet4", np.arange(7), np.ones(7, int), rng.integers(0, 99, (7, 4))),
    }
    masks = {"hex8": rng.random(10) < 0.7, "tet4": np.ones(7, bool)}
    whole = corner_tetrahedra(blocks, masks)
    table = np.array(CORNER_TRIPLES["hex8"])
    expected = np.concatenate(
        [blocks["hex8"].conn[masks["hex8"]][:, table].reshape(-1, 4), blocks["tet4"].conn]
    )
    np.testing.assert_array_equal(whole, expected)
    monkeypatch.setattr(topology, "CORNER_ELEMENT_CHUNK", 3)
    asked = []
    chunked = corner_tetrahedra(blocks, masks, cancel=lambda: asked.append(1) or False)
    np.testing.assert_array_equal(chunked, whole)
    assert len(asked) == -(-int(masks["hex8"].sum()) // 3) + 3  # ceil(hex / 3) + ceil(7 / 3)
    with pytest.raises(Cancelled):
        corner_tetrahedra(blocks, masks, cancel=lambda: True)


def test_row_groups_share_an_index_exactly_between_equal_rows():
    rng = np.random.default_rng(7)
    rows = rng.integers(0, 4, size=(200, 3))
    group = topology.row_groups(rows)
    same_group = group[:, None] == group[None, :]
    same_row = (rows[:, None, :] == rows[None, :, :]).all(axis=2)
    np.testing.assert_array_equal(same_group, same_row)
    assert sorted(set(group.tolist())) == list(range(len(np.unique(rows, axis=0))))
    np.testing.assert_array_equal(topology.row_multiplicity(rows), same_row.sum(axis=1))
    assert len(topology.row_groups(np.zeros((0, 3), dtype=np.int64))) == 0
