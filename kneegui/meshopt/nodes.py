"""Node selections the mesh improvement works with: boundary nodes and their normals, the
nodes of chosen elements, how many parts share a node (tables and boundary faces are
:mod:`kneegui.topology`'s)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np
from numpy.typing import NDArray

from kneegui.model import ElementBlock
from kneegui.topology import boundary_faces, sorted_unique


def unique_pairs(a: NDArray[np.int64], b: NDArray[np.int64], n_b: int) -> NDArray[np.int64]:
    """Sorted unique ``(a, b)`` pairs of non-negative integers with ``b < n_b``, as (p, 2)."""
    key = sorted_unique(a.astype(np.int64) * n_b + b.astype(np.int64))
    return np.stack([key // n_b, key % n_b], 1)


def boundary_node_mask(
    n_nodes: int, blocks: Mapping[str, ElementBlock], part_ids: Iterable[int] | None = None
) -> NDArray[np.bool_]:
    """``(n_nodes,)`` mask of the nodes on the boundary faces of the solid mesh."""
    quads, tris = boundary_faces(blocks, part_ids)
    mask = np.zeros(n_nodes, dtype=bool)
    mask[quads.reshape(-1)] = True
    mask[tris.reshape(-1)] = True
    return mask


def boundary_node_normals(
    coords: NDArray[np.float64],
    quads: NDArray[np.int64],
    tris: NDArray[np.int64],
    quad_signs: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Unit area-weighted normals of the boundary faces at every node (zero off the boundary).
    ``quad_signs`` (Q,) of +-1 turns each quad's normal to a chosen side (a deck's shells need
    not be oriented alike)."""
    normals = np.zeros_like(coords)
    if len(quads):
        p = coords[quads]
        n = 0.5 * np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
        if quad_signs is not None:
            n *= quad_signs[:, None]
        for k in range(4):
            np.add.at(normals, quads[:, k], n)
    if len(tris):
        p = coords[tris]
        n = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        for k in range(3):
            np.add.at(normals, tris[:, k], n)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def nodes_of_elements(
    blocks: Mapping[str, ElementBlock], masks: Mapping[str, NDArray[np.bool_]], n_nodes: int
) -> NDArray[np.bool_]:
    """``(n_nodes,)`` mask of the nodes used by the selected elements of each block."""
    out = np.zeros(n_nodes, dtype=bool)
    for etype, mask in masks.items():
        block = blocks.get(etype)
        if block is not None and len(block):
            out[block.conn[np.asarray(mask, dtype=bool)].reshape(-1)] = True
    return out


def node_part_count(blocks: Mapping[str, ElementBlock], n_nodes: int) -> NDArray[np.int64]:
    """Number of distinct parts whose elements (any type) use each node."""
    pairs = []
    for block in blocks.values():
        if len(block):
            k = block.conn.shape[1]
            pairs.append(np.stack([block.conn.reshape(-1), np.repeat(block.part_ids, k)], 1))
    if not pairs:
        return np.zeros(n_nodes, dtype=np.int64)
    node_part = np.concatenate(pairs)
    _, part_code = np.unique(node_part[:, 1], return_inverse=True)
    n_codes = int(part_code.max()) + 1
    uniq = unique_pairs(node_part[:, 0], part_code.reshape(-1), n_codes)
    return np.bincount(uniq[:, 0], minlength=n_nodes)
