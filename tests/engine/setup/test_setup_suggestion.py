"""A whole setup suggested from titles and geometry validates and reproduces the design."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.errors import SetupError
from kneegui.geometry import compute_joint_axes, measure_flexion
from kneegui.kinematics import pose_bones
from kneegui.model import Model
from kneegui.setup import load_setup, suggest_setup
from kneegui.setup.synthetic import build_synthetic_knee, random_rotation


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("seed", [None, 5, 6])
def test_suggested_setup_reproduces_design(side, seed):
    rot = None if seed is None else random_rotation(seed)
    knee = build_synthetic_knee(side=side, rotation=rot, flexion_deg=20.0)
    data = suggest_setup(knee.model, side)
    assert data["roles"]["femur"] == [101, 102] and data["roles"]["tibia"] == [201]
    assert data["roles"]["fibula"] == [301] and data["roles"]["patella"] == [401]
    setup = load_setup(data, knee.model)
    axes = compute_joint_axes(knee.model.coords, setup)
    assert axes.lateral_fit.radius == pytest.approx(20.5, abs=0.3)
    assert axes.medial_fit.radius == pytest.approx(23.3, abs=0.3)
    assert axes.initial_flexion_deg == pytest.approx(20.0, abs=0.5)
    # the L-R axis starts on the medial side of the tibial axis
    plateau = np.array(data["landmarks"]["lr_axis"][0])
    assert (plateau - axes.tibia_axis.point) @ axes.sagittal_normal > 0
    coords = pose_bones(knee.model, setup, 90.0, axes)
    assert measure_flexion(coords, setup) == pytest.approx(90.0, abs=1e-6)


def test_no_femur_part_is_an_error():
    knee = build_synthetic_knee()
    parts = {pid: p for pid, p in knee.model.parts.items() if pid != 101}
    parts[101] = type(knee.model.parts[101])(101, "Bone_17")
    parts[102] = type(knee.model.parts[102])(102, "Bone_18")
    model = Model(knee.model.node_ids, knee.model.coords, knee.model.blocks, parts)
    with pytest.raises(SetupError, match=r"roles\.femur: no part could be identified as femur"):
        suggest_setup(model, "right")
