"""Patellar seating on boxes: clearances restored, smallest lift, radial direction, both ways."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.geometry.transforms import RigidTransform
from kneegui.reposition.bone_overlap import BoneOverlapCheck
from kneegui.reposition.contact import BoneSurfaceDistance
from kneegui.reposition.patella_tracking import LIFT_PRECISION, PatellaSeating

UNIT = np.array(
    [[x, y, z] for z in (0.0, 1.0) for y in (0.0, 1.0) for x in (0.0, 1.0)], dtype=np.float64
)
QUADS = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
TRIANGLES = np.array([t for a, b, c, d in QUADS for t in ((a, b, c), (a, c, d))])
AXIS_POINT, AXIS = np.zeros(3), np.array([0.0, 1.0, 0.0])


def box(lo, hi) -> BoneSurfaceDistance:
    corners = np.asarray(lo) + UNIT * (np.asarray(hi) - np.asarray(lo))
    return BoneSurfaceDistance(corners[TRIANGLES])


def femur_and_patella(patella_box):
    femur = box((-10, -10, -10), (10, 10, 10))
    patella = box(*patella_box)
    return femur, patella, PatellaSeating(patella, femur, AXIS_POINT, AXIS, band=20.0)


def clearances(seating: PatellaSeating, patella: RigidTransform, femur: RigidTransform):
    lift = seating._lift_direction(patella, femur)
    return seating._shortfalls(patella, femur, lift)[0]


def test_a_patella_turned_into_the_femur_is_lifted_radially_to_its_rest_gap():
    femur_srf, patella_srf, seating = femur_and_patella(((12, -2, -2), (16, 2, 2)))
    assert seating.rest_gap == pytest.approx(2.0)
    turned = RigidTransform.about_axis(AXIS_POINT, AXIS, 40.0)  # its inner corners enter
    identity = RigidTransform.identity()
    overlap = BoneOverlapCheck({"femur": femur_srf, "patella": patella_srf})
    assert max(o.depth for o in overlap.measure({"patella": turned})) > 0.5
    seated, lift = seating.seat(turned, identity)
    assert lift > 0
    assert all(o.depth == 0.0 for o in overlap.measure({"patella": seated}))
    assert clearances(seating, seated, identity).max() <= 1e-3  # the 2.0 gap is back
    # radial: the shift is along the line from the axis to the patella's turned centroid
    shift = seated.translation - turned.translation
    centroid = turned.apply(np.array([14.0, 0.0, 0.0]))
    np.testing.assert_allclose(shift, lift * centroid / np.linalg.norm(centroid), atol=1e-12)
    np.testing.assert_allclose(seated.rotation, turned.rotation)
    # smallest: a lift shorter by twice the precision leaves a node too close
    radial = centroid / np.linalg.norm(centroid)
    short = turned.then(RigidTransform(np.eye(3), (lift - 2 * LIFT_PRECISION) * radial))
    assert clearances(seating, short, identity).max() > 1e-3


def test_a_patella_clear_of_the_femur_is_not_moved():
    _, _, seating = femur_and_patella(((12, -2, -2), (16, 2, 2)))
    for away in (
        RigidTransform.identity(),
        RigidTransform(np.eye(3), np.array([3.0, 0.0, 0.0])),  # lifted off the femur
        RigidTransform.about_axis((14.0, 0.0, 0.0), AXIS, 5.0).then(
            RigidTransform(np.eye(3), np.array([1.0, 0.0, 0.0]))
        ),
    ):
        seated, lift = seating.seat(away, RigidTransform.identity())
        assert lift == 0.0 and seated is away


def test_a_femur_corner_poking_into_the_patella_lifts_it_too():
    """A wide patella plate whose own corners stay clear while the femur's edge enters it."""
    *_, seating = femur_and_patella(((12, -20, -20), (14, 20, 20)))
    assert seating.rest_gap == pytest.approx(2.0)  # femur corners to the plate's face
    pushed = RigidTransform(np.eye(3), np.array([-3.0, 0.0, 0.0]))  # plate spans x 9..11
    seated, lift = seating.seat(pushed, RigidTransform.identity())
    assert lift == pytest.approx(3.0, abs=LIFT_PRECISION)
    np.testing.assert_allclose(seated.translation, [lift - 3.0, 0.0, 0.0], atol=1e-12)


def test_the_femur_moving_instead_gives_the_same_relative_seat():
    """Only the relative pose matters: moving both bones by one rigid motion moves the seated
    patella by it too."""
    _, _, seating = femur_and_patella(((12, -2, -2), (16, 2, 2)))
    turned = RigidTransform.about_axis(AXIS_POINT, AXIS, 40.0)
    both = RigidTransform.about_axis((3.0, 1.0, -2.0), (0.3, 0.2, 1.0), 25.0)
    seated, lift = seating.seat(turned, RigidTransform.identity())
    seated_both, lift_both = seating.seat(turned.then(both), both)
    assert lift_both == pytest.approx(lift, abs=1e-9)
    np.testing.assert_allclose(seated_both.matrix, seated.then(both).matrix, atol=1e-9)
