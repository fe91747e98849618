"""The rigid blend's mesh graph (kneegui.reposition.rigid_blend)."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.geometry.transforms import RigidTransform
from kneegui.model import ElementBlock
from kneegui.reposition.rigid_blend import (
    exp_twists_apply,
    exp_twists_apply_numpy,
    log_rigid,
    mesh_edges,
)
from kneegui.topology import ELEMENT_EDGES


def _reference_edges(blocks, masks):
    chunks = []
    for etype, block in blocks.items():
        conn = block.conn[masks[etype]]
        for a, b in ELEMENT_EDGES[etype]:
            chunks.append(np.column_stack([conn[:, a], conn[:, b]]))
    e = np.sort(np.concatenate(chunks), axis=1)
    return np.unique(e[e[:, 0] != e[:, 1]], axis=0)


def test_mesh_edges_are_the_unique_sorted_rows_with_collapsed_edges_dropped():
    rng = np.random.default_rng(3)
    n_nodes = 5000
    hexes = rng.integers(0, n_nodes, size=(3000, 8))
    hexes[:50, 1] = hexes[:50, 0]  # degenerate (collapsed) edges are dropped
    tets = rng.integers(0, n_nodes, size=(2000, 4))
    blocks = {
        "hex8": ElementBlock("hex8", np.arange(3000), np.zeros(3000), hexes),
        "tet4": ElementBlock("tet4", np.arange(2000), np.zeros(2000), tets),
    }
    masks = {"hex8": rng.random(3000) < 0.7, "tet4": np.ones(2000, dtype=bool)}
    got = mesh_edges(blocks, masks)
    expected = _reference_edges(blocks, masks)
    assert got.dtype == np.int64 and got.shape == expected.shape
    np.testing.assert_array_equal(got, expected)
    assert not np.any(got[:, 0] == got[:, 1])


def test_mesh_edges_sorted_in_pieces_are_the_same_array_and_ask_between_pieces(monkeypatch):
    from kneegui.errors import Cancelled
    from kneegui.reposition import rigid_blend

    rng = np.random.default_rng(5)
    n_nodes = 20_000
    hexes = rng.integers(0, n_nodes, size=(4000, 8))
    hexes[:30, 6] = hexes[:30, 5]
    blocks = {"hex8": ElementBlock("hex8", np.arange(4000), np.zeros(4000), hexes)}
    masks = {"hex8": rng.random(4000) < 0.8}
    expected = _reference_edges(blocks, masks)
    monkeypatch.setattr(rigid_blend, "EDGE_SORT_PIECE", 5000)
    asked = []
    got = mesh_edges(blocks, masks, lambda: bool(asked.append(1)))
    np.testing.assert_array_equal(got, expected)
    n_keys = sum(  # the edges that are not collapsed, duplicates included
        int(np.count_nonzero(hexes[masks["hex8"]][:, a] != hexes[masks["hex8"]][:, b]))
        for a, b in ELEMENT_EDGES["hex8"]
    )
    pieces = -(-n_keys // 5000)
    assert pieces >= 5
    assert len(asked) == 1 + 12 + pieces  # the type, each of its edges, each piece
    np.testing.assert_array_equal(mesh_edges(blocks, masks), expected)  # no cancel: one sort
    calls = []

    def cancel_at_the_third_piece() -> bool:
        calls.append(1)
        return len(calls) == 1 + 12 + 3

    with pytest.raises(Cancelled, match="edges"):
        mesh_edges(blocks, masks, cancel_at_the_third_piece)


def test_block_cg_gives_the_same_bits_with_any_number_of_threads():
    import numba
    import scipy.sparse as sp

    from kneegui.reposition.rigid_blend import _CG_CHUNK_ROWS, block_cg

    n = 5 * _CG_CHUNK_ROWS + 123  # several chunks, the last one partial
    rng = np.random.default_rng(11)
    off = rng.random(n - 1)
    lap = sp.diags([-off, np.r_[off, 0.0] + np.r_[0.0, off] + 1e-3, -off], [-1, 0, 1]).tocsr()
    rhs = rng.random((n, 4))
    rhs[:, 2] *= 1e-9  # converges at another iteration than the others
    rhs[:, 3] = 0.0  # nothing to solve: never iterates, stays at its start
    results = []
    before = numba.get_num_threads()
    try:
        for threads in sorted({1, before}):
            numba.set_num_threads(threads)
            results.append(block_cg(lap, rhs, np.zeros_like(rhs), 1.0 / lap.diagonal()))
    finally:
        numba.set_num_threads(before)
    for other in results[1:]:
        np.testing.assert_array_equal(other, results[0])
    residual = rhs - lap @ results[0]
    assert np.all(np.linalg.norm(residual, axis=0) <= 1e-7 * np.linalg.norm(rhs, axis=0))
    assert np.all(results[0][:, 3] == 0.0) and np.all(results[0][:, :3] != 0.0)


def test_the_nearest_of_several_surfaces_is_the_distance_to_their_union_to_the_bit():
    """The bone coupling takes the nearest of the per-bone distances the prior measured, in
    place of a search of all bones' nodes together: the same bits."""
    from scipy.spatial import cKDTree

    from kneegui.reposition.rigid_blend import surface_distances

    rng = np.random.default_rng(5)
    coords = rng.normal(size=(4000, 3)) * [40.0, 30.0, 200.0]
    surfaces = [rng.choice(4000, 300, replace=False) for _ in range(3)] + [np.zeros(0, int)]
    nodes = rng.choice(4000, 1500, replace=False)
    distance = surface_distances(coords, nodes, surfaces)
    assert distance.shape == (1500, 4) and np.all(np.isinf(distance[:, 3]))
    union = np.concatenate(surfaces[:3])
    expected = cKDTree(coords[union]).query(coords[nodes])[0]
    np.testing.assert_array_equal(distance[:, :3].min(axis=1), expected)


