"""The demo leg's local mesh repair: metrics, targets, what moves and what must not."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.demo import DemoDesign
from kneegui.demo import grid as g
from kneegui.demo.generator import repair_grid
from kneegui.demo.layout import make_layout
from kneegui.demo.repair import (
    QualityTargets,
    _hex_metrics,
    _inverts,
    _quad_metrics,
    element_scores,
    repair_quality,
)
from kneegui.quality.kernels import hex8_quality, quad4_quality

CUBE = np.array(
    [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)],
    dtype=float,
)
FAIL_LIMITS = QualityTargets(jacobian=0.3, aspect=10.0, warpage=30.0)


def _block(n: int = 4):
    """A structured n x n x n block of unit hexes: coordinates and connectivity."""
    i, j, k = np.meshgrid(np.arange(n + 1), np.arange(n + 1), np.arange(n + 1), indexing="ij")
    coords = np.column_stack([i.ravel(), j.ravel(), k.ravel()]).astype(float)

    def node(a, b, c):
        return (a * (n + 1) + b) * (n + 1) + c

    a, b, c = (x.ravel() for x in np.meshgrid(*(np.arange(n),) * 3, indexing="ij"))
    hexes = np.column_stack(
        [
            node(a, b, c),
            node(a + 1, b, c),
            node(a + 1, b + 1, c),
            node(a, b + 1, c),
            node(a, b, c + 1),
            node(a + 1, b, c + 1),
            node(a + 1, b + 1, c + 1),
            node(a, b + 1, c + 1),
        ]
    )
    interior = np.all((coords > 0) & (coords < n), axis=1)
    return coords, hexes, interior, node


def test_lean_metrics_equal_the_quality_kernels():
    """The repair's own metrics are the QUALITY.md definitions of kneegui.quality."""
    rng = np.random.default_rng(3)
    hexes = CUBE + 0.25 * rng.standard_normal((400, 8, 3))
    quads = CUBE[:4] + 0.3 * rng.standard_normal((400, 4, 3))
    for lean, kernel, pts in (
        (_hex_metrics, hex8_quality, hexes),
        (_quad_metrics, quad4_quality, quads),
    ):
        mine = lean(pts)
        ref = kernel([np.ascontiguousarray(pts[:, k].T) for k in range(pts.shape[1])])
        for name in ("jacobian_corner", "aspect", "warpage"):
            assert np.allclose(mine[name], ref[name], atol=1e-9), name


def test_targets_come_from_the_thresholds_table_with_a_margin():
    t = QualityTargets.from_thresholds()
    assert 0.3 < t.jacobian < 0.35
    assert 9.5 < t.aspect < 10.0
    assert 28.0 < t.warpage < 30.0
    exact = QualityTargets.from_thresholds((1.0, 1.0, 1.0))
    assert (exact.jacobian, exact.aspect, exact.warpage) == (0.3, 10.0, 30.0)


def test_a_displaced_interior_node_is_moved_back_into_bounds():
    coords, hexes, interior, node = _block()
    bad = coords.copy()
    centre = node(2, 2, 2)
    bad[centre] += [0.75, 0.7, 0.65]  # folds the corner cells around the centre node
    before, _ = element_scores(bad, hexes, np.zeros((0, 4), np.int64), FAIL_LIMITS)
    assert (before > 0).sum() >= 1
    snapshot = bad.copy()
    fixed = repair_quality(
        bad, hexes, np.zeros((0, 4), np.int64), interior, QualityTargets.from_thresholds()
    )
    assert np.array_equal(bad, snapshot)  # input not mutated
    after, _ = element_scores(fixed, hexes, np.zeros((0, 4), np.int64), FAIL_LIMITS)
    assert after.max() <= 0.0
    moved = np.any(fixed != bad, axis=1)
    assert moved[centre]
    assert not np.any(moved & ~interior)  # boundary nodes stay where they are


def test_nothing_moves_when_every_element_is_good():
    coords, hexes, interior, _ = _block(3)
    out = repair_quality(
        coords, hexes, np.zeros((0, 4), np.int64), interior, QualityTargets.from_thresholds()
    )
    assert np.array_equal(out, coords)


def test_guard_cells_are_never_turned_inside_out():
    """A flattened guard cell next to the bad ones: the repair must not push a node through it."""
    coords, hexes, interior, node = _block()
    bad = coords.copy()
    bad[node(2, 2, 2)] += [0.75, 0.7, 0.65]
    # the cells of the upper half act as guards (a cavity), the lower half as elements
    upper = coords[hexes].mean(axis=1)[:, 2] > 2.0
    fixed = repair_quality(
        bad,
        hexes[~upper],
        np.zeros((0, 4), np.int64),
        interior,
        QualityTargets.from_thresholds(),
        guards=hexes[upper],
    )
    guard_before = _hex_metrics(bad[hexes[upper]])["jacobian_corner"]
    guard_after = _hex_metrics(fixed[hexes[upper]])["jacobian_corner"]
    assert np.all(guard_after[guard_before > 0] > 0)


def test_a_move_through_a_guard_cell_is_flagged():
    guard = np.arange(8)[None, :]
    trials = np.array([CUBE[6], CUBE[6] + [0.1, 0.1, 0.1], [1.0, 1.0, -0.5]])  # last: through
    flagged = _inverts(CUBE, 6, trials, guard)
    assert flagged.tolist() == [False, False, True]
    # a guard that is already inverted does not block anything
    assert not _inverts(CUBE[[4, 5, 6, 7, 0, 1, 2, 3]], 2, trials, guard).any()


@pytest.fixture(scope="module")
def coarsest_grid():
    return g.build_grid(DemoDesign(), make_layout(0.05))


def test_repair_moves_only_free_flesh_nodes_and_keeps_the_landmarks(coarsest_grid):
    grid = coarsest_grid
    free = g.free_flesh_nodes(grid)
    repaired, moved = repair_grid(grid)
    changed = np.any(repaired.coords != grid.coords, axis=1)
    assert moved == changed.sum() > 0
    assert not np.any(changed & ~free)
    # no bone, ligament, meniscus or skin node is free
    for label in (g.FEMUR, g.TIBIA, g.FIBULA, g.PATELLA, g.ACL, g.PCL, g.MCL, g.LCL):
        assert not free[grid.cell_conn[grid.cell_label == label].ravel()].any()
    skin = grid.shells["skin"][0].ravel()
    assert not free[skin].any()
    for key in ("lateral_condyle", "medial_condyle"):
        idx = grid.landmarks[key]
        assert np.array_equal(repaired.coords[idx], grid.coords[idx])


def test_repair_fixes_the_coarsest_grid(coarsest_grid):
    grid = coarsest_grid
    hexes = grid.cell_conn[grid.cell_label != g.VOID]
    quads = np.concatenate([conn for conn, _ in grid.shells.values()])
    before = element_scores(grid.coords, hexes, quads, FAIL_LIMITS)
    assert max(b.max() for b in before) > 0  # the coarsest grid needs the repair
    repaired, _ = repair_grid(grid)
    after = element_scores(repaired.coords, hexes, quads, FAIL_LIMITS)
    assert max(a.max() for a in after) <= 0
