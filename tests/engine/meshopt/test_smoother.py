"""Smoothing: free-node selection, guarantees (worst Jacobian, fixed nodes, determinism),
untangling, sliding skin nodes, progress and cancel."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.errors import Cancelled
from kneegui.meshopt import (
    SmoothOptions,
    degraded_elements,
    smooth_mesh,
    smooth_posed_model,
    smoothing_free_nodes,
    smoothing_sliding_nodes,
)
from kneegui.meshopt.nodes import boundary_node_mask
from kneegui.meshopt.smoother import SMOOTHED_TYPES, edge_ratio
from kneegui.quality import compute_quality


def _swirl(model, amplitude, width):
    """Twist the block's interior about the vertical axis through its centre (boundary stays)."""
    c = model.coords
    centre = c.max(axis=0) / 2
    r = np.linalg.norm(c - centre, axis=1)
    th = amplitude * np.exp(-((r / width) ** 2))
    dx, dy = c[:, 0] - centre[0], c[:, 1] - centre[1]
    out = c.copy()
    out[:, 0] = centre[0] + dx * np.cos(th) - dy * np.sin(th)
    out[:, 1] = centre[1] + dx * np.sin(th) + dy * np.cos(th)
    return model.with_coords(out)


def _jiggle(model, seed, amplitude=0.6, fraction=0.08):
    """Move a random subset of interior flesh nodes at random: some elements invert."""
    rng = np.random.default_rng(seed)
    free = smoothing_free_nodes(model, [2], [1])
    idx = np.flatnonzero(free)
    pick = rng.choice(idx, size=max(3, int(fraction * len(idx))), replace=False)
    c = model.coords.copy()
    c[pick] += rng.uniform(-amplitude, amplitude, (len(pick), 3))
    return model.with_coords(c)


# ---------------------------------------------------------------------- free nodes
def test_free_nodes_exclude_bone_part_boundary_and_surface(block_model):
    model = block_model(6, 6, 6, bone_layers=2)
    free = smoothing_free_nodes(model, [2], [1])
    bone = model.part_node_indices([1])
    surface = boundary_node_mask(model.n_nodes, model.blocks)
    assert free.any()
    assert not free[bone].any()  # includes the bone/flesh interface (part boundary)
    assert not free[surface].any()
    assert not free[model.part_node_indices([3])].any()  # skin shells
    # every interior flesh node off the interface is free
    z = model.coords[:, 2]
    interior = ~surface & (z > 2.0)
    assert np.array_equal(free, interior)


def test_free_nodes_ask_cancel_between_their_steps(block_model):
    """About a second on a whole-body model: ``cancel`` is asked between the steps, True
    stops them, False changes nothing."""
    model = block_model(6, 6, 6, bone_layers=2)
    asked = []
    free = smoothing_free_nodes(model, [2], [1], cancel=lambda: asked.append(1) or False)
    assert len(asked) == 5
    assert free.any()
    np.testing.assert_array_equal(free, smoothing_free_nodes(model, [2], [1]))
    with pytest.raises(Cancelled):
        smoothing_free_nodes(model, [2], [1], cancel=lambda: True)


def test_free_nodes_follow_degraded_elements_and_rings(block_model):
    model = block_model(8, 8, 8, bone_layers=1, skin=False)
    hexes = model.blocks["hex8"]
    centre = model.coords[hexes.conn].mean(axis=1)
    one = np.all(np.isclose(centre, (4.5, 4.5, 4.5)), axis=1)
    assert one.sum() == 1
    mask = {"hex8": one}
    ring0 = smoothing_free_nodes(model, [2], [1], mask, rings=0)
    ring1 = smoothing_free_nodes(model, [2], [1], mask, rings=1)
    ring2 = smoothing_free_nodes(model, [2], [1], mask, rings=2)
    assert ring0.sum() == 8 and ring1.sum() == 64 and ring2.sum() == 216 - 0
    assert np.all(ring1[ring0]) and np.all(ring2[ring1])


