"""Circle fit: exact and noisy arcs, degenerate input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kneegui.errors import GeometryError
from kneegui.geometry import fit_circle_2d
from kneegui.geometry.circle_fit import _algebraic_start, fit_outer_profile


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


def _crescent(seed, noise=0.0):
    """Boundary nodes on a 20.5 mm arc plus 'side' nodes projected inside it (a picked patch)."""
    rng = np.random.default_rng(seed)
    t = np.radians(rng.uniform(180.0, 300.0, 400))
    r = np.concatenate([np.full(150, 20.5), rng.uniform(14.0, 20.5, 250)])
    pts = np.column_stack([5.0 + r * np.cos(t), 7.0 + r * np.sin(t)])
    return pts + rng.normal(0.0, noise, pts.shape)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("noise", [0.0, 0.1])
def test_outer_profile_of_a_patch(seed, noise):
    pts = _crescent(seed, noise)
    plain = fit_circle_2d(pts)
    assert plain.rms > 1.5  # the side nodes spoil a plain fit
    fit, used = fit_outer_profile(pts)
    assert fit.radius == pytest.approx(20.5, abs=0.1)
    np.testing.assert_allclose(fit.center, [5.0, 7.0], atol=0.15)
    assert 0.3 * len(pts) < used.sum() < 0.5 * len(pts)


@pytest.mark.parametrize("noise", [0.05, 0.3, 0.7, 2.0])
def test_outer_profile_keeps_every_point_of_a_noisy_arc(noise):
    rng = np.random.default_rng(3)
    pts = arc((0.0, 0.0), 20.5, 180.0, 300.0, 400) + rng.normal(0.0, noise, (400, 2))
    fit, used = fit_outer_profile(pts)
    assert used.all()
    assert fit.radius == fit_circle_2d(pts).radius