def _cube_model(n: int) -> tuple:
    """A cube of n x n x n nodes on a unit grid: its coordinates, node index grid, edges, three
    anchor groups (two opposite faces and an edge line) and the free nodes."""
    ticks = np.arange(n, dtype=float)
    coords = np.stack(np.meshgrid(ticks, ticks, ticks, indexing="ij"), -1).reshape(-1, 3)
    index = np.arange(n**3).reshape(n, n, n)
    edges = np.concatenate(
        [
            np.column_stack([index[:-1].ravel(), index[1:].ravel()]),
            np.column_stack([index[:, :-1].ravel(), index[:, 1:].ravel()]),
            np.column_stack([index[:, :, :-1].ravel(), index[:, :, 1:].ravel()]),
        ]
    )
    anchors = [index[0].ravel(), index[-1].ravel(), index[:, 0, 0]]
    anchors[2] = np.setdiff1d(anchors[2], np.concatenate(anchors[:2]))
    free = np.setdiff1d(np.arange(n**3), np.concatenate(anchors))
    return coords, index, edges, anchors, free


def _coarse_spaces_built(monkeypatch) -> list:
    """Force the iterative weights (no direct solve) and record every coarse space built."""
    from kneegui.reposition import rigid_blend

    built = []
    real = rigid_blend.coarse_space
    monkeypatch.setattr(rigid_blend, "DIRECT_SOLVE_MAX", 0)
    monkeypatch.setattr(rigid_blend, "coarse_space", lambda *a: built.append(real(*a)) or built[-1])
    return built


def test_harmonic_weights_are_the_same_given_the_surface_distances():
    from kneegui.reposition.rigid_blend import harmonic_weights, surface_distances

    n = 12
    coords, index, edges, anchors, free = _cube_model(n)
    measured = harmonic_weights(n**3, edges, free, anchors, coords)
    given = harmonic_weights(
        n**3,
        edges,
        free,
        anchors,
        coords,
        surface_distance=surface_distances(coords, free, anchors),
    )
    np.testing.assert_array_equal(given, measured)
    np.testing.assert_allclose(measured.sum(axis=1), 1.0, rtol=1e-12)
    # the weight of the first group falls from its face to the opposite one
    column = measured[np.searchsorted(free, index[1:-1, 5, 5]), 0]
    assert np.all(np.diff(column) < 0)


