"""Condyles that are not circles: the fit and the F-E axis spread against known geometry.

A real femoral condyle's sagittal radius decreases from the distal towards the posterior arc.
Here each condyle is a spiral arc r(theta) decreasing linearly along the arc, theta measured
from the distal point (0) towards posterior (90), sampled uniformly in theta.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.optimize import minimize

from kneegui.errors import GeometryError
from kneegui.geometry import compute_joint_axes, fit_circle_2d, rotation_matrix
from kneegui.geometry.axis_sensitivity import SensitivitySettings, axis_sensitivity
from kneegui.setup import load_setup
from kneegui.setup.synthetic import build_synthetic_knee

# frame of the synthetic points: x anterior, y lateral -> medial, z superior
FRAME = dict(anterior=[1.0, 0.0, 0.0], superior=[0.0, 0.0, 1.0], lateral_to_medial=[0.0, 1.0, 0.0])


def spiral_profile(theta_deg, r_start, r_end, arc=(10.0, 160.0)):
    """Sagittal (anterior, superior) points of r(theta) = r_start -> r_end along ``arc``."""
    t = np.radians(np.asarray(theta_deg, dtype=np.float64))
    lo, hi = np.radians(arc[0]), np.radians(arc[1])
    r = r_start + (r_end - r_start) * (t - lo) / (hi - lo)
    return np.column_stack([-r * np.sin(t), -r * np.cos(t)])


def condyle(n, r_start, r_end, noise=0.0, seed=0, ml=0.0, arc=(10.0, 160.0)):
    """(n, 3) nodes of a spiral condyle at medial-lateral position ``ml`` (+-2 mm across)."""
    rng = np.random.default_rng(seed)
    p2 = spiral_profile(np.linspace(*arc, n), r_start, r_end, arc)
    p2 = p2 + rng.normal(0.0, noise, p2.shape)
    y = ml + rng.uniform(-2.0, 2.0, n)
    return np.column_stack([p2[:, 0], y, p2[:, 1]])


def least_squares_circle(points2d):
    """Geometric least-squares circle by a generic simplex search (not the code under test)."""

    def cost(p):
        return np.mean((np.hypot(points2d[:, 0] - p[0], points2d[:, 1] - p[1]) - p[2]) ** 2)

    c0 = points2d.mean(axis=0)
    r0 = float(np.hypot(*(points2d - c0).T).mean())
    sol = minimize(
        cost,
        [c0[0], c0[1], r0],
        method="Nelder-Mead",
        options={"xatol": 1e-9, "fatol": 1e-15, "maxiter": 40000, "maxfev": 80000},
    )
    return sol.x[:2], sol.x[2], float(np.sqrt(sol.fun))


def spread(lat, med, seed=0):
    return axis_sensitivity(
        lat, med, origin=[0.0, 0.0, 0.0], **FRAME, settings=SensitivitySettings(seed=seed)
    )


# --------------------------------------------------------------------------- the fit
def test_spiral_fit_is_the_least_squares_circle_of_the_arc():
    """24 -> 18 mm over 10-160 deg: the fit of 31 noisy nodes is the arc's least-squares circle."""
    dense = spiral_profile(np.linspace(10.0, 160.0, 20001), 24.0, 18.0)
    centre, radius, rms = least_squares_circle(dense)
    # bounds from the geometry alone: the radius lies between the arc's extreme radii, the
    # centre is off the spiral's pole (the origin) and the arc is visibly not a circle
    assert 18.5 < radius < 23.5
    assert rms > 0.1
    nodes = spiral_profile(np.linspace(10.0, 160.0, 31), 24.0, 18.0)
    nodes += np.random.default_rng(1).normal(0.0, 0.1, nodes.shape)
    fit = fit_circle_2d(nodes)
    assert fit.radius == pytest.approx(radius, abs=0.3)
    np.testing.assert_allclose(fit.center, centre, atol=0.3)
    assert fit.rms == pytest.approx(np.hypot(rms, 0.1), abs=0.1)


def test_fit_uses_every_node_of_a_strong_spiral():
    """A spiral whose residual pattern looks like an outline plus inner nodes is fitted whole.

    (The former outer-boundary trimming kept 13 of these 31 nodes and gave 26.2 mm.)
    """
    nodes = spiral_profile(np.linspace(0.0, 160.0, 31), 34.0, 15.0, arc=(0.0, 160.0))
    nodes += np.random.default_rng(1).normal(0.0, 0.1, nodes.shape)
    lat = np.column_stack([nodes[:, 0], np.full(31, -25.0), nodes[:, 1]])
    med = lat + np.array([0.0, 50.0, 0.0])
    fit = fit_circle_2d(nodes)
    _, radius, _ = least_squares_circle(nodes)
    assert fit.radius == pytest.approx(radius, abs=1e-4)
    assert 22.0 < fit.radius < 26.0
    s = spread(lat, med)
    assert s.lateral_radius_spread_mm > 0.3  # the node choice matters on such a condyle


