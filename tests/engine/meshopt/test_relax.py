"""The elastic relaxation on small synthetic blocks: derivatives, untangling, fixed nodes."""

from __future__ import annotations

import numpy as np
import pytest

import kneegui.reposition.relax as relax_module
from kneegui.errors import Cancelled, GeometryError
from kneegui.geometry.transforms import RigidTransform
from kneegui.meshopt.lbfgs import minimize_lbfgs, round_monitor
from kneegui.meshopt.quality_optimiser import (
    QualityOptimisationReport,
    QualityOptions,
    optimise_quality,
    quality_aims,
)
from kneegui.model import ElementBlock
from kneegui.quality import compute_quality
from kneegui.quality.kernels import corner_determinants
from kneegui.reposition.relax import (
    ElasticRelaxation,
    RelaxOptions,
    shell_face_tetrahedra,
)
from kneegui.topology import corner_tetrahedra


def hex_block(n: int = 4, size: float = 10.0):
    """An n x n x n block of hexes with quad shells on its top face."""
    ticks = np.arange(n + 1) * size
    grid = np.stack(np.meshgrid(ticks, ticks, ticks, indexing="ij"), axis=-1).reshape(-1, 3)

    def node(i, j, k):
        return (i * (n + 1) + j) * (n + 1) + k

    hexes, quads = [], []
    for i in range(n):
        for j in range(n):
            for k in range(n):
                hexes.append(
                    [
                        node(i, j, k),
                        node(i + 1, j, k),
                        node(i + 1, j + 1, k),
                        node(i, j + 1, k),
                        node(i, j, k + 1),
                        node(i + 1, j, k + 1),
                        node(i + 1, j + 1, k + 1),
                        node(i, j + 1, k + 1),
                    ]
                )
            quads.append(
                [node(i, j, n), node(i + 1, j, n), node(i + 1, j + 1, n), node(i, j + 1, n)]
            )
    hexes, quads = np.array(hexes), np.array(quads)
    blocks = {
        "hex8": ElementBlock("hex8", np.arange(len(hexes)) + 1, np.ones(len(hexes), int), hexes),
        "quad4": ElementBlock("quad4", np.arange(len(quads)) + 1, np.full(len(quads), 2), quads),
    }
    boundary = np.flatnonzero(((grid == 0) | (grid == n * size)).any(axis=1))
    return grid.astype(float), blocks, boundary, node


def relaxation(coords, blocks, free, **options):
    solids = {"hex8": np.ones(len(blocks["hex8"].ids), bool)}
    shells = {"quad4": np.ones(len(blocks["quad4"].ids), bool)}
    tets = corner_tetrahedra(blocks, solids)
    face_tets, virtual = shell_face_tetrahedra(blocks, shells, solids, len(coords))
    return ElasticRelaxation(
        coords,
        np.concatenate([tets, face_tets]),
        free,
        options=RelaxOptions(**options),
        virtual=virtual,
        quads=blocks["quad4"].conn,
    )


def test_every_top_shell_gets_four_face_tetrahedra():
    coords, blocks, _, _ = hex_block(3)
    solids = {"hex8": np.ones(27, bool)}
    tets, virtual = shell_face_tetrahedra(blocks, {"quad4": np.ones(9, bool)}, solids, len(coords))
    assert tets.shape == (36, 4) and virtual.shape == (9, len(coords))
    np.testing.assert_allclose(np.asarray(virtual.sum(axis=1)).ravel(), 1.0)


@pytest.mark.parametrize("eps", [0.5, 0.05])
@pytest.mark.parametrize("own_weights", [False, True], ids=["theta", "corner-theta"])
def test_gradient_matches_finite_differences_and_the_numpy_reference(eps, own_weights):
    coords, blocks, boundary, _ = hex_block(3)
    free = np.setdiff1d(np.arange(len(coords)), boundary)
    free = np.union1d(free, np.flatnonzero(coords[:, 2] == 30.0))  # top face too (shells)
    rx = relaxation(coords, blocks, free)
    rng = np.random.default_rng(3)
    x = coords + rng.normal(scale=1.5, size=coords.shape)
    sub = rx.energy(rx.free)
    xl = x[sub.nodes]
    theta = rng.uniform(0.2, 0.95, len(sub.tets)) if own_weights else None
    energy, grad, det = sub.energy(xl, eps, theta)
    ref_energy, ref_grad, ref_det = sub.energy_numpy(xl, eps, theta)
    if own_weights:  # each corner's own weight, not the energy's
        assert energy != pytest.approx(sub.energy(xl, eps)[0], rel=1e-3)
    assert energy == pytest.approx(ref_energy, rel=1e-12)
    np.testing.assert_allclose(grad, ref_grad, rtol=1e-9, atol=1e-9 * np.abs(grad).max())
    np.testing.assert_allclose(det, ref_det, rtol=1e-12, atol=1e-12)
    # the reference's edge-major rest matrices and gradient scatter are made when it runs:
    # kept on every energy, they were a fifth of the 1M demo's peak memory
    assert "g" not in vars(sub) and "scatter" not in vars(sub)
    h = 1e-6
    for i in rng.choice(sub.free, 6, replace=False):
        for k in range(3):
            up, down = xl.copy(), xl.copy()
            up[i, k] += h
            down[i, k] -= h
            fd = (sub.energy(up, eps, theta)[0] - sub.energy(down, eps, theta)[0]) / (2 * h)
            assert grad[i, k] == pytest.approx(fd, rel=1e-4, abs=1e-5 * np.abs(grad).max())


def test_corner_weights_must_be_one_per_corner():
    coords, blocks, boundary, _ = hex_block(2)
    free = np.setdiff1d(np.arange(len(coords)), boundary)
    sub = relaxation(coords, blocks, free).energy(free)
    with pytest.raises(ValueError, match="corner_theta has 3 values"):
        sub.energy(coords[sub.nodes], 1e-3, np.full(3, 0.5))


def test_healthy_corners_keep_their_volume_through_a_bend():
    """The top face of a block hinged through 60 deg about one of its edges (the bottom
    fixed, the sides free), the inside left where it was: relaxed as a compressible material
    (every corner at theta = 0.5, the default) the elements end 37 % off their volume on
    average (measured 0.368); with the healthy corners' volume weight 0.95, 6 % (0.063)."""
    coords, blocks, _, _ = hex_block(4)
    z = coords[:, 2]
    free = np.flatnonzero((z > 0) & (z < 40))
    top = z == 40
    c, s = np.cos(np.radians(60)), np.sin(np.radians(60))
    y, h = coords[top, 1], coords[top, 2] - 40
    posed = coords.copy()
    posed[top, 1], posed[top, 2] = c * y - s * h, 40 + s * y + c * h
    rest = corner_determinants(coords[blocks["hex8"].conn], "hex8").mean(axis=1)

    def mean_volume_change(**options) -> float:
        out, report = relaxation(coords, blocks, free, **options).relax(posed)
        assert report.free_nodes > 0 and compute_quality(out, blocks).n_inverted == 0
        volume = corner_determinants(out[blocks["hex8"].conn], "hex8").mean(axis=1)
        return float(np.mean(np.abs(volume / rest - 1)))

    compressible, kept = mean_volume_change(), mean_volume_change(healthy_volume_weight=0.95)
    assert compressible > 0.2 and kept < 0.4 * compressible


