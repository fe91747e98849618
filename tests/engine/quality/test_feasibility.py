"""The proof that an element's free nodes cannot make it valid (kneegui.quality.feasibility)."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.model import ElementBlock
from kneegui.quality import compute_quality
from kneegui.quality.feasibility import could_be_valid
from kneegui.topology import CORNER_TRIPLES

CUBE = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    dtype=np.float64,
)


def _best_corner_volume(fixed: np.ndarray, free_slot: int) -> float:
    """Independently of the pre-flight's proof: the largest achievable smallest corner
    determinant (scaled) of a hex whose nodes other than ``free_slot`` are fixed, over the
    free node's position, counting only the corners in which it is the only free node (an LP:
    maximise t with every such corner's determinant >= t, t <= 1)."""
    from scipy.optimize import linprog

    from kneegui.topology import CORNER_TRIPLES

    a_rows, b_rows = [], []
    for corner in CORNER_TRIPLES["hex8"]:
        if free_slot not in corner:
            continue

        def det(x, corner=corner):
            p = fixed.copy()
            p[free_slot] = x
            i, a, b, c = corner
            return np.linalg.det(np.array([p[a] - p[i], p[b] - p[i], p[c] - p[i]]))

        d0 = det(np.zeros(3))
        a_rows.append([det(e) - d0 for e in np.eye(3)])
        b_rows.append(d0)
    a_ub = np.c_[-np.array(a_rows), np.ones(len(a_rows))]
    res = linprog([0, 0, 0, -1], A_ub=a_ub, b_ub=b_rows, bounds=[(None, None)] * 3 + [(None, 1)])
    return -res.fun if res.status == 0 else float("-inf")


@pytest.mark.parametrize("seed", range(3))
def test_the_proof_that_a_free_node_cannot_save_an_element_is_exact(seed):
    """One free node of a hex whose other nodes are placed at random: where the corners
    without it are valid, the proof finds the element cannot be valid exactly when no
    position of the free node gives its own four corners positive determinants (an
    independent LP); and it never proves a valid element invalid."""
    rng = np.random.default_rng(seed)
    n = 20000
    hexes = CUBE[None] + rng.normal(scale=0.7, size=(n, 8, 3))
    slot = int(rng.integers(8))
    free = np.zeros((n, 8), dtype=bool)
    free[:, slot] = True
    fixed_ok = np.ones(n, dtype=bool)
    for i, a, b, c in CORNER_TRIPLES["hex8"]:
        if slot not in (i, a, b, c):
            edges = np.stack([hexes[:, k] - hexes[:, i] for k in (a, b, c)], axis=1)
            fixed_ok &= np.linalg.det(edges) > 0
    proved = ~could_be_valid(hexes, free, "hex8")
    assert np.all(proved[~fixed_ok])  # a corner of fixed nodes inverted is proof enough
    by_planes = np.flatnonzero(proved & fixed_ok)
    unproved = rng.choice(np.flatnonzero(~proved), 150, replace=False)
    best_proved = np.array([_best_corner_volume(hexes[k], slot) for k in by_planes])
    best_unproved = np.array([_best_corner_volume(hexes[k], slot) for k in unproved])
    assert len(by_planes) >= 10
    assert np.all(best_proved < -1e-6) and np.all(best_unproved > 1e-6)
    block = ElementBlock(
        "hex8", np.arange(n), np.ones(n, dtype=int), np.arange(8 * n).reshape(n, 8)
    )
    valid_now = ~compute_quality(hexes.reshape(-1, 3), {"hex8": block})["hex8"].inverted
    assert valid_now.sum() > 100 and not proved[valid_now].any()


def test_a_fixed_corner_inverted_by_the_bones_is_proof_enough():
    """A hex with its bottom face on the tibia and three top nodes on the femur: turned far
    enough, a corner of four bone nodes inverts and the one free node cannot help."""
    free = np.zeros((1, 8), dtype=bool)
    free[0, 6] = True
    flat = CUBE.copy()
    flat[4:, 2] = -0.2  # the top face pushed below the bottom one
    assert not could_be_valid(flat[None], free, "hex8")[0]
    assert could_be_valid(CUBE[None], free, "hex8")[0]


def test_a_margin_proves_less_never_more():
    rng = np.random.default_rng(7)
    hexes = CUBE[None] + rng.normal(scale=0.7, size=(5000, 8, 3))
    free = np.zeros((5000, 8), dtype=bool)
    free[:, 6] = True
    exact = ~could_be_valid(hexes, free, "hex8")
    margin = ~could_be_valid(hexes, free, "hex8", 1e-6)
    assert not (margin & ~exact).any()
    assert margin.sum() >= 0.95 * exact.sum() > 100


@pytest.mark.parametrize("lift", [-1e-13, 0.0, 1e-13])
def test_a_corner_flat_to_rounding_is_no_proof_with_a_margin(lift):
    """Node 4 on node 0 (a corner flat in the deck, moved rigidly: its determinant is zero to
    the last bits, of either sign): the exact test follows the sign, the margin does not."""
    hexes = CUBE.copy()[None]
    hexes[0, 4] = [0.0, 0.0, lift]
    free = np.zeros((1, 8), dtype=bool)
    free[0, 6] = True
    assert could_be_valid(hexes, free, "hex8", 1e-6)[0]
    assert could_be_valid(hexes, free, "hex8")[0] == (lift > 0.0)
