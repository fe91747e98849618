"""The pre-flight check: locked elements and their flexion limits, coincident node pairs, the
movable region; and its figures in the pose report."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.geometry.transforms import RigidTransform
from kneegui.kinematics.posing import BonePose
from kneegui.model import ElementBlock, Model
from kneegui.quality import compute_quality, jsonable
from kneegui.reposition import NodeGroups, Repositioner, RepositionOptions
from kneegui.reposition.pipeline import locked_inverted_warning, pose_model
from kneegui.reposition.preflight import preflight_of, run_preflight
from kneegui.setup import load_setup

# ------------------------------------------------------------------ a synthetic two-bone case
INITIAL = 0.37
#: The tibia turns by this many degrees per degree of flexion (so that no crossing falls on the
#: sampling grid).
RATE = 0.8
CUBE = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    dtype=float,
)


def _bone_pose(flexion: float) -> BonePose:
    """Femur and patella stay, the tibia turns about the y axis through the origin."""
    tibia = RigidTransform.about_axis((0, 0, 0), (0, 1, 0), RATE * (flexion - INITIAL))
    identity = RigidTransform.identity()
    return BonePose(
        {"femur": identity, "tibia": tibia, "patella": identity},
        flexion,
        INITIAL,
        flexion,
        flexion - INITIAL,
        0.0,
        0.0,
        0.0,
        0,
    )


@pytest.fixture(scope="module")
def two_bones():
    """Four hexes: A bottom on the tibia, top on the femur (locked); B on the femur alone;
    C femur and fixed nodes (neither moves: not locked); D tibia with one movable node."""
    offsets = [0.0, 5.0, 10.0, 15.0]
    coords = np.concatenate([CUBE + np.array([dx, 0.0, 0.0]) for dx in offsets])
    conn = np.arange(32).reshape(4, 8)
    model = Model(
        np.arange(1, 33),
        coords,
        {"hex8": ElementBlock("hex8", [11, 12, 13, 14], [1, 2, 3, 4], conn)},
    )
    groups = NodeGroups(
        segment={
            "femur": np.r_[4:8, 8:16, 20:24],
            "tibia": np.r_[0:4, 24:31],
            "patella": np.zeros(0, dtype=np.int64),
            "fixed": np.r_[16:20],
        },
        skin=np.zeros(0, dtype=np.int64),
        band=np.zeros(0, dtype=np.int64),
        flesh=np.array([31]),
        bone_surface=np.zeros(0, dtype=np.int64),
    )
    return model, groups


def _inverted(model, flexion: float) -> bool:
    tr = _bone_pose(flexion).transforms["tibia"]
    xyz = model.coords.copy()
    xyz[0:4] = tr.apply(xyz[0:4])
    return bool(compute_quality(xyz, model.blocks)["hex8"].inverted[0])


def _first_inversion(model, end: float, coarse: float = 0.25, fine: float = 0.005) -> float:
    """Independently: the first flexion from INITIAL towards ``end`` at which element A is
    inverted, scanned with the quality kernels on the whole posed model (coarse, then fine)."""
    sign = np.sign(end - INITIAL)
    steps = np.arange(INITIAL, end, sign * coarse)
    hit = next(k for k, f in enumerate(steps) if _inverted(model, f))
    return next(
        f
        for f in np.arange(steps[hit - 1], steps[hit] + sign * fine, sign * fine)
        if _inverted(model, f)
    )


def test_locked_element_and_its_limits_on_two_bones(two_bones):
    model, groups = two_bones
    pre = run_preflight(model, groups, _bone_pose, INITIAL, flexion_range_deg=(-80.0, 150.0))
    assert pre.locked.ids.tolist() == [11]
    assert pre.locked.segments == (("femur", "tibia"),)
    # analytically: the corner at node 0 has det cos(t), the one at node 1 sin(t) + cos(t),
    # t = RATE (flexion - INITIAL): inverted from t = 90 up and t = -45 down
    above, below = INITIAL + 90.0 / RATE, INITIAL - 45.0 / RATE
    res = pre.resolution_deg
    assert res <= 0.05
    assert above - 1e-9 <= pre.locked.inverts_above_deg[0] <= above + res + 1e-9
    assert below - res - 1e-9 <= pre.locked.inverts_below_deg[0] <= below + 1e-9
    # the same crossings found by brute force on the whole posed model
    up, down = _first_inversion(model, 150.0), _first_inversion(model, -80.0)
    assert abs(up - pre.locked.inverts_above_deg[0]) <= 0.005 + res
    assert abs(down - pre.locked.inverts_below_deg[0]) <= 0.005 + res
    limits = (pre.locked.inverts_below_deg[0], pre.locked.inverts_above_deg[0])
    assert pre.valid_range_deg() == limits
    # the movable region: node 31 and element D
    assert pre.movable_nodes == 1 and pre.movable_elements == 1
    assert pre.movable_elements_by_part == {4: 1}
    assert len(pre.coincident_pairs) == 0


def test_the_check_asks_to_cancel_between_its_steps_and_changes_nothing(two_bones):
    from kneegui.errors import Cancelled

    model, groups = two_bones
    kwargs = {"flexion_range_deg": (-80.0, 150.0)}
    asked = []
    pre = run_preflight(
        model, groups, _bone_pose, INITIAL, cancel=lambda: bool(asked.append(1)), **kwargs
    )
    plain = run_preflight(model, groups, _bone_pose, INITIAL, **kwargs)
    assert pre.to_dict() | {"seconds": 0} == plain.to_dict() | {"seconds": 0}
    # the element type twice, the coincident pairs' tree and query, the incidence, and one
    # question per sampled angle of the locked element's limits
    assert len(asked) >= 6
    for stop_at in range(len(asked)):  # a True at any of the questions stops the check

        def cancel(calls=[], stop_at=stop_at) -> bool:  # noqa: B006 - one list per question
            calls.append(1)
            return len(calls) > stop_at

        with pytest.raises(Cancelled, match="pre-flight"):
            run_preflight(model, groups, _bone_pose, INITIAL, cancel=cancel, **kwargs)


def test_a_limit_beyond_the_range_is_none(two_bones):
    model, groups = two_bones
    pre = run_preflight(model, groups, _bone_pose, INITIAL, flexion_range_deg=(-10.0, 100.0))
    assert pre.locked.ids.tolist() == [11]
    assert np.isnan(pre.locked.inverts_above_deg[0]) and np.isnan(pre.locked.inverts_below_deg[0])
    element = pre.to_dict()["locked"]["elements"][0]
    assert element["inverts_above_deg"] is None and element["segments"] == ["femur", "tibia"]
    assert pre.valid_range_deg() == (-10.0, 100.0)


def test_coincident_pairs_are_found_and_joined_by_part(two_bones):
    model, groups = two_bones
    # a fifth hex of part 9 sharing the place of element B's nodes but not its nodes
    coords = np.concatenate([model.coords, model.coords[8:16]])
    blocks = {
        "hex8": ElementBlock(
            "hex8",
            [11, 12, 13, 14, 15],
            [1, 2, 3, 4, 9],
            np.concatenate([model.blocks["hex8"].conn, [np.arange(32, 40)]]),
        )
    }
    doubled = Model(np.arange(1, 41), coords, blocks)
    groups = NodeGroups(
        {**groups.segment}, groups.skin, groups.band, np.r_[31, 32:40], groups.bone_surface
    )
    pre = run_preflight(doubled, groups, _bone_pose, INITIAL)
    assert len(pre.coincident_pairs) == 8
    assert sorted(pre.coincident_pairs[:, 1].tolist()) == list(range(32, 40))
    assert pre.coincident_joins == [
        {"parts_a": [2], "segment_a": "femur", "parts_b": [9], "segment_b": "movable", "pairs": 8}
    ]
    assert pre.movable_nodes == 9 and pre.movable_elements == 2


# ------------------------------------------------------------------ the demo leg
def test_sliding_demo_has_no_locked_elements(small_leg, small_repositioner):
    pre = preflight_of(small_repositioner)
    assert len(pre.locked) == 0
    # the sliding interface: soft-tissue copies of bone nodes, bone on one side only
    assert len(pre.coincident_pairs) > 100
    sides = {(j["segment_a"], j["segment_b"]) for j in pre.coincident_joins}
    assert sides <= {("femur", "movable"), ("tibia", "movable"), ("patella", "movable")}
    # the movable region is the soft tissue the repositioner maps
    assert pre.movable_nodes == len(small_repositioner.groups.soft)
    assert preflight_of(small_repositioner) is pre  # run once per repositioner


@pytest.fixture(scope="module")
def welded(welded_leg):
    model, setup = welded_leg
    repositioner = Repositioner(model, load_setup(setup, model), RepositionOptions(relax=False))
    return repositioner, preflight_of(repositioner)


def test_welded_demo_lists_elements_tied_to_two_bones(welded):
    repositioner, pre = welded
    assert len(pre.locked) >= 5
    assert len(pre.coincident_pairs) == 0
    setup, model = repositioner.setup, repositioner.model
    # independently: the nodes of a locked element not on a bone part are its free nodes, and
    # its bone nodes lie on two segments
    on = {s: np.zeros(model.n_nodes, bool) for s in ("femur", "tibia", "patella")}
    for s in on:
        on[s][setup.segment_nodes[s]] = True
    locked = pre.locked
    for etype, row, segments, free in zip(
        locked.etype, locked.rows, locked.segments, locked.free_nodes, strict=True
    ):
        nodes = model.blocks[etype].conn[row]
        tied = {s for s in on if on[s][nodes].any()}
        assert sum(not any(on[s][n] for s in on) for n in nodes) == free
        assert len(tied) >= 2 and set(segments) == tied
    # some with free nodes too, each with a limit: their bone nodes alone leave no valid shape
    partial = locked.free_nodes > 0
    assert partial.sum() >= 5
    assert np.all(
        np.isfinite(locked.inverts_above_deg[partial])
        | np.isfinite(locked.inverts_below_deg[partial])
    )
    assert np.all(pre.locked.inverts_above_deg[np.isfinite(pre.locked.inverts_above_deg)] > 9.0)


def test_welded_limits_are_where_the_pose_inverts(welded):
    """Each locked element that inverts within the range is valid in the real pose just before
    its limit and inverted at it."""
    repositioner, pre = welded
    model = repositioner.model
    finite = np.flatnonzero(
        np.isfinite(pre.locked.inverts_above_deg) & (pre.locked.free_nodes == 0)
    )
    assert len(finite) >= 5
    for k in finite[:6]:
        etype, row = str(pre.locked.etype[k]), int(pre.locked.rows[k])
        limit = float(pre.locked.inverts_above_deg[k])
        before = repositioner.pose(limit - 2 * pre.resolution_deg)
        at = repositioner.pose(limit)
        rows = {etype: np.array([row])}
        assert not compute_quality(before, model.blocks, rows)[etype].inverted[0]
        assert compute_quality(at, model.blocks, rows)[etype].inverted[0]


@pytest.mark.parametrize("angle", [90.0, 120.0])
def test_every_rigidly_inverted_element_is_locked_with_a_limit_below(welded, angle):
    repositioner, pre = welded
    model = repositioner.model
    q = compute_quality(repositioner.pose(angle), model.blocks)
    limits = {
        (str(t), int(r)): a
        for t, r, a in zip(
            pre.locked.etype, pre.locked.rows, pre.locked.inverts_above_deg, strict=True
        )
    }
    found = 0
    for etype in q:
        rows = q[etype].rows[q[etype].inverted]
        no_movable = ~pre.movable_rows[etype][rows]
        for row in rows[no_movable].tolist():
            found += 1
            assert (etype, row) in limits
            assert limits[(etype, row)] <= angle + pre.resolution_deg
    assert found >= 3


def test_pose_report_counts_locked_and_movable_apart(welded):
    repositioner, pre = welded
    posed = pose_model(repositioner, 90.0, smooth=False)
    report = posed.report
    inv = report["inverted"]
    final = compute_quality(posed.model.coords, posed.model.blocks)
    assert inv["total"] == final.n_inverted == report["quality"]["posed"]["inverted"]
    assert inv["locked"] >= 3 and inv["locked"] + inv["movable"] + inv["other"] == inv["total"]
    assert set(inv["locked_ids"]) <= set(pre.locked.ids.tolist())
    assert not set(inv["movable_ids"]) & set(pre.locked.ids.tolist())
    # the gate names both, and a warning names the locked ones with the pre-flight limit
    reason = report["gate"]["reasons"][0]
    assert reason.startswith(f"{inv['total']} inverted element(s): ")
    assert f"{inv['locked']} locked between segments" in reason
    warning = next(w for w in report["warnings"] if "locked element(s) inverted" in w)
    assert str(inv["locked_ids"][0]) in warning
    assert f"{pre.valid_range_deg()[1]:.1f} deg" in warning
    # no relaxation here: no corner left out, and the warning says nothing of it
    assert report["relaxation"] is None and "out of its energy" not in warning
    (told,) = locked_inverted_warning(inv, pre, 12)
    assert told.startswith(warning) and "left 12 corner(s)" in told
    expected = pre.to_dict()
    del expected["coincident_pairs"]["node_ids"]
    assert report["preflight"] == jsonable(expected)


def test_pose_report_has_the_axis_sensitivity(small_repositioner):
    report = pose_model(small_repositioner, 30.0, smooth=False).report
    sensitivity = small_repositioner.axes.sensitivity
    assert sensitivity is not None
    assert report["axis_sensitivity"] == pytest.approx(sensitivity.to_dict())
    assert report["axis_sensitivity"]["n_subsets"] > 0
    # the sliding demo: nothing locked, every inverted element (if any) movable
    assert report["inverted"]["locked"] == 0 and report["preflight"]["locked"]["count"] == 0


def test_the_welded_demo_variant():
    """``kneegui demo --joint welded`` (flesh, menisci and cruciates sharing nodes with both
    bones): locked elements between femur and tibia, and every element the bones' motion
    inverts at 90 deg among them with a limit below it."""
    from kneegui import demo

    leg = demo.generate_demo_leg(2000, joint="welded")
    model = leg.model
    repositioner = Repositioner(model, load_setup(leg.setup, model), RepositionOptions(relax=False))
    pre = preflight_of(repositioner)
    assert len(pre.locked) >= 20 and len(pre.coincident_pairs) == 0
    assert ("femur", "tibia") in set(pre.locked.segments)
    limits = {
        (str(t), int(r)): a
        for t, r, a in zip(
            pre.locked.etype, pre.locked.rows, pre.locked.inverts_above_deg, strict=True
        )
    }
    q = compute_quality(repositioner.pose(90.0), model.blocks)
    rigid = [
        (etype, row)
        for etype in q
        for row in q[etype].rows[q[etype].inverted].tolist()
        if not pre.movable_rows[etype][row]
    ]
    assert len(rigid) >= 10
    assert all(key in limits and limits[key] <= 90.0 + pre.resolution_deg for key in rigid)


def test_the_gate_names_its_worst_element_and_what_may_move_it(welded):
    """On the welded demo at 30 deg nothing is inverted, but a locked element is below the
    initial worst Jacobian: the gate's reason names it, as locked, so the analyst sees it is
    the kinematics' shape, not the repositioner's."""
    repositioner, pre = welded
    posed = pose_model(repositioner, 30.0, smooth=False)
    reasons = posed.report["gate"]["reasons"]
    final = compute_quality(posed.model.coords, posed.model.blocks)
    worst = min(
        (
            float(final[t].jacobian_corner.min()),
            t,
            int(final[t].rows[final[t].jacobian_corner.argmin()]),
        )
        for t in final
        if len(final[t]) and final[t].has("jacobian")
    )
    _, etype, row = worst
    element = int(posed.model.blocks[etype].ids[row])
    locked = zip(pre.locked.etype, pre.locked.rows, strict=True)
    assert (etype, row) in {(str(t), int(r)) for t, r in locked}
    jacobian = next(r for r in reasons if r.startswith("worst Jacobian "))
    assert jacobian.endswith(f"(element {element}, locked between segments)"), reasons
    assert pre.kind_of(etype, row) == "locked between segments"
    free = np.flatnonzero(pre.movable_rows["hex8"])[0]
    assert pre.kind_of("hex8", int(free)) == "movable"
