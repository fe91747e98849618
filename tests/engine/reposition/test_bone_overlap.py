"""Bone-to-bone overlap: exact depths on boxes, rest overlap, and the demo's kinematics."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.geometry.transforms import RigidTransform
from kneegui.reposition.bone_overlap import BoneOverlapCheck
from kneegui.reposition.contact import BoneSurfaceDistance

# a unit cube's outer surface as 12 outward triangles over its 8 corners
CUBE_CORNERS = np.array(
    [[x, y, z] for z in (0.0, 1.0) for y in (0.0, 1.0) for x in (0.0, 1.0)], dtype=np.float64
)
CUBE_QUADS = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
CUBE_TRIANGLES = np.array([t for a, b, c, d in CUBE_QUADS for t in ((a, b, c), (a, c, d))])


def check_of(coords: np.ndarray, triangles: dict[str, np.ndarray]) -> BoneOverlapCheck:
    return BoneOverlapCheck({n: BoneSurfaceDistance(coords[t]) for n, t in triangles.items()})


def two_cubes(gap: float) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A unit 'femur' cube and a half-size 'tibia' cube centred ``gap`` below it (negative:
    overlapping); the tibia's corners lie inside the femur's faces, not on its edges."""
    tibia = 0.5 * CUBE_CORNERS + [0.25, 0.25, -0.5 - gap]
    coords = np.vstack([CUBE_CORNERS, tibia])
    return coords, {"femur": CUBE_TRIANGLES, "tibia": CUBE_TRIANGLES + 8}


def test_cube_triangles_face_outwards():
    tri = CUBE_CORNERS[CUBE_TRIANGLES]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(np.einsum("ij,ij->i", normal, tri.mean(axis=1) - 0.5) > 0)


def test_separate_bones_do_not_overlap():
    coords, triangles = two_cubes(gap=0.5)
    found = check_of(coords, triangles).measure({})
    assert [(o.inner, o.outer) for o in found] == [("femur", "tibia"), ("tibia", "femur")]
    assert all(o.depth == 0.0 and o.nodes == 0 and o.rest_depth == 0.0 for o in found)


def test_a_bone_moved_into_another_reports_the_depth_of_its_deepest_node():
    coords, triangles = two_cubes(gap=0.5)
    check = check_of(coords, triangles)
    # lift the tibia 0.7: its top face (4 corners) is then 0.2 inside the femur's bottom face
    # (and 0.25 from its sides)
    lift = RigidTransform(np.eye(3), np.array([0.0, 0.0, 0.7]))
    by_pair = {(o.inner, o.outer): o for o in check.measure({"tibia": lift})}
    tibia_in_femur = by_pair["tibia", "femur"]
    assert tibia_in_femur.depth == pytest.approx(0.2)
    assert tibia_in_femur.nodes == 4
    assert tibia_in_femur.added_depth == pytest.approx(0.2)
    assert "tibia reaches 0.20 into the femur" in tibia_in_femur.describe()
    assert by_pair["femur", "tibia"].depth == 0.0
    # the same motion given to both bones changes nothing
    both = check.measure({"tibia": lift, "femur": lift})
    assert all(o.depth == 0.0 for o in both)


def test_overlap_present_at_rest_is_not_blamed_on_the_pose():
    coords, triangles = two_cubes(gap=-0.2)
    found = check_of(coords, triangles).measure({})
    tibia_in_femur = next(o for o in found if o.inner == "tibia")
    assert tibia_in_femur.rest_depth == pytest.approx(0.2)
    assert tibia_in_femur.added_depth == 0.0


@pytest.mark.parametrize("angle", [-10.0, -5.0, 0.0, 30.0, 60.0, 90.0, 120.0])
def test_demo_bones_keep_clear_of_each_other(small_repositioner, angle):
    """The demo's plateaus sit a cartilage gap beyond the condyle circles, so flexing about the
    GCA never drives the tibia into the femur (it did by 3.3 mm from 60 deg before); the
    patella, turned by its tables, is lifted off the trochlea to its rest clearance (it rode
    3.5 mm into the femur at -5 deg and 0.6 mm at 30 deg before)."""
    bone = small_repositioner.bone_pose(angle)
    for overlap in small_repositioner.bone_overlap(bone):
        assert overlap.depth == 0.0, overlap.describe()
    if angle < 60.0:
        assert bone.patellar_lift > 0.0


def test_without_patellar_tracking_the_demo_patella_rides_into_the_femur(small_leg, small_setup):
    from kneegui.reposition import Repositioner, RepositionOptions

    rep = Repositioner(small_leg.model, small_setup, RepositionOptions(patella_tracking=False))
    bone = rep.bone_pose(-5.0)
    assert bone.patellar_lift == 0.0
    depth = {(o.inner, o.outer): o.depth for o in rep.bone_overlap(bone)}
    assert depth["patella", "femur"] > 1.0
