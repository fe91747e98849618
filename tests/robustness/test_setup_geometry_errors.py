"""Bad setups and bad geometry end in precise errors before any work is done."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from kneegui import demo
from kneegui.errors import GeometryError, KneeguiError, SetupError
from kneegui.geometry.axes import compute_joint_axes
from kneegui.reposition import Repositioner
from kneegui.setup import load_setup
from kneegui.setup.synthetic import build_synthetic_knee


@pytest.fixture(scope="module")
def leg():
    return demo.generate_demo_leg(2000)


def test_setup_of_another_model_is_detected(leg):
    other = build_synthetic_knee()
    with pytest.raises(SetupError) as info:
        load_setup(leg.setup, other.model)
    message = str(info.value)
    assert "not in the model" in message or "unknown part" in message
    assert "roles" in message or "landmarks" in message


@pytest.mark.parametrize(
    "mutate, key",
    [
        (lambda s: s["roles"]["femur"].append(999999), "roles.femur"),
        (lambda s: s["landmarks"]["lateral_condyle"].__setitem__(0, 10**9), "lateral_condyle"),
        (
            lambda s: s["landmarks"].__setitem__(
                "lateral_condyle", s["landmarks"]["lateral_condyle"][:3]
            ),
            "lateral_condyle",
        ),
        (
            lambda s: s["landmarks"].__setitem__("lr_axis", [s["landmarks"]["lr_axis"][0]] * 2),
            "lr_axis",
        ),
        (lambda s: s.__setitem__("side", "middle"), "side"),
        (lambda s: s.__setitem__("version", 7), "version"),
        (
            lambda s: s["landmarks"].__setitem__(
                "femur_axis", [[0.0, 0.0, float("nan")], [0.0, 0.0, 1.0]]
            ),
            "femur_axis",
        ),
        (
            lambda s: s["kinematics"].__setitem__("tibial_rotation", "/no/such/table.csv"),
            "tibial_rotation",
        ),
    ],
)
def test_invalid_setup_names_key_and_value(leg, mutate, key):
    bad = copy.deepcopy(leg.setup)
    mutate(bad)
    with pytest.raises(SetupError) as info:
        load_setup(bad, leg.model)
    assert key in str(info.value)


def test_collinear_condyle_points_are_refused(leg):
    setup = load_setup(leg.setup, leg.model)
    coords = leg.model.coords.copy()
    idx = setup.lateral_condyle
    coords[idx] = coords[idx[0]] + np.outer(np.arange(len(idx)), [0.0, 0.0, 1.0])
    with pytest.raises(GeometryError):
        compute_joint_axes(coords, setup)


def test_condyle_sets_on_one_side_are_refused(leg):
    bad = copy.deepcopy(leg.setup)
    bad["landmarks"]["medial_condyle"] = list(bad["landmarks"]["lateral_condyle"])
    with pytest.raises(KneeguiError):
        setup = load_setup(bad, leg.model)
        compute_joint_axes(leg.model.coords, setup)


def test_non_finite_coordinates_are_refused(leg):
    setup = load_setup(leg.setup, leg.model)
    coords = leg.model.coords.copy()
    coords[setup.lateral_condyle[0], 1] = np.inf
    with pytest.raises(KneeguiError):
        Repositioner(leg.model.with_coords(coords), setup)


@pytest.mark.parametrize("angle", [float("nan"), float("inf"), -60.0, 179.0])
def test_flexion_outside_the_supported_range(leg, angle):
    rep = Repositioner(leg.model, load_setup(leg.setup, leg.model))
    with pytest.raises(SetupError, match="flexion"):
        rep.pose(angle)