def test_degraded_elements_needs_to_be_worse_than_initial(block_model):
    model = block_model(4, 4, 4, skin=False)
    posed = _jiggle(model, 1)
    q0 = compute_quality(model.coords, model.blocks)
    q1 = compute_quality(posed.coords, posed.blocks)
    deg = degraded_elements(q1, q0)["hex8"]
    j = q1["hex8"].jacobian_corner
    assert np.array_equal(deg, j < 0.6)  # the initial block is perfect
    assert not degraded_elements(q0, q0)["hex8"].any()


# ---------------------------------------------------------------------- guarantees
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_smoothing_never_worsens_worst_jacobian_nor_moves_fixed_nodes(seed, block_model):
    model = block_model(7, 7, 7, bone_layers=1)
    posed = _jiggle(model, seed)
    q_before = compute_quality(posed.coords, posed.blocks)
    free = smoothing_free_nodes(posed, [2], [1], degraded_elements(q_before), rings=1)
    coords_before = posed.coords.copy()
    new, report = smooth_mesh(posed, None, free)
    assert np.array_equal(posed.coords, coords_before)  # input untouched
    assert np.array_equal(new[~free], posed.coords[~free])  # fixed nodes exactly in place
    q_after = compute_quality(new, posed.blocks)
    assert q_after.worst_jacobian() >= q_before.worst_jacobian()
    assert q_before.n_inverted > 0 and q_after.n_inverted == 0
    assert report.inverted_after == 0 and report.worst_jacobian_after >= 0.6
    assert report.worst_jacobian_before == pytest.approx(q_before.worst_jacobian())
    assert report.moved_nodes == np.count_nonzero(np.any(new != posed.coords, axis=1))
    # no move raised the largest edge ratio above max(its old value, aspect_limit = 5)
    hexes = posed.blocks["hex8"].conn
    before = edge_ratio(posed.coords[hexes], "hex8").max()
    after = edge_ratio(new[hexes], "hex8").max()
    assert after <= max(before, 5.0) + 1e-12
    # ... nor the largest warpage above max(its old value, warpage_limit = 15 degrees)
    warp_before = q_before["hex8"].warpage.max()
    assert q_after["hex8"].warpage.max() <= max(warp_before, 15.0) + 1e-9


def test_smoothing_is_deterministic(block_model):
    model = block_model(8, 8, 8)
    posed = _swirl(model, 2.0, 2.5)
    a, ra = smooth_posed_model(posed, [2], [1], initial=model)
    b, rb = smooth_posed_model(posed, [2], [1], initial=model)
    assert np.array_equal(a.coords, b.coords)
    assert {k: v for k, v in ra.to_dict().items() if k != "seconds"} == {
        k: v for k, v in rb.to_dict().items() if k != "seconds"
    }


def test_smoothing_untangles_a_twisted_core_and_keeps_topology(block_model):
    model = block_model(12, 12, 12)
    posed = _swirl(model, 2.5, 2.0)
    q_posed = compute_quality(posed.coords, posed.blocks)
    assert q_posed.n_inverted > 0
    smoothed, report = smooth_posed_model(posed, [2], [1], initial=model)
    q = compute_quality(smoothed.coords, smoothed.blocks)
    assert q.n_inverted == 0
    assert q.worst_jacobian() > 0.3 > q_posed.worst_jacobian()
    assert report.stage1_moves > 0 and report.inverted_before == q_posed.n_inverted
    for etype, block in posed.blocks.items():
        assert smoothed.blocks[etype] is block  # same ids, parts and connectivity
    assert np.array_equal(smoothed.node_ids, posed.node_ids)
    bone = posed.part_node_indices([1])
    skin = posed.part_node_indices([3])
    assert np.array_equal(smoothed.coords[bone], posed.coords[bone])
    assert np.array_equal(smoothed.coords[skin], posed.coords[skin])