def test_the_compiled_twist_exponential_gives_the_numpy_reference():
    # every branch: no rotation, the small-angle series (below 1e-6 rad), up to nearly 180 deg
    rng = np.random.default_rng(5)
    scale = rng.choice([0.0, 1e-9, 1e-7, 5e-7, 2e-6, 1e-3, 0.1, 1.0, 3.0], size=(20_000, 1))
    twists = rng.normal(size=(20_000, 6)) * scale
    points = rng.normal(size=(20_000, 3)) * 50.0
    got = exp_twists_apply(twists, points)
    expected = exp_twists_apply_numpy(twists, points)
    assert got.shape == points.shape
    # the same bits on this project's machine (NumPy's sin, cos and pow are libm's there, as
    # the compiled loop's); a few ulps of margin for another CPU's NumPy, whose norm or
    # transcendental functions may take another path
    scale = np.abs(points).max(axis=1, keepdims=True) + np.abs(twists).max(axis=1, keepdims=True)
    scale *= 1.0 + np.abs(twists[:, :3]).max(axis=1, keepdims=True) ** 2
    bound = np.broadcast_to(1e-14 * scale + 1e-300, got.shape)
    np.testing.assert_array_less(np.abs(got - expected), bound)


def test_the_twist_exponential_moves_points_by_the_rigid_motion_it_came_from():
    rng = np.random.default_rng(6)
    axis = rng.normal(size=3)
    motion = RigidTransform.about_axis(rng.normal(size=3) * 20.0, axis, 70.0)
    points = rng.normal(size=(50, 3)) * 40.0
    twists = np.tile(log_rigid(motion), (50, 1))
    np.testing.assert_allclose(exp_twists_apply(twists, points), motion.apply(points), atol=1e-9)


def _grid_laplacian(side: int) -> tuple:
    """A 3-D grid's graph Laplacian (6 neighbours) with a small shift, and its nodes' coords."""
    import scipy.sparse as sp

    line = sp.diags([-np.ones(side - 1), -np.ones(side - 1)], [-1, 1])
    eye = sp.identity(side)
    along = [sp.kron(sp.kron(line, eye), eye), sp.kron(sp.kron(eye, line), eye)]
    adjacency = along[0] + along[1] + sp.kron(sp.kron(eye, eye), line)
    degree = -np.asarray(adjacency.sum(axis=1)).ravel()
    lap = (sp.diags(degree + 1e-4) + adjacency).tocsr()
    ticks = np.arange(side, dtype=float)
    coords = np.stack(np.meshgrid(ticks, ticks, ticks, indexing="ij"), axis=-1).reshape(-1, 3)
    return lap, coords


def test_the_coarse_space_solves_to_the_same_tolerance_in_fewer_iterations():
    """The two-level preconditioner changes how fast block CG gets there, not where: the
    residual test is the same, the solution agrees with a direct solve, and the iterations
    (counted by the cancel polls, one per 25) drop at least by half on a grid Laplacian."""
    import scipy.sparse.linalg as spla

    from kneegui.reposition.rigid_blend import block_cg, coarse_space

    lap, coords = _grid_laplacian(32)
    rng = np.random.default_rng(3)
    rhs = np.zeros((len(coords), 3))
    rhs[coords[:, 0] == 0, 0] = 1.0  # a Dirichlet-like face: a solution smooth over the grid
    rhs[coords[:, 2] == 31, 1] = 1.0
    rhs[:, 2] = rng.random(len(coords))
    exact = spla.splu(lap.tocsc()).solve(rhs)
    polls = {}
    results = {}
    for name, coarse in (("jacobi", None), ("two-level", coarse_space(lap, coords, 4.0))):
        calls = []
        results[name] = block_cg(
            lap, rhs, np.zeros_like(rhs), 1.0 / lap.diagonal(), rtol=1e-10,
            cancel=lambda calls=calls: bool(calls.append(1)), coarse=coarse,
        )  # fmt: skip
        polls[name] = len(calls)
        # the true residual, not the recurrence the solver tests: it drifts by rounding
        residual = np.linalg.norm(rhs - lap @ results[name], axis=0)
        assert np.all(residual <= 1e-9 * np.linalg.norm(rhs, axis=0))
        np.testing.assert_allclose(results[name], exact, rtol=0, atol=1e-5 * np.abs(exact).max())
    # here 10 polls against 3: the bound leaves a margin of 100 iterations
    assert polls["two-level"] * 2 <= polls["jacobi"], polls


