"""Joint axes and flexion on synthetic knees in arbitrary orientations, both sides."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from kneegui.errors import GeometryError
from kneegui.geometry import (
    RigidTransform,
    best_fit_transform,
    compute_joint_axes,
    flexion_angle_deg,
    measure_flexion,
    rotation_matrix,
)
from kneegui.setup import load_setup
from kneegui.setup.synthetic import build_synthetic_knee, random_rotation

ORIENTATIONS = [None, random_rotation(1), random_rotation(2)]


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("orientation", range(len(ORIENTATIONS)))
def test_axes_match_design(side, orientation):
    rot = ORIENTATIONS[orientation]
    knee = build_synthetic_knee(side=side, rotation=rot, translation=[250.0, -80.0, 700.0])
    setup = load_setup(knee.setup, knee.model)
    axes = compute_joint_axes(knee.model.coords, setup)
    world = knee.to_world[:3, :3]
    assert axes.lateral_fit.radius == pytest.approx(20.5, abs=1e-6)
    assert axes.medial_fit.radius == pytest.approx(23.3, abs=1e-6)
    assert axes.lateral_fit.rms < 1e-6 and axes.medial_fit.rms < 1e-6
    assert axes.initial_flexion_deg == pytest.approx(9.0, abs=1e-6)
    assert axes.warnings == ()
    # medial is +y of the knee as built; the left knee is that knee mirrored (world includes it)
    lateral_to_medial = world @ [0.0, 1.0, 0.0]
    sign = 1 if side == "right" else -1
    np.testing.assert_allclose(axes.fe_axis.direction, lateral_to_medial, atol=1e-9)
    np.testing.assert_allclose(axes.sagittal_normal, lateral_to_medial, atol=1e-9)
    np.testing.assert_allclose(axes.left, sign * lateral_to_medial, atol=1e-9)
    np.testing.assert_allclose(axes.anterior, world[:, 0], atol=1e-9)
    np.testing.assert_allclose(axes.superior, world[:, 2], atol=1e-9)
    # the knee joint point: mid-way between the circle centres at (-8, +-30, 0) (built frame)
    np.testing.assert_allclose(
        axes.knee_center,
        knee.to_world[:3, :3] @ [-8.0, 0.0, 0.0] + knee.to_world[:3, 3],
        atol=1e-6,
    )
    assert measure_flexion(knee.model.coords, setup) == pytest.approx(9.0, abs=1e-6)
    assert measure_flexion(knee.model.coords, axes) == pytest.approx(9.0, abs=1e-6)


def test_left_mirrors_right():
    right = build_synthetic_knee("right", flexion_deg=23.0)
    left = build_synthetic_knee("left", flexion_deg=23.0)
    np.testing.assert_allclose(left.model.coords, right.model.coords * [1, -1, 1])
    ar = compute_joint_axes(right.model.coords, load_setup(right.setup, right.model))
    al = compute_joint_axes(left.model.coords, load_setup(left.setup, left.model))
    assert al.initial_flexion_deg == pytest.approx(ar.initial_flexion_deg, abs=1e-9)
    np.testing.assert_allclose(al.fe_axis.direction, ar.fe_axis.direction * [1, -1, 1], atol=1e-12)
    np.testing.assert_allclose(al.left, ar.left, atol=1e-12)  # the subject's left is +y for both
    np.testing.assert_allclose(al.lateral_center, ar.lateral_center * [1, -1, 1], atol=1e-9)


@pytest.mark.parametrize("side", ["right", "left"])
def test_flexion_sign(side):
    for angle in (-5.0, 0.0, 9.0, 45.0, 90.0, 140.0):
        knee = build_synthetic_knee(side=side, flexion_deg=angle, rotation=random_rotation(5))
        setup = load_setup(knee.setup, knee.model)
        assert measure_flexion(knee.model.coords, setup) == pytest.approx(angle, abs=1e-6)


def test_flexion_angle_formula():
    n = np.array([0.0, 1.0, 0.0])
    f = np.array([0.0, 0.0, 1.0])
    t = rotation_matrix(n, 30.0) @ f
    assert flexion_angle_deg(f, t, n, +1) == pytest.approx(30.0)
    assert flexion_angle_deg(f, t, n, -1) == pytest.approx(-30.0)
    # out-of-plane components of the tibial axis are ignored
    assert flexion_angle_deg(f, np.add(t, [0.0, 5.0, 0.0]), n, +1) == pytest.approx(30.0)
    with pytest.raises(GeometryError):
        flexion_angle_deg(f, n, n, +1)


def test_coordinate_landmarks_follow_their_bone():
    knee = build_synthetic_knee(coordinate_landmarks=True, rotation=random_rotation(9))
    setup = load_setup(knee.setup, knee.model)
    assert setup.femur_axis[0].node_id is None
    moved = knee.model.coords.copy()
    tib = setup.segment_nodes["tibia"]
    t = RigidTransform.about_axis([3.0, 1.0, 2.0], [0.2, 0.9, 0.1], 25.0)
    moved[tib] = t.apply(moved[tib])
    p0 = setup.tibia_axis[0]
    np.testing.assert_allclose(p0.position(moved), t.apply(p0.coords), atol=1e-9)
    np.testing.assert_allclose(setup.femur_axis[0].position(moved), setup.femur_axis[0].coords)


def test_fit_warnings():
    knee = build_synthetic_knee(lateral_radius=12.0, medial_radius=33.0)
    axes = compute_joint_axes(knee.model.coords, load_setup(knee.setup, knee.model))
    assert any("lateral condyle radius 12.00 mm is outside 15-30 mm" in w for w in axes.warnings)
    assert any("medial condyle radius 33.00 mm" in w for w in axes.warnings)
    noisy = build_synthetic_knee(noise_mm=2.0, seed=3)
    axes = compute_joint_axes(noisy.model.coords, load_setup(noisy.setup, noisy.model))
    assert any("RMS" in w and "exceeds 1 mm" in w for w in axes.warnings)


def test_noisy_condyles_radius():
    knee = build_synthetic_knee(noise_mm=0.1, seed=11)
    axes = compute_joint_axes(knee.model.coords, load_setup(knee.setup, knee.model))
    assert axes.lateral_fit.radius == pytest.approx(20.5, abs=0.05)
    assert axes.medial_fit.radius == pytest.approx(23.3, abs=0.05)
    assert axes.warnings == ()


def test_wrong_side_is_flagged():
    knee = build_synthetic_knee("right")
    data = copy.deepcopy(knee.setup)
    data["side"] = "left"
    axes = compute_joint_axes(knee.model.coords, load_setup(data, knee.model))
    assert axes.initial_flexion_deg == pytest.approx(-9.0, abs=1e-6)
    knee2 = build_synthetic_knee("right", flexion_deg=40.0)
    data = copy.deepcopy(knee2.setup)
    data["side"] = "left"
    axes = compute_joint_axes(knee2.model.coords, load_setup(data, knee2.model))
    assert any("implausible" in w for w in axes.warnings)


def test_to_dict_is_json_ready():
    knee = build_synthetic_knee()
    axes = compute_joint_axes(knee.model.coords, load_setup(knee.setup, knee.model))
    d = json.loads(json.dumps(axes.to_dict()))
    for key in ("lateral_radius", "medial_radius", "lateral_rms", "medial_rms", "initial_flexion"):
        assert isinstance(d[key], float)
    for key in ("fe_axis", "lr_axis"):
        assert len(d[key]["point"]) == 3
        assert np.linalg.norm(d[key]["direction"]) == pytest.approx(1.0)


def test_coords_of_another_model_rejected():
    knee = build_synthetic_knee()
    setup = load_setup(knee.setup, knee.model)
    with pytest.raises(GeometryError, match="nodes"):
        compute_joint_axes(knee.model.coords[:-1], setup)


def test_best_fit_transform_recovers_motion():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(20, 3)) * 50
    t = RigidTransform.about_axis([1.0, 2.0, 3.0], [1.0, -2.0, 0.5], 71.0)
    fit = best_fit_transform(pts, t.apply(pts))
    np.testing.assert_allclose(fit.matrix, t.matrix, atol=1e-12)
    np.testing.assert_allclose(t.then(t.inverse()).matrix, np.eye(4), atol=1e-12)
    assert t.angle_deg() == pytest.approx(71.0)
