"""Bone contact and the smoother's bone guard: exact pushes on a cube, and the demo's export."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.geometry.transforms import RigidTransform
from kneegui.reposition.checks import penetrating, surface_triangles
from kneegui.reposition.contact import BoneContact, BoneDepthGuard, BoneSurfaceDistance
from kneegui.reposition.pipeline import pose_model

# a 10 mm cube's outer surface as 12 outward triangles over its 8 corners
CUBE = 10.0 * np.array(
    [[x, y, z] for z in (0.0, 1.0) for y in (0.0, 1.0) for x in (0.0, 1.0)], dtype=np.float64
)
QUADS = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
TRIANGLES = np.array([t for a, b, c, d in QUADS for t in ((a, b, c), (a, c, d))])
IDENTITY = RigidTransform(np.eye(3), np.zeros(3))


def cube_contact(rest_node, ray_depth=None, clearance=0.2):
    coords = np.vstack([CUBE, rest_node])
    surfaces = {"bone": BoneSurfaceDistance(CUBE[TRIANGLES])}
    contact = BoneContact(
        coords,
        surfaces,
        np.array([8]),
        np.zeros((0, 2), dtype=np.int64),
        10.0,
        clearance,
        ray_depth=ray_depth,
    )
    return coords, contact


def test_a_shallow_node_goes_to_the_nearest_surface_point():
    coords, contact = cube_contact([-0.5, 5.0, 8.0], ray_depth=(2.0, 3.0))
    posed = coords.copy()
    posed[8] = [4.0, 5.0, 8.5]  # 1.5 below the top face, 4 inside the side face
    assert contact.resolve(posed, {"bone": IDENTITY}) == 1
    np.testing.assert_allclose(posed[8], [4.0, 5.0, 10.2], atol=1e-9)


def test_a_deep_node_leaves_the_bone_on_its_way_back_to_its_rest_place():
    # nearest point: the top face; the way back to the rest place leaves through the side face
    coords, contact = cube_contact([-0.5, 5.0, 8.0], ray_depth=(0.5, 1.0))
    posed = coords.copy()
    posed[8] = [4.0, 5.0, 8.5]
    contact.resolve(posed, {"bone": IDENTITY})
    t = (4.0 + 0.2) / 4.5  # where x reaches -clearance on the segment to (-0.5, 5, 8)
    np.testing.assert_allclose(posed[8], [-0.2, 5.0, 8.5 - 0.5 * t], atol=1e-3)
    # halfway between the two depths: halfway between the two places
    coords, contact = cube_contact([-0.5, 5.0, 8.0], ray_depth=(1.0, 2.0))
    half = coords.copy()
    half[8] = [4.0, 5.0, 8.5]
    contact.resolve(half, {"bone": IDENTITY})
    np.testing.assert_allclose(half[8], 0.5 * (posed[8] + [4.0, 5.0, 10.2]), atol=1e-3)


def test_the_guard_keeps_outside_nodes_outside_and_inside_ones_from_going_deeper():
    start = np.vstack([CUBE, [[5.0, 5.0, 11.0], [5.0, 5.0, 9.0]]])  # 1 above, 1 inside
    guard = BoneDepthGuard(
        {"bone": BoneSurfaceDistance(CUBE[TRIANGLES])}, {"bone": IDENTITY}, start
    )
    trial = start.copy()
    trial[8] = [5.0, 5.0, 10.5]  # still outside
    trial[9] = [5.0, 5.0, 9.5]  # less deep
    assert guard(np.array([8, 9]), trial).tolist() == [True, True]
    trial[8] = [5.0, 5.0, 9.9]  # into the bone
    trial[9] = [5.0, 5.0, 8.0]  # deeper
    assert guard(np.array([8, 9]), trial).tolist() == [False, False]
    # the bone moved up 3: the start depths are taken in the pose the guard was made for
    lifted = RigidTransform(np.eye(3), np.array([0.0, 0.0, 3.0]))
    guard = BoneDepthGuard({"bone": BoneSurfaceDistance(CUBE[TRIANGLES])}, {"bone": lifted}, start)
    trial = start.copy()
    trial[8] = [5.0, 5.0, 10.5]  # was 2 inside the lifted cube, now 2.5: deeper
    assert guard(np.array([8]), trial).tolist() == [False]


@pytest.mark.parametrize("angle", [90.0])
def test_smoothing_the_export_pushes_no_tissue_into_a_bone(small_repositioner, angle):
    # the smoother used to buy better Jacobians by moving tissue into the tibia
    # (default demo at 90 deg: 2 nodes deeper than 0.5 mm relaxed, 20 after smoothing)
    rep = small_repositioner
    relaxed = rep.pose_detailed(angle, remeasure=False)
    posed = pose_model(rep, angle, smooth=True)
    moved = np.flatnonzero(np.any(posed.model.coords != relaxed.coords, axis=1))
    assert len(moved) > 0  # the smoother did something
    guard = rep.bone_depth_guard(relaxed.coords, relaxed.bone_pose)
    before = guard.start_depth(moved)
    after = guard.depths(moved, posed.model.coords[moved])
    assert np.all(after >= np.minimum(before, 0.0) - 1e-9)


def test_tissue_in_bones_agrees_with_the_independent_check(
    small_leg, small_setup, small_repositioner
):
    rep, model = small_repositioner, small_leg.model
    assert rep.tissue_in_bones(model.coords, rep.bone_pose(rep.initial_flexion))["nodes"] == 0
    mapped = rep.pose(90.0)  # the slider's mapping carries tissue into femur and tibia
    found = rep.tissue_in_bones(mapped, rep.bone_pose(90.0))
    ml = rep.axes.fe_axis.direction
    for name, roles in (("femur", ("femur",)), ("tibia", ("tibia", "fibula"))):
        tris = surface_triangles(model, small_setup.parts_of(*roles), shells=False)
        inside = penetrating(mapped[rep._near_soft], mapped, tris, ml, found["tolerance"])
        assert found["bones"][name]["nodes"] == int(inside.sum()) > 0, name
    assert found["nodes"] <= sum(b["nodes"] for b in found["bones"].values())
    assert found["deepest"] > 10 * found["tolerance"]


def test_tissue_in_bones_skips_nodes_outside_a_bone_box_with_the_same_answer(
    small_repositioner,
):
    """The in-bone check measures only the nodes in a bone's bounding box (a node outside it is
    outside the bone); the counts and depths are those of measuring every node."""
    rep = small_repositioner
    mapped, bone = rep.pose(90.0), rep.bone_pose(90.0)
    found = rep.tissue_in_bones(mapped, bone)
    guard = rep.bone_depth_guard(mapped, bone)
    nodes = rep._soft_near_joint()
    every = -guard.start_depth(nodes)  # every node measured, + inside
    skipped = 0
    for j, name in enumerate(guard.segments):
        assert found["bones"][name]["nodes"] == int(np.sum(every[:, j] > found["tolerance"]))
        deepest = max(float(every[:, j].max()), 0.0)
        assert found["bones"][name]["deepest"] == pytest.approx(deepest, rel=1e-12, abs=1e-12)
        rest = bone.transforms[name].inverse().apply(mapped[nodes])
        boxed = rep._bone_surfaces()[name].in_box(rest)
        assert np.all(every[~boxed, j] < 0.0), name  # outside the box: outside the bone
        skipped += int(np.sum(~boxed))
    assert skipped > len(nodes)  # most of the bone tests are skipped
    assert found["bones"]["tibia"]["nodes"] > 0  # the mapping left tissue in a bone


def test_a_point_outside_the_surface_box_is_outside_the_surface():
    surface = BoneSurfaceDistance(CUBE[TRIANGLES])
    points = np.array([[5.0, 5.0, 5.0], [10.0, 0.0, 5.0], [10.001, 5.0, 5.0], [-1.0, 5.0, 5.0]])
    np.testing.assert_array_equal(surface.in_box(points), [True, True, False, False])
    assert np.all(surface.query(points[~surface.in_box(points)])[0] > 0.0)


def test_the_pose_report_counts_tissue_in_bones_and_warns(small_repositioner):
    posed = pose_model(small_repositioner, 120.0, smooth=False)
    found = posed.report["tissue_in_bones"]
    assert set(found) == {"tolerance", "nodes", "deepest", "bones"}
    assert set(found["bones"]) == {"femur", "tibia", "patella"}
    warned = [w for w in posed.report["warnings"] if "soft-tissue node" in w]
    assert len(warned) == sum(1 for b in found["bones"].values() if b["nodes"])


def _winding_number(points: np.ndarray, tri_xyz: np.ndarray) -> np.ndarray:
    """Generalised winding number (van Oosterom & Strackee): 1 inside a closed outward
    surface, 0 outside."""
    out = np.zeros(len(points))
    for i, p in enumerate(points):
        a, b, c = (tri_xyz[:, j] - p for j in range(3))
        la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
        num = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = (
            la * lb * lc
            + np.einsum("ij,ij->i", a, b) * lc
            + np.einsum("ij,ij->i", b, c) * la
            + np.einsum("ij,ij->i", c, a) * lb
        )
        out[i] = np.sum(2.0 * np.arctan2(num, den)) / (4.0 * np.pi)
    return out


def test_signed_distance_to_the_demo_bones_gets_the_side_and_the_depth_inside_right(
    small_repositioner,
):
    # points up to 20 mm around each bone of the coarse demo: one point 10.7 mm outside the
    # patella was reported inside it (a saddle vertex's plain mean of face normals), and a
    # node 14 mm behind the 20k demo's tibia was reported 14 mm inside it (the nearest node's
    # triangles missed the closest one). Every side must be right, every depth inside exact,
    # and no distance below the true one (the export's report of tissue in bones relies on it).
    from kneegui.reposition.contact import closest_on_triangles

    coords = small_repositioner.model.coords
    rng = np.random.default_rng(5)
    for name, tris in small_repositioner._bone_triangles().items():
        tri_xyz = coords[tris]
        surface = BoneSurfaceDistance(tri_xyz)
        lo = tri_xyz.reshape(-1, 3).min(axis=0) - 20.0
        hi = tri_xyz.reshape(-1, 3).max(axis=0) + 20.0
        hi[2] = min(hi[2], lo[2] + 120.0)  # the joint's end of a long bone
        points = rng.uniform(lo, hi, (800, 3))
        signed = surface.query(points)[0]
        exact = np.array(
            [
                np.linalg.norm(
                    p - closest_on_triangles(np.repeat(p[None], len(tri_xyz), 0), tri_xyz), axis=1
                ).min()
                for p in points
            ]
        )
        inside = _winding_number(points, tri_xyz) > 0.5
        assert np.array_equal(signed < 0, inside), name
        deep = inside & (exact > surface.corner_reach)
        assert deep.sum() > 10 or name != "femur"  # the femur's condyles do hold such points
        np.testing.assert_allclose(-signed[deep], exact[deep], rtol=1e-9, atol=1e-9, err_msg=name)
        assert np.all(np.abs(signed) >= exact - 1e-9), name


def test_contact_planes_hold_nodes_at_their_true_depth(small_repositioner):
    """A contact plane through the closest bone point measures the node's signed distance
    exactly when its normal is the distance's gradient. With the surface's pseudo-normal the
    plane of a node near an edge or vertex tilts away from the node: on the hex leg built at
    0 deg and posed to 90 deg a node settled exactly on its plane 0.66 mm inside the femur."""
    from kneegui.reposition.relax import _distance_gradient

    coords = small_repositioner.model.coords
    rng = np.random.default_rng(11)
    tilted = 0
    for tris in small_repositioner._bone_triangles().values():
        surface = BoneSurfaceDistance(coords[tris])
        # points within 3 mm of the surface, on either side
        anchors = coords[np.unique(tris)]
        points = anchors[rng.integers(len(anchors), size=600)] + rng.normal(0.0, 1.5, (600, 3))
        depth, closest, normal, _ = surface.query(points)
        gradient = _distance_gradient(points, closest, depth, normal)
        np.testing.assert_allclose(np.linalg.norm(gradient, axis=1), 1.0, rtol=1e-12)
        plane_gap = np.einsum("ij,ij->i", gradient, points - closest)
        np.testing.assert_allclose(plane_gap, depth, rtol=1e-9, atol=1e-9)
        pseudo_gap = np.einsum("ij,ij->i", normal, points - closest)
        tilted += int(np.sum(np.abs(pseudo_gap - depth) > 0.05))
    assert tilted > 0  # the surface normal alone would not do


def test_no_points_queried_gives_empty_answers():
    distance, point, normal, node_distance = BoneSurfaceDistance(CUBE[TRIANGLES]).query(
        np.zeros((0, 3))
    )
    assert distance.shape == (0,) and point.shape == normal.shape == (0, 3)
    assert node_distance.shape == (0,)


def test_the_distance_memo_skips_only_points_provably_beyond_its_threshold():
    """Points measured once and moved since are measured again unless the distance, less
    how far they moved, is still beyond the threshold; what is measured is the full query's
    answer, and every skipped point's bound is at most its true distance."""
    from kneegui.reposition.contact import DistanceMemo

    surface = BoneSurfaceDistance(CUBE[TRIANGLES])
    rng = np.random.default_rng(2)
    start = rng.uniform(-15.0, 25.0, (400, 3))
    d0, _, _, nd0 = surface.query(start)
    memo = DistanceMemo(surface, start, d0, nd0)
    rows = np.arange(len(start))
    band = 3.0
    for step in range(4):
        moved = start + rng.normal(0.0, 1.0 + step, start.shape)
        depth, point, normal, measured = memo.query(rows, moved, band)
        full_depth, full_point, full_normal, _ = surface.query(moved)
        assert 0 < measured.sum() < len(moved)
        np.testing.assert_array_equal(depth[measured], full_depth[measured])
        np.testing.assert_array_equal(point[measured], full_point[measured])
        np.testing.assert_array_equal(normal[measured], full_normal[measured])
        skipped = ~measured
        assert np.all(depth[skipped] > band)
        assert np.all(depth[skipped] <= full_depth[skipped] + 1e-12)
        assert np.all(np.isnan(point[skipped]))
        start = moved


