"""The exact closest-point search on a bone surface (kneegui.reposition.triangle_grid) and the
distance query that uses it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from kneegui.reposition.contact import BoneSurfaceDistance, DistanceMemo


def _hull_surface(points: np.ndarray) -> np.ndarray:
    """Outward triangles (T, 3, 3) of the convex hull of ``points``."""
    tris = points[ConvexHull(points).simplices]
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    flip = np.einsum("ij,ij->i", normal, tris.mean(axis=1) - points.mean(axis=0)) < 0
    tris[flip] = tris[flip][:, [0, 2, 1]]
    return tris


def _brute_force(surface: BoneSurfaceDistance, p: np.ndarray):
    """``_closest`` over every (point, triangle) pair: the reference."""
    rows = np.repeat(np.arange(len(p)), len(surface.tri_xyz))
    tris = np.tile(np.arange(len(surface.tri_xyz)), len(p))
    return surface._closest(p, rows, tris)


@pytest.fixture
def rock() -> BoneSurfaceDistance:
    """A bumpy closed surface of long, thin and small triangles (the hull of random points
    on a stretched ellipsoid)."""
    rng = np.random.default_rng(7)
    direction = rng.normal(size=(300, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = direction * rng.uniform(0.9, 1.1, (300, 1)) * np.array([60.0, 20.0, 12.0])
    return BoneSurfaceDistance(_hull_surface(points))


def _assert_same(found, reference):
    """The grid's answer is the brute force's: the same arithmetic, so the same bits here; a
    few ulps of margin for another CPU's NumPy, whose norm of a 3-vector may sum in another
    order (the same margin as the compiled closest point's test in test_contact.py)."""
    for got, want in zip(found, reference, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_the_grid_finds_the_closest_point_of_every_triangle(rock):
    rng = np.random.default_rng(3)
    p = rng.uniform(-80.0, 80.0, (400, 3)) * np.array([1.0, 0.5, 0.4])
    _assert_same(rock.grid.closest(p, np.full(len(p), np.inf)), _brute_force(rock, p))


def test_the_grid_stops_at_the_bound_it_is_given(rock):
    """A bound below the true distance finds nothing (``inf``); the search does not run on
    past it."""
    p = np.array([[0.0, 0.0, 40.0]])
    exact = _brute_force(rock, p)[0][0]
    assert np.isinf(rock.grid.closest(p, np.array([0.5 * exact]))[0][0])
    assert rock.grid.closest(p, np.array([exact]))[0][0] == pytest.approx(exact, rel=1e-12)


def test_a_point_next_to_a_second_bone_is_measured_to_the_face_it_nearly_touches(box_surface):
    """The tibia and the fibula are one segment's surface: a point 0.1 mm above the middle of
    the tibia's large face, with a fibula corner 3 mm away, was measured 3 mm away (against
    the triangles around the nearest surface node, the fibula's), beyond a contact band it
    lies well inside."""
    tibia = box_surface((-50.0, -50.0, -100.0), (50.0, 50.0, 0.0))
    fibula = box_surface((-3.0, -3.0, 3.1), (3.0, 3.0, 9.0))
    surface = BoneSurfaceDistance(np.concatenate([tibia, fibula]), exact_within=3.0)
    p = np.array([[-3.0, -3.0, 0.1], [0.0, 0.0, 1.0], [10.0, 10.0, -0.4]])
    depth, _, normal, node_distance = surface.query(p)
    assert node_distance[0] == pytest.approx(3.0)  # the nearest node: a fibula corner
    np.testing.assert_allclose(depth, [0.1, 1.0, -0.4], atol=1e-12)
    np.testing.assert_allclose(normal[:2], [[0.0, 0.0, 1.0]] * 2, atol=1e-12)


def test_farther_points_get_at_least_the_exact_distance_and_the_memo_a_lower_bound(rock):
    """Beyond ``exact_within`` the fan's distance may be more than the exact one (never
    less), and what the memo keeps for them is at most the exact distance: its bounds stay
    bounds."""
    rng = np.random.default_rng(11)
    p = rng.uniform(-120.0, 120.0, (500, 3))
    depth, _, _, node_distance = rock.query(p)
    exact = _brute_force(rock, p)[0]
    outside = depth > 0
    assert np.all(depth[outside] >= exact[outside] - 1e-12)
    near = node_distance < rock.exact_reach
    np.testing.assert_allclose(np.abs(depth[near]), exact[near], rtol=1e-12, atol=1e-12)
    memo = DistanceMemo(rock, p, depth, node_distance)
    assert np.all(memo.depth[outside] <= exact[outside] + 1e-12)


def test_degenerate_triangles_are_measured_as_the_reference_measures_them(rock):
    """A damaged deck's bone can hold triangles of zero area (two corners at one point, or
    three on a line): their 0 / 0 is NaN, clipped as the NumPy reference clips it, not an
    error (the robustness fuzz found one)."""
    tri = rock.tri_xyz.copy()
    tri[0, 1] = tri[0, 0]  # a == b
    tri[1, 2] = tri[1, 1]  # b == c
    tri[2, 2] = tri[2, 0]  # c == a
    tri[3, 1:] = tri[3, 0]  # one point
    tri[4, 2] = 0.5 * (tri[4, 0] + tri[4, 1])  # three on a line
    surface = BoneSurfaceDistance(tri)
    rng = np.random.default_rng(5)
    p = (tri[:5, None, :, :].mean(axis=2) + rng.normal(0.0, 2.0, (5, 200, 3))).reshape(-1, 3)
    _assert_same(surface.grid.closest(p, np.full(len(p), np.inf)), _brute_force(surface, p))
