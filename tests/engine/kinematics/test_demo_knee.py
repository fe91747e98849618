"""The built-in demo leg: its setup validates, axes match the design, posing is exact and rigid."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui import demo
from kneegui.geometry import compute_joint_axes, measure_flexion
from kneegui.kinematics import pose_bones, solve_bone_pose
from kneegui.setup import load_setup, suggest_condyle_nodes, suggest_roles, suggest_setup

if not hasattr(demo, "generate_demo_leg"):
    pytest.skip("kneegui.demo.generate_demo_leg is not there yet", allow_module_level=True)


@pytest.fixture(scope="module", params=["right", "left"])
def leg(request):
    return demo.generate_demo_leg(elements=20000, side=request.param)


@pytest.fixture(scope="module")
def setup_and_axes(leg):
    setup = load_setup(leg.setup, leg.model)
    return setup, compute_joint_axes(leg.model.coords, setup)


def test_demo_setup_validates(leg, setup_and_axes):
    setup, _ = setup_and_axes
    assert setup.unassigned_parts == ()
    assert setup.side == leg.setup["side"]
    for role in ("femur", "tibia", "patella", "skin", "flesh"):
        assert setup.roles[role], role


def test_demo_axes_match_design(setup_and_axes):
    _, axes = setup_and_axes
    assert axes.lateral_fit.radius == pytest.approx(20.5, abs=0.3)
    assert axes.medial_fit.radius == pytest.approx(23.3, abs=0.3)
    assert axes.initial_flexion_deg == pytest.approx(9.0, abs=1.0)
    assert not [w for w in axes.warnings if "radius" in w or "RMS" in w]


@pytest.mark.parametrize("target", [0.0, 30.0, 60.0, 90.0, 120.0])
def test_demo_posed_flexion_and_rigidity(leg, setup_and_axes, target):
    setup, axes = setup_and_axes
    coords = pose_bones(leg.model, setup, target, axes)
    assert measure_flexion(coords, setup) == pytest.approx(target, abs=0.1)
    rng = np.random.default_rng(0)
    for group in ("femur", "tibia", "patella"):
        idx = setup.segment_nodes[group]
        pick = rng.choice(idx, size=min(80, len(idx)), replace=False)
        d0 = np.linalg.norm(leg.model.coords[pick][:, None] - leg.model.coords[pick][None], axis=-1)
        d1 = np.linalg.norm(coords[pick][:, None] - coords[pick][None], axis=-1)
        mask = d0 > 0
        assert np.max(np.abs(d1[mask] - d0[mask]) / d0[mask]) < 1e-9, group
    pose = solve_bone_pose(axes, setup, target)
    table = setup.tables["tibial_rotation"]
    phi0 = axes.initial_flexion_deg
    assert pose.tibial_rotation_deg == pytest.approx(table.value_at(target) - table.value_at(phi0))


def test_demo_suggestions_reproduce_its_setup(leg, setup_and_axes):
    _setup, axes = setup_and_axes
    side = leg.setup["side"]
    roles = suggest_roles(leg.model, side=side)
    for role in ("femur", "tibia", "fibula", "patella"):
        assert sorted(roles[role]) == sorted(leg.setup["roles"][role]), role
    lateral, medial = suggest_condyle_nodes(
        leg.model,
        roles["femur"],
        side,
        tibia_part_ids=roles["tibia"],
        patella_part_ids=roles["patella"],
    )
    data = suggest_setup(leg.model, side)
    data["landmarks"]["lateral_condyle"] = lateral.tolist()
    data["landmarks"]["medial_condyle"] = medial.tolist()
    suggested = compute_joint_axes(leg.model.coords, load_setup(data, leg.model))
    assert suggested.lateral_fit.radius == pytest.approx(20.5, abs=0.3)
    assert suggested.medial_fit.radius == pytest.approx(23.3, abs=0.3)
    assert suggested.initial_flexion_deg == pytest.approx(axes.initial_flexion_deg, abs=2.0)


def test_demo_condyles_found_without_hints_in_any_orientation(leg, setup_and_axes):
    """No tibia or patella given: the notch tells posterior from anterior."""
    from kneegui.setup.synthetic import random_rotation

    _, axes = setup_and_axes
    side = leg.setup["side"]
    rot = random_rotation(7)
    moved = leg.model.with_coords(leg.model.coords @ rot.T + [100.0, 200.0, -50.0])
    lateral, medial = suggest_condyle_nodes(moved, leg.setup["roles"]["femur"], side)
    # the same nodes as in the original pose, on the designed circles
    rel_lat = leg.model.coords[leg.model.node_index(lateral)] - axes.lateral_center
    rel_med = leg.model.coords[leg.model.node_index(medial)] - axes.medial_center
    for rel, radius in ((rel_lat, 20.5), (rel_med, 23.3)):
        in_plane = np.hypot(rel @ axes.anterior, rel @ axes.superior)
        assert len(rel) >= 5
        np.testing.assert_allclose(in_plane, radius, atol=0.05)
