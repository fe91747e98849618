"""Corners of elements the bones leave no valid shape (kneegui.reposition.relax.LockedCorners)."""

from __future__ import annotations

import numpy as np

from kneegui.model import ElementBlock
from kneegui.reposition.relax import LockedCorners, NodeRows
from kneegui.topology import corner_tetrahedra

CUBE = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    dtype=np.float64,
)


def _two_hexes():
    """Hex 0: bottom face on segment 0, three top nodes on segment 1, node 6 free. Hex 1
    (beside it, nodes 8-15): bottom face on segment 0, top face free (one segment only)."""
    coords = np.concatenate([CUBE, CUBE + np.array([2.0, 0.0, 0.0])])
    conn = np.arange(16).reshape(2, 8)
    blocks = {"hex8": ElementBlock("hex8", np.array([1, 2]), np.array([1, 1]), conn)}
    segment_of = np.full(16, -1, dtype=np.int64)
    segment_of[[0, 1, 2, 3, 8, 9, 10, 11]] = 0
    segment_of[[4, 5, 7]] = 1
    is_free = np.zeros(16, dtype=bool)
    is_free[[6, 12, 13, 14, 15]] = True
    tets = corner_tetrahedra(blocks)
    return coords, blocks, segment_of, is_free, tets


def test_the_corners_of_an_element_the_bones_tear_apart_are_listed_at_that_pose_only():
    coords, blocks, segment_of, is_free, tets = _two_hexes()
    locked = LockedCorners(blocks, is_free, segment_of, tets, NodeRows(tets, 16))
    assert locked.elements == 1  # hex 1 lies on one segment
    assert len(locked.rows(coords, is_free)) == 0  # valid at rest
    torn = coords.copy()
    torn[[4, 5, 7], 2] = -0.2  # segment 1 turned through segment 0: no place for node 6
    np.testing.assert_array_equal(locked.rows(torn, is_free), np.arange(8))
    # the relaxation's own corners (fewer, in another order) are found by their nodes
    kept = tets[[7, 2, 5, 9, 12]]
    locked = LockedCorners(blocks, is_free, segment_of, kept, NodeRows(kept, 16))
    np.testing.assert_array_equal(locked.rows(torn, is_free), [0, 1, 2])


def test_an_element_its_free_node_can_save_is_not_listed():
    """Segment 1's three top nodes lifted and tilted: the corners without the free node stay
    positive and the free node has room, so no proof, nothing left out."""
    coords, blocks, segment_of, is_free, tets = _two_hexes()
    locked = LockedCorners(blocks, is_free, segment_of, tets, NodeRows(tets, 16))
    moved = coords.copy()
    moved[[4, 5, 7], 2] += [0.5, 0.8, 0.6]
    assert len(locked.rows(moved, is_free)) == 0