def test_corners_weigh_volume_by_their_health_when_a_round_starts():
    coords, blocks, boundary, _ = hex_block(2)
    free = np.setdiff1d(np.arange(len(coords)), boundary)
    rx = relaxation(coords, blocks, free)
    sub = rx.energy(rx.free)
    xl = coords[sub.nodes].copy()
    centre = np.searchsorted(sub.nodes, free[0])
    xl[centre] += [9.0, 9.0, 9.0]  # squashes the corners at the far side of the centre node
    det = sub.energy(xl, 1e-3)[2][: len(sub.tets)]
    opt = RelaxOptions(healthy_volume_weight=0.9, healthy_det=(0.0, 1.0))
    weights = ElasticRelaxation._corner_volume_weights(sub, xl, 1e-3, opt)
    assert (det <= 0.0).any() and (det >= 1.0).any() and ((det > 0.0) & (det < 1.0)).any()
    np.testing.assert_allclose(weights, 0.5 + 0.4 * np.clip(det, 0, 1))
    assert set(weights[det <= 0.0]) == {0.5} and set(weights[det >= 1.0]) == {0.9}
    assert ElasticRelaxation._corner_volume_weights(sub, xl, 1e-3, RelaxOptions()) is None
    with pytest.raises(ValueError, match="healthy_volume_weight"):
        RelaxOptions(healthy_volume_weight=1.5)
    with pytest.raises(ValueError, match="healthy_det"):
        RelaxOptions(healthy_det=(0.6, 0.3))


def test_untangles_a_folded_block_and_keeps_fixed_nodes():
    coords, blocks, boundary, node = hex_block(4)
    free = np.setdiff1d(np.arange(len(coords)), boundary)
    tangled = coords.copy()
    centre = node(2, 2, 2)
    tangled[centre] += [14.0, 3.0, -2.0]  # through the neighbouring node's cells
    assert compute_quality(tangled, blocks).n_inverted > 0
    rx = relaxation(coords, blocks, free)
    relaxed, report = rx.relax(tangled)
    assert report.inverted_corners_before > 0 and report.inverted_corners_after == 0
    assert compute_quality(relaxed, blocks).n_inverted == 0
    np.testing.assert_array_equal(relaxed[boundary], tangled[boundary])
    again, _ = rx.relax(tangled)
    np.testing.assert_array_equal(again, relaxed)  # deterministic
    assert np.array_equal(tangled[centre], coords[centre] + [14.0, 3.0, -2.0])  # input untouched


def test_folded_skin_shells_are_unfolded():
    coords, blocks, boundary, node = hex_block(4)
    top = np.flatnonzero(coords[:, 2] == 40.0)
    inner_top = top[~((coords[top, :2] == 0) | (coords[top, :2] == 40)).any(axis=1)]
    free = np.union1d(np.setdiff1d(np.arange(len(coords)), boundary), inner_top)
    tangled = coords.copy()
    tangled[node(2, 2, 4)] += [12.0, 0.0, 0.0]  # the skin node slides over its neighbour
    before = corner_determinants(tangled[blocks["quad4"].conn], "quad4")
    assert (before <= 0).any()
    relaxed, _ = relaxation(coords, blocks, free).relax(tangled)
    assert (corner_determinants(relaxed[blocks["quad4"].conn], "quad4") > 0).all()
    assert compute_quality(relaxed, blocks).n_inverted == 0


def test_a_pose_with_nothing_degraded_is_returned_unchanged():
    coords, blocks, boundary, _ = hex_block(3)
    free = np.setdiff1d(np.arange(len(coords)), boundary)
    rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    moved = coords @ rotation.T + 5.0  # rigid: every corner keeps its shape
    relaxed, report = relaxation(coords, blocks, free).relax(moved)
    assert report.free_nodes == 0
    np.testing.assert_array_equal(relaxed, moved)


def test_lbfgs_minimises_a_badly_scaled_quadratic_and_stops_at_a_barrier():
    scale = np.array([1.0, 100.0, 1e-2])

    def quadratic(x):
        return float(np.sum(scale * (x - 1.0) ** 2)), 2 * scale * (x - 1.0)

    result = minimize_lbfgs(quadratic, np.zeros(3), 200, ftol=1e-15)
    np.testing.assert_allclose(result.x, 1.0, atol=1e-5)

    def barrier(x):  # infinite for x <= 0: the line search must stay on the right side
        if x[0] <= 0:
            return float("inf"), np.zeros(1)
        return float(x[0] - np.log(x[0])), np.array([1.0 - 1.0 / x[0]])

    result = minimize_lbfgs(barrier, np.array([5.0]), 100)
    assert result.x[0] == pytest.approx(1.0, abs=1e-4)


def test_lbfgs_calls_its_hook_after_every_iteration_without_changing_the_iterates():
    evaluations = []

    def rosenbrock(x):  # not solved in 30 iterations from the origin
        evaluations.append(1)
        a, b = x[:-1], x[1:]
        f = float(np.sum(100.0 * (b - a * a) ** 2 + (1.0 - a) ** 2))
        g = np.zeros_like(x)
        g[:-1] = -400.0 * a * (b - a * a) - 2.0 * (1.0 - a)
        g[1:] += 200.0 * (b - a * a)
        return f, g

    plain = minimize_lbfgs(rosenbrock, np.zeros(8), 30, ftol=0.0)
    assert plain.nit == 30
    calls = []
    hooked = minimize_lbfgs(
        rosenbrock, np.zeros(8), 30, ftol=0.0, each_iteration=lambda *a: calls.append(a)
    )
    np.testing.assert_array_equal(hooked.x, plain.x)
    assert calls == [(k, 30) for k in range(1, 31)]

    def stop_after_five(done: int, limit: int) -> None:
        if done == 5:
            raise Cancelled("stopped")

    evaluations.clear()
    with pytest.raises(Cancelled):
        minimize_lbfgs(rosenbrock, np.zeros(8), 30, ftol=0.0, each_iteration=stop_after_five)
    assert len(evaluations) < plain.nfev  # it stopped mid-run, not at the end


def test_round_monitor_cancels_and_throttles_its_progress(monkeypatch):
    import kneegui.meshopt.lbfgs as lbfgs

    clock = iter([0.0, 0.1, 0.3, 0.4, 0.7])
    monkeypatch.setattr(lbfgs.time, "perf_counter", lambda: next(clock))
    reports, stop = [], []
    monitor = round_monitor(
        lambda: bool(stop), lambda f, m: reports.append((f, m)), lambda d: 0.5 * d, "x", "gone"
    )
    for done in (1, 2, 3, 4):  # at 0.1, 0.3, 0.4 and 0.7 s after the start
        monitor(done, 10)
    # reported at 0.3 and 0.7 s, a quarter second or more apart
    assert [m for _, m in reports] == ["x", "x"]
    assert [f for f, _ in reports] == pytest.approx([0.1, 0.2])
    stop.append(1)
    with pytest.raises(Cancelled, match="gone"):
        monitor(5, 10)


def test_quality_optimisation_brings_the_region_within_its_aims():
    """After the energy has untangled the region, every element around the free nodes is
    brought to its aim (its initial corner Jacobian, capped at 0.6), the boundary untouched."""
    coords, blocks, boundary, node = hex_block(4)
    free = np.setdiff1d(np.arange(len(coords)), boundary)
    sheared = coords.copy()
    sheared[node(2, 2, 2)] += [6.0, 5.0, 0.0]
    sheared[node(1, 2, 2)] += [3.0, -2.0, 1.0]
    short = {"max_rounds": 1, "iterations_per_round": 1, "seed_shape": 1.05}
    plain, plain_report = relaxation(coords, blocks, free, **short).relax(sheared)
    rx = relaxation(coords, blocks, free, **short)
    rx.blocks = blocks
    rx.aims = quality_aims(compute_quality(coords, blocks), blocks)
    optimised, report = rx.relax(sheared)
    assert plain_report.quality is None and report.quality is not None
    worst_plain = compute_quality(plain, blocks).worst_jacobian()
    worst = compute_quality(optimised, blocks).worst_jacobian()
    assert worst_plain < 0.5 and worst >= 0.6 - 0.02
    assert report.quality.worst_after == pytest.approx(worst)
    assert report.to_dict()["quality"]["below_aim_after"] == 0
    np.testing.assert_array_equal(optimised[boundary], sheared[boundary])