def test_stage_two_alone_improves_the_worst_element(block_model):
    model = block_model(5, 5, 5, skin=False)
    c = model.coords.copy()
    node = np.flatnonzero(np.all(c == (2, 2, 3), axis=1))[0]
    c[node] += (0.7, 0.6, -0.8)
    posed = model.with_coords(c)
    free = np.zeros(model.n_nodes, dtype=bool)
    free[node] = True
    q0 = compute_quality(posed.coords, posed.blocks)
    new, report = smooth_mesh(posed, None, free, options=SmoothOptions(max_sweeps=0))
    q1 = compute_quality(new, posed.blocks)
    assert report.stage1_sweeps == 0 and report.stage2_improved >= 1
    assert q1.worst_jacobian() > q0.worst_jacobian() + 0.3
    assert np.linalg.norm(new[node] - model.coords[node]) < np.linalg.norm(
        c[node] - model.coords[node]
    )


# ---------------------------------------------------------------------- sliding skin nodes
def test_sliding_nodes_stay_on_the_flat_skin_and_keep_shells_valid(block_model):
    model = block_model(8, 8, 4, bone_layers=1)
    c = model.coords.copy()
    top = np.isclose(c[:, 2], 4.0) & (c[:, 0] > 0) & (c[:, 0] < 8) & (c[:, 1] > 0) & (c[:, 1] < 8)
    rng = np.random.default_rng(3)
    c[top, :2] += rng.uniform(-0.45, 0.45, (top.sum(), 2))  # skin nodes shuffled in their plane
    posed = model.with_coords(c)
    q0 = compute_quality(posed.coords, posed.blocks)
    deg = degraded_elements(q0, compute_quality(model.coords, model.blocks))
    free = smoothing_free_nodes(posed, [2], [1], deg)
    sliding = smoothing_sliding_nodes(posed, [2], [3], [1], deg)
    assert (
        sliding[top].any() and not sliding[~boundary_node_mask(model.n_nodes, model.blocks)].any()
    )
    new, report = smooth_mesh(posed, None, free, sliding_nodes=sliding)
    assert report.sliding_nodes > 0
    moved = np.any(new != posed.coords, axis=1)
    assert np.any(moved & sliding)
    # every sliding node stays on its face plane (x = 0 | 8, y = 0 | 8 or z = 4)
    lo, hi = np.zeros(3), np.array([8.0, 8.0, 4.0])
    on_plane = np.isclose(c, lo) | np.isclose(c, hi)
    on_plane[:, 2] &= ~np.isclose(c[:, 2], 0.0)
    np.testing.assert_allclose(
        new[sliding][on_plane[sliding]], c[sliding][on_plane[sliding]], atol=1e-12
    )
    assert np.any(moved[top])
    assert np.array_equal(new[~(free | sliding)], posed.coords[~(free | sliding)])
    q1 = compute_quality(new, posed.blocks)
    assert q1["quad4"].jacobian_corner.min() >= q0["quad4"].jacobian_corner.min()
    assert q1.worst_jacobian() >= q0.worst_jacobian()
    # edge and corner nodes of the flat skin are feature nodes: they never slide
    rim = np.isclose(c[:, 2], 4.0) & ~top
    assert np.array_equal(new[rim], posed.coords[rim])


# ---------------------------------------------------------------------- progress and cancel
def test_progress_reports_fractions_and_cancel_raises(block_model):
    model = block_model(6, 6, 6)
    posed = _jiggle(model, 5)
    free = smoothing_free_nodes(posed, [2], [1])
    calls = []
    smooth_mesh(posed, None, free, progress=lambda f, m: calls.append((f, m)))
    fractions = [f for f, _ in calls]
    assert fractions and all(0.0 <= f <= 1.0 for f in fractions)
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert all(isinstance(m, str) and m for _, m in calls)
    with pytest.raises(Cancelled):
        smooth_mesh(posed, None, free, cancel=lambda: True)
    polls = []

    def cancel_late():
        polls.append(1)
        return len(polls) > 1

    twisted = _swirl(block_model(8, 8, 8), 2.0, 2.5)
    with pytest.raises(Cancelled):
        smooth_mesh(twisted, None, smoothing_free_nodes(twisted, [2], [1]), cancel=cancel_late)
    assert len(polls) == 2


