"""Bone posing: target flexion reached, rigid bones, coupled rotations as specified, mirroring."""

from __future__ import annotations

import copy
import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kneegui.geometry import RigidTransform, compute_joint_axes, measure_flexion
from kneegui.kinematics import bone_transforms, pose_bones, solve_bone_pose
from kneegui.setup import load_setup
from kneegui.setup.synthetic import build_synthetic_knee, random_rotation

TARGETS = [-5.0, 0.0, 9.0, 30.0, 60.0, 90.0, 120.0, 140.0]


def _setup(knee, **changes):
    data = copy.deepcopy(knee.setup)
    data.update(changes)
    return load_setup(data, knee.model)


def _max_relative_distance_change(a, b, sample=60):
    idx = np.linspace(0, len(a) - 1, min(sample, len(a))).astype(int)
    da = np.linalg.norm(a[idx][:, None] - a[idx][None], axis=-1)
    db = np.linalg.norm(b[idx][:, None] - b[idx][None], axis=-1)
    mask = da > 0
    return float(np.max(np.abs(db[mask] - da[mask]) / da[mask]))


@pytest.mark.parametrize(
    ("side", "moving", "orientation"),
    list(itertools.product(["right", "left"], ["tibia", "femur"], [None, 4])),
)
def test_target_flexion_reached_and_bones_rigid(side, moving, orientation):
    rot = None if orientation is None else random_rotation(orientation)
    knee = build_synthetic_knee(side=side, rotation=rot, translation=[10.0, 20.0, -900.0])
    setup = _setup(knee, moving_segment=moving)
    axes = compute_joint_axes(knee.model.coords, setup)
    groups = {g: setup.segment_nodes[g] for g in ("femur", "tibia", "patella")}
    bone_nodes = np.unique(np.concatenate(list(groups.values())))
    for target in TARGETS:
        coords = pose_bones(knee.model, setup, target, axes)
        assert measure_flexion(coords, setup) == pytest.approx(target, abs=1e-6)
        for idx in groups.values():
            assert _max_relative_distance_change(knee.model.coords[idx], coords[idx]) < 1e-9
        others = np.setdiff1d(np.arange(knee.model.n_nodes), bone_nodes)
        np.testing.assert_array_equal(coords[others], knee.model.coords[others])
        fixed = groups["femur"] if moving == "tibia" else groups["tibia"]
        np.testing.assert_array_equal(coords[fixed], knee.model.coords[fixed])


def test_pose_at_initial_flexion_is_identity():
    knee = build_synthetic_knee(rotation=random_rotation(8))
    setup = load_setup(knee.setup, knee.model)
    coords = pose_bones(knee.model, setup, 9.0)
    np.testing.assert_allclose(coords, knee.model.coords, atol=1e-9)


def test_input_model_not_mutated():
    knee = build_synthetic_knee()
    setup = load_setup(knee.setup, knee.model)
    before = knee.model.coords.copy()
    pose_bones(knee.model, setup, 90.0)
    np.testing.assert_array_equal(knee.model.coords, before)


def test_left_mirrors_right_exactly():
    right = build_synthetic_knee("right")
    left = build_synthetic_knee("left")
    sr, sl = load_setup(right.setup, right.model), load_setup(left.setup, left.model)
    for target in (0.0, 45.0, 120.0):
        cr = pose_bones(right.model, sr, target)
        cl = pose_bones(left.model, sl, target)
        np.testing.assert_allclose(cl, cr * [1.0, -1.0, 1.0], atol=1e-9)
        assert measure_flexion(cl, sl) == pytest.approx(target, abs=1e-6)


@pytest.mark.parametrize("side", ["right", "left"])
def test_rotations_compose_as_specified(side):
    knee = build_synthetic_knee(side=side, rotation=random_rotation(21))
    setup = load_setup(knee.setup, knee.model)
    axes = compute_joint_axes(knee.model.coords, setup)
    s = setup.side_sign
    table = setup.tables["tibial_rotation"]
    for target in (30.0, 60.0, 90.0, 120.0):
        pose = solve_bone_pose(axes, setup, target)
        rot = pose.tibial_rotation_deg
        # the coupled rotation is the table's change from the initial flexion
        assert rot == pytest.approx(table.value_at(target) - table.value_at(9.0), abs=1e-12)
        assert rot > 0  # internal rotation grows with flexion
        fe = RigidTransform.about_axis(
            axes.fe_axis.point, axes.fe_axis.direction, s * pose.fe_rotation_deg
        )
        lr_initial = RigidTransform.about_axis(axes.lr_axis.point, axes.lr_axis.direction, s * rot)
        # flexion first, then the L-R axis carried by the flexed tibia ...
        lr_moved = RigidTransform.about_axis(
            fe.apply(axes.lr_axis.point), fe.apply_vector(axes.lr_axis.direction), s * rot
        )
        expected = fe.then(lr_moved)
        np.testing.assert_allclose(pose.transforms["tibia"].matrix, expected.matrix, atol=1e-9)
        # ... which equals the L-R rotation about the initial axis followed by flexion
        np.testing.assert_allclose(expected.matrix, lr_initial.then(fe).matrix, atol=1e-9)
        # removing the flexion leaves a rotation of exactly the table value about the L-R axis
        internal = lr_initial_from(pose.transforms["tibia"], fe)
        assert internal.angle_deg() == pytest.approx(abs(rot), abs=1e-9)
        np.testing.assert_allclose(
            internal.apply(axes.lr_axis.point), axes.lr_axis.point, atol=1e-9
        )
        np.testing.assert_allclose(
            internal.apply_vector(axes.lr_axis.direction), axes.lr_axis.direction, atol=1e-12
        )
        # the sense: a right knee rotates internally about +superior (anterior -> medial)
        probe = axes.anterior
        turned = internal.apply_vector(probe)
        medial = axes.sagittal_normal
        assert turned @ medial > 0