def test_the_coarse_space_gives_the_same_bits_with_any_number_of_threads():
    import numba

    from kneegui.reposition.rigid_blend import _CG_CHUNK_ROWS, block_cg, coarse_space

    lap, coords = _grid_laplacian(20)  # 8,000 unknowns: two row chunks
    assert len(coords) > _CG_CHUNK_ROWS
    rng = np.random.default_rng(7)
    rhs = rng.random((len(coords), 4))
    rhs[:, 2] *= 1e-9  # converges at another iteration than the others
    rhs[:, 3] = 0.0  # nothing to solve: stays at its start
    coarse = coarse_space(lap, coords, 5.0)
    assert 20 <= coarse.count <= 100
    results = []
    before = numba.get_num_threads()
    try:
        for threads in sorted({1, before}):
            numba.set_num_threads(threads)
            results.append(
                block_cg(lap, rhs, np.zeros_like(rhs), 1.0 / lap.diagonal(), coarse=coarse)
            )
    finally:
        numba.set_num_threads(before)
    for other in results[1:]:
        np.testing.assert_array_equal(other, results[0])
    assert np.all(results[0][:, 3] == 0.0) and np.all(results[0][:, :3] != 0.0)


def test_harmonic_weights_of_a_large_model_take_the_coarse_space_and_agree(monkeypatch):
    """Beyond DIRECT_SOLVE_MAX free nodes the weights come from block CG with the coarse space
    (cells of COARSE_CELL_EDGES median edges): the same weights as the direct solve, to well
    within what the blend can show (1e-6 of a unit weight)."""
    from kneegui.reposition.rigid_blend import harmonic_weights

    n = 22
    coords, _, edges, anchors, free = _cube_model(n)
    direct = harmonic_weights(n**3, edges, free, anchors, coords)
    built = _coarse_spaces_built(monkeypatch)
    iterative = harmonic_weights(n**3, edges, free, anchors, coords)
    assert len(built) == 1 and 8 <= built[0].count <= 64  # 22 nodes a side, cells of 8 edges
    np.testing.assert_allclose(iterative, direct, rtol=0, atol=1e-6)
    assert np.abs(iterative - direct).max() > 0  # not the direct solve's own answer


def test_the_coarse_space_solve_can_be_cancelled():
    """A whole-body model's weights take seconds: the two-level solve asks ``cancel`` as often
    as the Jacobi one (before the first iteration and every 25 after)."""
    from kneegui.errors import Cancelled
    from kneegui.reposition.rigid_blend import block_cg, coarse_space

    lap, coords = _grid_laplacian(24)
    rhs = np.zeros((len(coords), 2))
    rhs[coords[:, 0] == 0, 0] = 1.0
    rhs[coords[:, 1] == 0, 1] = 1.0
    calls = []

    def cancel() -> bool:
        calls.append(1)
        return len(calls) > 2

    with pytest.raises(Cancelled):
        block_cg(
            lap, rhs, np.zeros_like(rhs), 1.0 / lap.diagonal(), rtol=1e-14,
            cancel=cancel, coarse=coarse_space(lap, coords, 4.0),
        )  # fmt: skip
    assert len(calls) == 3


def test_the_coarse_space_needs_no_edge_between_free_nodes(monkeypatch):
    """Free nodes tied only to anchors give no free-free edge to measure the cells by: the
    cells then follow the nodes' extent, and the weights still match the direct solve."""
    from kneegui.reposition.rigid_blend import harmonic_weights

    rng = np.random.default_rng(9)
    coords = rng.random((3000, 3)) * 100.0
    anchors = [np.arange(0, 100), np.arange(100, 200)]
    free = np.arange(200, 3000)
    edges = np.column_stack([free, rng.integers(0, 200, len(free))])  # each to one anchor
    direct = harmonic_weights(3000, edges, free, anchors, coords)
    built = _coarse_spaces_built(monkeypatch)
    iterative = harmonic_weights(3000, edges, free, anchors, coords)
    # 2,800 nodes in a 100 mm box: cells of about 57 mm, 8 of them (no cell size: 1 cell)
    assert len(built) == 1 and 4 <= built[0].count <= 27
    np.testing.assert_allclose(iterative, direct, rtol=0, atol=1e-6)