def test_nothing_to_move_returns_a_copy(block_model):
    model = block_model(3, 3, 3)
    free = np.zeros(model.n_nodes, dtype=bool)
    new, report = smooth_mesh(model, None, free)
    assert new is not model.coords and np.array_equal(new, model.coords)
    assert report.moved_nodes == 0 and report.free_nodes == 0


# ---------------------------------------------------------------------- other element types
def _split_model(model, kind):
    """The same block with every flesh hex split into 2 wedges or 6 tets (bone stays hex)."""
    from kneegui.model import ElementBlock, Model

    hexes = model.blocks["hex8"]
    flesh = hexes.part_ids == 2
    conn = hexes.conn[flesh]
    if kind == "wedge6":
        pieces = [conn[:, [0, 1, 2, 4, 5, 6]], conn[:, [0, 2, 3, 4, 6, 7]]]
    else:
        pieces = [conn[:, list(t)] for t in ((0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6),
                                             (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6))]  # fmt: skip
    split = np.concatenate(pieces)
    if kind == "tet4":  # orient every tet positively
        p = model.coords[split]
        vol = np.einsum(
            "ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]
        )
        split[vol < 0] = split[vol < 0][:, [1, 0, 2, 3]]
    n0 = len(hexes)
    blocks = dict(model.blocks)
    blocks["hex8"] = hexes.select(~flesh)
    blocks[kind] = ElementBlock(
        kind, np.arange(n0 + 1, n0 + len(split) + 1), np.full(len(split), 2), split
    )
    blocks["quad4"] = ElementBlock(
        "quad4",
        model.blocks["quad4"].ids + len(split),
        model.blocks["quad4"].part_ids,
        model.blocks["quad4"].conn,
    )
    return Model(model.node_ids, model.coords, blocks, model.parts)


@pytest.mark.parametrize("kind", ["wedge6", "tet4"])
def test_smoothing_repairs_wedge_and_tet_meshes(block_model, kind):
    model = _split_model(block_model(7, 7, 7), kind)
    q_model = compute_quality(model.coords, model.blocks)
    assert q_model.n_inverted == 0 and q_model.worst_jacobian() > 0
    posed = _jiggle(model, 11, amplitude=0.5)
    q0 = compute_quality(posed.coords, posed.blocks)
    assert q0[kind].inverted.any()
    smoothed, _ = smooth_posed_model(posed, [2], [1], initial=model)
    q1 = compute_quality(smoothed.coords, smoothed.blocks)
    assert q1.n_inverted == 0 and q1.worst_jacobian() >= q0.worst_jacobian()
    fixed = ~smoothing_free_nodes(posed, [2], [1])
    assert np.array_equal(smoothed.coords[fixed], posed.coords[fixed])


def test_colouring_separates_nodes_that_share_an_element(block_model):
    from kneegui.meshopt.smoother import _build_neighbourhood, _colour

    model = block_model(6, 6, 6)
    movable = np.flatnonzero(smoothing_free_nodes(model, [2], [1]))
    nb = _build_neighbourhood(model.blocks, movable, model.n_nodes)
    compressed = np.full(model.n_nodes, -1)
    compressed[movable] = np.arange(len(movable))
    groups, ptr, nbrs = _colour(nb, compressed, len(movable))
    assert sorted(np.concatenate(groups).tolist()) == list(range(len(movable)))
    # the conflict graph: every ordered pair of movable nodes sharing an element, once
    expected = {
        (int(compressed[u]), int(compressed[v]))
        for row in model.blocks["hex8"].conn
        for u in row
        for v in row
        if u != v and compressed[u] >= 0 and compressed[v] >= 0
    }
    got = [(a, int(b)) for a in range(len(movable)) for b in nbrs[ptr[a] : ptr[a + 1]]]
    assert got == sorted(expected)
    colour = np.empty(model.n_nodes, dtype=int)
    colour[:] = -1
    for k, g in enumerate(groups):
        colour[movable[g]] = k
    conn = model.blocks["hex8"].conn
    for row in conn:
        c = colour[row][colour[row] >= 0]
        assert len(c) == len(set(c.tolist()))
    assert len(groups) <= 27  # a structured hex mesh needs 8; the greedy rounds stay close


