"""Tetrahedral and mixed variants of the demo leg: a conforming BCC-lattice tet mesh of the grid.

The labelled hexahedral cells of :mod:`kneegui.demo.grid` are turned into tetrahedra without
splitting each hex on its own: every tet cell gets a node at its centre (a body-centred cubic
lattice), and

* across a face shared by two tet cells of the same label, four tetrahedra span the two cell
  centres and each edge of the face (the BCC tets: they cross the face, so the mesh is not a set of
  split hexes; a centre node has 14 edge neighbours, 8 corners and 6 centres);
* on every other face of a tet cell (another label, a hexahedral neighbour, the outside, or a face
  carrying a shell) the face is cut into two triangles by the diagonal through its lowest node
  index (the same on both sides, so neighbours agree) and each triangle is joined to the cell's
  centre.

Both kinds of tet inside a cell share the triangles ``(centre, face edge)``, so the mesh is
conforming, every part stays a closed region of the same cells, and a hexahedron next to a tet
cell shares its four face nodes with the two triangles of the split face. Shells on split faces
become two triangles with the same diagonal.

The centre nodes are then moved (a few sweeps of a deterministic pattern search, one colour of
independent centres at a time) to raise the worst mean-ratio quality of their tetrahedra, so that
no tet is inverted and the worst ones are as good as the cell shapes allow. Measures:
:func:`tet_quality` (minimum and maximum dihedral angle, HyperMesh collapse).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kneegui.topology import SOLID_FACES

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

_HEX_FACES = np.array(SOLID_FACES["hex8"])  # outward from their cell
#: The 6 tet edges as corner pairs, and the mid-edge order of a 10-node tet (topology.tet10).
TET_EDGES = ((0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3))
#: HyperMesh collapse normalisation: height / sqrt(opposite face area) of the regular tet.
#: A centre stops trying once its step has halved this often without a better position.
MAX_HALVINGS = 8
_COLLAPSE_REGULAR = np.sqrt(2.0 / 3.0) / np.sqrt(np.sqrt(3.0) / 4.0)


@dataclass(frozen=True)
class TetMesh:
    """Result of :func:`tetrahedralise`.

    Attributes
    ----------
    coords : (N + C, 3) ndarray
        The input nodes followed by the C cell-centre nodes.
    tets : (m, 4) ndarray
        Positive tetrahedra (node indices; ``topology`` tet4 order).
    tet_cell : (m,) ndarray
        The cell (row of the input) each tet belongs to (a BCC tet: the first of its two cells).
    hex_rows : (h,) ndarray
        Rows of the input cells kept as hexahedra.
    centre_of : (n_cells,) ndarray
        Node index of each tet cell's centre (-1 for hex cells).
    split_face_keys : (f, 4) ndarray
        Sorted node indices of the faces cut into two triangles.
    """

    coords: FloatArray
    tets: IntArray
    tet_cell: IntArray
    hex_rows: IntArray
    centre_of: IntArray
    split_face_keys: IntArray


def face_neighbours(conn: IntArray) -> IntArray:
    """Neighbour cell across each face, ``(n_cells, 6)`` (-1: none), faces as ``SOLID_FACES``."""
    n_cells = len(conn)
    faces = conn[:, _HEX_FACES].reshape(-1, 4)
    key = np.sort(faces, axis=1)
    order = np.lexsort(key.T[::-1])
    key_s = key[order]
    same_next = np.all(key_s[1:] == key_s[:-1], axis=1)
    other = np.full(len(faces), -1, dtype=np.int64)
    owner = np.repeat(np.arange(n_cells), 6)
    first, second = order[:-1][same_next], order[1:][same_next]
    other[first] = owner[second]
    other[second] = owner[first]
    return other.reshape(n_cells, 6)


def split_triangles(coords: FloatArray, quads: IntArray) -> IntArray:
    """The two triangles ``(2 q, 3)`` of each quad ``(q, 4)``, cut along the shorter diagonal
    (a tie goes to the diagonal through the lowest node index), so that two cells sharing a face
    cut it the same way; orientation kept, triangles of quad ``i`` at rows ``2 i`` and ``2 i + 1``.
    """
    a, b, c, d = quads.T
    ac = np.linalg.norm(coords[a] - coords[c], axis=1)
    bd = np.linalg.norm(coords[b] - coords[d], axis=1)
    lowest_on_ac = (np.argmin(quads, axis=1) % 2) == 0
    via_ac = np.where(np.isclose(ac, bd, rtol=1e-9, atol=0.0), lowest_on_ac, ac < bd)
    t1 = np.where(via_ac[:, None], np.column_stack([a, b, c]), np.column_stack([a, b, d]))
    t2 = np.where(via_ac[:, None], np.column_stack([a, c, d]), np.column_stack([b, c, d]))
    return np.stack([t1, t2], axis=1).reshape(-1, 3)


def tetrahedralise(
    coords: FloatArray,
    conn: IntArray,
    labels: IntArray,
    is_tet: BoolArray,
    forced_split: IntArray | None = None,
) -> TetMesh:
    """Cut the tet cells of a conforming hex grid into a BCC-lattice tetrahedral mesh.

    Parameters
    ----------
    coords : (N, 3) ndarray
        Node positions.
    conn : (n, 8) ndarray
        Hexahedral cells (positive LS-DYNA order), all of them elements.
    labels : (n,) ndarray
        Cell labels: the BCC tets only cross faces between tet cells of the same label.
    is_tet : (n,) ndarray of bool
        Cells to mesh with tetrahedra; the others stay hexahedra.
    forced_split : (f, 4) ndarray, optional
        Faces (node indices, any order) that must be cut into triangles even between two tet
        cells of the same label (faces that carry shells).

    Returns
    -------
    TetMesh
    """
    n_nodes, n_cells = len(coords), len(conn)
    nbr = face_neighbours(conn)
    faces = conn[:, _HEX_FACES]  # (n, 6, 4) outward
    tet_rows = np.flatnonzero(is_tet)
    centre_of = np.full(n_cells, -1, dtype=np.int64)
    centre_of[tet_rows] = n_nodes + np.arange(len(tet_rows))
    centres = coords[conn[tet_rows]].mean(axis=1)

    nb = np.maximum(nbr, 0)
    bcc = is_tet[:, None] & (nbr >= 0) & is_tet[nb] & (labels[nb] == labels[:, None])
    if forced_split is not None and len(forced_split):
        forced = _rows_in(np.sort(faces.reshape(-1, 4), axis=1), np.sort(forced_split, axis=1))
        bcc &= ~forced.reshape(n_cells, 6)
    split = is_tet[:, None] & ~bcc

    # pyramid-split faces: two tets (a, c, b, centre) per outward triangle (a, b, c)
    cell_s, face_s = np.nonzero(split)
    tris = split_triangles(coords, faces[cell_s, face_s]).reshape(-1, 2, 3)
    apex = np.repeat(centre_of[cell_s], 2)
    tris = tris.reshape(-1, 3)
    split_tets = np.column_stack([tris[:, 0], tris[:, 2], tris[:, 1], apex])
    split_cell = np.repeat(cell_s, 2)

    # BCC faces, once per pair (from the lower cell): four tets around the centre-centre axis
    cell_b, face_b = np.nonzero(bcc & (nbr > np.arange(n_cells)[:, None]))
    quad = faces[cell_b, face_b]  # outward from cell_b
    ca, cb = centre_of[cell_b], centre_of[nbr[cell_b, face_b]]
    bcc_tets = np.concatenate(
        [np.column_stack([quad[:, e], quad[:, (e + 1) % 4], ca, cb]) for e in range(4)]
    )
    bcc_cell = np.tile(cell_b, 4)

    tets = np.concatenate([split_tets, bcc_tets]).astype(np.int64)
    tet_cell = np.concatenate([split_cell, bcc_cell]).astype(np.int64)
    order = np.argsort(tet_cell, kind="stable")
    split_keys = np.unique(np.sort(faces[cell_s, face_s], axis=1), axis=0)
    return TetMesh(
        np.vstack([coords, centres]),
        tets[order],
        tet_cell[order],
        np.flatnonzero(~is_tet),
        centre_of,
        split_keys,
    )


def _rows_in(rows: IntArray, table: IntArray) -> BoolArray:
    """Which rows of ``rows`` (r, k) occur in ``table`` (t, k) (both sorted along axis 1)."""
    if len(table) == 0:
        return np.zeros(len(rows), dtype=bool)
    both = np.concatenate([table, rows])
    _, inverse = np.unique(both, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    known = np.zeros(inverse.max() + 1, dtype=bool)
    known[inverse[: len(table)]] = True
    return known[inverse[len(table) :]]


def signed_volumes(coords: FloatArray, tets: IntArray) -> FloatArray:
    """Signed volume of each tet (positive: topology tet4 orientation)."""
    p = coords[tets[:, :4]]
    return (
        np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
        / 6.0
    )


def mean_ratio(p: FloatArray) -> FloatArray:
    """Mean-ratio-like shape quality of tets ``(..., 4, 3)``: ``6 sqrt(2) V / l_rms^3``, 1 for
    the regular tet, <= 0 when inverted or flat."""
    d = [p[..., j, :] - p[..., i, :] for i, j in TET_EDGES]
    vol = np.einsum("...i,...i", np.cross(d[0], -d[2]), d[3]) / 6.0
    l2 = sum(np.einsum("...i,...i", e, e) for e in d) / 6.0
    return 6.0 * np.sqrt(2.0) * vol / np.maximum(l2, 1e-300) ** 1.5


def tet_quality(coords: FloatArray, tets: IntArray) -> dict[str, FloatArray]:
    """Shape measures of tets (the first 4 nodes of each row are the corners).

    Returns
    -------
    dict
        ``volume`` (signed), ``min_dihedral`` and ``max_dihedral`` (degrees, over the 6 edges),
        ``collapse`` (HyperMesh: the smallest height over the square root of the opposite face's
        area, divided by its value for the regular tet; 1 regular, 0 flat, negative inverted).
    """
    p = coords[tets[:, :4]]
    vol = signed_volumes(coords, tets)
    # outward unit normals of a positive tet: face i is opposite corner i
    opposite = ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))
    normals = []
    heights = []
    for a, b, c in opposite:
        n = np.cross(p[:, b] - p[:, a], p[:, c] - p[:, a])
        area2 = np.linalg.norm(n, axis=1)
        normals.append(n / np.maximum(area2, 1e-300)[:, None])
        h = 3.0 * vol / np.maximum(0.5 * area2, 1e-300)
        heights.append(h / np.sqrt(np.maximum(0.5 * area2, 1e-300)))
    collapse = np.min(heights, axis=0) / _COLLAPSE_REGULAR
    dihedral = []
    for i in range(4):
        for j in range(i + 1, 4):
            # the faces opposite corners i and j meet at the edge of the two other corners
            cosang = -np.einsum("ij,ij->i", normals[i], normals[j])
            dihedral.append(np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0))))
    dih = np.array(dihedral)
    return {
        "volume": vol,
        "min_dihedral": dih.min(axis=0),
        "max_dihedral": dih.max(axis=0),
        "collapse": collapse,
    }


def improve_centres(
    coords: FloatArray,
    tets: IntArray,
    movable: IntArray,
    sweeps: int = 20,
    active_below: float = 0.25,
) -> FloatArray:
    """Move the ``movable`` nodes (cell centres) to raise the worst mean ratio of their tets.

    A deterministic pattern search: in each sweep, every movable node (one colour of nodes that
    share no tet at a time, all of a colour at once) tries steps along the axes and the cube
    diagonals and the centroid of its tets' other nodes, and keeps the trial with the best worst
    mean ratio of its own tets if it is better than where it is; the step halves where nothing
    helped. No tet's worst quality around a moved node goes down.

    Parameters
    ----------
    coords : (N, 3) ndarray
    tets : (m, 4) ndarray
    movable : (c,) ndarray of int
        Node indices that may move (not on any part boundary).
    sweeps : int
    active_below : float
        Only nodes with a tet of mean ratio below this move (the others are left as they are).

    Returns
    -------
    (N, 3) ndarray
    """
    out = np.array(coords, dtype=np.float64, copy=True)
    n = len(out)
    worst = np.full(n, np.inf)
    np.minimum.at(worst, tets.ravel(), np.repeat(mean_ratio(out[tets[:, :4]]), 4))
    movable = movable[worst[movable] < active_below]
    if len(movable) == 0:
        return out
    pos = np.full(n, -1, dtype=np.int64)
    pos[movable] = np.arange(len(movable))
    # incidence: tets of each movable node, padded to the largest star (rows of -1)
    rows, cols = np.nonzero(pos[tets] >= 0)
    owner = pos[tets[rows, cols]]
    order = np.lexsort((rows, owner))
    owner, rows = owner[order], rows[order]
    counts = np.bincount(owner, minlength=len(movable))
    width = int(counts.max())
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(owner)) - start[owner]
    star = np.full((len(movable), width), -1, dtype=np.int64)
    star[owner, slot] = rows
    colour = _colour(movable, tets, pos)
    directions = np.array(
        [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
        + [[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)],
        dtype=np.float64,
    )
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    edge = np.linalg.norm(out[tets[:, 0]] - out[tets[:, 1]], axis=1)
    step = np.full(len(movable), np.inf)
    np.minimum.at(step, owner, edge[rows])
    step *= 0.15
    # each star tet as (base triangle, moving apex), orientation kept: base = the reversed
    # outward face opposite the node (tet4 SOLID_FACES order is opposite corners 3, 2, 0, 1)
    opposite = {3: (0, 1, 2), 2: (0, 3, 1), 0: (1, 3, 2), 1: (2, 3, 0)}
    st_valid = star >= 0
    st_conn = tets[np.maximum(star, 0)]  # (c, w, 4)
    corner = np.argmax(st_conn == movable[:, None, None], axis=2)  # (c, w)
    base_nodes = np.stack(
        [np.choose(corner, [st_conn[..., opposite[k][m]] for k in range(4)]) for m in range(3)],
        axis=-1,
    )  # (c, w, 3)
    min_step = step / 2.0**MAX_HALVINGS
    for _ in range(sweeps):
        for c in range(colour.max() + 1):
            # a node whose step has halved MAX_HALVINGS times found nothing better: it is done
            sel = np.flatnonzero((colour == c) & (step > min_step))
            if len(sel) == 0:
                continue
            node = movable[sel]
            valid = st_valid[sel]
            base = out[base_nodes[sel]]  # (s, w, 3, 3)
            here = out[node]
            centroid = np.where(valid[..., None, None], base, 0.0).sum(axis=(1, 2)) / (
                3.0 * valid.sum(axis=1)[:, None]
            )
            trials = np.concatenate(
                [
                    here[:, None],
                    here[:, None] + step[sel, None, None] * directions[None],
                    centroid[:, None],
                    (0.5 * (here + centroid))[:, None],
                ],
                axis=1,
            )  # (s, t, 3)
            q = _apex_quality(base, trials)  # (s, t, w)
            q = np.where(valid[:, None, :], q, np.inf)
            # fewer inverted tets first, then the better worst quality
            q = q.min(axis=2) - 4.0 * np.sum(q <= 0.0, axis=2)
            best = np.argmax(q, axis=1)
            gain = q[np.arange(len(sel)), best] > q[:, 0] + 1e-9
            out[node[gain]] = trials[gain, best[gain]]
            step[sel[~gain]] *= 0.5
    return out


def _apex_quality(base: FloatArray, apex: FloatArray) -> FloatArray:
    """Mean ratio (:func:`mean_ratio`) of tets ``(base triangle, apex)`` for every apex trial:
    ``base`` (s, w, 3, 3), ``apex`` (s, t, 3) -> (s, t, w)."""
    b0, b1, b2 = base[..., 0, :], base[..., 1, :], base[..., 2, :]
    normal = np.cross(b1 - b0, b2 - b0)  # (s, w, 3)
    vol = (
        np.einsum("stj,swj->stw", apex, normal) - np.einsum("swj,swj->sw", b0, normal)[:, None]
    ) / 6.0
    base_l2 = sum(np.einsum("swj,swj->sw", u - v, u - v) for u, v in ((b0, b1), (b1, b2), (b2, b0)))
    bsum = b0 + b1 + b2
    bsq = sum(np.einsum("swj,swj->sw", u, u) for u in (b0, b1, b2))
    apex_sq = np.einsum("stj,stj->st", apex, apex)
    apex_l2 = (
        3.0 * apex_sq[:, :, None] - 2.0 * np.einsum("stj,swj->stw", apex, bsum) + bsq[:, None, :]
    )
    l2 = (base_l2[:, None, :] + apex_l2) / 6.0
    return 6.0 * np.sqrt(2.0) * vol / np.maximum(l2, 1e-300) ** 1.5


def _colour(movable: IntArray, tets: IntArray, pos: IntArray) -> IntArray:
    """Greedy colouring of the movable nodes so that no two of one colour share a tet."""
    has = pos[tets] >= 0
    pairs = []
    for i in range(4):
        for j in range(4):
            if i != j:
                m = has[:, i] & has[:, j]
                pairs.append(np.column_stack([pos[tets[m, i]], pos[tets[m, j]]]))
    pairs = np.unique(np.concatenate(pairs), axis=0)
    bounds = np.searchsorted(pairs[:, 0], np.arange(len(movable) + 1))
    colour = np.full(len(movable), -1, dtype=np.int64)
    for a in range(len(movable)):
        used = colour[pairs[bounds[a] : bounds[a + 1], 1]]
        c = 0
        while c in used:
            c += 1
        colour[a] = c
    return colour


def add_mid_edge_nodes(coords: FloatArray, tets: IntArray) -> tuple[FloatArray, IntArray]:
    """Make 10-node tets: a node at the middle of every (straight) edge, shared between tets.

    Returns the coordinates with the mid-edge nodes appended and the ``(m, 10)`` connectivity
    (corners, then the mid-edge nodes of edges 0-1, 1-2, 2-0, 0-3, 1-3, 2-3).
    """
    edges = np.stack([tets[:, list(e)] for e in TET_EDGES], axis=1).reshape(-1, 2)
    key = np.sort(edges, axis=1)
    unique, inverse = np.unique(key, axis=0, return_inverse=True)
    mids = 0.5 * (coords[unique[:, 0]] + coords[unique[:, 1]])
    mid_index = len(coords) + inverse.reshape(len(tets), 6)
    return np.vstack([coords, mids]), np.column_stack([tets, mid_index]).astype(np.int64)
