"""Geometric checks of a pose: ray-cast inside-ness against every triangle and binned."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

from kneegui.reposition.checks import (
    RAY_PERTURBATION,
    _count_crossings,
    crossings_along_ray,
    inside_closed_surface,
)


def closed_surface(seed: int = 0, n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangulated surface: the hull of points on an ellipsoid (radii 30, 20, 60)."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    coords = u / np.linalg.norm(u, axis=1, keepdims=True) * (30.0, 20.0, 60.0)
    return coords, ConvexHull(coords).simplices.astype(np.int64)


def test_binned_crossings_equal_every_triangle():
    """The binned count is the count against every triangle, point by point, for points
    inside, outside and beyond the surface's shadow (generic points: one exactly on a vertex
    or an edge could be counted either way by the last bit of the arithmetic)."""
    coords, tris = closed_surface()
    rng = np.random.default_rng(1)
    points = rng.uniform(-65, 65, (4000, 3))
    direction = np.array([1.0, 0.2, 0.0])
    d = direction / np.linalg.norm(direction) + RAY_PERTURBATION
    binned = crossings_along_ray(points, coords[tris], direction)
    every = _count_crossings(points, coords[tris], d, 256)
    np.testing.assert_array_equal(binned, every)
    assert binned.max() >= 2 and np.count_nonzero(binned % 2) > 100


def test_inside_closed_surface():
    """Inside-ness by the crossings' parity, away from the surface; a point outside the
    surface's box is outside without a ray."""
    coords, tris = closed_surface(2)
    rng = np.random.default_rng(3)
    points = rng.uniform(-70, 70, (4000, 3))
    level = np.sum((points / (30.0, 20.0, 60.0)) ** 2, axis=1)
    clear = (level < 0.8) | (level > 1.2)  # the hull of 400 points is within 20 % of it
    inside = inside_closed_surface(points, coords, tris, np.array([0.0, 1.0, 0.0]))
    np.testing.assert_array_equal(inside[clear], level[clear] < 1.0)
    far = np.array([[0.0, 0.0, 500.0], [100.0, 0.0, 0.0]])
    assert not inside_closed_surface(far, coords, tris, np.array([0.0, 1.0, 0.0])).any()