@pytest.mark.parametrize("etype", SMOOTHED_TYPES)
def test_smoother_measure_equals_reported_corner_jacobian(etype, reference_shape):
    """The smoother's fast corner Jacobian is the one the quality report shows."""
    from kneegui.meshopt import corner_quality
    from kneegui.model import ElementBlock

    shape = reference_shape(etype)
    n, k = 3000, len(shape)
    pts = np.tile(shape, (n, 1)) + np.random.default_rng(9).uniform(-0.3, 0.3, (n * k, 3))
    conn = np.arange(n * k).reshape(n, k)
    reported = compute_quality(pts, {etype: ElementBlock(etype, np.arange(n), np.zeros(n), conn)})
    jac, scaled = corner_quality(pts[conn], etype)
    np.testing.assert_allclose(jac, reported[etype].jacobian_corner, atol=1e-12)
    assert np.all((scaled > 0) == (jac > 0))
    assert np.any(jac <= 0) or etype == "tet4"


@pytest.mark.parametrize("kind", ["hex8", "wedge6", "tet4"])
def test_batched_local_problem_is_the_exact_affine_map(kind, block_model):
    """d0 + G . delta equals the corner determinants recomputed with the node moved."""
    from kneegui.meshopt.batched import build_problems, objective
    from kneegui.meshopt.smoother import CORNER_TRIPLES
    from kneegui.quality.kernels import corner_determinants

    model = block_model(3, 3, 3, skin=False)
    if kind != "hex8":
        model = _split_model(block_model(3, 3, 3), kind)
    rng = np.random.default_rng(4)
    coords = model.coords + rng.uniform(-0.2, 0.2, model.coords.shape)
    node = int(np.flatnonzero(np.all(model.coords == (1, 1, 2), axis=1))[0])
    block = model.blocks[kind]
    conn = block.conn[np.any(block.conn == node, axis=1)]
    n_el = len(conn)
    problem = build_problems(
        np.array([node]), coords, [(kind, np.zeros(n_el, int), np.arange(n_el), conn)],
        CORNER_TRIPLES, np.eye(3)[None], np.array([0.0]), np.array([0.0]), np.array([5.0]),
        np.array([n_el]),
    )  # fmt: skip
    delta = np.array([0.13, -0.07, 0.05])
    moved = coords.copy()
    moved[node] += delta
    exact = corner_determinants(moved[conn], kind)
    predicted = problem.d0[0] + problem.grad[0] @ delta
    np.testing.assert_allclose(predicted[:, : exact.shape[1]], exact, rtol=1e-10, atol=1e-12)
    assert objective(problem, np.zeros((1, 2, 3))).shape == (1, 2)