def lr_initial_from(tibia: RigidTransform, fe: RigidTransform) -> RigidTransform:
    """The part of ``tibia`` applied before ``fe``: ``fe^-1 o tibia``."""
    return tibia.then(fe.inverse())


def test_patella_flexion_and_tilt():
    knee = build_synthetic_knee(rotation=random_rotation(13))
    setup = load_setup(knee.setup, knee.model)
    axes = compute_joint_axes(knee.model.coords, setup)
    no_tilt = copy.deepcopy(knee.setup)
    no_tilt["kinematics"]["patellar_tilt"] = "none"
    setup_nt = load_setup(no_tilt, knee.model)
    for target in (30.0, 90.0):
        pose = solve_bone_pose(axes, setup_nt, target)
        assert pose.patellar_tilt_deg == 0.0
        assert pose.patellar_flexion_deg == pytest.approx(0.65 * (target - 9.0))
        flex = RigidTransform.about_axis(
            axes.fe_axis.point, axes.fe_axis.direction, pose.patellar_flexion_deg
        )
        np.testing.assert_allclose(pose.transforms["patella"].matrix, flex.matrix, atol=1e-9)
        tilted = solve_bone_pose(axes, setup, target)
        tilt_only = tilted.transforms["patella"].then(flex.inverse())
        expected_tilt = setup.tables["patellar_tilt"].change(9.0, target)
        assert tilt_only.angle_deg() == pytest.approx(abs(expected_tilt), abs=1e-9)
        # the tilt axis passes through the flexed patella centroid
        centre = flex.apply(axes.patella_center)
        np.testing.assert_allclose(
            tilted.transforms["patella"].apply(axes.patella_center), centre, atol=1e-9
        )


def test_moving_femur_gives_the_same_relative_pose():
    knee = build_synthetic_knee(rotation=random_rotation(17))
    s_tib = _setup(knee, moving_segment="tibia")
    s_fem = _setup(knee, moving_segment="femur")
    axes = compute_joint_axes(knee.model.coords, s_tib)
    for target in (-5.0, 60.0, 140.0):
        t_tib = bone_transforms(axes, s_tib, target)
        t_fem = bone_transforms(axes, s_fem, target)
        assert t_tib["femur"].angle_deg() == 0.0 and t_fem["tibia"].angle_deg() == 0.0
        rel = t_fem["tibia"].then(t_fem["femur"].inverse())
        np.testing.assert_allclose(rel.matrix, t_tib["tibia"].matrix, atol=1e-9)
        rel_pat = t_fem["patella"].then(t_fem["femur"].inverse())
        np.testing.assert_allclose(rel_pat.matrix, t_tib["patella"].matrix, atol=1e-9)


def test_user_table_drives_the_tibial_rotation(tmp_path):
    knee = build_synthetic_knee()
    path = tmp_path / "rot.csv"
    path.write_text("flexion_deg,value_deg\n0,0\n100,-10\n")
    data = copy.deepcopy(knee.setup)
    data["kinematics"]["tibial_rotation"] = str(path)
    setup = load_setup(data, knee.model)
    axes = compute_joint_axes(knee.model.coords, setup)
    pose = solve_bone_pose(axes, setup, 59.0)
    assert pose.tibial_rotation_deg == pytest.approx(-5.0)
    assert measure_flexion(pose_bones(knee.model, setup, 59.0, axes), setup) == pytest.approx(59.0)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    side=st.sampled_from(["right", "left"]),
    moving=st.sampled_from(["tibia", "femur"]),
    initial=st.floats(-5.0, 60.0),
    target=st.floats(-5.0, 140.0),
    table=st.sampled_from(["default", "walker1988", "asano2001", "johal2005"]),
)
def test_any_pose_reaches_its_target(seed, side, moving, initial, target, table):
    knee = build_synthetic_knee(
        side=side,
        flexion_deg=initial,
        rotation=random_rotation(seed),
        translation=[seed % 97, -(seed % 13), 500.0],
    )
    data = copy.deepcopy(knee.setup)
    data["moving_segment"] = moving
    data["kinematics"]["tibial_rotation"] = table
    setup = load_setup(data, knee.model)
    axes = compute_joint_axes(knee.model.coords, setup)
    assert axes.initial_flexion_deg == pytest.approx(initial, abs=1e-6)
    coords = pose_bones(knee.model, setup, target, axes)
    assert measure_flexion(coords, setup) == pytest.approx(target, abs=1e-6)
    for group in ("femur", "tibia", "patella"):
        idx = setup.segment_nodes[group]
        assert _max_relative_distance_change(knee.model.coords[idx], coords[idx], 30) < 1e-9