_LBFGS_RUN = """
import hashlib
import numpy as np
from kneegui.meshopt.lbfgs import minimize_lbfgs

rng = np.random.default_rng(3)
n = 120_000
scale = 10.0 ** rng.uniform(-2, 2, n)
target = rng.normal(size=n)

def fun(x):
    r = scale * (x - target)
    return float(np.sum(np.log(np.cosh(r)))), scale * np.tanh(r)

x = minimize_lbfgs(fun, np.zeros(n), 40).x
print(hashlib.sha1(x.tobytes()).hexdigest())
"""


def test_lbfgs_result_does_not_depend_on_the_thread_count():
    # BLAS splits long dot products over threads and sums the parts in another order; the
    # relaxation then took other paths on machines with other core counts. The L-BFGS vector
    # sums run on numba's threads in fixed chunks: one thread or three, the same bits.
    import os
    import subprocess
    import sys

    digests = set()
    for threads in ("1", "2", "3"):
        env = dict(
            os.environ,
            OPENBLAS_NUM_THREADS=threads,
            OMP_NUM_THREADS=threads,
            NUMBA_NUM_THREADS=threads,
        )
        run = subprocess.run(
            [sys.executable, "-c", _LBFGS_RUN], env=env, capture_output=True, text=True, check=True
        )
        digests.add(run.stdout.strip())
    assert len(digests) == 1


def test_sliding_nodes_move_only_in_their_surface_plane():
    coords, blocks, boundary, node = hex_block(4)
    n = 4
    top = np.flatnonzero(np.isclose(coords[:, 2], n * 10.0))
    side = np.flatnonzero(((coords[:, :2] == 0) | (coords[:, :2] == n * 10.0)).any(axis=1))
    sliding = np.setdiff1d(top, side)  # the top face's inner nodes
    free = np.union1d(np.setdiff1d(np.arange(len(coords)), boundary), sliding)
    moved = coords.copy()
    moved[node(2, 2, 3)] += [6.0, 5.0, 0.0]  # a poor interior node pulls on the top face
    moved[node(2, 2, 4)] += [4.0, -3.0, 0.0]  # and one top node slid off its place
    common = {"rings": 4, "seed_shape": 1.01}
    solids = {"hex8": np.ones(len(blocks["hex8"].ids), bool)}
    slid, report = ElasticRelaxation(
        coords,
        corner_tetrahedra(blocks, solids),
        free,
        options=RelaxOptions(**common, skin_outward=False),
        quads=blocks["quad4"].conn,  # the surface the nodes slide on
        sliding=sliding,
    ).relax(moved)
    unconstrained = relaxation(coords, blocks, free, **common).relax(moved)[0]
    assert report.free_nodes > 0
    np.testing.assert_allclose(slid[sliding, 2], moved[sliding, 2], atol=1e-9)
    assert np.abs(slid[sliding, :2] - moved[sliding, :2]).max() > 0.5  # they did slide
    assert np.abs(unconstrained[sliding, 2] - moved[sliding, 2]).max() > 1e-4  # free ones leave


def test_corners_pinned_between_two_bones_are_left_out():
    """A corner with one free node and the others on two rigid segments is shaped by the
    bones' relative motion, not by the energy; a corner on one segment, or with two free
    nodes, stays in."""
    rest = np.array(
        [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [0, -1, 0]], dtype=float
    )
    tets = np.array([[0, 1, 2, 3], [4, 1, 2, 3], [0, 1, 5, 4]])
    segment_of = np.array([0, 0, 1, 1, -1, 0])  # nodes 0, 5 on bone 0; 2, 3 on bone 1
    for tet in tets:
        assert np.linalg.det(rest[tet[1:]] - rest[tet[0]]) != 0
    relax = ElasticRelaxation(rest, tets, np.array([4]), segment_of=segment_of)
    # corner 0 has no free node (dropped anyway), corner 1 one free node over bones 0 and 1
    # (pinned), corner 2 one free node over bone 0 only (kept)
    assert relax.pinned_corners == 1
    assert relax.tets.tolist() == [[0, 1, 5, 4]]


def test_a_pinned_corner_gets_a_plane_on_its_free_node():
    """The pinned corner's determinant is linear in its free node: on its plane it is
    PINNED_MARGIN times the rest value, beyond the plane more, before it less (inverted where
    the bones turned its fixed nodes through it); no plane where the node may not move."""
    rest = np.array(
        [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [0, -1, 0]], dtype=float
    )
    tets = np.array([[0, 1, 2, 3], [4, 1, 2, 3], [0, 1, 5, 4]])
    segment_of = np.array([0, 0, 1, 1, -1, 0])
    relax = ElasticRelaxation(rest, tets, np.array([4]), segment_of=segment_of)
    rest_det = np.linalg.det(rest[[1, 2, 3]] - rest[4])  # -2: oriented the other way round
    posed = rest.copy()
    posed[[2, 3]] += [1.5, 1.5, 1.5]  # bone 1 moved: the corner at node 4 inverted
    assert np.linalg.det(posed[[1, 2, 3]] - posed[4]) * np.sign(rest_det) < 0
    movable = np.zeros(len(rest), dtype=bool)
    movable[4] = True
    nodes, normals, offsets = relax._pinned_planes(posed, movable)
    assert nodes.tolist() == [4]
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    on_plane = posed[4] + (offsets[0] - normals[0] @ posed[4]) * normals[0]
    for step, sign in ((0.0, 0), (0.2, 1), (-0.2, -1)):
        moved = posed.copy()
        moved[4] = on_plane + step * normals[0]
        det = np.linalg.det(moved[[1, 2, 3]] - moved[4]) * np.sign(rest_det)
        expected = relax_module.PINNED_MARGIN * abs(rest_det)
        assert np.sign(round(det - expected, 9)) == sign
    assert len(relax._pinned_planes(posed, np.zeros(len(rest), dtype=bool))[0]) == 0


def test_edge_adjacency_asks_cancel_between_its_two_ways():
    a, b = np.array([0, 1, 2]), np.array([1, 2, 3])
    asked = []
    adj = relax_module.edge_adjacency(a, b, 4, cancel=lambda: asked.append(1) or False)
    assert asked == [1]
    np.testing.assert_array_equal(adj.toarray(), relax_module.edge_adjacency(a, b, 4).toarray())
    assert adj.toarray().sum() == 6
    with pytest.raises(Cancelled):
        relax_module.edge_adjacency(a, b, 4, cancel=lambda: True)


def test_edge_adjacency_sorts_in_pieces_and_asks_between_them(monkeypatch):
    """A whole-body region's pairs are sorted a value range at a time, with a question to
    cancel between ranges (the 1.76M demo: 1.8 s in one sort); the same matrix."""
    from kneegui.reposition import rigid_blend

    rng = np.random.default_rng(8)
    a, b = rng.integers(0, 3000, 40_000), rng.integers(0, 3000, 40_000)
    whole = relax_module.edge_adjacency(a, b, 2500).toarray()
    monkeypatch.setattr(rigid_blend, "EDGE_SORT_PIECE", 4000)
    asked = []
    pieces = relax_module.edge_adjacency(a, b, 2500, cancel=lambda: asked.append(1) or False)
    np.testing.assert_array_equal(pieces.toarray(), whole)
    assert len(asked) > 10


def test_corners_touching_nodes_are_the_same_sorted_or_marked():
    """:meth:`NodeRows.touching` marks many corners in a mask instead of sorting them (1 s of
    the 1M demo's untangling set-up); both ways give ``np.unique`` of the corners' rows."""
    rng = np.random.default_rng(3)
    n = 500
    tets = rng.integers(0, n + 40, size=(4000, 4))  # nodes >= n: virtual
    rows = relax_module.NodeRows(tets, n)
    for size in (3, 50, 400):  # few corners (sorted), many (marked)
        nodes = np.sort(rng.choice(n, size, replace=False))
        expected = np.flatnonzero(np.isin(tets, nodes).any(axis=1))
        got = rows.touching(nodes)
        assert got.dtype == np.int64
        np.testing.assert_array_equal(got, expected)
    assert len(rows.touching(np.sort(rng.choice(n, 400, replace=False)))) > (
        rows.n_rows // relax_module.TOUCHING_MASK_SHARE
    )


