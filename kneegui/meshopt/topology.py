"""Mesh topology the smoother needs: element edges and faces, boundary faces, node incidence."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np
from numpy.typing import NDArray

from kneegui.model import ELEMENT_EDGES as MODEL_EDGES
from kneegui.model import SOLID_FACES, ElementBlock

#: Edges of the element types the smoother works on, as local corner-node pairs.
ELEMENT_EDGES: dict[str, tuple[tuple[int, int], ...]] = {
    t: MODEL_EDGES[t] for t in ("hex8", "wedge6", "pyramid5", "tet4", "quad4", "tri3")
}


def row_multiplicity(rows: NDArray[np.int64]) -> NDArray[np.int64]:
    """How many times each row of a 2-D integer array occurs in it (via lexsort)."""
    if len(rows) == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.lexsort(rows.T[::-1])
    srt = rows[order]
    new_group = np.ones(len(rows), dtype=bool)
    new_group[1:] = np.any(srt[1:] != srt[:-1], axis=1)
    group = np.cumsum(new_group) - 1
    counts = np.bincount(group)
    out = np.empty(len(rows), dtype=np.int64)
    out[order] = counts[group]
    return out


def unique_pairs(a: NDArray[np.int64], b: NDArray[np.int64], n_b: int) -> NDArray[np.int64]:
    """Sorted unique ``(a, b)`` pairs of non-negative integers with ``b < n_b``, as (p, 2)."""
    key = np.unique(a.astype(np.int64) * n_b + b.astype(np.int64))
    return np.stack([key // n_b, key % n_b], 1)


def boundary_faces(
    blocks: Mapping[str, ElementBlock], part_ids: Iterable[int] | None = None
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Faces of the solid mesh that belong to exactly one solid element.

    Parameters
    ----------
    blocks : mapping of str to ElementBlock
        Element blocks; only solid types are used.
    part_ids : iterable of int, optional
        Restrict the solid mesh to these parts (default: every solid).

    Returns
    -------
    quads : (q, 4) ndarray of int64
        Boundary quad faces (node indices), outward for positive elements.
    tris : (t, 3) ndarray of int64
        Boundary triangles. (tet10 faces are given by their corner nodes.)
    """
    wanted = None if part_ids is None else np.array(sorted(set(part_ids)), dtype=np.int64)
    quads, tris = [], []
    for etype, faces in SOLID_FACES.items():
        block = blocks.get(etype)
        if block is None or len(block) == 0:
            continue
        conn = block.conn if wanted is None else block.conn[np.isin(block.part_ids, wanted)]
        for face in faces:
            (quads if len(face) == 4 else tris).append(conn[:, list(face)])
    out = []
    for chunks, k in ((quads, 4), (tris, 3)):
        if not chunks:
            out.append(np.zeros((0, k), dtype=np.int64))
            continue
        faces = np.concatenate(chunks)
        out.append(faces[row_multiplicity(np.sort(faces, axis=1)) == 1])
    return out[0], out[1]


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
    coords: NDArray[np.float64], quads: NDArray[np.int64], tris: NDArray[np.int64]
) -> NDArray[np.float64]:
    """Unit area-weighted normals of the boundary faces at every node (zero off the boundary)."""
    normals = np.zeros_like(coords)
    if len(quads):
        p = coords[quads]
        n = 0.5 * np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
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