def test_the_contact_planes_are_the_same_with_the_memo(small_repositioner):
    """The memo only skips nodes the full query would put beyond the contact band (or, for
    attached nodes, beyond the clearance), so every call's planes and penetrations match those
    of a relaxation that measures every node, while the nodes drift as a solver moves them."""
    rep = small_repositioner
    bone = rep.bone_pose(90.0)
    coords = rep.pose(90.0)
    memo, full = rep._elastic_relaxation(), rep._elastic_relaxation()
    nodes = memo.contact_nodes
    rng = np.random.default_rng(4)
    skipped = 0
    for _ in range(4):
        coords = coords + rng.normal(0.0, 0.3, coords.shape)
        for name in full.bones:  # forget everything: every node measured
            full._contact_memo[name].depth[:] = np.nan
            if full._attached_nb is not None:
                full._attached_memo[name].depth[:] = np.nan
        before = {n: m.where.copy() for n, m in memo._contact_memo.items()}
        got = memo._contact_planes(coords, nodes, bone.transforms)
        want = full._contact_planes(coords, nodes, bone.transforms)
        for a, b in zip(got[:3], want[:3], strict=True):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(got[3] < 0, want[3] < 0)
        np.testing.assert_array_equal(np.minimum(got[3], 0), np.minimum(want[3], 0))
        skipped += sum(
            int(np.sum(np.all(m.where == before[n], axis=1))) for n, m in memo._contact_memo.items()
        )
    assert skipped > 0  # the memo did spare queries