def test_free_midside_nodes_of_tet10_follow_their_edge():
    """The energy sees a 10-node tet's corner tetrahedron; a free mid-side node sits at the
    middle of its edge's corners plus its offset from there at rest, so a curved edge keeps its
    bow and a straight one stays straight whatever the mapping did to the mid-side node (the
    coarse 10-node demo at 90 deg kept mid-side nodes 1.4 edge lengths off their edges)."""
    corners = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    edges = [(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)]
    mids = np.array([(corners[a] + corners[b]) / 2 for a, b in edges])
    mids[0] += [0, -1, 0]  # a bowed edge
    rest = np.vstack([corners, mids])
    block = ElementBlock("tet10", np.array([1]), np.array([1]), np.arange(10)[None, :])
    free = np.array([3, 7, 8, 9])  # the apex and the mid-side nodes of its edges
    relax = ElasticRelaxation(
        rest, corner_tetrahedra({"tet10": block}), free, blocks={"tet10": block}
    )
    moved = rest.copy()
    moved[3] += [1.0, 2.0, 3.0]
    out = relax.carry_midside(rest, moved)
    np.testing.assert_allclose(out[7], rest[7] + [0.5, 1.0, 1.5])  # edge 0-3
    np.testing.assert_allclose(out[4], rest[4])  # edge 0-1 not free: stays
    np.testing.assert_allclose(out[:4], moved[:4])
    mapped = rest.copy()
    mapped[7] += [3.0, 0.0, 0.0]  # the mapping put the mid-side node off its straight edge
    out = relax.carry_midside(mapped, moved)
    np.testing.assert_allclose(out[7], (moved[0] + moved[3]) / 2)