# --------------------------------------------------------------------------- the spread
def test_spread_is_zero_for_exact_circles():
    lat = condyle(31, 21.0, 21.0, ml=-25.0, seed=2)
    med = condyle(31, 23.0, 23.0, ml=25.0, seed=3)
    s = spread(lat, med)
    assert s.direction_spread_deg < 1e-6
    assert max(s.lateral_center_spread_mm, s.medial_radius_spread_mm) < 1e-6


def test_spread_is_larger_for_a_spiral_than_for_a_circle():
    circle = spread(
        condyle(31, 21.0, 21.0, noise=0.05, ml=-25.0, seed=2),
        condyle(31, 23.0, 23.0, noise=0.05, ml=25.0, seed=3),
    )
    spiral = spread(
        condyle(31, 24.0, 18.0, noise=0.05, ml=-25.0, seed=2),
        condyle(31, 26.0, 20.0, noise=0.05, ml=25.0, seed=3),
    )
    assert spiral.direction_spread_deg > 2.0 * circle.direction_spread_deg
    assert spiral.lateral_center_spread_mm > 2.0 * circle.lateral_center_spread_mm
    assert spiral.medial_radius_spread_mm > 2.0 * circle.medial_radius_spread_mm


def test_spread_shrinks_with_more_nodes():
    few = spread(
        condyle(31, 24.0, 18.0, ml=-25.0, seed=2), condyle(31, 26.0, 20.0, ml=25.0, seed=3)
    )
    many = spread(
        condyle(124, 24.0, 18.0, ml=-25.0, seed=2), condyle(124, 26.0, 20.0, ml=25.0, seed=3)
    )
    assert many.direction_spread_deg < 0.7 * few.direction_spread_deg
    assert many.lateral_center_spread_mm < 0.7 * few.lateral_center_spread_mm
    assert many.medial_radius_spread_mm < 0.7 * few.medial_radius_spread_mm


def test_spread_is_deterministic_and_inputs_untouched():
    lat = condyle(31, 24.0, 18.0, noise=0.1, ml=-25.0, seed=2)
    med = condyle(31, 26.0, 20.0, noise=0.1, ml=25.0, seed=3)
    before = (lat.copy(), med.copy())
    a, b = spread(lat, med), spread(lat, med)
    np.testing.assert_array_equal(a.direction_deg, b.direction_deg)
    np.testing.assert_array_equal(lat, before[0])
    np.testing.assert_array_equal(med, before[1])
    c = spread(lat, med, seed=1)
    assert not np.array_equal(a.direction_deg, c.direction_deg)
    assert c.direction_spread_deg == pytest.approx(a.direction_spread_deg, rel=0.5)
    d = a.to_dict()
    assert d["n_subsets"] == 200 and d["leave_out_fraction"] == 0.2
    assert d["direction_spread_deg"] == a.direction_spread_deg
    assert "F-E axis within" in a.summary()


@pytest.mark.parametrize(
    "kwargs", [{"n_subsets": 5}, {"leave_out_fraction": 0.0}, {"percentile": 40.0}]
)
def test_settings_validated(kwargs):
    with pytest.raises(ValueError):
        SensitivitySettings(**kwargs)


def test_too_few_nodes_to_resample():
    lat = condyle(3, 21.0, 21.0, ml=-25.0)
    med = condyle(31, 23.0, 23.0, ml=25.0)
    with pytest.raises(GeometryError, match="too few"):
        spread(lat, med)


# --------------------------------------------------------------------------- two condyles
def spiral_knee(side="right", wide=False):
    """Synthetic knee whose condyle rims are spirals (lateral 22 -> 17, medial 25 -> 19 mm along
    0-120 deg), 0.05 mm noise; returns the knee, its setup, the coordinates and the known axis
    (through each rim's least-squares circle centre, found by a generic simplex search)."""
    knee = build_synthetic_knee(side=side)
    setup = load_setup(knee.setup, knee.model)
    coords = knee.model.coords.copy()
    world = knee.to_world[:3, :3]
    to_local = np.linalg.inv(world)  # the knee as built: x anterior, y medial, z superior
    origin = knee.to_world[:3, 3]
    rng = np.random.default_rng(7)
    expected = []
    for idx, (r0, r1) in (
        (setup.lateral_condyle, (22.0, 17.0)),
        (setup.medial_condyle, (25.0, 19.0)),
    ):
        local = (coords[idx] - origin) @ to_local.T
        d = local[:, [0, 2]] - np.array([-8.0, 0.0])
        theta = np.degrees(np.arctan2(-d[:, 0], -d[:, 1]))  # 0 distal, 90 posterior
        profile = spiral_profile(theta, r0, r1, arc=(0.0, 120.0)) + np.array([-8.0, 0.0])
        centre2d, _, _ = least_squares_circle(profile)
        y = local[:, 1]
        if wide:  # spread the rows across 4x the width, as a wide picked band
            y = y.mean() + 4.0 * (y - y.mean())
        expected.append(np.array([centre2d[0], y.mean(), centre2d[1]]))
        noisy = profile + rng.normal(0.0, 0.05, profile.shape)
        local = np.column_stack([noisy[:, 0], y, noisy[:, 1]])
        coords[idx] = local @ world.T + origin
    known = world @ (expected[1] - expected[0])
    known /= np.linalg.norm(known)
    turn = rotation_matrix([0.3, 0.2, 1.0], 4.0)
    centre = coords.mean(axis=0)
    coords = (coords - centre) @ turn.T + centre
    return knee, setup, coords, turn @ known