def test_compiled_closest_points_are_the_numpy_reference():
    """Every Voronoi region of a triangle (corners, edges, face) and degenerate triangles (two
    corners together, all three together) give the reference's bits."""
    from kneegui.reposition.contact import closest_on_triangles, closest_on_triangles_numpy

    rng = np.random.default_rng(11)
    m = 20000
    tri = rng.normal(size=(m, 3, 3)) * 10.0 ** rng.integers(-3, 4, (m, 1, 1))
    p = rng.normal(size=(m, 3)) * 10.0 ** rng.integers(-3, 4, (m, 1))
    tri[::50, 1] = tri[::50, 0]
    tri[::77] = tri[::77, :1]
    p[::33] = tri[::33, 1]
    got = closest_on_triangles(p, tri)
    expected = closest_on_triangles_numpy(p, tri)
    # the same bits on this project's machine; a few ulps of margin for another CPU's NumPy
    scale = np.abs(tri).max(axis=(1, 2))[:, None] + np.abs(p)
    np.testing.assert_array_less(np.abs(got - expected), 1e-13 * scale + 1e-300)
    # the points fall in every region: on a corner, inside an edge's span, inside the face
    at_corner = np.isclose(got[:, None, :], tri).all(axis=2).any(axis=1)
    assert 0.05 < at_corner.mean() < 0.95