def test_report_counts_inverted_elements_out_of_reach(block_model):
    # a flesh layer one element thick: every node is on the bone interface or the surface
    thin = block_model(5, 5, 2, bone_layers=1, skin=False)
    c = thin.coords.copy()
    c[np.all(c == (2, 2, 2), axis=1)] = (2.0, 2.0, 0.8)  # pushed through the layer
    posed = thin.with_coords(c)
    q = compute_quality(posed.coords, posed.blocks)
    free = smoothing_free_nodes(posed, [2], [1], degraded_elements(q))
    assert not free.any() and q.n_inverted > 0
    new, report = smooth_mesh(posed, None, free)
    assert np.array_equal(new, posed.coords)
    assert report.inverted_out_of_reach == q.n_inverted
    assert report.to_dict()["inverted_out_of_reach"] == q.n_inverted
    # in a thick block the same push is repaired and nothing is out of reach
    thick = block_model(5, 5, 4, bone_layers=1, skin=False)
    c = thick.coords.copy()
    c[np.all(c == (2, 2, 3), axis=1)] = (2.0, 2.0, 1.8)
    posed = thick.with_coords(c)
    q = compute_quality(posed.coords, posed.blocks)
    new, report = smooth_mesh(posed, None, smoothing_free_nodes(posed, [2], [1]))
    assert q.n_inverted > 0 and report.inverted_out_of_reach == 0
    assert compute_quality(new, posed.blocks).n_inverted == 0


def test_position_guard_is_obeyed(block_model):
    model = block_model(7, 7, 7, bone_layers=1)
    posed = _jiggle(model, 0)
    q_before = compute_quality(posed.coords, posed.blocks)
    free = smoothing_free_nodes(posed, [2], [1], degraded_elements(q_before), rings=1)
    # a wall: no node may go to x > its position now + 0.05 (each move is checked)
    start = posed.coords.copy()
    calls = []

    def guard(nodes, coords):
        calls.append(len(nodes))
        return coords[nodes, 0] <= start[nodes, 0] + 0.05

    free_run, _ = smooth_mesh(posed, None, free)
    assert (free_run[:, 0] > start[:, 0] + 0.05).any()  # unguarded, some node crosses it
    new, report = smooth_mesh(posed, None, free, position_guard=guard)
    assert calls and report.moved_nodes > 0
    assert (new[:, 0] <= start[:, 0] + 0.05 + 1e-12).all()
    assert compute_quality(new, posed.blocks).worst_jacobian() >= q_before.worst_jacobian()
    # a guard that refuses everything leaves the mesh as it was
    frozen, report = smooth_mesh(
        posed, None, free, position_guard=lambda n, c: np.zeros(len(n), bool)
    )
    np.testing.assert_array_equal(frozen, posed.coords)
    assert report.moved_nodes == 0


@pytest.mark.parametrize(
    "bad",
    [
        {"max_sweeps": -1},
        {"passes": 0},
        {"relaxation": ()},
        {"relaxation": (1.0, 1.5)},
        {"aspect_limit": 0.5},
        {"warpage_limit": 0.0},
    ],
)
def test_smooth_options_are_validated_where_they_are_made(bad):
    with pytest.raises(ValueError, match="SmoothOptions"):
        SmoothOptions(**bad)


@pytest.mark.parametrize("soft_interfaces", [False, True])
def test_free_and_sliding_nodes_read_only_the_elements_around_them(soft_interfaces):
    """Which nodes the smoother may move depends on the elements around each candidate (the
    parts sharing it, the boundary faces through it): worked out from those alone, as a
    whole-body model needs, it is the same selection as from every element of the model."""
    from kneegui import demo
    from kneegui.meshopt.free_nodes import MOVABLE_SOLID_TYPES, _base_candidates
    from kneegui.meshopt.nodes import node_part_count
    from kneegui.setup import load_setup

    leg = demo.generate_demo_leg(2000)
    model, setup = leg.model, load_setup(leg.setup, leg.model)
    soft = setup.parts_of("flesh", "ligament", "meniscus", "tendon", "capsule")
    skin, fixed = setup.parts_of("skin"), setup.parts_of("femur", "tibia", "patella")
    rng = np.random.default_rng(11)
    degraded = {e: rng.random(len(b)) < 0.02 for e, b in model.blocks.items()}
    free = smoothing_free_nodes(model, soft, fixed, degraded, 2, soft_interfaces)
    sliding = smoothing_sliding_nodes(model, soft, skin, fixed, degraded, 2)
    # the whole-model reference
    near, soft_ids = _base_candidates(model, soft, degraded, 2)
    if soft_interfaces:
        other = np.zeros(model.n_nodes, dtype=bool)
        for etype, block in model.blocks.items():
            outside = ~np.isin(block.part_ids, soft_ids) | (etype not in MOVABLE_SOLID_TYPES)
            other[block.conn[outside].reshape(-1)] = True
        expected = near & ~other
    else:
        expected = near & (node_part_count(model.blocks, model.n_nodes) == 1)
    expected &= ~boundary_node_mask(model.n_nodes, model.blocks)
    expected[model.part_node_indices(fixed)] = False
    assert expected.sum() > 50
    np.testing.assert_array_equal(free, expected)
    allowed = list(set(soft_ids.tolist()) | set(skin))
    other = np.zeros(model.n_nodes, dtype=bool)
    for block in model.blocks.values():
        other[block.conn[~np.isin(block.part_ids, allowed)].reshape(-1)] = True
    expected_sliding = near & ~other & boundary_node_mask(model.n_nodes, model.blocks)
    expected_sliding[model.part_node_indices(fixed)] = False
    assert expected_sliding.sum() > 10
    np.testing.assert_array_equal(sliding, expected_sliding)