@pytest.mark.parametrize("side", ["right", "left"])
def test_known_axis_of_two_spiral_condyles_is_within_the_reported_spread(side):
    """The synthetic knee's condyle rims made spirals (lateral 22 -> 17 mm, medial 25 -> 19 mm
    along their 0-120 deg arc), the whole knee externally rotated by 4 deg and tilted.

    The known axis runs through each rim's least-squares circle centre, found here by a
    generic simplex search on the noise-free nodes; the fit of the noisy nodes through
    compute_joint_axes must recover its direction within the spread it reports.
    """
    _, setup, coords, known = spiral_knee(side)
    axes = compute_joint_axes(coords, setup)
    angle = np.degrees(np.arccos(np.clip(axes.fe_axis.direction @ known, -1.0, 1.0)))
    assert axes.sensitivity is not None
    reported = axes.sensitivity.direction_spread_deg
    assert 0.05 < reported < 2.0  # a real spread, not a degenerate one
    assert angle < 0.5 * reported
    assert axes.lateral_fit.rms > 0.05 and axes.medial_fit.rms > 0.05
    assert "sensitivity" in axes.to_dict()


def test_subsets_go_through_the_same_estimator_as_compute_joint_axes(monkeypatch):
    """The batched resampling (with the frame re-aimed per subset) against the obvious slow
    path: compute_joint_axes on each subset's node sets. The rows are spread wide across the
    condyle so that the frame refinement matters; both paths refine the frame to its fixed
    point (30 refinements) so that they are compared at convergence."""
    import kneegui.geometry.axes
    from kneegui.geometry.axis_sensitivity import _subsets

    monkeypatch.setattr(kneegui.geometry.axes, "SAGITTAL_REFINEMENTS", 30)
    knee, setup, coords, _ = spiral_knee("left", wide=True)
    settings = SensitivitySettings(n_subsets=12, seed=3)
    full = compute_joint_axes(coords, setup)
    fast = axis_sensitivity(
        coords[setup.lateral_condyle],
        coords[setup.medial_condyle],
        full.anterior,
        full.superior,
        full.sagittal_normal,
        full.origin,
        settings=settings,
        frame_refinements=30,
    )
    fixed = axis_sensitivity(
        coords[setup.lateral_condyle],
        coords[setup.medial_condyle],
        full.anterior,
        full.superior,
        full.sagittal_normal,
        full.origin,
        settings=settings,
        frame_refinements=0,
    )
    rng = np.random.default_rng(settings.seed)
    keep_lat = _subsets(rng, len(setup.lateral_condyle), settings)
    keep_med = _subsets(rng, len(setup.medial_condyle), settings)
    u = full.fe_axis.direction
    for k in range(settings.n_subsets):
        data = copy.deepcopy(knee.setup)
        ids = knee.model.node_ids
        data["landmarks"]["lateral_condyle"] = ids[setup.lateral_condyle[keep_lat[k]]].tolist()
        data["landmarks"]["medial_condyle"] = ids[setup.medial_condyle[keep_med[k]]].tolist()
        one = compute_joint_axes(coords, load_setup(data, knee.model))
        v = one.fe_axis.direction
        angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(v, u)), v @ u))
        assert fast.direction_deg[k] == pytest.approx(angle, abs=1e-6)
        d = one.lateral_center - full.lateral_center
        shift = np.linalg.norm(d - (d @ u) * u)
        assert fast.lateral_center_mm[k] == pytest.approx(shift, abs=1e-6)
        dr = one.medial_fit.radius - full.medial_fit.radius
        assert fast.medial_radius_mm[k] == pytest.approx(dr, abs=1e-6)
    # on such a wide set, holding the frame would misjudge the spread
    assert np.abs(fixed.direction_deg - fast.direction_deg).max() > 1e-3


def test_subsets_without_a_circle_make_the_spread_infinite():
    """Four collinear nodes and one off the line: every subset leaving out the fifth node has
    no circle. Those subsets count as infinitely far, and are counted."""
    line = np.column_stack([np.linspace(-20.0, -5.0, 4), np.full(4, -30.0), np.full(4, -20.0)])
    lat = np.vstack([line, [-15.0, -30.0, -12.0]])
    med = condyle(31, 23.0, 23.0, ml=25.0, seed=3)
    s = spread(lat, med)
    left_out_fifth = 200 / 5  # one of the five nodes is left out of each subset
    assert 0.5 * left_out_fifth < s.n_failed < 1.5 * left_out_fifth
    assert np.isinf(s.direction_spread_deg)
    d = s.to_dict()
    assert d["direction_spread_deg"] is None and d["failed_subsets"] == s.n_failed
    assert s.summary().startswith("F-E axis unstable")
    assert np.all(np.isinf(s.direction_deg[~np.isfinite(s.lateral_radius_mm)]))