def test_the_push_measures_each_bone_only_where_it_holds_a_clearance(small_repositioner):
    """A candidate with no surface node of a bone within reach keeps no clearance from that
    bone, so the contact measures it against the others only; the push is the same as
    measuring every candidate against every bone (to 1e-9 model units: each point is measured
    on its own, but another CPU's NumPy may round a batch of another length differently)."""
    rep = small_repositioner
    contact = rep._bone_contact(rep.options.relax_contact_reach)
    n = len(contact.candidates)
    for srf in contact.surfaces:
        np.testing.assert_array_equal(srf.rows, np.flatnonzero(np.isfinite(srf.floor)))
    assert sum(len(srf.rows) for srf in contact.surfaces) < len(contact.surfaces) * n
    mapped = rep.pose(90.0)
    bone = rep.bone_pose(90.0)
    fast = mapped.copy()
    pushed = contact.resolve(fast, bone.transforms)
    assert pushed > 0
    for srf in contact.surfaces:  # the former way: every candidate against every bone
        srf.rows = np.arange(n)
    every = mapped.copy()
    assert contact.resolve(every, bone.transforms) == pushed
    np.testing.assert_allclose(fast, every, rtol=0, atol=1e-9)


def test_a_long_distance_query_asks_to_cancel_per_wave_and_gives_the_same_values(monkeypatch):
    """A whole-body model's contact nodes are measured against a bone for seconds: the query
    asks between waves of chunks, on one thread or many, without changing a value."""
    from kneegui.errors import Cancelled
    from kneegui.reposition import contact

    monkeypatch.setattr(contact, "QUERY_CHUNK", 50)
    monkeypatch.setattr(contact, "QUERY_WAVE", 3)
    surface = BoneSurfaceDistance(CUBE[TRIANGLES])
    points = np.random.default_rng(2).uniform(-5.0, 15.0, (1000, 3))
    whole = surface._query(points)  # every point at once
    waves = -(-(1000 // 50) // 3)
    for threads in (1, 2, 3):
        asked = []
        got = surface.query(
            points, threads=threads, cancel=lambda asked=asked: bool(asked.append(1))
        )
        assert len(asked) == waves
        for a, b in zip(got, whole, strict=True):
            np.testing.assert_array_equal(a, b)
        with pytest.raises(Cancelled, match="distance"):
            surface.query(points, threads=threads, cancel=lambda: True)
    for a, b in zip(surface.query(points, threads=2), whole, strict=True):
        np.testing.assert_array_equal(a, b)
