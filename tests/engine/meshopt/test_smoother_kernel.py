"""The smoother's compiled element measures are the NumPy reference's, to the last bit."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.meshopt.parallel import PARALLEL_MIN_ELEMENTS
from kneegui.meshopt.smoother import SMOOTHED_TYPES, corner_quality, edge_ratio, warp_cosine
from kneegui.meshopt.smoother_kernel import element_measures

SHAPES = {
    "hex8": [
        (0, 0, 0),
        (1, 0, 0),
        (1, 1, 0),
        (0, 1, 0),
        (0, 0, 1),
        (1, 0, 1),
        (1, 1, 1),
        (0, 1, 1),
    ],
    "wedge6": [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (0, 1, 1)],
    "pyramid5": [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0.5, 0.5, 0.7)],
    "tet4": [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)],
    "quad4": [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)],
}


def _elements(etype: str, count: int, seed: int):
    """Perturbed reference shapes: many inverted, some with a collapsed edge or a flat face."""
    shape = np.array(SHAPES[etype], dtype=float)
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
def test_element_measures_are_the_numpy_reference_bit_for_bit(etype, count):
    coords, conn = _elements(etype, count, seed=len(etype) + count)
    rows = np.random.default_rng(3).permutation(count)[: count - 17]  # a subset, in any order
    got = element_measures(coords, conn, rows, etype)
    points = coords[conn[rows]]
    jac, scaled = corner_quality(points, etype)
    expected = np.stack([jac, scaled, edge_ratio(points, etype), warp_cosine(points, etype)])
    assert got.shape == (4, len(rows))
    # the same bits, not merely close: the smoother's accept/reject decisions compare these
    np.testing.assert_array_equal(got, expected)
    assert np.any(jac <= 0) and np.any(jac > 0)  # both branches were exercised
    assert np.isinf(got[2]).any()  # and the zero-length edge's
    if etype != "tet4":
        assert (got[3] < 1).any()  # warped quad faces