def test_the_count_of_inverted_elements_out_of_reach_asks_to_cancel_per_chunk():
    """It measures every element the smoothing cannot move: seconds on a whole-body model."""
    from kneegui.meshopt.smoother import _inverted_out_of_reach
    from kneegui.model import ElementBlock

    cube = np.array(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
        dtype=float,
    )
    coords = np.concatenate([cube, cube + np.array([2.0, 0.0, 0.0])])
    coords[8:12, 2] = 2.0  # the second hex's bottom face above its top: inverted
    blocks = {"hex8": ElementBlock("hex8", [1, 2], [1, 1], np.arange(16).reshape(2, 8))}
    movable = np.zeros(16, dtype=bool)
    asked = []
    assert _inverted_out_of_reach(blocks, coords, movable, lambda: asked.append(1)) == 1
    assert len(asked) == 1  # one chunk
    movable[8] = True  # the inverted one can move: not counted
    assert _inverted_out_of_reach(blocks, coords, movable) == 0

    def stop() -> None:
        raise Cancelled("smoothing cancelled")

    with pytest.raises(Cancelled):
        _inverted_out_of_reach(blocks, coords, np.zeros(16, dtype=bool), stop)


def test_the_neighbourhood_build_and_each_colour_of_a_sweep_ask_to_cancel(block_model):
    from kneegui.meshopt.smoother import _build_neighbourhood

    model = block_model(6, 6, 6)
    movable = np.flatnonzero(smoothing_free_nodes(model, [2], [1]))
    asked = []
    nb = _build_neighbourhood(model.blocks, movable, model.n_nodes, lambda: asked.append(1))
    plain = _build_neighbourhood(model.blocks, movable, model.n_nodes)
    assert len(asked) >= 3  # each element type, the handles' sort, the edge neighbours
    for name in ("offset", "node_ptr", "node_handles", "nbr_ptr", "nbr"):
        np.testing.assert_array_equal(getattr(nb, name), getattr(plain, name))

    twisted = _swirl(block_model(8, 8, 8), 2.0, 2.5)
    free = smoothing_free_nodes(twisted, [2], [1])
    polls = []
    out, report = smooth_mesh(twisted, None, free, cancel=lambda: bool(polls.append(1)))
    np.testing.assert_array_equal(out, smooth_mesh(twisted, None, free)[0])
    assert len(polls) > 4 * report.stage1_sweeps  # several colours per Laplacian sweep
    for stop_at in sorted({1, 3, len(polls) // 3, len(polls) // 2, len(polls)}):
        calls = []

        def cancel(calls=calls, stop_at=stop_at) -> bool:
            calls.append(1)
            return len(calls) >= stop_at

        with pytest.raises(Cancelled):
            smooth_mesh(twisted, None, free, cancel=cancel)
        assert len(calls) == stop_at
