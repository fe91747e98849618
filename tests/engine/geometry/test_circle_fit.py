"""Circle fit: exact and noisy arcs, degenerate input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kneegui.errors import GeometryError
from kneegui.geometry import fit_circle_2d
from kneegui.geometry.circle_fit import _algebraic_start, fit_circles_2d_subsets


def arc(center, radius, start_deg, stop_deg, n):
    t = np.radians(np.linspace(start_deg, stop_deg, n))
    return np.column_stack([center[0] + radius * np.cos(t), center[1] + radius * np.sin(t)])


def test_exact_arc():
    pts = arc((12.0, -7.0), 20.52, -100.0, 20.0, 25)
    fit = fit_circle_2d(pts)
    np.testing.assert_allclose(fit.center, [12.0, -7.0], atol=1e-9)
    assert fit.radius == pytest.approx(20.52, abs=1e-9)
    assert fit.rms < 1e-9
    assert fit.arc_span_deg == pytest.approx(120.0, abs=1e-6)
    np.testing.assert_allclose(fit.residuals(pts), 0.0, atol=1e-9)


def test_noisy_arc_radius_within_0_05_mm():
    rng = np.random.default_rng(2012)
    pts = arc((3.0, 40.0), 23.31, 180.0, 300.0, 200)
    noisy = pts + rng.normal(0.0, 0.1, pts.shape)
    fit = fit_circle_2d(noisy)
    assert fit.radius == pytest.approx(23.31, abs=0.05)
    np.testing.assert_allclose(fit.center, [3.0, 40.0], atol=0.1)
    assert fit.rms == pytest.approx(0.1, rel=0.2)


def test_geometric_refinement_beats_the_algebraic_start_on_a_short_noisy_arc():
    rng = np.random.default_rng(7)
    errors_kasa, errors_fit = [], []
    for _ in range(20):
        pts = arc((0.0, 0.0), 20.5, 200.0, 260.0, 40) + rng.normal(0.0, 0.3, (40, 2))
        errors_kasa.append(abs(_algebraic_start(pts)[1] - 20.5))
        errors_fit.append(abs(fit_circle_2d(pts).radius - 20.5))
    assert np.mean(errors_fit) < np.mean(errors_kasa)


@settings(max_examples=40, deadline=None)
@given(
    cx=st.floats(-1e3, 1e3),
    cy=st.floats(-1e3, 1e3),
    radius=st.floats(1.0, 200.0),
    start=st.floats(-180.0, 180.0),
    span=st.floats(30.0, 300.0),
)
def test_any_exact_arc_is_recovered(cx, cy, radius, start, span):
    fit = fit_circle_2d(arc((cx, cy), radius, start, start + span, 30))
    assert fit.radius == pytest.approx(radius, rel=1e-7, abs=1e-7)
    np.testing.assert_allclose(fit.center, [cx, cy], atol=1e-6 * max(1.0, radius))
    assert fit.arc_span_deg == pytest.approx(span, abs=1e-4)


def test_full_circle_span():
    fit = fit_circle_2d(arc((0, 0), 5.0, 0.0, 350.0, 36))
    assert fit.arc_span_deg == pytest.approx(350.0)


@pytest.mark.parametrize(
    "points",
    [
        np.zeros((0, 2)),
        np.array([[0.0, 0.0], [1.0, 1.0]]),
        np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]),
        np.array([[1.0, 1.0]] * 5),
        np.array([[0.0, 0.0], [1.0, np.nan], [2.0, 0.5]]),
        np.zeros((4, 3)),
    ],
)
def test_degenerate_input_raises(points):
    with pytest.raises(GeometryError):
        fit_circle_2d(points)


def test_input_not_mutated():
    pts = arc((1.0, 2.0), 3.0, 0.0, 90.0, 10)
    before = pts.copy()
    fit_circle_2d(pts)
    np.testing.assert_array_equal(pts, before)


@pytest.mark.parametrize("noise", [0.0, 0.1, 1.0])
def test_subset_fits_equal_one_by_one_fits(noise):
    """The batched fast path against the obvious slow one, subset by subset, from the algebraic
    starts and from a common start.

    ``fit_circle_2d`` stops on its cost tolerance up to ~1e-7 mm from the optimum on a 1 mm noisy
    arc; the batch iterates to a zero gradient, so agreement is asked to 1e-6 mm.
    """
    rng = np.random.default_rng(5)
    pts = arc((3.0, -4.0), 22.0, 190.0, 320.0, 31) + rng.normal(0.0, noise, (31, 2))
    keep = rng.random((40, 31)) > 0.2
    keep[:, :3] = True
    full = fit_circle_2d(pts)
    start = np.tile([*full.center, full.radius], (len(keep), 1))
    for centres, radii in (
        fit_circles_2d_subsets(pts, keep),
        fit_circles_2d_subsets(pts, keep, start),
    ):
        for k in range(len(keep)):
            one = fit_circle_2d(pts[keep[k]])
            np.testing.assert_allclose(centres[k], one.center, atol=1e-6)
            assert radii[k] == pytest.approx(one.radius, abs=1e-6)


def test_subset_without_a_circle_is_nan():
    pts = np.column_stack([np.linspace(0.0, 10.0, 6), np.zeros(6)])
    pts[5] = [5.0, 3.0]
    keep = np.ones((2, 6), dtype=bool)
    keep[0, 5] = False  # five collinear points
    centres, radii = fit_circles_2d_subsets(pts, keep)
    assert np.isnan(radii[0]) and np.all(np.isnan(centres[0]))
    assert np.isfinite(radii[1])


def test_subset_fit_rejects_tiny_subsets():
    pts = arc((0.0, 0.0), 20.0, 180.0, 300.0, 10)
    keep = np.zeros((2, 10), dtype=bool)
    keep[:, :2] = True
    with pytest.raises(GeometryError, match="fewer than 3"):
        fit_circles_2d_subsets(pts, keep)