def test_midside_nodes_inside_a_bone_go_back_to_its_surface(box_surface):
    """Contact holds a 10-node tet's corners out of a bone, but the straight edge between two
    corners lying on a convex bone cuts into it: a free mid-side node inside the posed bone is
    put back on its surface; the others and the corners stay."""
    corners = np.array([[0.0, -1, 0], [0.0, 1, 0], [1, 0, 0], [0.5, 0, 1]])
    edges = [(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)]
    rest = np.vstack([corners, [(corners[a] + corners[b]) / 2 for a, b in edges]])
    block = ElementBlock("tet10", np.array([1]), np.array([1]), np.arange(10)[None, :])
    bone = box_surface((-10.0, -10.0, -10.0), (0.0, 10.0, 10.0))  # its face x = 0 outward
    relax = ElasticRelaxation(
        rest,
        corner_tetrahedra({"tet10": block}),
        np.arange(10),
        bones={"femur": bone},
        blocks={"tet10": block},
    )
    posed = rest.copy()
    posed[4] = [-0.7, 0.1, 0.2]  # edge 0-1's mid-side node 0.7 deep in the bone
    posed[5] += [0.1, 0.0, 0.0]
    out = relax.midside_out_of_bones(posed, {"femur": RigidTransform.identity()})
    np.testing.assert_allclose(out[4], [0.0, 0.1, 0.2], atol=1e-12)
    np.testing.assert_array_equal(np.delete(out, 4, axis=0), np.delete(posed, 4, axis=0))
    # the bone turned 90 deg about z: its face x = 0 is now y = 0, the bone on y < 0, so a
    # node at y = -0.5 lies inside it and goes to its surface
    turn = RigidTransform.about_axis([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 90.0)
    posed = rest.copy()
    posed[9] = [0.2, -0.5, 0.3]
    out = relax.midside_out_of_bones(posed, {"femur": turn})
    assert turn.inverse().apply(out[9:10])[0, 0] == pytest.approx(0.0, abs=1e-12)


def _skin_block_relaxed(lift: float, flip_quads: bool = False, **options):
    """The 4 x 4 x 4 block, its top face's inner nodes skin, the interior node under the
    middle one held ``lift`` above where it was (2 above the skin, or below the next layer);
    relaxed with ``options``. Returns the block's node function, the skin nodes, the pose, the
    relaxed coordinates, the report and the blocks."""
    coords, blocks, boundary, node = hex_block(4)
    n = 4
    top = np.flatnonzero(np.isclose(coords[:, 2], n * 10.0))
    side = np.flatnonzero(((coords[:, :2] == 0) | (coords[:, :2] == n * 10.0)).any(axis=1))
    sliding = np.setdiff1d(top, side)
    held = node(2, 2, 3)
    free = np.setdiff1d(np.union1d(np.setdiff1d(np.arange(len(coords)), boundary), sliding), held)
    moved = coords.copy()
    moved[held, 2] += lift
    quads = blocks["quad4"].conn
    solids = {"hex8": np.ones(len(blocks["hex8"].ids), bool)}
    relax = ElasticRelaxation(
        coords,
        corner_tetrahedra(blocks, solids),
        free,
        options=RelaxOptions(**options),
        quads=quads[:, ::-1] if flip_quads else quads,
        sliding=sliding,
    )
    relaxed, report = relax.relax(moved)
    return node, sliding, moved, relaxed, report, blocks


#: the held node 2 above the skin (z = 40)
PUSHED_OUT = 12.0


def test_skin_pressed_from_inside_moves_out_without_a_restart():
    """With the skin allowed out of its tangent planes (``skin_outward``, the default), the
    tissue pushed out through it takes the skin node with it in the first attempt: no restart,
    nothing inverted, the skin node above where the pose had it."""
    node, _, moved, relaxed, report, blocks = _skin_block_relaxed(
        PUSHED_OUT, max_rounds=5, restarts=1
    )
    assert report.restarts == 0 and report.sliding_released == 0
    assert report.inverted_corners_after == 0
    assert compute_quality(relaxed, blocks).n_inverted == 0
    assert relaxed[node(2, 2, 4), 2] > moved[node(2, 2, 3), 2]


def test_the_skins_outward_side_does_not_depend_on_how_its_shells_are_numbered():
    """A deck's shells need not face out: the same skin with its quads numbered the other way
    round relaxes to the same coordinates (the outward side is taken from the solids under
    the shells, not from their node order)."""
    kept = _skin_block_relaxed(PUSHED_OUT, max_rounds=5, restarts=1)
    flipped = _skin_block_relaxed(PUSHED_OUT, flip_quads=True, max_rounds=5, restarts=1)
    assert flipped[4].restarts == 0
    np.testing.assert_allclose(flipped[3], kept[3], atol=1e-6)


def test_skin_pulled_from_inside_stays_out_of_its_tangent_planes():
    """Tissue pulled down from under the skin: the skin may not follow it in, neither when it
    slides nor when it may move outwards (the fold the energy would pull into a crease)."""
    outcomes = {}
    for outward in (True, False):
        # below the next layer: its corners inverted
        node, sliding, moved, relaxed, report, _ = _skin_block_relaxed(
            -12.0, skin_outward=outward, restarts=0
        )
        assert report.inverted_corners_after == 0
        outcomes[outward] = relaxed
    coords, blocks, boundary, _ = hex_block(4)
    free = np.setdiff1d(
        np.union1d(np.setdiff1d(np.arange(len(coords)), boundary), sliding), node(2, 2, 3)
    )
    free_skin = relaxation(coords, blocks, free, restarts=0).relax(moved)[0]
    # free, the skin over the pulled node follows it in by millimetres (3.2 measured)
    assert free_skin[node(2, 2, 4), 2] < 40.0 - 1.0
    # held, it stays in its plane, or above it to the penalty's give (0.07 measured)
    assert outcomes[False][sliding, 2].min() > 40.0 - 1e-9
    assert outcomes[True][sliding, 2].min() > 40.0 - 0.3


def test_a_restart_lets_stuck_skin_nodes_off_their_tangent_planes():
    """Tissue pushed out through the skin (here an interior node held above the top face) can
    only be undone by the skin moving out of its tangent plane: where the skin only slides
    (``skin_outward=False``), the skin node that sliding keeps in that plane is freed by the
    first restart, and nothing stays inverted."""
    node, _, moved, relaxed, report, blocks = _skin_block_relaxed(
        PUSHED_OUT, max_rounds=5, restarts=1, skin_outward=False
    )
    pushed = node(2, 2, 3)
    assert report.restarts == 1 and report.sliding_released >= 1
    assert report.inverted_corners_after == 0
    assert compute_quality(relaxed, blocks).n_inverted == 0
    assert relaxed[node(2, 2, 4), 2] > moved[pushed, 2]  # the skin node left its plane
    np.testing.assert_array_equal(relaxed[pushed], moved[pushed])


def _block_with_a_node_held_outside(offset=(30.0, 0.0, 0.0)):
    """A 4 x 4 x 4 hex block whose centre node is held (not free) ``offset`` away, beyond its
    side: the cells around it cannot all be untangled, whatever the free nodes do."""
    coords, blocks, boundary, node = hex_block(4)
    centre = node(2, 2, 2)
    free = np.setdiff1d(np.arange(len(coords)), np.union1d(boundary, [centre]))
    tangled = coords.copy()
    tangled[centre] += offset
    return coords, blocks, free, tangled


def test_corners_that_cannot_be_freed_end_with_the_round_that_left_the_fewest():
    """A restart puts the stuck nodes back where the pose had them; where they cannot come free
    the attempt after it can end worse than an earlier round (the welded demo at 120 deg: 197
    inverted corners in the first attempt, 438 at the end of the last). The relaxation hands on
    the round that left the fewest, and its coordinates."""
    coords, blocks, free, tangled = _block_with_a_node_held_outside((0.0, 30.0, 0.0))
    # every round of every attempt, and no slow pass after them (its own test below)
    rx = relaxation(coords, blocks, free, stall_rounds=100, slow_eps_decrease=0.0)
    relaxed, report = rx.relax(tangled)
    assert report.slow_pass is None
    history = report.history
    assert report.rounds == 60 and report.restarts == 2
    # the kept round is the best (fewest inverted, then the largest smallest det) whichever
    # round that is; here the last attempt ends worse (4 inverted corners against 3), so the
    # best of an earlier attempt is handed on
    best = min(range(len(history)), key=lambda i: (history[i]["inverted"], -history[i]["min_det"]))
    assert report.inverted_corners_after == history[best]["inverted"] < history[-1]["inverted"]
    assert report.kept_attempt in (0, 1)
    sub = rx.energy(rx.free)
    _, _, det = sub.energy(relaxed[sub.nodes], 1e-3)
    assert int(np.sum(det <= 0)) == report.inverted_corners_after


def test_a_slow_pass_around_what_stays_inverted_is_kept_only_when_it_leaves_fewer():
    """When the rounds and restarts leave corners inverted, the nodes around them start again
    from the pose with eps falling more slowly; the result with fewer inverted corners is
    handed on (the leg built at 20 deg, posed to 120 deg: 5 corners left by the fast schedule,
    none by the slow pass), and when the slow pass does no better, the first pass's result to
    the bit."""
    coords, blocks, free, tangled = _block_with_a_node_held_outside((0.0, 30.0, 0.0))
    fast = relaxation(coords, blocks, free, stall_rounds=100, slow_eps_decrease=0.0)
    x_fast, first = fast.relax(tangled)
    rx = relaxation(coords, blocks, free, stall_rounds=100)
    x_slow, report = rx.relax(tangled)
    slow = report.slow_pass
    assert slow is not None and slow["inverted_corners_before"] == first.inverted_corners_after
    assert slow["rounds"] > 0 and 0 < slow["nodes"] <= len(free)
    assert report.rounds == first.rounds  # the first pass's rounds, the slow pass's apart
    sub = rx.energy(rx.free)
    _, _, det = sub.energy(x_slow[sub.nodes], 1e-3)
    assert int(np.sum(det <= 0)) == report.inverted_corners_after
    # the slow schedule frees one more corner here (3 -> 2 inverted), so its result is kept
    assert slow["kept"]
    assert (
        report.inverted_corners_after
        == slow["inverted_corners_after"]
        < first.inverted_corners_after
    )
    # a pass that does worse is not kept: with eps falling slower still (the paper's floor of
    # 0.1) it ends with 6 corners inverted, and the first pass's result is handed on to the bit
    worse = relaxation(coords, blocks, free, stall_rounds=100, slow_eps_decrease=0.1)
    x_worse, report_worse = worse.relax(tangled)
    assert not report_worse.slow_pass["kept"]
    assert report_worse.slow_pass["inverted_corners_after"] > first.inverted_corners_after
    assert report_worse.inverted_corners_after == first.inverted_corners_after
    np.testing.assert_array_equal(x_worse, x_fast)


def test_no_slow_pass_over_more_nodes_than_it_is_for():
    """``slow_pass_nodes``: a slow pass that would move more nodes than that does not run (the
    1M demo's: 15,259 nodes, 55 rounds, never kept); the report says so and the first pass's
    result is handed on to the bit. At its size exactly it runs."""
    coords, blocks, free, tangled = _block_with_a_node_held_outside((0.0, 30.0, 0.0))
    fast = relaxation(coords, blocks, free, stall_rounds=100, slow_eps_decrease=0.0)
    x_fast, first = fast.relax(tangled)
    size = relaxation(coords, blocks, free, stall_rounds=100).relax(tangled)[1].slow_pass["nodes"]
    assert size >= 2 and first.inverted_corners_after > 0
    capped = relaxation(coords, blocks, free, stall_rounds=100, slow_pass_nodes=size - 1)
    x_capped, report = capped.relax(tangled)
    assert report.slow_pass["ran"] is False and report.slow_pass["nodes"] == size
    assert report.slow_pass["rounds"] == 0 and not report.slow_pass["kept"]
    assert report.inverted_corners_after == first.inverted_corners_after
    np.testing.assert_array_equal(x_capped, x_fast)
    at = relaxation(coords, blocks, free, stall_rounds=100, slow_pass_nodes=size)
    assert at.relax(tangled)[1].slow_pass["ran"] is True


def test_relax_options_reject_a_slow_pass_out_of_range():
    with pytest.raises(ValueError, match="slow_eps_decrease"):
        RelaxOptions(slow_eps_decrease=1.0)
    with pytest.raises(ValueError, match="slow_rings"):
        RelaxOptions(slow_rings=0)
    with pytest.raises(ValueError, match="slow_pass_nodes"):
        RelaxOptions(slow_pass_nodes=0)


def test_an_attempt_that_stops_freeing_corners_goes_on_to_the_restart():
    """Rounds that do not lower the attempt's fewest inverted corners for ``stall_rounds`` in a
    row end it, and the restarts still do their work: fewer rounds (25 against 60 with the
    pinned kernels), fewer corners inverted than the first pass left (3 against 8)."""
    coords, blocks, free, tangled = _block_with_a_node_held_outside()
    _, first_pass = relaxation(coords, blocks, free, restarts=0).relax(tangled)
    _, every_round = relaxation(coords, blocks, free, stall_rounds=100).relax(tangled)
    _, stalled = relaxation(coords, blocks, free, stall_rounds=4).relax(tangled)
    assert stalled.restarts == every_round.restarts == 2
    assert stalled.rounds < 0.6 * every_round.rounds
    assert stalled.inverted_corners_after < first_pass.inverted_corners_after


def test_the_quality_stage_brings_tissue_out_of_a_bone_around_elements_left_inverted(
    monkeypatch, box_surface
):
    """Two held nodes of one hex swapped: that hex and its neighbours stay inverted whatever
    the free nodes do, so the untangling never ends untangled and never stiffens its bone
    contact. The quality stage used to wait for an untangled region, which left tissue in the
    bones (the 177k demo at 90 deg: 316 nodes up to 4.65 mm deep). Now it runs around the nodes
    past their constraints, every node of the inverted elements held: a node 2 deep in a bone
    comes out, the held nodes stay, and nothing far from that node moves."""
    coords, blocks, boundary, node = hex_block(6)
    a, b = node(1, 1, 1), node(2, 1, 1)
    free = np.setdiff1d(np.arange(len(coords)), np.union1d(boundary, [a, b]))
    lo, hi = np.array([41.0, 41.0, 21.0]), np.array([49.0, 49.0, 29.0])  # inside one cell
    rx = ElasticRelaxation(
        coords,
        corner_tetrahedra(blocks, {"hex8": np.ones(len(blocks["hex8"].ids), bool)}),
        free,
        bones={"tibia": box_surface(lo, hi)},
        blocks=blocks,
        aims=quality_aims(compute_quality(coords, blocks), blocks),
    )
    pose = coords.copy()
    pose[a], pose[b] = coords[b], coords[a]
    sunk = node(4, 4, 2)
    pose[sunk] += 3.0  # 2 deep in the bone
    transforms = {"tibia": RigidTransform.identity()}
    held = rx.inverted_element_nodes(pose)
    assert len(held) and compute_quality(pose, blocks).n_inverted > 0
    with pytest.raises(GeometryError):  # as before: the stage needs an untangled region
        rx.optimise(pose, transforms, QualityOptions(hold_inverted=False), _ignore, None)
    out, report = rx.optimise(pose, transforms, QualityOptions(), _ignore, None)
    assert report.held_nodes == np.count_nonzero(np.isin(held, free)) > 0
    np.testing.assert_array_equal(out[held], pose[held])
    depth = np.min(np.minimum(out[sunk] - lo, hi - out[sunk]))  # > 0 inside the box
    assert depth < 0.05 * 0.2  # out, to within a fifth of the stage's tolerance
    moved = np.flatnonzero(np.any(out != pose, axis=1))
    assert sunk in moved and len(moved) < 0.5 * len(free)
    assert np.abs(coords[moved] - coords[sunk]).max() <= 2 * 10.0 + 1e-9  # two cells around it
    # there, no gate rounds (the held elements fail the gate whatever the rest does); the
    # other rounds as asked; then the same over the region's whole shortfall, holding the
    # elements around the inverted ones as well
    seen = []

    def spy(*args, options, **kwargs):
        seen.append(options)
        return optimise_quality(*args, options=options, **kwargs)

    monkeypatch.setattr(relax_module, "optimise_quality", spy)
    rx.optimise(pose, transforms, QualityOptions(rounds=15, gate_rounds=4), _ignore, None)
    assert [(o.rounds, o.gate_rounds) for o in seen] == [(15, 0), (15, 0)]


def _two_nodes_in_bones(box_surface, tangle: bool):
    """A 10-cube block with two nodes 2 deep in two box bones, one near a corner of the block
    and one far from it, in groups that no element ties together; with ``tangle``, two held
    nodes near the first swapped, so that their hexes stay inverted. Returns the relaxation,
    the pose, the two nodes, the boxes, the bones' transforms and the contact constraints."""
    coords, blocks, boundary, node = hex_block(10)
    a, b = node(1, 1, 1), node(2, 1, 1)
    free = np.setdiff1d(np.arange(len(coords)), np.union1d(boundary, [a, b]))
    near, far = node(3, 3, 3), node(9, 9, 9)
    lo, hi = np.array([-4.0, -4.0, 1.0]), np.array([4.0, 4.0, 9.0])  # no node inside at rest
    boxes = {"tibia": (coords[near] + lo, coords[near] + hi)}
    boxes["femur"] = (coords[far] + lo, coords[far] + hi)
    rx = ElasticRelaxation(
        coords,
        corner_tetrahedra(blocks, {"hex8": np.ones(len(blocks["hex8"].ids), bool)}),
        free,
        bones={name: box_surface(*box) for name, box in boxes.items()},
        blocks=blocks,
        aims=quality_aims(compute_quality(coords, blocks), blocks),
    )
    pose = coords.copy()
    if tangle:
        pose[a], pose[b] = coords[b], coords[a]
    pose[[near, far], 2] += 3.0  # 2 deep, and the hexes above each 0.7 of their height
    transforms = {name: RigidTransform.identity() for name in boxes}
    contact = rx.contact_nodes[np.isin(rx.contact_nodes, [near, far])]
    assert len(contact) == 2

    def constraints(x):
        which, normals, offsets, _ = rx._contact_planes(x, contact, transforms, None, chords=False)
        return contact[which], normals, offsets

    return rx, pose, (near, far), boxes, transforms, contact, constraints


def _depth_in_box(point, box):
    lo, hi = box
    return float(np.min(np.minimum(point - lo, hi - point)))  # > 0 inside


def test_settling_in_the_bones_moves_when_its_floor_is_the_worst_solid(box_surface):
    """The settling of the nodes left in a bone may take no solid below the worst there now.
    That floor was the worst itself, measured as a ratio, and the line search measures it as
    a difference of logs: on the last bit the start lay below its own floor, and nothing moved
    (here: both nodes stayed 2 deep). The floor now lies a relative 1e-9 below it."""
    rx, pose, sunk, boxes, transforms, contact, constraints = _two_nodes_in_bones(
        box_surface, tangle=False
    )
    options = QualityOptions()
    out, settled = rx._settle_in_bones(
        pose, transforms, contact, constraints, options, QualityOptimisationReport(), None
    )
    for node_, box in zip(sunk, boxes.values(), strict=True):
        assert _depth_in_box(out[node_], box) < 0.2 * options.constraint_tolerance
    assert settled.bone_settled_nodes > 0
    # no solid below the worst there was
    worst = compute_quality(pose, rx.blocks).worst_jacobian()
    assert compute_quality(out, rx.blocks).worst_jacobian() >= worst - 1e-6


def test_settling_in_the_bones_holds_the_inverted_elements_and_settles_each_group_apart(
    box_surface,
):
    """One node in a bone near an element the untangling left inverted used to stop the
    settling of every node: the inverted element's nodes were among those moving, which the
    stage refuses. Now they are held, and each group of nodes that no element or constraint
    ties to another is settled apart (a group the floor holds does not hold the others): a
    node near the tangle and one far from it both come out, and the held nodes stay."""
    rx, pose, sunk, boxes, transforms, contact, constraints = _two_nodes_in_bones(
        box_surface, tangle=True
    )
    held = rx.inverted_element_nodes(pose)
    assert len(held) and not np.isin(sunk, held).any()
    options = QualityOptions()
    out, settled = rx._settle_in_bones(
        pose, transforms, contact, constraints, options, QualityOptimisationReport(), None, held
    )
    for node_, box in zip(sunk, boxes.values(), strict=True):
        assert _depth_in_box(out[node_], box) < 0.2 * options.constraint_tolerance
    np.testing.assert_array_equal(out[held], pose[held])
    assert settled.bone_settled_nodes > 0
    groups = rx._coupled_groups(pose, np.array(sunk), constraints)
    assert sorted(map(len, groups)) == [1, 1]
    near_pair = np.array([sunk[0], sunk[0] + 1])  # one hex holds both
    assert [len(g) for g in rx._coupled_groups(pose, near_pair, constraints)] == [2]


def test_a_settling_group_held_by_a_nearly_flat_solid_is_settled_again_without_it(
    monkeypatch, box_surface
):
    """A group whose settling brings its deepest node out by less than the tolerance (a nearly
    flat solid holds its line search: the 1M demo's crease, corner Jacobian 1e-5) is settled
    again with the nodes of the solids below 0.05 and one ring around them held, in place of
    that attempt. The stall is played here by the stage itself: it moves nothing while such a
    node is free."""
    rx, pose, sunk, boxes, transforms, contact, constraints = _two_nodes_in_bones(
        box_surface, tangle=False
    )
    near = sunk[0]
    squeezed = near + 3 * 11  # node (3, 6, 3): three cells from the sunk node
    pose[squeezed, 1] -= 9.7  # the hexes below it 0.3 of their height at it: nearly flat
    flat = rx.flat_element_nodes(pose, relax_module.TANGLE_FLAT_BELOW)
    assert squeezed in flat and near not in flat
    calls = []

    def stalls_on_flat(x, blocks, free, *args, **kwargs):
        calls.append(np.isin(flat, free).any())
        if calls[-1]:
            return x.copy(), QualityOptimisationReport()
        return optimise_quality(x, blocks, free, *args, **kwargs)

    monkeypatch.setattr(relax_module, "optimise_quality", stalls_on_flat)
    options = QualityOptions()
    out, settled = rx._settle_in_bones(
        pose, transforms, contact, constraints, options, QualityOptimisationReport(), None
    )
    assert calls[0] and not calls[1]  # the stalled attempt, then without the flat solids
    assert _depth_in_box(out[near], boxes["tibia"]) < 0.2 * options.constraint_tolerance
    np.testing.assert_array_equal(out[flat], pose[flat])
    assert settled.bone_settled_nodes > 0


def _ignore(fraction, message):
    pass


def test_relax_options_reject_a_stall_of_no_rounds():
    with pytest.raises(ValueError, match="stall_rounds"):
        RelaxOptions(stall_rounds=0)
    with pytest.raises(ValueError, match="restart_rings"):
        RelaxOptions(restart_rings=-1)


def test_a_restart_moves_only_the_nodes_around_the_stuck_ones():
    """A restart puts the stuck nodes back and moves only the free nodes within
    ``restart_rings`` mesh edges of them: the rest of the region keeps what the first pass
    reached, to the bit (the 177k demo at 90 deg: its two restarts over 52,706 free nodes took
    most of the untangling's time for a handful of corners)."""
    coords, blocks, free, tangled = _block_with_a_node_held_outside((0.0, 0.0, 30.0))
    first_pass = relaxation(coords, blocks, free, restarts=0)
    x0, report0 = first_pass.relax(tangled)
    sub = first_pass.energy(first_pass.free)
    _, _, det = sub.energy(x0[sub.nodes], 1e-3)
    stuck = sub.nodes[first_pass._stuck_nodes(sub, det)]
    assert len(stuck) and report0.inverted_corners_after > 0
    x1, report1 = relaxation(coords, blocks, free, restarts=1, restart_rings=1).relax(tangled)
    # a round of the restart is kept (its last: -1, or its best: 1), not the first pass's
    assert report1.restarts == 1 and report1.kept_attempt in (-1, 1)
    assert report1.inverted_corners_after < report0.inverted_corners_after
    around = first_pass._within_rings(stuck, 1, free)
    beyond = np.setdiff1d(np.arange(len(coords)), around)
    np.testing.assert_array_equal(x1[beyond], x0[beyond])
    assert np.abs(x1[around] - x0[around]).max() > 1.0


def test_rounds_after_one_that_left_corners_inverted_move_only_the_nodes_around_them():
    """After a round that left corners inverted, the next moves only the free nodes within
    ``focus_rings`` mesh edges of them, and a round that untangles them hands the next one the
    whole region back (the contact stiffens everywhere): the rest of the region has left its
    tangles behind (the 177k demo at 90 deg: 4,801 corners inverted after the first round over
    52,706 free nodes, 90 after the eighth, and every round moved all 52,706)."""
    coords, blocks, boundary, node = hex_block(8)
    free = np.setdiff1d(np.arange(len(coords)), boundary)
    tangled = coords.copy()
    tangled[node(2, 2, 2)] += [25.0, 3.0, -2.0]  # two folds far apart; two L-BFGS iterations
    tangled[node(6, 6, 6)] += [-9.0, 0.0, 0.0]  # per round leave one of them for later rounds
    slow = {"iterations_per_round": 2}
    _, whole = relaxation(coords, blocks, free, focus_rings=0, **slow).relax(tangled)
    assert whole.rounds >= 3 and whole.inverted_corners_after == 0
    assert all(h["nodes"] == whole.free_nodes for h in whole.history)
    focused_x, focused = relaxation(coords, blocks, free, focus_rings=1, **slow).relax(tangled)
    assert focused.inverted_corners_after == 0
    assert compute_quality(focused_x, blocks).n_inverted == 0
    nodes = [h["nodes"] for h in focused.history]
    assert nodes[0] == nodes[-1] == whole.free_nodes  # the first and the stiffening round
    inverted = [h["inverted"] for h in focused.history[:-1]]
    assert min(inverted[:-1]) > 0 and inverted[-1] == 0
    assert max(nodes[1:-1]) < 0.5 * whole.free_nodes  # rounds in between: around the fold


def test_a_focused_round_lets_the_last_rounds_energy_go_before_building_its_own():
    """Each energy holds its corners' inverse rest matrices (hundreds of MB over a whole-body
    region): when a round focuses on other nodes, the energy of the round before is released
    first, so at most the whole region's and the one being built exist together."""
    import gc
    import weakref

    coords, blocks, boundary, node = hex_block(8)
    free = np.setdiff1d(np.arange(len(coords)), boundary)
    tangled = coords.copy()
    tangled[node(2, 2, 2)] += [25.0, 3.0, -2.0]
    tangled[node(6, 6, 6)] += [-9.0, 0.0, 0.0]
    relax = relaxation(coords, blocks, free, focus_rings=1, iterations_per_round=2)
    built, alive_then = [], []
    energy = relax.energy

    def counting_energy(nodes, cancel=None, skip=None):
        gc.collect()
        alive_then.append(sum(ref() is not None for ref in built))
        sub = energy(nodes, cancel, skip)
        built.append(weakref.ref(sub))
        return sub

    relax.energy = counting_energy
    _, report = relax.relax(tangled)
    assert report.inverted_corners_after == 0
    assert len(built) >= 3  # the whole region, then focused rounds
    assert max(alive_then) == 1  # the whole region's energy only


def test_relax_options_reject_negative_focus_rings():
    with pytest.raises(ValueError, match="focus_rings"):
        RelaxOptions(focus_rings=-1)


def test_the_quality_stage_mends_an_element_the_pose_took_past_the_gate_beyond_its_region():
    """The relaxed region is the left half; the pose took an element of the right half below
    the initial model's worst Jacobian (the gate's level). Given the right half as ``beyond``
    nodes, a pass after the region's lifts it past that level moving only those nodes, the
    skin among them sliding in its plane; without them it stays below (the coarse demo posed
    to 0 deg: a calf hex 6 condyle radii from the axis, 0.327 against 0.330)."""
    coords, blocks, boundary, node = hex_block(4)
    rest = coords.copy()
    rest[node(3, 2, 2)] += [2.5, 2.0, 0.0]  # the initial model's worst elements
    initial = compute_quality(rest, blocks)
    aims = quality_aims(initial, blocks)
    posed = rest.copy()
    posed[node(3, 1, 3)] += [2.0, 2.0, 1.5]  # below the top face, the skin
    assert compute_quality(posed, blocks).worst_jacobian() < 0.85 * aims.gate["jacobian"]
    interior = np.setdiff1d(np.arange(len(rest)), boundary)
    skin = np.flatnonzero(rest[:, 2] == 40.0)
    skin_inside = skin[((rest[skin, :2] > 0.0) & (rest[skin, :2] < 40.0)).all(axis=1)]
    left = interior[rest[interior, 0] < 15.0]
    right = np.concatenate([interior, skin_inside])
    right = right[rest[right, 0] > 15.0]

    def relax(beyond):
        rx = ElasticRelaxation(
            rest,
            corner_tetrahedra(blocks, {"hex8": np.ones(len(blocks["hex8"]), bool)}),
            left,
            blocks=blocks,
            aims=aims,
            sliding=skin,
            beyond=beyond,
            initial_quality=initial,
        )
        return rx.relax(posed)

    held, _ = relax(None)
    np.testing.assert_array_equal(held, posed)  # nothing in the left half to do
    mended, report = relax(right)
    assert compute_quality(mended, blocks).worst_jacobian() > 1.05 * aims.gate["jacobian"]
    moved = np.flatnonzero(np.linalg.norm(mended - posed, axis=1) > 0.0)
    assert np.isin(moved, right).all() and node(3, 1, 3) in moved
    assert len(moved) <= report.quality.beyond_region_nodes <= len(right)
    slid = np.abs(mended[skin] - posed[skin])
    assert slid[:, :2].max() > 0.05  # the skin helped, along its plane
    assert slid[:, 2].max() < 1e-4  # and stayed in it


@pytest.mark.parametrize("n_nodes", [50, 2**31])  # the second overflows the packing: bytes
def test_row_labels_are_equal_exactly_where_the_rows_are(n_nodes):
    from kneegui.reposition.relax import row_labels

    rng = np.random.default_rng(5)
    rows = np.sort(rng.integers(-1, 50, size=(400, 4)), axis=1)
    keys = np.concatenate([rows, rows[rng.integers(0, 400, 300)]])  # with repeats
    labels = row_labels(keys, n_nodes)
    same_label = labels[:, None] == labels[None, :]
    same_row = np.all(keys[:, None, :] == keys[None, :, :], axis=2)
    np.testing.assert_array_equal(same_label, same_row)


def test_rest_corner_geometry_in_chunks_is_measuring_every_corner_at_once(monkeypatch):
    from kneegui.meshopt.foldover import edge_matrices

    rng = np.random.default_rng(11)
    x = rng.normal(size=(60, 3))
    tets = np.array([rng.choice(60, 4, replace=False) for _ in range(500)])
    tets[::7, 3] = tets[::7, 2]  # flat corners are left out
    monkeypatch.setattr(relax_module, "CORNER_CHUNK", 37)  # chunks that split the flat ones
    usable, inv, det = relax_module._rest_corner_geometry(x, tets)
    e0 = edge_matrices(x, tets)
    det_all = np.linalg.det(e0)
    expected = np.abs(det_all) > 1e-12 * np.maximum(np.abs(e0).max(axis=(1, 2)) ** 3, 1e-300)
    np.testing.assert_array_equal(usable, expected)
    assert not usable[::7].any() and usable.sum() > 400
    np.testing.assert_array_equal(inv, np.linalg.inv(e0[usable]))  # the same bits
    np.testing.assert_array_equal(det, det_all[usable])


def test_edge_adjacency_and_node_rows_are_the_sparse_products_they_replace():
    import scipy.sparse as sp

    from kneegui.reposition.relax import NodeRows, edge_adjacency

    rng = np.random.default_rng(12)
    n = 40
    tets = np.array([rng.choice(n + 5, 4, replace=False) for _ in range(300)])  # >= n: virtual
    tets[:, 0] = rng.integers(0, n, len(tets))  # a corner's base is a real node
    tets = tets[np.array([len(set(t)) == 4 for t in tets])]
    a, b = np.repeat(tets[:, 0], 3), tets[:, 1:].ravel()
    real = b < n
    adj = sp.csr_matrix((np.ones(int(real.sum())), (a[real], b[real])), shape=(n, n))
    expected = ((adj + adj.T) > 0).astype(np.int8).toarray()
    got = edge_adjacency(a, b, n)
    assert got.dtype == np.int8
    np.testing.assert_array_equal(got.toarray(), expected)

    rows = NodeRows(tets, n)
    for nodes in (np.arange(n), np.array([3, 17, 3]), np.array([], dtype=np.int64)):
        touching = np.flatnonzero(np.isin(tets, nodes).any(axis=1))
        np.testing.assert_array_equal(rows.touching(nodes), touching)


def test_a_region_energy_reads_the_relaxations_rest_matrices_without_copying_them():
    """The energy of a region holds the rows of its corners, not copies of their inverse rest
    matrices and weights (80 bytes a corner, millions of corners over a whole-body region),
    and gives the same bits as an energy over copies."""
    from kneegui.meshopt.foldover import FoldoverEnergy

    coords, blocks, boundary, node = hex_block(6)
    free = np.setdiff1d(np.arange(len(coords)), boundary)
    relax = relaxation(coords, blocks, free)
    nodes = free[: len(free) // 3]
    sub = relax.energy(nodes)
    assert np.shares_memory(sub.inv_rest, relax.inv_rest)
    assert np.shares_memory(sub.weights, relax.weight)
    assert sub.rows.dtype == np.int32 and len(sub.rows) < len(relax.tets)
    rows = relax._node_rows.touching(nodes)
    copied = FoldoverEnergy(
        relax.tets[rows],
        relax.inv_rest[rows],
        relax.weight[rows],
        relax.virtual,
        relax.quads[relax.is_free_quad(nodes)],
        relax.rest,
        nodes,
        relax.options.volume_weight,
        relax.options.shell_weight,
    )
    tangled = coords.copy()
    tangled[node(2, 3, 3)] += [14.0, -3.0, 2.0]
    for eps in (1e-3, 0.5):
        e_shared, g_shared, d_shared = sub.energy(tangled[sub.nodes], eps)
        e_copied, g_copied, d_copied = copied.energy(tangled[copied.nodes], eps)
        assert e_shared == e_copied and np.min(d_shared) < 0
        np.testing.assert_array_equal(g_shared, g_copied)
        np.testing.assert_array_equal(d_shared, d_copied)
    np.testing.assert_array_equal(sub.diagonal, copied.diagonal)


def test_inverted_element_nodes_in_blocks_are_those_of_one_block(monkeypatch):
    coords, blocks, boundary, node = hex_block(5)
    free = np.setdiff1d(np.arange(len(coords)), boundary)
    relax = relaxation(coords, blocks, free)
    relax.blocks = blocks  # (the helper builds it without, as the unit tests' energy needs)
    tangled = coords.copy()
    tangled[node(1, 1, 1)] += [14.0, 0.0, 0.0]
    tangled[node(3, 3, 5)] += [0.0, 0.0, -14.0]  # a skin node through the flesh under it
    whole = relax.inverted_element_nodes(tangled)
    monkeypatch.setattr(relax_module, "CORNER_CHUNK", 7)
    assert len(whole) > 8
    np.testing.assert_array_equal(relax.inverted_element_nodes(tangled), whole)


def test_pinned_corners_in_chunks_are_the_same_and_ask_to_cancel(monkeypatch):
    """Corners tied to two bones by all but one node: found a chunk at a time on a whole-body
    region, the same as at once."""
    relax = relax_module
    rng = np.random.default_rng(11)
    n = 400
    segment_of = rng.integers(-1, 3, size=n)  # -1: not on a bone
    is_free = np.zeros(n + 50, dtype=bool)
    is_free[rng.choice(n, 120, replace=False)] = True
    is_free[n:] = True  # virtual nodes count as free
    tets = rng.integers(0, n + 50, size=(5000, 4))
    whole = relax._pinned_corners(tets, is_free, segment_of)
    assert 0 < whole.sum() < len(whole)
    monkeypatch.setattr(relax, "CORNER_CHUNK", 700)
    asked = []
    chunked = relax._pinned_corners(tets, is_free, segment_of, lambda: bool(asked.append(1)))
    np.testing.assert_array_equal(chunked, whole)
    assert len(asked) == -(-5000 // 700)
    with pytest.raises(Cancelled):
        relax._pinned_corners(tets, is_free, segment_of, lambda: True)
