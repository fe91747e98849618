"""The smoother's compiled kernels against their NumPy references."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.meshopt.parallel import PARALLEL_MIN_ELEMENTS
from kneegui.meshopt.smoother import SMOOTHED_TYPES, corner_quality, edge_ratio, warp_cosine
from kneegui.meshopt.smoother_kernel import element_measures


def _elements(shape, count: int, seed: int):
    """Perturbed copies of ``shape``: many inverted, some with a collapsed edge or a flat face."""
    k = len(shape)
    rng = np.random.default_rng(seed)
    pts = np.tile(shape, (count, 1)) + rng.uniform(-0.6, 0.6, (count * k, 3))
    conn = rng.permutation(count * k).reshape(count, k)  # nodes shared by no order
    coords = np.empty_like(pts)
    coords[conn.ravel()] = pts
    coords[conn[::7, 1]] = coords[conn[::7, 0]]  # a zero-length edge every seventh element
    coords[conn[::11]] = coords[conn[::11]] * [1.0, 1.0, 0.0]  # flattened elements
    return coords, conn


@pytest.mark.parametrize("etype", SMOOTHED_TYPES)
@pytest.mark.parametrize("count", [300, PARALLEL_MIN_ELEMENTS + 500])
def test_element_measures_are_the_numpy_reference(etype, count, reference_shape):
    coords, conn = _elements(reference_shape(etype), count, seed=len(etype) + count)
    rows = np.random.default_rng(3).permutation(count)[: count - 17]  # a subset, in any order
    got = element_measures(coords, conn, rows, etype)
    points = coords[conn[rows]]
    jac, scaled = corner_quality(points, etype)
    expected = np.stack([jac, scaled, edge_ratio(points, etype), warp_cosine(points, etype)])
    assert got.shape == (4, len(rows))
    # the same arithmetic in the same order: on this project's machine the same bits (the
    # smoother's exports were checked identical); a margin of a few ulps for a NumPy whose
    # SIMD loops round another way on another CPU
    np.testing.assert_allclose(got, expected, rtol=1e-13, atol=1e-13)
    assert np.any(jac <= 0) and np.any(jac > 0)  # both branches were exercised
    assert np.isinf(got[2]).any()  # and the zero-length edge's
    if etype != "tet4":
        assert (got[3] < 1).any()  # warped quad faces


def _local_problems(block_model, nodes_wanted: int, seed: int):
    """Local problems of interior nodes of a perturbed block, some sliding in a plane."""
    from kneegui.meshopt.batched import build_problems
    from kneegui.meshopt.smoother import CORNER_TRIPLES

    model = block_model(9, 9, 9, skin=False)
    rng = np.random.default_rng(seed)
    coords = model.coords + rng.uniform(-0.15, 0.15, model.coords.shape)
    block = model.blocks["hex8"]
    interior = np.flatnonzero(np.all((model.coords > 0.5) & (model.coords < 8.5), axis=1))
    nodes = rng.choice(interior, nodes_wanted, replace=False)
    owner, slot, conns = [], [], []
    counts = np.zeros(len(nodes), dtype=np.int64)
    for i, node in enumerate(nodes):
        rows = np.flatnonzero(np.any(block.conn == node, axis=1))
        owner += [i] * len(rows)
        slot += list(range(len(rows)))
        conns.append(block.conn[rows])
        counts[i] = len(rows)
    normal = rng.normal(size=(len(nodes), 3))
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    projector = np.repeat(np.eye(3)[None], len(nodes), axis=0)
    sliding = rng.random(len(nodes)) < 0.3
    projector[sliding] -= normal[sliding, :, None] * normal[sliding, None, :]
    return build_problems(
        nodes, coords,
        [("hex8", np.array(owner), np.array(slot), np.concatenate(conns))],
        CORNER_TRIPLES, projector,
        rng.uniform(-1.5, 0.6, len(nodes)), rng.integers(0, 2, len(nodes)).astype(float),
        rng.uniform(1.5, 4.0, len(nodes)), counts,
    )  # fmt: skip


@pytest.mark.parametrize("nodes", [20, 400])
def test_batched_objective_compiled_is_the_numpy_objective(block_model, nodes):
    from kneegui.meshopt.batched import objective, objective_numpy

    problems = _local_problems(block_model, nodes, seed=nodes)
    moves = np.random.default_rng(1).normal(0.0, 0.35, (nodes, 4, 3))  # some invert elements
    got = objective(problems, moves)
    expected = objective_numpy(problems, moves)
    assert got.shape == (nodes, 4)
    # squared edge lengths |end|^2 - 2 end.x + |x|^2 cancel about 8 digits here (coordinates
    # near 9, edges near 1), and NumPy's matmul sums in its own order
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9)
    # both branches of an element's score were reached: valid at the start, inverted by moves
    real = problems.element
    assert not ((problems.d0.min(axis=2) <= 0) & real).any()
    delta = moves @ problems.projector.transpose(0, 2, 1)
    dets = problems.d0[..., None] + np.einsum("newk,npk->newp", problems.grad, delta)
    assert ((dets.min(axis=2) <= 0) & real[..., None]).any()


def _jones_plassmann(ptr, nbrs, priority):
    """Reference: rounds of the uncoloured nodes whose priority beats every uncoloured
    neighbour's, each taking the smallest colour its coloured neighbours leave."""
    n = len(ptr) - 1
    colour = np.full(n, -1)
    while (colour < 0).any():
        chosen = []
        for i in np.flatnonzero(colour < 0):
            around = nbrs[ptr[i] : ptr[i + 1]]
            if all(colour[j] >= 0 or priority[j] < priority[i] for j in around):
                used = {colour[j] for j in around if colour[j] >= 0}
                chosen.append((i, min(set(range(len(around) + 1)) - used)))
        for i, c in chosen:
            colour[i] = c
    return colour


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_greedy_colours_are_the_jones_plassmann_colouring(seed):
    from kneegui.meshopt.smoother_kernel import greedy_colours

    rng = np.random.default_rng(seed)
    n = 400
    a = rng.integers(0, n, 3000)
    b = rng.integers(0, n, 3000)
    keep = a != b
    pairs = np.unique(np.stack([np.r_[a[keep], b[keep]], np.r_[b[keep], a[keep]]], 1), axis=0)
    ptr = np.searchsorted(pairs[:, 0], np.arange(n + 1))
    nbrs = pairs[:, 1]
    priority = rng.permutation(n)
    colour = greedy_colours(ptr, nbrs, priority)
    np.testing.assert_array_equal(colour, _jones_plassmann(ptr, nbrs, priority))
    assert np.all(colour[pairs[:, 0]] != colour[pairs[:, 1]])  # a proper colouring
    assert colour.max() >= 5  # a graph that needs several
