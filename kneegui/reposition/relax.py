"""The relaxed region of a pose: where soft tissue may move, and what holds it.

The rigid blend moves every soft-tissue node by a mix of the bones' motions. That is cheap and
smooth, but it cannot make the tissue behind a deeply flexed knee bulge, nor keep it out of a
condyle that is not a circle about the F-E axis, so some elements fold. The mesh-improvement
chain (:mod:`kneegui.meshopt.chain`: the foldover-free energy, the quality optimisation, the
smoother) then moves the soft-tissue nodes near the joint; this module says which and how, with
the bones (and the tissue attached to them) held where the kinematics put them:

- the region: corners that are inverted, flat or distorted (and nodes that entered a bone) seed
  it grows ``rings`` mesh edges and ``region_radius``
  (:meth:`ElasticRelaxation.degraded_region`);
- the element geometry: every soft solid's corner tetrahedra (:func:`corner_tetrahedra`), and
  for shells lying on solid faces (skin, capsule, tendon) tetrahedra to a virtual apex inside the
  solid (:func:`shell_face_tetrahedra`);
- bone contact: a soft-tissue node near a bone is kept on the outside of a plane through its
  closest surface point, across the direction in which the distance grows (a penalty whose
  force stops growing 1 mm deep in the energy, a constraint in the quality optimisation), with
  the planes recomputed from the bone surfaces between rounds, so tissue slides along a condyle
  instead of entering it;
- the skin: held to its tangent planes during the untangling (``RelaxOptions.slide_skin``),
  which it may leave outwards only (``RelaxOptions.skin_outward``), and its contours kept in
  order (``contour_margin``) in the untangling as well as in the quality optimisation, so that
  the energy's shape terms, not the optimiser's penalties, carry back the contours the mapping
  crossed.

Element count, node ids and connectivity never change; only the free nodes move.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import replace

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from kneegui.errors import Cancelled, GeometryError, raise_if_cancelled
from kneegui.geometry.transforms import RigidTransform
from kneegui.meshopt.chain import ImprovementOptions, improve_region, progress_span
from kneegui.meshopt.foldover import (
    FoldoverEnergy,
    RelaxOptions,
    RelaxReport,
    edge_matrices,
    next_eps,
    penalised_objective,
)
from kneegui.meshopt.lbfgs import minimize_lbfgs, round_monitor
from kneegui.meshopt.nodes import boundary_node_normals
from kneegui.meshopt.quality_optimiser import (
    REGION_CHUNK,
    SOLID_CORNER_TYPES,
    ConstraintCallback,
    QualityAims,
    QualityOptimisationReport,
    QualityOptions,
    gate_shortfall_nodes,
    optimise_quality,
    shortfall_region,
    with_partners,
)
from kneegui.meshopt.smoother import SmoothingReport, SmoothOptions
from kneegui.model import ElementBlock
from kneegui.quality.feasibility import corner_determinant_gradients, could_be_valid
from kneegui.quality.kernels import corner_determinants
from kneegui.quality.metrics import QualityResult, compute_quality
from kneegui.reposition.contact import BoneSurfaceDistance, DistanceMemo
from kneegui.reposition.midside import MidsideNodes
from kneegui.reposition.rigid_blend import sorted_unique_in_pieces
from kneegui.reposition.skin_contours import ContourOrder, SkinContours
from kneegui.topology import CORNER_NODES, CORNER_TRIPLES, SOLID_FACES, SOLID_TYPES, sorted_unique

__all__ = [
    "ElasticRelaxation",
    "RelaxOptions",
    "RelaxReport",
    "shell_face_tetrahedra",
]

ProgressCallback = Callable[[float, str], None]

#: Around the elements the untangling left inverted, the solids whose corner Jacobian (tet
#: collapse) is below this are held too, with one ring of nodes around them: a nearly flat
#: element holds the quality stage's line search, one for every node
#: (:meth:`ElasticRelaxation._optimise_around_tangles`).
TANGLE_FLAT_BELOW = 0.05

#: Where the virtual apex of a shell's tetrahedra sits, from the shell's centroid (0) to the
#: centroid of the solid it covers (1).
APEX_DEPTH = 0.3


def row_labels(keys: NDArray[np.int64], n_nodes: int) -> NDArray[np.int64]:
    """One label per row of ``keys`` (M, 4) (node indices, or -1), equal exactly where the
    rows are equal.

    ``np.unique(keys, axis=0)`` compares rows as raw bytes and took seconds for a whole-body
    model's faces. Here each pair of columns is packed into one integer, and the rank of the
    first pair with the second becomes one sortable integer. The labels are not ``np.unique``'s
    inverse, but the callers only match equal rows, which is the same in both.
    """
    base = n_nodes + 1
    first = (keys[:, 0] + 1) * base + (keys[:, 1] + 1)
    second = (keys[:, 2] + 1) * base + (keys[:, 3] + 1)
    _, rank = np.unique(first, return_inverse=True)
    if (int(rank.max(initial=0)) + 1) * base * base >= np.iinfo(np.int64).max:
        _, labels = np.unique(keys, axis=0, return_inverse=True)  # would overflow: bytes
        return labels.ravel()
    _, labels = np.unique(rank.ravel() * (base * base) + second, return_inverse=True)
    return labels.ravel()


def shell_face_tetrahedra(
    blocks: Mapping[str, ElementBlock],
    shell_masks: Mapping[str, NDArray[np.bool_]],
    solid_masks: Mapping[str, NDArray[np.bool_]],
    n_nodes: int,
) -> tuple[NDArray[np.int64], sp.csr_matrix]:
    """Tetrahedra that keep shells lying on solid faces from folding.

    For every selected shell that is a face of a selected solid, each triangle of the shell
    (both diagonals of a quad) and an apex inside the solid make a tetrahedron; the apex lies
    :data:`APEX_DEPTH` of the way from the shell's centroid to the solid's. The apexes are
    *virtual nodes* numbered from ``n_nodes`` on; the returned matrix gives their positions as
    linear combinations of the real nodes.

    Returns
    -------
    tets : (T, 4) ndarray of int
        Node indices; index ``n_nodes + k`` is virtual node ``k``.
    virtual : (V, n_nodes) sparse matrix
        ``virtual @ coords`` are the virtual nodes' coordinates.
    """
    shell_keys, shell_conn = [], []
    on_shell = np.zeros(n_nodes, dtype=bool)
    for etype, mask in shell_masks.items():
        block = blocks.get(etype)
        if block is None:
            continue
        conn = block.conn[mask]
        on_shell[conn.ravel()] = True
        k = np.full((len(conn), 4), -1, dtype=np.int64)
        k[:, : conn.shape[1]] = conn
        shell_keys.append(np.sort(k, axis=1))
        padded = np.full((len(conn), 4), -1, dtype=np.int64)
        padded[:, : conn.shape[1]] = conn
        shell_conn.append(padded)
    # every face of the selected solids that could be a shell (all its nodes on shells: a
    # whole-body model's knee region has millions of faces and a few thousand shells) as a
    # sorted, -1 padded 4-tuple, with its owner
    keys, owners, owner_types = [], [], []
    solid_types = [e for e in SOLID_FACES if e in blocks and e in solid_masks]
    for t_index, etype in enumerate(solid_types):
        block = blocks[etype]
        rows = np.flatnonzero(solid_masks[etype])
        for face in SOLID_FACES[etype]:
            nodes = block.conn[np.ix_(rows, list(face))]
            kept = on_shell[nodes].all(axis=1)
            k = np.full((int(np.count_nonzero(kept)), 4), -1, dtype=np.int64)
            k[:, : len(face)] = np.sort(nodes[kept], axis=1)
            keys.append(np.sort(k, axis=1))
            owners.append(rows[kept])
            owner_types.append(np.full(len(k), t_index))
    empty = (np.zeros((0, 4), dtype=np.int64), sp.csr_matrix((0, n_nodes)))
    if not keys or not shell_keys:
        return empty
    face_keys = np.concatenate(keys)
    face_owner = np.concatenate(owners)
    face_type = np.concatenate(owner_types)
    s_keys = np.concatenate(shell_keys)
    s_conn = np.concatenate(shell_conn)
    if len(s_keys) == 0:  # shell roles present but without shells (e.g. no skin part)
        return empty
    # match shells to solid faces by their sorted node tuples
    inverse = row_labels(np.concatenate([face_keys, s_keys]), n_nodes)
    face_id, shell_id = inverse[: len(face_keys)], inverse[len(face_keys) :]
    order = np.argsort(face_id, kind="stable")
    sorted_ids = face_id[order]
    lo = np.searchsorted(sorted_ids, shell_id, side="left")
    hi = np.searchsorted(sorted_ids, shell_id, side="right")
    counts = hi - lo
    shell_rows = np.repeat(np.arange(len(s_keys)), counts)
    face_rows = order[np.concatenate([np.arange(a, b) for a, b in zip(lo, hi, strict=True)])]
    if len(face_rows) == 0:
        return empty
    # one virtual apex per (shell, owning solid): a point inside the solid close to the shell,
    # so that the tetrahedra also see a shell that twists or turns into a dart
    conn = s_conn[shell_rows]
    quad = conn[:, 3] >= 0
    n_pairs = len(face_rows)
    v_rows, v_cols, v_vals = [], [], []
    for t_index, etype in enumerate(solid_types):
        mine = np.flatnonzero(face_type[face_rows] == t_index)
        if len(mine) == 0:
            continue
        solid = blocks[etype].conn[face_owner[face_rows[mine]]]
        solid = solid[:, :4] if etype == "tet10" else solid
        v_rows.append(np.repeat(mine, solid.shape[1]))
        v_cols.append(solid.ravel())
        v_vals.append(np.full(solid.size, APEX_DEPTH / solid.shape[1]))
    for is_quad, width in ((True, 4), (False, 3)):
        mine = np.flatnonzero(quad == is_quad)
        v_rows.append(np.repeat(mine, width))
        v_cols.append(conn[mine, :width].ravel())
        v_vals.append(np.full(len(mine) * width, (1.0 - APEX_DEPTH) / width))
    virtual = sp.csr_matrix(
        (np.concatenate(v_vals), (np.concatenate(v_rows), np.concatenate(v_cols))),
        shape=(n_pairs, n_nodes),
    )
    apex = n_nodes + np.arange(n_pairs)
    tets = [np.column_stack([conn[~quad, 0], conn[~quad, 1], conn[~quad, 2], apex[~quad]])]
    q, qa = conn[quad], apex[quad]
    for a, b, c in ((0, 1, 2), (0, 2, 3), (1, 2, 3), (1, 3, 0)):
        tets.append(np.column_stack([q[:, a], q[:, b], q[:, c], qa]))
    return np.concatenate(tets).astype(np.int64), virtual


#: Corners measured at a time when the relaxation is built (bounds the temporaries: the
#: whole-body demos have millions of corners).
CORNER_CHUNK = 1 << 16


def _rest_corner_geometry(
    x: NDArray[np.float64],
    tets: NDArray[np.int64],
    cancel: Callable[[], bool] | None = None,
) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]:
    """Which corners are usable (not flat at rest), and the inverse rest edge matrices
    ``(U, 3, 3)`` and rest determinants ``(U,)`` of the usable ones.

    Measured :data:`CORNER_CHUNK` corners at a time: each corner's figures are computed on
    their own, so they are those of measuring all at once, without the (C, 3, 3) edge matrices
    of every corner held together. ``cancel()`` is asked before each chunk (True raises
    :class:`kneegui.errors.Cancelled`).
    """
    bounds = range(0, len(tets), CORNER_CHUNK)
    usable = np.zeros(len(tets), dtype=bool)
    det = np.empty(len(tets))
    for lo in bounds:
        raise_if_cancelled(cancel, "relaxation set-up cancelled")
        e0 = edge_matrices(x, tets[lo : lo + CORNER_CHUNK])
        d = det[lo : lo + CORNER_CHUNK] = np.linalg.det(e0)
        scale = np.maximum(np.abs(e0).max(axis=(1, 2)) ** 3, 1e-300)
        usable[lo : lo + CORNER_CHUNK] = np.abs(d) > 1e-12 * scale
    inv = np.empty((int(usable.sum()), 3, 3))
    at = 0
    for lo in bounds:
        raise_if_cancelled(cancel, "relaxation set-up cancelled")
        keep = usable[lo : lo + CORNER_CHUNK]
        if keep.any():
            rows = tets[lo : lo + CORNER_CHUNK][keep]
            inv[at : at + len(rows)] = np.linalg.inv(edge_matrices(x, rows))
            at += len(rows)
    return usable, inv, det[usable]


def edge_adjacency(
    a: NDArray[np.int64],
    b: NDArray[np.int64],
    n: int,
    cancel: Callable[[], bool] | None = None,
) -> sp.csr_matrix:
    """(n, n) int8 adjacency (1 where two nodes share an edge ``a[i]``-``b[i]``, both ways) of
    the edges whose ends are both below ``n``; from the unique node pairs (as
    :func:`~kneegui.meshopt.nodes.unique_pairs`, one way first: the corners repeat each edge
    many times), without the float64 triplets of a sparse sum. ``cancel`` is asked between
    the value ranges the pairs are sorted in
    (:func:`~kneegui.reposition.rigid_blend.sorted_unique_in_pieces`; the 1.76M demo's region:
    1.8 s for the first way at once)."""
    real = (a < n) & (b < n)

    def pairs_of(first: NDArray[np.int64], second: NDArray[np.int64]) -> NDArray[np.int64]:
        key = sorted_unique_in_pieces(first.astype(np.int64) * n + second.astype(np.int64), cancel)
        return np.stack([key // n, key % n], 1)

    one_way = pairs_of(a[real], b[real])
    raise_if_cancelled(cancel, "relaxation set-up cancelled")
    pairs = pairs_of(one_way.ravel(), one_way[:, ::-1].ravel())
    del one_way
    index = np.int32 if max(n, len(pairs)) < 2**31 else np.int64
    indptr = np.zeros(n + 1, dtype=index)
    np.cumsum(np.bincount(pairs[:, 0], minlength=n), out=indptr[1:])
    return sp.csr_matrix(
        (np.ones(len(pairs), dtype=np.int8), pairs[:, 1].astype(index), indptr), shape=(n, n)
    )


#: :meth:`NodeRows.touching` marks the rows in a mask rather than sorting them once they are
#: more than one in this many of all rows (the same sorted rows either way).
TOUCHING_MASK_SHARE = 16


#: The margin :class:`LockedCorners` asks of the proof, relative to an element's largest corner
#: determinant (:func:`~kneegui.quality.feasibility.could_be_valid`): which corners the energy
#: leaves out must not turn on the last bits of a determinant.
LOCKED_PROOF_TOLERANCE = 1e-6


class LockedCorners:
    """The corners (rows of a relaxation's ``tets``) of the elements whose fixed nodes lie on
    two rigid segments or more while some of their nodes are free: tissue welded to femur and
    tibia across the joint. At a pose, :meth:`rows` gives the corners of those the bones'
    motion leaves no valid shape, whatever their free nodes do
    (:func:`~kneegui.quality.feasibility.could_be_valid`, the pre-flight check's proof).

    Such an element stays inverted however the tissue moves; its corners in the energy would
    pull its free nodes, and the neighbours they share, towards a shape that does not exist
    (the coarse welded demo at 90 deg: 54 movable elements inverted with them, 27 without).
    """

    def __init__(
        self,
        blocks: Mapping[str, ElementBlock],
        is_free: NDArray[np.bool_],
        segment_of: NDArray[np.int64],
        tets: NDArray[np.integer],
        node_rows: NodeRows,
    ) -> None:
        n = len(segment_of)
        self._groups: list[tuple[str, NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]]
        self._groups = []
        self.elements = 0
        for etype, block in blocks.items():
            table = CORNER_TRIPLES.get(etype)
            if table is None or etype not in SOLID_TYPES or len(block.conn) == 0:
                continue
            picks = []
            # CORNER_CHUNK elements at a time: a whole-body model has millions, few of them
            # welded to two bones
            for start in range(0, len(block.conn), CORNER_CHUNK):
                part = np.asarray(block.conn[start : start + CORNER_CHUNK], dtype=np.int64)
                welded = is_free[part].any(axis=1) & _on_two_segments(part, is_free, segment_of)
                picks.append(start + np.flatnonzero(welded))
            pick = np.concatenate(picks)
            if not len(pick):
                continue
            conn = np.asarray(block.conn[pick], dtype=np.int64)
            corners = conn[:, np.array(table)].reshape(-1, 4)
            owner = np.repeat(np.arange(len(pick)), len(table))
            # the relaxation keeps only some of an element's corners (a free node, usable at
            # rest, not pinned): find each kept one's row among the corners around its nodes
            near = node_rows.touching(sorted_unique(corners.ravel()[corners.ravel() < n]))
            where = {tuple(int(v) for v in tets[r]): int(r) for r in near}
            found = np.array([where.get(tuple(int(v) for v in c), -1) for c in corners.tolist()])
            kept = found >= 0
            self._groups.append((etype, conn, found[kept], owner[kept]))
            self.elements += len(pick)

    def rows(self, x: NDArray[np.float64], is_free: NDArray[np.bool_]) -> NDArray[np.int64]:
        """Sorted corner rows of the elements that no position of their ``is_free`` nodes can
        make valid with their other nodes at ``x``."""
        out = [np.zeros(0, dtype=np.int64)]
        for etype, conn, rows, owner in self._groups:
            locked = ~could_be_valid(x[conn], is_free[conn], etype, LOCKED_PROOF_TOLERANCE)
            out.append(rows[locked[owner]])
        return sorted_unique(np.concatenate(out))


class NodeRows:
    """The corners (rows of ``tets``) around each real node (below ``n``), as a compressed
    row index: :meth:`touching` picks the corners touching a set of nodes."""

    def __init__(self, tets: NDArray[np.int64], n: int) -> None:
        flat = tets.ravel()
        real = flat < n
        # stable: each node's corners in ascending order
        order = np.argsort(np.where(real, flat, n), kind="stable")[: int(real.sum())]
        index = np.int32 if len(tets) < 2**31 else np.int64
        self.indices = (order // tets.shape[1]).astype(index)
        del order
        self.indptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(flat[real], minlength=n), out=self.indptr[1:])
        self.n_rows = len(tets)

    def touching(self, nodes: NDArray[np.int64]) -> NDArray[np.int64]:
        """Sorted rows of the corners with a node among ``nodes``."""
        nodes = np.asarray(nodes, dtype=np.int64)
        starts = self.indptr[nodes]
        counts = self.indptr[nodes + 1] - starts
        total = int(counts.sum())
        if total == 0:
            return np.zeros(0, dtype=np.int64)
        offsets = np.repeat(starts - np.cumsum(counts) + counts, counts) + np.arange(total)
        if total < self.n_rows // TOUCHING_MASK_SHARE:
            return sorted_unique(self.indices[offsets]).astype(np.int64)
        # many corners: marking them costs a pass over every row, sorting them far more (the
        # 1M demo's region: 1 s, the longest wait for a cancel of the untangling's set-up)
        mask = np.zeros(self.n_rows, dtype=bool)
        mask[self.indices[offsets]] = True
        return np.flatnonzero(mask)


#: A pinned corner's plane in the untangling asks its determinant for this fraction of its rest
#: value (:meth:`ElasticRelaxation._pinned_planes`). Coarse welded demo, movable elements left
#: inverted at 60 / 90 deg (7 December, one run each): 8 / 27 without the planes, 7 / 28 with
#: 0, 6 / 27 with 0.02, 5 / 26 with 0.1 and with 0.3 (tissue deeper than 0.5 mm in a bone at
#: 90 deg: 4, 2, 3, 0 and 1 nodes).
PINNED_MARGIN = 0.1


def _pinned_corners(
    tets: NDArray[np.int64],
    is_free: NDArray[np.bool_],
    segment_of: NDArray[np.int64],
    cancel: Callable[[], bool] | None = None,
) -> NDArray[np.bool_]:
    """Corners with at most one free node whose other real nodes lie on two rigid segments or
    more (virtual nodes count as free); a chunk of :data:`CORNER_CHUNK` corners at a time,
    ``cancel`` asked before each (a whole-body model's region: millions of corners)."""
    out = np.zeros(len(tets), dtype=bool)
    for start in range(0, len(tets), CORNER_CHUNK):
        raise_if_cancelled(cancel, "relaxation set-up cancelled")
        part = tets[start : start + CORNER_CHUNK]
        out[start : start + len(part)] = (is_free[part].sum(axis=1) <= 1) & _on_two_segments(
            part, is_free, segment_of
        )
    return out


def _on_two_segments(
    part: NDArray[np.int64], is_free: NDArray[np.bool_], segment_of: NDArray[np.int64]
) -> NDArray[np.bool_]:
    """Rows of ``part`` (corners or elements) whose fixed real nodes lie on two rigid segments
    or more (free and virtual nodes lie on none)."""
    n = len(segment_of)
    seg = np.where(part < n, segment_of[np.minimum(part, n - 1)], -1)
    seg = np.where(is_free[part], -1, seg)
    on = seg >= 0
    lo = np.where(on, seg, np.iinfo(np.int64).max).min(axis=1)
    hi = np.where(on, seg, -1).max(axis=1)
    return (hi >= 0) & (lo != hi)


def _free_midside_nodes(
    blocks: Mapping[str, ElementBlock] | None,
    is_free: NDArray[np.bool_],
    free: NDArray[np.int64],
    rest: NDArray[np.float64],
) -> MidsideNodes:
    """Mid-side nodes of the 10-node tets among ``free`` whose edge has a free corner."""
    requested = np.zeros(len(is_free), dtype=bool)
    requested[free] = True
    block = None if blocks is None else blocks.get("tet10")
    return MidsideNodes.of_block(block, requested, rest, is_free)


def _distance_gradient(
    p: NDArray[np.float64],
    closest: NDArray[np.float64],
    depth: NDArray[np.float64],
    normal: NDArray[np.float64],
) -> NDArray[np.float64]:
    """The outward unit direction in which the signed distance grows fastest at ``p``: from
    the closest surface point to the point (outside) or from the point to it (inside); the
    surface's own ``normal`` where the point is on the surface. A contact plane with this
    normal through the closest point measures the true depth: with the surface's
    pseudo-normal at an edge or vertex, a node 0.66 mm inside the femur (the hex leg built at
    0 deg, posed to 90 deg) sat exactly on its plane."""
    offset = p - closest
    length = np.linalg.norm(offset, axis=1)
    on_surface = length <= 1e-9 * (1.0 + np.abs(p).max(initial=0.0))
    direction = offset / np.where(on_surface, 1.0, length)[:, None]
    direction *= np.where(depth < 0.0, -1.0, 1.0)[:, None]
    return np.where(on_surface[:, None], normal, direction)


class ElasticRelaxation:
    """Precomputed relaxation of a model's soft tissue (see the module docstring).

    Only the tissue around what the pose degraded is relaxed: corners that are inverted, flat
    or distorted (and nodes that entered a bone) seed a region that grows ``rings`` mesh edges;
    its free nodes move, everything else stays as posed.

    Parameters
    ----------
    rest_coords : (N, 3) ndarray
        Initial coordinates (the reference shapes).
    tets : (C, 4) ndarray of int
        Corner tetrahedra of the soft-tissue solids (:func:`kneegui.topology.corner_tetrahedra`).
    free : (F,) ndarray of int
        Nodes the relaxation may move; every other node stays where the pose put it.
    bones : mapping of segment name to BoneSurfaceDistance or (T, 3, 3) ndarray, optional
        Rest-pose outer surface of each rigid segment (or its triangles), for contact.
    contact_nodes : (K,) ndarray of int, optional
        Free nodes that are kept out of the bones (default: every free node).
    options : RelaxOptions, optional
    virtual : (V, N) sparse matrix, optional
        Virtual nodes ``N + k`` used by ``tets`` (:func:`shell_face_tetrahedra`).
    attached : (A,) ndarray of int, optional
        Nodes that move with a bone; tissue next to them may go as deep into a bone as they do.
    quads : (Q, 4) ndarray of int, optional
        Quad shells whose corner determinants are kept positive (skin, capsule, tendon).
    sliding : (L,) ndarray of int, optional
        Free nodes on the outer surface (the skin) that only slide in their surface's tangent
        plane of the pose being relaxed (``options.slide_skin``): the mapping's smooth crease
        behind a flexed knee keeps its shape instead of being pulled into a fold.
    region_radius : float
        Besides ``options.rings`` mesh edges, the relaxed region takes every free node within
        this distance (model units) of a seed: a fold needs room in millimetres, not in
        elements, to unfold.
    blocks : mapping of str to ElementBlock, optional
        The model's element blocks, for the quality optimisation.
    aims : QualityAims, optional
        Per element of ``blocks``, the quality the optimisation aims at
        (:func:`kneegui.meshopt.quality_optimiser.quality_aims`); without them there is no
        quality optimisation.
    skin_contours : SkinContours, optional
        The skin's contours, kept in order by the quality optimisation.
    contour_margin : float or None
        Every skin contour keeps at least this far (model units) beyond the plane of its
        neighbour nearer the joint in the quality optimisation, so that no contour crosses
        another; None lets them cross.
    segment_of : (N,) ndarray of int, optional
        The rigid segment each node moves with (-1: none). A corner tetrahedron with at most
        one free node whose other nodes lie on two segments or more is left out of the
        energy: the bones' relative motion dictates its shape (tissue welded to femur and
        tibia across the joint), and an inverted one would keep the barrier from hardening
        for every other corner.
    beyond : (B,) ndarray of int, optional
        Soft-tissue nodes outside ``free`` that the quality optimisation may also move, only
        around an element the pose left past one of the gate's levels and worse than at rest
        (:func:`~kneegui.meshopt.quality_optimiser.gate_shortfall_nodes`), and only farther
        than ``options.contact_band`` from every bone (no contact plane holds them): the
        mapping deforms the whole leg a little, and far from the joint that alone took an
        element below the initial model's worst (the demo posed to 0 deg: a calf hex 6 condyle
        radii from the axis, 0.327 against 0.330). Needs ``initial_quality``.
    initial_quality : QualityResult, optional
        Quality of the rest model (every row of ``blocks``): what "worse than at rest" means
        for the ``beyond`` nodes.
    cancel : callable, optional
        Asked between the set-up's steps (seconds each on a whole-body model); True raises
        :class:`kneegui.errors.Cancelled`.
    """

    def __init__(
        self,
        rest_coords: NDArray[np.float64],
        tets: NDArray[np.int64],
        free: NDArray[np.int64],
        bones: Mapping[str, BoneSurfaceDistance | NDArray[np.float64]] | None = None,
        contact_nodes: NDArray[np.int64] | None = None,
        options: RelaxOptions | None = None,
        virtual: sp.csr_matrix | None = None,
        attached: NDArray[np.int64] | None = None,
        quads: NDArray[np.int64] | None = None,
        region_radius: float = 0.0,
        sliding: NDArray[np.int64] | None = None,
        blocks: Mapping[str, ElementBlock] | None = None,
        aims: QualityAims | None = None,
        skin_contours: SkinContours | None = None,
        contour_margin: float | None = None,
        segment_of: NDArray[np.int64] | None = None,
        beyond: NDArray[np.int64] | None = None,
        initial_quality: QualityResult | None = None,
        cancel: Callable[[], bool] | None = None,
    ) -> None:
        def check() -> None:
            raise_if_cancelled(cancel, "relaxation set-up cancelled")

        self.options = options or RelaxOptions()
        self.blocks = blocks
        self.aims = aims
        self.contour_order = (
            ContourOrder(skin_contours, rest_coords, contour_margin)
            if skin_contours is not None and contour_margin is not None
            else None
        )
        n = len(rest_coords)
        self.rest = np.asarray(rest_coords, dtype=np.float64)
        self.region_radius = float(region_radius)
        self.virtual = sp.csr_matrix((0, n)) if virtual is None else sp.csr_matrix(virtual)
        n_aug = n + self.virtual.shape[0]
        free = sorted_unique(np.asarray(free, dtype=np.int64))
        is_free = np.zeros(n_aug, dtype=bool)
        is_free[free] = True
        tets = np.asarray(tets, dtype=np.int64)
        tets = tets[is_free[tets].any(axis=1)]
        self.pinned_corners = 0
        #: the pinned corners with one free node, none virtual: (P, 4) node indices, the free
        #: node's column and the rest determinant (:meth:`_pinned_planes`)
        self._pinned = (np.zeros((0, 4), dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0))
        if segment_of is not None and len(tets):
            pinned = _pinned_corners(tets, is_free, np.asarray(segment_of, dtype=np.int64), cancel)
            self.pinned_corners = int(pinned.sum())
            held = tets[pinned]
            held = held[np.all(held < n, axis=1) & (is_free[held].sum(axis=1) == 1)]
            rest_det = np.linalg.det(edge_matrices(self.rest, held)) if len(held) else np.zeros(0)
            self._pinned = (held, np.argmax(is_free[held], axis=1), rest_det)
            tets = tets[~pinned]
        usable, self.inv_rest, det0 = _rest_corner_geometry(self.augment(rest_coords), tets, cancel)
        check()
        # node indices fit 32 bits below 2**31 nodes: half the memory of the corners' table,
        # held for every later export (the 2M-node deck: millions of corners)
        index = np.int32 if n_aug < 2**31 else np.int64
        self.tets = tets[usable].astype(index)
        del tets
        self.weight = (
            np.ones(len(self.tets)) if self.options.uniform_weights else np.abs(det0) / 6.0
        )
        del det0
        # free nodes that are not in any tetrahedron have no energy: leave them alone
        in_tet = np.zeros(n_aug, dtype=bool)
        in_tet[self.tets.ravel()] = True
        self.free = free[in_tet[free]]
        self.is_free = np.zeros(n, dtype=bool)
        self.is_free[self.free] = True
        self._rest_flat: bool | None = None  # :meth:`_flat_at_rest`
        self.n_nodes = n
        check()
        # node adjacency along the corner edges (real nodes), for growing the relaxed region
        self._adjacency = edge_adjacency(
            np.repeat(self.tets[:, 0], 3), self.tets[:, 1:].ravel(), n, cancel
        )
        check()
        # corner rows by (real) node, to pick the corners touching a set of nodes
        self._node_rows = NodeRows(self.tets, n)
        # elements welded to two bones with free nodes: their corners leave the energy at a
        # pose that proves them locked
        self._locked = None
        if segment_of is not None and blocks is not None:
            check()
            self._locked = LockedCorners(
                blocks, self.is_free, np.asarray(segment_of, dtype=np.int64), self.tets,
                self._node_rows,
            )  # fmt: skip
        self.bones = {
            name: tri if isinstance(tri, BoneSurfaceDistance) else BoneSurfaceDistance(tri)
            for name, tri in (bones or {}).items()
            if isinstance(tri, BoneSurfaceDistance) or len(tri)
        }
        if contact_nodes is None:
            contact_nodes = self.free
        contact_nodes = np.asarray(contact_nodes, dtype=np.int64)
        keep = self.is_free[contact_nodes]
        self.contact_nodes = contact_nodes[keep]
        # each contact node keeps at least its rest clearance from each bone, up to
        # contact_clearance (tissue lying on a bone at rest may stay on it)
        self._rest_floor: dict[str, NDArray[np.float64]] = {}
        self._contact_memo: dict[str, DistanceMemo] = {}
        for name, surface in self.bones.items():
            check()
            depth, _, _, node_distance = surface.query(self.rest[self.contact_nodes], cancel=cancel)
            self._rest_floor[name] = np.clip(depth, 0.0, self.options.contact_clearance)
            self._contact_memo[name] = DistanceMemo(
                surface, self.rest[self.contact_nodes], depth, node_distance
            )
        quads = np.zeros((0, 4), dtype=np.int64) if quads is None else np.asarray(quads)
        if len(quads):
            rest_det = corner_determinants(self.rest[quads], "quad4")
            quads = quads[(rest_det > 0).all(axis=1) & self.is_free[quads].any(axis=1)]
        self.quads = quads.astype(np.int64)
        sliding = np.zeros(0, dtype=np.int64) if sliding is None else np.asarray(sliding)
        self.is_skin = np.zeros(n, dtype=bool)
        self.is_skin[sliding.astype(np.int64)] = True
        self.sliding = np.intersect1d(sliding.astype(np.int64), self.free)
        self._quad_outward = self._outward_quad_signs()
        # tissue next to an attachment may go as deep into another bone as the attachment
        # itself (a patella pressed into the trochlea): holding it out would tear the elements
        # between the attachment and the contact plane
        self._attached_nb: sp.csr_matrix | None = None
        check()
        if attached is not None and len(attached):
            attached = sorted_unique(np.asarray(attached, dtype=np.int64))
            nb = self._adjacency[self.contact_nodes][:, attached].tocsr()
            used = sorted_unique(nb.indices)
            self._attached_nodes = attached[used]
            self._attached_memo = {}
            for name, surface in self.bones.items():
                depth, _, _, node_distance = surface.query(self.rest[self._attached_nodes])
                self._attached_memo[name] = DistanceMemo(
                    surface, self.rest[self._attached_nodes], depth, node_distance
                )
            self._attached_nb = sp.csr_matrix(
                (np.ones(nb.nnz), np.searchsorted(used, nb.indices), nb.indptr),
                shape=(len(self.contact_nodes), len(used)),
            )

        # 10-node tets: the energy and the quality optimisation see their corner tetrahedra only;
        # a free mid-side node sits where it sat at rest relative to its edge's ends
        self._midside = _free_midside_nodes(blocks, self.is_free, free, self.rest)
        self.initial_quality = initial_quality
        self.is_beyond = np.zeros(n, dtype=bool)
        if beyond is not None:
            self.is_beyond[np.asarray(beyond, dtype=np.int64)] = True
            self.is_beyond &= ~self.is_free

    def carry_midside(
        self, before: NDArray[np.float64], after: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """``after`` with each free mid-side node at the middle of its edge's two corner nodes,
        plus its offset from there at rest (:meth:`MidsideNodes.straighten
        <kneegui.reposition.midside.MidsideNodes.straighten>`; ``before`` is not read, kept for
        the callers).

        Not moved from ``before`` by its ends' mean motion: the mapping places a mid-side node
        on its own, up to 1.4 edge lengths off its edge's straight line on the coarse 10-node
        demo at 90 deg (the gate's mid-side normal offset; 0 at rest), and that offset stayed."""
        return self._midside.straighten(after)

    def midside_out_of_bones(
        self, x: NDArray[np.float64], transforms: Mapping[str, RigidTransform] | None
    ) -> NDArray[np.float64]:
        """``x`` with each free mid-side node that lies deeper inside a posed bone than at rest
        (or inside it, when it was outside) moved out to that depth, at right angles to its
        edge (:meth:`MidsideNodes.out_of_bones
        <kneegui.reposition.midside.MidsideNodes.out_of_bones>` with no tolerance; a new array
        when any moves).

        The contact holds the corner nodes out of the bones; a straight edge between two corners
        pressed onto a convex bone cuts into it, and its mid-side node with it (the coarse
        10-node demo at 90 deg: 140 mid-side nodes deeper than 0.5 mm, no corner node).
        """
        if not self.bones or transforms is None:
            return x
        return self._midside.out_of_bones(x, self.bones, transforms, 0.0)

    def is_free_quad(self, free: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Which of :attr:`quads` have a node among ``free``."""
        mask = np.zeros(self.n_nodes, dtype=bool)
        mask[free] = True
        return mask[self.quads].any(axis=1)

    def augment(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Coordinates of the real nodes followed by those of the virtual nodes."""
        return np.vstack([x, self.virtual @ x]) if self.virtual.shape[0] else x

    # ------------------------------------------------------------------ region
    def corner_distortion(
        self, x: NDArray[np.float64], cancel: Callable[[], bool] | None = None
    ) -> tuple[NDArray, NDArray]:
        """Per corner: det J and the shape distortion ``|J|^2 / (3 det J^(2/3))`` (1 = similar);
        ``cancel`` is asked before every chunk of corners."""
        xa = self.augment(x)
        det, shape = np.empty(len(self.tets)), np.empty(len(self.tets))
        for lo in range(0, len(self.tets), CORNER_CHUNK):
            raise_if_cancelled(cancel, "relaxation cancelled while finding its region")
            part = slice(lo, lo + CORNER_CHUNK)
            jac = edge_matrices(xa, self.tets[part]) @ self.inv_rest[part]
            d = det[part] = np.linalg.det(jac)
            frob = np.einsum("cij,cij->c", jac, jac)
            with np.errstate(invalid="ignore", divide="ignore"):
                shape[part] = np.where(d > 0, frob / (3.0 * np.cbrt(d) ** 2), np.inf)
        return det, shape

    def degraded_region(
        self,
        x: NDArray[np.float64],
        extra_seeds: NDArray[np.int64] | None = None,
        cancel: Callable[[], bool] | None = None,
    ) -> NDArray[np.int64]:
        """Free nodes within ``rings`` edges or ``region_radius`` of a degraded corner (or of
        ``extra_seeds``); ``cancel`` as for :meth:`corner_distortion`."""
        opt = self.options
        det, shape = self.corner_distortion(x, cancel)
        bad = (det < opt.seed_volume_ratio) | (det > 1.0 / opt.seed_volume_ratio)
        bad |= shape > opt.seed_shape
        seed = np.zeros(self.n_nodes, dtype=bool)
        nodes = self.tets[bad].ravel()
        seed[nodes[nodes < self.n_nodes]] = True
        if extra_seeds is not None:
            seed[extra_seeds] = True
        region = self._reach(seed, opt.rings)
        if self.region_radius > 0 and seed.any():
            from scipy.spatial import cKDTree

            dist, _ = cKDTree(x[seed]).query(x[self.free], distance_upper_bound=self.region_radius)
            region[self.free[np.isfinite(dist)]] = True
        return np.flatnonzero(region & self.is_free)

    # ------------------------------------------------------------------ contact
    def _contact_planes(
        self,
        x: NDArray[np.float64],
        nodes: NDArray[np.int64],
        transforms: Mapping[str, RigidTransform],
        cancel: Callable[[], bool] | None = None,
        chords: bool = True,
    ) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Constraints ``n . x_node >= offset`` for the given nodes near a bone (with
        ``chords``, those of :meth:`_chord_planes` too), and each
        node's smallest margin ``depth - allowed depth`` over the bones (< 0: too deep; a lower
        bound where it is more than the contact band: those nodes are not measured again,
        :class:`~kneegui.reposition.contact.DistanceMemo`). ``cancel`` is asked before each
        bone (the first call of an export measures every contact node: seconds at 1.76M)."""
        clearance, band = self.options.contact_clearance, self.options.contact_band
        out_nodes, normals, offsets = [], [], []
        nearest = np.full(len(nodes), np.inf)
        p = x[nodes]
        nb = None
        if self._attached_nb is not None:
            nb = self._attached_nb[np.searchsorted(self.contact_nodes, nodes)].tocsr()
        for name in self.bones:
            raise_if_cancelled(cancel, "relaxation cancelled while measuring the contact")
            tr = transforms.get(name)
            if tr is None:
                continue
            local = tr.inverse().apply(p)
            slot = np.searchsorted(self.contact_nodes, nodes)
            depth, point, normal, measured = self._contact_memo[name].query(
                slot, local, band, cancel
            )
            normal[measured] = _distance_gradient(
                local[measured], point[measured], depth[measured], normal[measured]
            )
            floor = self._rest_floor[name][slot].copy()
            if nb is not None and nb.nnz:
                att = tr.inverse().apply(x[self._attached_nodes])
                every = np.arange(len(att))
                att_depth = np.minimum(
                    self._attached_memo[name].query(every, att, clearance)[0], clearance
                )
                rows = np.repeat(np.arange(len(nodes)), np.diff(nb.indptr))
                np.minimum.at(floor, rows, att_depth[nb.indices])
            nearest = np.minimum(nearest, depth - floor)
            near = depth < band
            if not near.any():
                continue
            n_world = tr.apply_vector(normal[near])
            p_world = tr.apply(point[near])
            out_nodes.append(np.flatnonzero(near))
            normals.append(n_world)
            offsets.append(np.einsum("ij,ij->i", n_world, p_world) + floor[near])
            if chords and len(self._midside):
                rows, n_chord, off_chord = self._chord_planes(x, nodes, name, tr, band)
                out_nodes.append(rows)
                normals.append(n_chord)
                offsets.append(off_chord)
        if not out_nodes:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0), nearest
        return (
            np.concatenate(out_nodes),
            np.concatenate(normals),
            np.concatenate(offsets),
            nearest,
        )

    def _pinned_planes(
        self, x: NDArray[np.float64], movable: NDArray[np.bool_]
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """Planes (global ``nodes, normals, offsets``) that ask each pinned corner (one free
        node, its other nodes on two bones) whose free node is ``movable`` for a positive
        determinant: linear in that node, ``det = g . x + c``, so the plane
        ``g . x >= PINNED_MARGIN * rest det - c`` (unit normal) is exact. The corners stay out
        of the energy: its barrier on them pulled the tissue around them apart (when kept, 295
        corners and 87 movable elements inverted on the welded demo at 90 deg, 4 December)."""
        tets, column, rest_det = self._pinned
        node = tets[np.arange(len(tets)), column] if len(tets) else np.zeros(0, dtype=np.int64)
        keep = movable[node] & (rest_det != 0)
        tets, column, rest_det, node = tets[keep], column[keep], rest_det[keep], node[keep]
        if not len(tets):
            return node, np.zeros((0, 3)), np.zeros(0)
        det, grads = corner_determinant_gradients(x[tets])
        # oriented as at rest: the determinant's sign there is the valid one
        sign = np.sign(rest_det)
        det = sign * det
        g = sign[:, None] * grads[np.arange(len(tets)), column]
        size = np.linalg.norm(g, axis=1)
        ok = size > 0
        g, size, det, node, rest_det = g[ok], size[ok], det[ok], node[ok], np.abs(rest_det[ok])
        offsets = (PINNED_MARGIN * rest_det - det + np.einsum("ij,ij->i", g, x[node])) / size
        return node, g / size[:, None], offsets

    def _chord_planes(
        self,
        x: NDArray[np.float64],
        nodes: NDArray[np.int64],
        name: str,
        tr: RigidTransform,
        band: float,
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """Constraints on the corner nodes of 10-node tet edges near bone ``name``: the edge's
        mid-side node, carried with it (:meth:`carry_midside`), no deeper inside the bone than
        at rest or than its surface. Rows index ``nodes``.

        The corner contact alone holds the corners out of a bone, and a corner slides along it:
        around a bone's rim, an edge between two corners lying on it cut up to 0.47 edge lengths
        deep into the tibia (the coarse 10-node demo at 90 deg), and its mid-side node put back
        on the surface bent the edge that far (the gate's mid-side normal offset). Each corner
        of such an edge among ``nodes`` gets the plane at its current position moved out by the
        depth the edge's middle must gain (each may give up the margin the middle has, when it
        has one): if both keep theirs, so does the middle. The planes are refitted every round,
        like the corners' own. The untangling's form; the quality stage holds the middle
        itself (:meth:`_chord_middle_planes`)."""
        found = self._chords_in_bone(x, nodes, name, tr, band)
        if found is None:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0)
        edges, slot, listed, n, need = found
        mid = self._midside
        rows, normals, offsets = [], [], []
        for k in range(2):
            keep = listed[edges, k]
            corner = mid.ends[edges[keep], k]
            rows.append(slot[edges[keep], k])
            normals.append(n[keep])
            offsets.append(np.einsum("ij,ij->i", n[keep], x[corner]) + need[keep])
        return np.concatenate(rows), np.concatenate(normals), np.concatenate(offsets)

    def _chord_middle_planes(
        self,
        x: NDArray[np.float64],
        nodes: NDArray[np.int64],
        transforms: Mapping[str, RigidTransform],
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
        """The quality stage's form of :meth:`_chord_planes`: one plane on the middle of each
        such edge's two corners (global ``nodes, normals, offsets, partners``,
        :data:`~kneegui.meshopt.quality_optimiser.ConstraintCallback`), moved out by the depth
        the middle must gain, so that either corner may give way. Asking each corner for the
        whole depth crushed knee-flesh tets squeezed behind the joint (the coarse 10-node demo
        at 90 deg: three corners of a tet moved about 20 mm, collapse 0.061 against the initial
        worst 0.108)."""
        mid = self._midside
        out: list[tuple] = []
        for name in self.bones:
            tr = transforms.get(name)
            if tr is None:
                continue
            found = self._chords_in_bone(x, nodes, name, tr, self.options.contact_band)
            if found is None:
                continue
            edges, _, _, n, need = found
            a, b = mid.ends[edges, 0], mid.ends[edges, 1]
            middle = 0.5 * (x[a] + x[b])
            out.append((a, n, np.einsum("ij,ij->i", n, middle) + need, b))
        if not out:
            return (
                np.zeros(0, dtype=np.int64),
                np.zeros((0, 3)),
                np.zeros(0),
                np.zeros(0, dtype=np.int64),
            )
        return tuple(np.concatenate(p) for p in zip(*out, strict=True))

    def _chords_in_bone(
        self,
        x: NDArray[np.float64],
        nodes: NDArray[np.int64],
        name: str,
        tr: RigidTransform,
        band: float,
    ) -> tuple | None:
        """The 10-node tet edges with a corner among ``nodes`` whose carried middle lies
        within ``band`` of bone ``name``: ``(edges, slot, listed, normals, need)`` (the
        corners' rows in ``nodes`` and whether each is there, the surface normals in world
        axes, how far out each middle must move); None without any."""
        mid = self._midside
        slot = np.searchsorted(nodes, mid.ends)
        slot = np.minimum(slot, len(nodes) - 1)
        listed = nodes[slot] == mid.ends  # (M, 2)
        edges = np.flatnonzero(listed.any(axis=1))
        if len(edges) == 0:
            return None
        local = tr.inverse().apply(mid.carried(x, edges))
        boxed = np.flatnonzero(self.bones[name].in_box(local))
        depth, _, normal, _ = self.bones[name].query(local[boxed])
        near = depth < band
        if not near.any():
            return None
        edges, boxed = edges[boxed[near]], boxed[near]
        floor = np.minimum(mid.rest_depth(name, self.bones[name])[edges], 0.0)
        need = floor - depth[near]  # > 0: the middle must move out this far
        return edges, slot, listed, tr.apply_vector(normal[near]), need

    # ------------------------------------------------------------------ solve
    def energy(
        self,
        free: NDArray[np.int64],
        cancel: Callable[[], bool] | None = None,
        skip: NDArray[np.int64] | None = None,
    ) -> FoldoverEnergy:
        """The foldover-free energy of the corners touching the nodes ``free`` but the sorted
        rows ``skip`` (``cancel`` is asked while it is built)."""
        rows = self._node_rows.touching(free)
        if skip is not None and len(skip):
            rows = rows[~np.isin(rows, skip, assume_unique=True)]
        raise_if_cancelled(cancel, "relaxation cancelled while its energy was built")
        return FoldoverEnergy(
            self.tets[rows],
            self.inv_rest,
            self.weight,
            self.virtual,
            self.quads[self.is_free_quad(free)],
            self.rest,
            free,
            self.options.volume_weight,
            self.options.shell_weight,
            rows=rows,
            cancel=cancel,
        )

    def locked_corners(self, x: NDArray[np.float64]) -> NDArray[np.int64]:
        """Sorted rows of the corners of the elements that the bones at ``x`` leave no valid
        shape whatever the free nodes do (:class:`LockedCorners`); none without ``segment_of``
        and ``blocks``."""
        if self._locked is None:
            return np.zeros(0, dtype=np.int64)
        return self._locked.rows(x, self.is_free)

    def region(self, transforms: Mapping[str, RigidTransform] | None = None) -> RelaxedRegion:
        """This relaxation for a pose whose bones moved by ``transforms`` (None: no contact), as
        the region of the mesh-improvement chain (:func:`kneegui.meshopt.chain.improve_region`);
        it has no smoothing stage of its own (:class:`RelaxedRegion`)."""
        return RelaxedRegion(self, transforms)

    def relax(
        self,
        coords: NDArray[np.float64],
        transforms: Mapping[str, RigidTransform] | None = None,
        progress: ProgressCallback | None = None,
        cancel: Callable[[], bool] | None = None,
        quality: QualityOptions | None = None,
    ) -> tuple[NDArray[np.float64], RelaxReport]:
        """Untangle a pose and bring its region within the quality aims (the chain's first two
        stages; the second only with ``blocks`` and ``aims``).

        Parameters
        ----------
        coords : (N, 3) ndarray
            The pose to start from (not modified).
        transforms : mapping of segment name to RigidTransform, optional
            The bones' motions in this pose (needed for contact).
        progress, cancel : callable, optional
        quality : QualityOptions, optional
            The quality optimisation's parameters (default: the export's,
            :class:`~kneegui.meshopt.chain.ImprovementOptions`).

        Returns
        -------
        coords : (N, 3) ndarray
            Relaxed coordinates (a new array).
        report : RelaxReport
        """
        options = ImprovementOptions(relax=self.options, smooth=None)
        if quality is not None:
            options = ImprovementOptions(relax=self.options, quality=quality, smooth=None)
        x, report = improve_region(coords, self.region(transforms), options, progress, cancel)
        return x, report.relaxation

    def untangle(
        self,
        coords: NDArray[np.float64],
        transforms: Mapping[str, RigidTransform] | None,
        stop_when_untangled: bool,
        progress: ProgressCallback,
        cancel: Callable[[], bool],
        untangled: Callable[[NDArray[np.float64]], None] | None = None,
    ) -> tuple[NDArray[np.float64], RelaxReport, bool]:
        """The chain's first stage on the degraded region (seeded also by skin nodes out of
        contour order): the energy's rounds (and restarts), ending when ``stop_when_untangled``
        as soon as nothing is inverted and the contact and contour-order planes have reached
        their final stiffness. Returns the new coordinates, the report and whether the quality
        optimisation may follow. ``untangled(coords)`` is called once with a copy of the whole
        pose after the first round that leaves nothing inverted (before the rounds at full
        stiffness: a window shows it while they run); it cannot change the result."""
        x = np.array(coords, dtype=np.float64, copy=True)
        report = RelaxReport()
        if len(self.free) == 0 or len(self.tets) == 0:
            return x, report, False
        use_contact = bool(self.bones) and transforms is not None
        penetrating, report.deepest_penetration = self._penetrating(x, transforms, cancel)
        raise_if_cancelled(cancel, "relaxation cancelled")
        t = time.perf_counter()
        if self.contour_order is not None:
            crossing = self.contour_order.crossing(x)
            penetrating = crossing if penetrating is None else np.union1d(penetrating, crossing)
        free = self.degraded_region(x, penetrating, cancel)
        report.region_seconds = time.perf_counter() - t
        raise_if_cancelled(cancel, "relaxation cancelled")
        report.free_nodes = len(free)
        d_min = np.inf  # nothing tangled
        if len(free):
            pose = x.copy()
            contact_transforms = transforms if use_contact else None
            # without blocks and aims there is no quality optimisation to hand over to
            optimise_next = (
                stop_when_untangled and self.blocks is not None and self.aims is not None
            )
            skip = self.locked_corners(x)
            report.locked_corners = len(skip)
            skin = self.skin_outward_planes(pose)
            x, d_min, whole, det = self._minimise_energy(
                x,
                free,
                contact_transforms,
                optimise_next,
                report,
                progress,
                cancel,
                skip=skip,
                untangled=untangled,
                skin=skin,
            )
            if d_min <= 0 and self.options.slow_eps_decrease > 0:
                x, d_min = self._slow_pass(
                    pose, x, whole, det, contact_transforms, optimise_next, report, progress,
                    cancel, skip, skin,
                )  # fmt: skip
        x = self.carry_midside(coords, x)
        return self.midside_out_of_bones(x, transforms if use_contact else None), report, d_min > 0

    def _slow_pass(
        self,
        pose: NDArray[np.float64],
        x: NDArray[np.float64],
        whole: FoldoverEnergy,
        det: NDArray[np.float64],
        transforms: Mapping[str, RigidTransform] | None,
        optimise_next: bool,
        report: RelaxReport,
        report_progress: ProgressCallback,
        should_cancel: Callable[[], bool],
        skip: NDArray[np.int64] | None = None,
        skin: tuple[NDArray, NDArray, NDArray] | None = None,
    ) -> tuple[NDArray[np.float64], float]:
        """The last pass when the rounds and restarts left corners inverted at ``x`` (``det``
        over the corners of their region's energy ``whole``, as :meth:`_minimise_energy`
        returns them): the free nodes within ``slow_rings`` of them start again from ``pose``
        and run the rounds with
        ``eps`` falling more slowly (:class:`RelaxOptions`); the rest of the region keeps
        ``x``. Returns whichever of the two leaves fewer corners of the region inverted (then
        the larger smallest det J), and records the pass in ``report.slow_pass`` (its rounds are
        not counted in ``report.rounds``, which are the first pass's). Beyond
        ``slow_pass_nodes`` it does not run and ``x`` is returned as it is. ``skin``: the
        first pass's one-sided skin planes (:meth:`skin_outward_planes`)."""
        opt = self.options
        stuck = whole.nodes[self._stuck_nodes(whole, det)]
        region = self._within_rings(stuck, opt.slow_rings, whole.nodes[whole.free])
        before = (int(np.sum(det <= 0)), -float(det.min()))
        if len(region) > opt.slow_pass_nodes:
            report.slow_pass = {
                "nodes": len(region),
                "ran": False,
                "rounds": 0,
                "restarts": 0,
                "iterations": 0,
                "inverted_corners_before": before[0],
                "inverted_corners_after": before[0],
                "kept": False,
            }
            return x, -before[1]
        start = x.copy()
        start[region] = pose[region]
        second = RelaxReport()

        def progress(fraction: float, message: str) -> None:
            report_progress(fraction, f"{message} (slow pass around what stayed inverted)")

        slow = replace(opt, eps_decrease=opt.slow_eps_decrease)
        x_slow, _, _, _ = self._minimise_energy(
            start, region, transforms, optimise_next, second, progress, should_cancel, slow, skip,
            skin=skin,
        )  # fmt: skip
        _, _, det_slow = whole.energy(x_slow[whole.nodes], 1e-9)
        after = (int(np.sum(det_slow <= 0)), -float(det_slow.min()))
        kept = after < before
        report.slow_pass = {
            "nodes": len(region),
            "ran": True,
            "rounds": second.rounds,
            "restarts": second.restarts,
            "iterations": second.iterations,
            "inverted_corners_before": before[0],
            "inverted_corners_after": after[0],
            "kept": kept,
        }
        if not kept:
            return x, -before[1]
        report.min_det_after = -after[1]
        report.inverted_corners_after = after[0]
        report.contact_released = second.contact_released
        report.sliding_released = second.sliding_released
        return x_slow, -after[1]

    def _minimise_energy(
        self,
        x: NDArray[np.float64],
        free: NDArray[np.int64],
        transforms: Mapping[str, RigidTransform] | None,
        optimise_next: bool,
        report: RelaxReport,
        report_progress: ProgressCallback,
        should_cancel: Callable[[], bool],
        options: RelaxOptions | None = None,
        skip: NDArray[np.int64] | None = None,
        untangled: Callable[[NDArray[np.float64]], None] | None = None,
        skin: tuple[NDArray, NDArray, NDArray] | None = None,
    ) -> tuple[NDArray[np.float64], float, FoldoverEnergy, NDArray[np.float64]]:
        """The energy's rounds (and restarts) over the region ``free``, with contact when
        ``transforms`` are given, ending as soon as nothing is inverted when the quality
        optimisation follows (``optimise_next``); fills ``report``. Returns the new coordinates,
        the smallest corner det J, the region's energy and its corners' det J at the end (what
        the slow pass starts from). ``options`` replaces the relaxation's own for this run (the
        slow pass's schedule). The corners ``skip`` (:meth:`locked_corners`) are left out.
        ``untangled``: as :meth:`untangle`'s. ``skin``: one-sided planes (global ``nodes,
        normals, offsets``, :meth:`skin_outward_planes`) held like the bone contact."""
        opt = options or self.options
        if skin is None:
            skin = (np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0))
        whole = sub = self.energy(free, should_cancel, skip)
        raise_if_cancelled(should_cancel, "relaxation cancelled")
        x_start = x.copy()  # the pose: where a restart puts stuck nodes back
        _, _, det = sub.energy(x[sub.nodes], 1e-3)
        report.corners = len(sub.tets)
        report.min_det_before = float(det.min())
        report.inverted_corners_before = int(np.sum(det <= 0))
        d_min = report.min_det_before
        eps = float(np.sqrt(1e-12 + 0.04 * min(d_min, 0.0) ** 2)) if d_min <= 0 else 1e-9
        eps = max(eps, 1e-9)
        contact_region = self.contact_nodes[np.isin(self.contact_nodes, free)]
        if transforms is None:
            contact_region = contact_region[:0]
        stiffness = opt.untangling_contact_stiffness
        planes = (np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros(0))
        released = np.zeros(0, dtype=np.int64)  # let off the bone contact
        unslid = np.zeros(0, dtype=np.int64)  # sliding skin nodes let off their planes
        order = self.contour_order

        def variables(sub: FoldoverEnergy, contact: NDArray[np.int64]) -> tuple:
            """What the rounds need of the nodes ``sub`` moves, from ``x``: their coordinates,
            the variables' scale (the diagonal of the Hessian at rest, Jacobi preconditioning:
            elements of very different sizes otherwise make L-BFGS crawl), its sliding rows, its
            free nodes and those of the ``contact`` nodes among them."""
            scale = 1.0 / np.sqrt(np.maximum(sub.diagonal[sub.free], 1e-300))[:, None]
            rows, normals = self._sliding_rows(x_start, sub)  # the pose's tangent planes
            keep = ~np.isin(sub.nodes[sub.free[rows]], unslid)
            is_sub_free = np.zeros(self.n_nodes, dtype=bool)
            is_sub_free[sub.nodes[sub.free]] = True
            sliding = (rows[keep], normals[keep])
            return x[sub.nodes], scale, sliding, is_sub_free, contact[is_sub_free[contact]]

        xl, scale, sliding, is_sub_free, contact_global = variables(sub, contact_region)
        # the round that left the fewest corners inverted: a restart puts the stuck nodes back
        # where the pose had them, and where they cannot come free (tissue locked between two
        # bones) the attempts after it end with more corners inverted than the first
        best: tuple | None = None
        best_round = 0
        for attempt in range(1 + opt.restarts):
            if attempt:
                if d_min > 0:
                    break
                # the schedule drove eps to its floor with corners still inverted (typically
                # nodes pressed onto one point while the barrier was soft): put those nodes
                # back where the pose had them and start again from a soft barrier, moving
                # only the nodes around them (the rest of the region keeps what it reached)
                x[sub.nodes] = xl
                if sub is not whole:
                    _, _, det = whole.energy(x[whole.nodes], eps)
                stuck = whole.nodes[self._stuck_nodes(whole, det)]
                x[stuck] = x_start[stuck]
                sub = whole
                if opt.restart_rings > 0:
                    sub = self.energy(
                        self._within_rings(stuck, opt.restart_rings, free), should_cancel, skip
                    )
                # a sliding skin node cannot leave its tangent plane, so the tissue pressed
                # against it from inside (by a bone, or pinched in a crease) has nowhere to go:
                # the stuck ones may now move off their plane
                slides = self._sliding_rows(x_start, sub)
                letting = np.intersect1d(sub.nodes[sub.free[slides[0]]], stuck)
                letting = np.setdiff1d(letting, unslid)
                unslid = np.union1d(unslid, letting)
                report.sliding_released += len(letting)
                if attempt == opt.restarts:
                    # last chance: where bone contact presses the tissue flat (tissue pinched
                    # between femur and tibia at deep flexion) a valid element matters more
                    # than a node slightly inside a bone, which the pose report counts
                    released = np.union1d(released, stuck)
                    report.contact_released = len(released)
                contact = np.setdiff1d(contact_region, released)
                xl, scale, sliding, is_sub_free, contact_global = variables(sub, contact)
                eps = opt.restart_eps
                stiffness = opt.untangling_contact_stiffness
                report.restarts += 1
            # the attempt's region; a round leaving corners inverted focuses the next on them
            pass_sub, pass_contact = sub, contact_global
            pass_free = pass_sub.nodes[pass_sub.free]
            rnd_untangled = False
            fewest_inverted, stalled = np.inf, 0
            for rnd in range(opt.max_rounds):
                if should_cancel():
                    raise Cancelled("relaxation cancelled")
                if len(contact_global) or order is not None or len(self._pinned[0]) or len(skin[0]):
                    x[sub.nodes] = xl
                    parts = []
                    if len(contact_global):
                        which, c_normals, c_offsets, _ = self._contact_planes(
                            x, contact_global, transforms
                        )
                        parts.append((contact_global[which], c_normals, c_offsets))
                        report.contact_nodes = len(sorted_unique(contact_global[which]))
                    if order is not None:
                        o_nodes, o_normals, o_offsets = order.constraints(x)
                        keep = is_sub_free[o_nodes]
                        parts.append((o_nodes[keep], o_normals[keep], o_offsets[keep]))
                    # the pinned corners stay out of the energy (a barrier on corners the
                    # bones alone shape pulled the tissue around them apart); a plane on their
                    # free node asks them positive, softly, like the bone contact
                    parts.append(self._pinned_planes(x, is_sub_free))
                    # the skin may bulge out where the flesh under it is pressed together (the
                    # crease behind a flexed knee), never fold in (RelaxOptions.skin_outward)
                    keep = is_sub_free[skin[0]]
                    parts.append((skin[0][keep], skin[1][keep], skin[2][keep]))
                    c_global, c_normals, c_offsets = (
                        np.concatenate(p) for p in zip(*parts, strict=True)
                    )
                    c_local = np.searchsorted(sub.nodes, c_global)
                    planes = (c_local, c_normals, c_offsets, stiffness * sub.diagonal[c_local])
                fun = penalised_objective(
                    sub,
                    xl,
                    scale,
                    eps,
                    planes,
                    opt.contact_force_depth,
                    sliding,
                    self._corner_volume_weights(sub, xl, eps, opt),
                )
                start = (xl[sub.free] / scale).ravel()
                before = fun(start)[0]
                monitor = round_monitor(
                    should_cancel,
                    report_progress,
                    lambda done, rnd=rnd: min(1.0, (rnd + done) / opt.max_rounds),
                    "relaxing soft tissue",
                    "relaxation cancelled",
                )
                result = minimize_lbfgs(
                    fun, start, opt.iterations_per_round, each_iteration=monitor
                )
                xl[sub.free] = result.x.reshape(-1, 3) * scale
                _, _, det = sub.energy(xl, eps)
                report.rounds += 1
                report.iterations += int(result.nit)
                report.evaluations += int(result.nfev)
                d_min = float(det.min())
                after = float(result.fun)
                report.history.append(
                    {
                        "eps": eps,
                        "energy": after,
                        "min_det": d_min,
                        "inverted": int(np.sum(det <= 0)),
                        "nodes": len(sub.free),
                    }
                )
                report_progress(min(1.0, (rnd + 1) / opt.max_rounds), "relaxing soft tissue")
                if d_min > 0 and untangled is not None:
                    # nothing inverted in the round's region, and outside it nothing moved
                    # since it was focused on the corners still inverted: the pose so far
                    shown = x.copy()
                    shown[sub.nodes] = xl
                    untangled(shown)
                    untangled = None
                decrease = (before - after) / max(abs(before), 1e-300)
                eps = next_eps(eps, before, after, d_min, opt.eps_decrease)
                stiff_enough = stiffness >= opt.contact_stiffness or not len(planes[0])
                if d_min > 0 and stiff_enough and (decrease < opt.tolerance or rnd_untangled):
                    break
                if d_min > 0 and optimise_next and (order is None or stiff_enough):
                    break  # untangled: the quality optimisation takes it from here
                rnd_untangled = d_min > 0 and eps <= 1e-9
                if d_min > 0:
                    stiffness = opt.contact_stiffness
                else:
                    inverted, d_whole, det_whole = report.history[-1]["inverted"], d_min, det
                    if sub is not whole:  # counted over the whole region
                        x[sub.nodes] = xl
                        _, _, det_whole = whole.energy(x[whole.nodes], eps)
                        inverted, d_whole = int(np.sum(det_whole <= 0)), float(det_whole.min())
                        report.history[-1].update(inverted=inverted, min_det=d_whole)
                    if best is None or (inverted, -d_whole) < (best[0], -best[1]):
                        x[sub.nodes] = xl
                        released_then = (report.contact_released, report.sliding_released)
                        best = (inverted, d_whole, x.copy(), det_whole, attempt, released_then)
                        best_round = report.rounds
                    # corners a round after round cannot free: go on to the restart (the 177k
                    # demo at 90 deg spent 27 of its 60 rounds with 6 or 1 corners inverted)
                    stalled = 0 if inverted < fewest_inverted else stalled + 1
                    fewest_inverted = min(fewest_inverted, inverted)
                    if stalled >= opt.stall_rounds:
                        break
                if not opt.focus_rings:
                    continue
                if d_min > 0:
                    focus = pass_sub  # untangled: stiffen the contact over the whole region
                else:
                    # the rest of the region has left its tangles behind: the next rounds
                    # move only the nodes around the corners still inverted (the 177k demo at
                    # 90 deg: 4,801 of them after the first round, 90 after the eighth)
                    stuck = whole.nodes[self._stuck_nodes(whole, det_whole)]
                    nodes = self._within_rings(stuck, opt.focus_rings, pass_free)
                    focus = sub if np.array_equal(nodes, sub.nodes[sub.free]) else nodes
                if focus is not sub:
                    x[sub.nodes] = xl
                    # let the last round's energy go before the next one is built: on a
                    # whole-body model each holds hundreds of MB of corners
                    sub = fun = None
                    if isinstance(focus, np.ndarray):
                        sub = self.energy(focus, should_cancel, skip)
                    else:
                        sub = focus
                    xl, scale, sliding, is_sub_free, contact_global = variables(sub, pass_contact)
        x[sub.nodes] = xl
        if sub is not whole:
            _, _, det = whole.energy(x[whole.nodes], max(eps, 1e-9))
            d_min = float(det.min())
        if d_min <= 0 and best is not None and best_round != report.rounds:
            _, d_min, x_best, det, report.kept_attempt, released_then = best
            x[:] = x_best
            report.contact_released, report.sliding_released = released_then
        report.min_det_after = d_min
        report.inverted_corners_after = int(np.sum(det <= 0))
        return x, d_min, whole, det

    @staticmethod
    def _corner_volume_weights(
        sub: FoldoverEnergy, xl: NDArray[np.float64], eps: float, opt: RelaxOptions
    ) -> NDArray[np.float64] | None:
        """Each corner's volume weight for a round starting at ``xl``: ``volume_weight`` up to
        det J = ``healthy_det[0]``, ``healthy_volume_weight`` from ``healthy_det[1]``, linear
        between (:class:`RelaxOptions`; continuous, so that a det J a rounding apart gives
        weights a rounding apart, not another class); None when every corner weighs volume
        the same."""
        if opt.healthy_volume_weight == 0 or opt.healthy_volume_weight == opt.volume_weight:
            return None
        _, _, det = sub.energy(xl, eps)
        low, high = opt.healthy_det
        health = np.clip((det[: len(sub.tets)] - low) / (high - low), 0.0, 1.0)  # shells after
        return opt.volume_weight + (opt.healthy_volume_weight - opt.volume_weight) * health

    def _reach(self, seed: NDArray[np.bool_], rings: int) -> NDArray[np.bool_]:
        """Mask of the nodes within ``rings`` mesh edges of the ``seed`` nodes."""
        reach = seed.astype(np.int8)
        for _ in range(rings):
            reach = ((reach + self._adjacency @ reach) > 0).astype(np.int8)
        return reach > 0

    def _within_rings(
        self, seeds: NDArray[np.int64], rings: int, free: NDArray[np.int64]
    ) -> NDArray[np.int64]:
        """The nodes of ``free`` within ``rings`` mesh edges of ``seeds``."""
        seed = np.zeros(self.n_nodes, dtype=bool)
        seed[seeds] = True
        return free[self._reach(seed, rings)[free]]

    def _penetrating(
        self,
        x: NDArray[np.float64],
        transforms: Mapping[str, RigidTransform] | None,
        cancel: Callable[[], bool] | None = None,
    ) -> tuple[NDArray[np.int64] | None, float]:
        """The contact nodes deeper in a bone than ``penetration_tolerance`` at ``x`` and the
        deepest penetration (None and 0 without bones or transforms); ``cancel`` is asked
        before each bone."""
        if not self.bones or transforms is None or len(self.contact_nodes) == 0:
            return None, 0.0
        _, _, _, depth = self._contact_planes(x, self.contact_nodes, transforms, cancel)
        deep = self.contact_nodes[depth < -self.options.penetration_tolerance]
        return deep, float(max(0.0, -depth.min()))

    def _flat_at_rest(self) -> bool:
        """Whether an element around the relaxable nodes is flat or inverted in the deck
        (computed once)."""
        if self._rest_flat is None:
            self._rest_flat = bool(len(self.inverted_element_nodes(self.rest)))
        return self._rest_flat

    def flat_element_nodes(
        self,
        x: NDArray[np.float64],
        below: float,
        cancel: Callable[[], bool] | None = None,
    ) -> NDArray[np.int64]:
        """Every node of the solids around the relaxable nodes that are nearly flat at ``x``:
        a corner Jacobian (a tetrahedron's collapse) below ``below``."""
        out = []
        for etype, block in (self.blocks or {}).items():
            if etype not in SOLID_TYPES:
                continue
            rows_all = np.flatnonzero(self.is_free[block.conn].any(axis=1))
            for lo in range(0, len(rows_all), REGION_CHUNK):
                raise_if_cancelled(cancel, "relaxation cancelled")
                rows = rows_all[lo : lo + REGION_CHUNK]
                q = compute_quality(x, {etype: block}, rows={etype: rows})[etype]
                measure = q.jacobian_corner if q.tet_collapse is None else q.tet_collapse
                flat = measure < below
                if flat.any():
                    out.append(block.conn[rows[flat]].ravel())
        return sorted_unique(np.concatenate(out)) if out else np.zeros(0, dtype=np.int64)

    def inverted_element_nodes(self, x: NDArray[np.float64]) -> NDArray[np.int64]:
        """Every node of the elements around the relaxable nodes that have a corner with
        ``det J <= 0`` at ``x``: solids, and skin quads against their own normal (the corners
        the quality optimiser checks before it starts)."""
        held = []
        for etype, block in (self.blocks or {}).items():
            if etype not in CORNER_TRIPLES:
                continue
            conn = block.conn[self.is_free[block.conn].any(axis=1)]
            # a block of elements at a time: the corner geometry is a dozen (E, corners)
            # temporaries, 0.5 GB around the 1M demo's region at once
            for lo in range(0, len(conn), CORNER_CHUNK):
                part = conn[lo : lo + CORNER_CHUNK]
                p = x[part]
                normal = None
                if etype == "quad4":
                    normal = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
                bad = (corner_determinants(p, etype, normal) <= 0).any(axis=1)
                if bad.any():
                    held.append(part[bad].ravel())
        return sorted_unique(np.concatenate(held)) if held else np.zeros(0, dtype=np.int64)

    @staticmethod
    def _stuck_nodes(sub: FoldoverEnergy, det: NDArray[np.float64]) -> NDArray[np.int64]:
        """Local indices of the free nodes of the inverted corners and quads.

        Nodes pressed onto one point while the barrier was soft make ``det J`` and its gradient
        zero, and the shape term holds them there; the pose had them apart.
        """
        c = len(sub.tets)
        corner_nodes = sub.tets[det[:c] <= 0].ravel()  # may name virtual nodes (>= m)
        quad_nodes = sub.quads[np.flatnonzero(det[c:] <= 0) % max(len(sub.quads), 1)].ravel()
        bad = np.concatenate([corner_nodes, quad_nodes])
        bad = sorted_unique(bad[bad < sub.m])
        is_free = np.zeros(sub.m, dtype=bool)
        is_free[sub.free] = True
        return bad[is_free[bad]]

    def _outward_quad_signs(self) -> NDArray[np.float64]:
        """Per quad, +1 where its node order's normal points away from the solids under it
        at rest, -1 where it points into them (a deck's shells need not be oriented alike):
        the side of the quad's centroid from the mean of its nodes' neighbours off the shells.
        +1 where no such neighbour tells."""
        quads = self.quads
        if len(quads) == 0:
            return np.ones(0)
        on_shell = np.zeros(self.n_nodes, dtype=bool)
        on_shell[quads.ravel()] = True
        nodes = sorted_unique(quads.ravel())
        # each shell node's neighbours off the shells (the rows of the shell nodes alone: a
        # whole-body model's adjacency has tens of millions of entries)
        pairs = self._adjacency[nodes].tocoo()
        off = ~on_shell[pairs.col]
        row, col = pairs.row[off], pairs.col[off]
        count = np.bincount(row, minlength=len(nodes))
        total = np.zeros((len(nodes), 3))
        np.add.at(total, row, self.rest[col])
        local = np.searchsorted(nodes, quads)
        p = self.rest[quads]
        normal = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
        n_inner = count[local].sum(axis=1)
        below = total[local].sum(axis=1) / np.maximum(n_inner, 1)[:, None]
        side = np.einsum("ij,ij->i", normal, p.mean(axis=1) - below)
        return np.where((n_inner > 0) & (side < 0), -1.0, 1.0)

    def _skin_normals(
        self, x: NDArray[np.float64], nodes: NDArray[np.int64]
    ) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
        """Unit outward surface normals at ``x`` of ``nodes`` (area-weighted over the quads
        around each, :meth:`_outward_quad_signs`); which have one, and those normals."""
        no_tris = np.zeros((0, 3), dtype=np.int64)
        n = boundary_node_normals(x, self.quads, no_tris, self._quad_outward)[nodes]
        ok = np.any(n != 0.0, axis=1)
        return ok, n[ok]

    def _slides(self) -> bool:
        """Whether the skin is held to its tangent planes in the untangling (sliding in them,
        or leaving them outwards only)."""
        slide = self.options.slide_skin is not False
        return slide and len(self.sliding) > 0 and len(self.quads) > 0

    def skin_outward_planes(
        self, x: NDArray[np.float64]
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """The skin's one-sided planes for the untangling of the pose ``x``
        (``RelaxOptions.skin_outward``): each sliding node kept on the outer side of its
        tangent plane at ``x`` (global ``nodes, normals, offsets``); none when the skin is not
        held or the option is off."""
        if not (self._slides() and self.options.skin_outward):
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0)
        ok, normals = self._skin_normals(x, self.sliding)
        nodes = self.sliding[ok]
        return nodes, normals, np.einsum("ij,ij->i", normals, x[nodes])

    def _sliding_rows(
        self, x: NDArray[np.float64], sub: FoldoverEnergy
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Rows of ``sub.free`` that slide, and their unit surface normals at ``x`` (area-weighted
        over the quads around each node); none when the skin leaves its planes outwards
        instead (``RelaxOptions.skin_outward``)."""
        if not self._slides() or self.options.skin_outward:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        free_global = sub.nodes[sub.free]
        rows = np.flatnonzero(np.isin(free_global, self.sliding))
        if len(rows) == 0:
            return rows, np.zeros((0, 3))
        ok, normals = self._skin_normals(x, free_global[rows])
        return rows[ok], normals

    def optimise(
        self,
        x: NDArray[np.float64],
        transforms: Mapping[str, RigidTransform] | None,
        options: QualityOptions,
        progress: ProgressCallback,
        cancel: Callable[[], bool] | None,
    ) -> tuple[NDArray[np.float64], QualityOptimisationReport | None]:
        """The chain's second stage: bring the elements around the relaxable nodes within their
        quality aims, every node moving together, bones kept out by their contact planes, skin
        contours in order. The skin is free here: held in its tangent planes, the folded crease
        behind a knee flexed to 120 deg kept 142 elements warped beyond 30 deg and a worst
        Jacobian of 0.11 (free: 80 and 0.19). Nothing to do without ``blocks`` and ``aims``."""
        if self.blocks is None or self.aims is None:
            return x, None
        order = self.contour_order
        t = time.perf_counter()
        crossing = None if order is None else order.crossing(x)
        raise_if_cancelled(cancel, "relaxation cancelled")
        held = self.inverted_element_nodes(x) if options.hold_inverted else None
        raise_if_cancelled(cancel, "relaxation cancelled")
        if held is not None and len(held) and self._flat_at_rest():
            held = None  # flat or inverted in the deck already: the error below names that
        tangled = held is not None and len(held) > 0
        if tangled:
            # left tangled: first only around what is past its constraints (in a bone, a
            # contour out of order), the inverted elements' nodes held
            deep, _ = self._penetrating(x, transforms)
            parts = [a for a in (deep, crossing) if a is not None]
            seeds = np.concatenate(parts) if parts else None
            free = shortfall_region(
                x,
                self.blocks,
                self.aims,
                self.free,
                self.options.rings,
                seeds,
                misses=False,
                cancel=cancel,
            )
            free = np.setdiff1d(free, held, assume_unique=True)
            # no rounds weighing up the elements past the gate's levels: the held elements fail
            # the gate whatever the rest does, and the other aims are the smoother's here (the
            # 177k demo at 90 deg: 4.7 s less, the same nodes out of the bones). The main
            # rounds stay: capped at 6 they left more tissue in the bones (welded 115k demo:
            # 22 nodes up to 3.6 mm against 7; 1M demo: 122 against 90)
            options = replace(options, gate_rounds=0)
        else:
            free = shortfall_region(
                x, self.blocks, self.aims, self.free, self.options.rings, crossing, cancel=cancel
            )
        region_seconds = time.perf_counter() - t
        raise_if_cancelled(cancel, "relaxation cancelled")
        if not len(free):
            return self._mend_beyond(x, transforms, options, None, cancel)
        # with a tangle left, the second pass over the whole region takes most of the time
        first_progress = progress_span(progress, 0.0, 0.2 if tangled else 1.0)
        second_progress = progress_span(progress, 0.2, 1.0)
        try:
            out, report, contact, constraints = self._optimise_region(
                x, free, transforms, options, first_progress, cancel
            )
        except ValueError:  # an element stayed inverted or flat: the input has one (#22)
            if tangled:
                return x, None  # the untangling's inverted elements: the gate counts them
            raise GeometryError(
                "the relaxation cannot untangle the soft tissue it moves: an element there "
                "is inverted or flat (coincident nodes or a collapsed element in the deck? "
                "'kneegui quality' lists them)"
            ) from None
        report = replace(
            report,
            region_seconds=region_seconds,
            held_nodes=0 if held is None else int(np.count_nonzero(self.is_free[held])),
        )
        if len(contact):
            out, report = self._settle_in_bones(
                out, transforms, contact, constraints, options, report, cancel, held
            )
        if tangled:
            out, report = self._optimise_around_tangles(
                out, held, crossing, transforms, options, report, second_progress, cancel
            )
        out = self.midside_out_of_bones(self.carry_midside(x, out), transforms)
        return self._mend_beyond(out, transforms, options, report, cancel)

    def _optimise_region(
        self,
        x: NDArray[np.float64],
        free: NDArray[np.int64],
        transforms: Mapping[str, RigidTransform] | None,
        options: QualityOptions,
        progress: ProgressCallback | None,
        cancel: Callable[[], bool] | None,
    ) -> tuple[NDArray[np.float64], QualityOptimisationReport, NDArray[np.int64], Callable]:
        """:func:`optimise_quality` over ``free``, its contact nodes held out of the bones by
        their planes and the skin contours in order. Returns the coordinates, the report, the
        contact nodes (none without bones or ``transforms``) and the constraints' function.
        Raises ValueError where an element around ``free`` is inverted or flat."""
        order = self.contour_order
        contact = self.contact_nodes[np.isin(self.contact_nodes, free)]
        if not (self.bones and transforms is not None):
            contact = contact[:0]

        def constraints(coords: NDArray[np.float64]) -> tuple[NDArray, ...]:
            parts = []
            if len(contact):
                which, normals, offsets, _ = self._contact_planes(
                    coords, contact, transforms, cancel, chords=False
                )
                parts.append(with_partners((contact[which], normals, offsets)))
                if len(self._midside):
                    parts.append(self._chord_middle_planes(coords, contact, transforms))
            if order is not None:
                parts.append(with_partners(order.constraints(coords)))
            if not parts:
                return with_partners((np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0)))
            return tuple(np.concatenate(p) for p in zip(*parts, strict=True))

        out, report = optimise_quality(
            x,
            self.blocks,
            free,
            self.aims,
            constraints=constraints,
            options=options,
            progress=progress,
            cancel=cancel,
        )
        return out, report, contact, constraints

    def _optimise_around_tangles(
        self,
        x: NDArray[np.float64],
        inverted: NDArray[np.int64],
        crossing: NDArray[np.int64] | None,
        transforms: Mapping[str, RigidTransform] | None,
        options: QualityOptions,
        report: QualityOptimisationReport,
        progress: ProgressCallback,
        cancel: Callable[[], bool] | None,
    ) -> tuple[NDArray[np.float64], QualityOptimisationReport]:
        """With elements left inverted (their nodes ``inverted``) and the tissue in the bones
        settled around them: the region's whole shortfall is optimised, holding also the
        nodes of the solids nearly flat (below :data:`TANGLE_FLAT_BELOW`) and one ring around
        them. Such elements, around an inverted one or not, hold the line search, which is one
        for every node: any step of theirs takes one below its floor. The first pass, around
        what is past its constraints alone, left the rest of the region where the untangling
        did (the leg built at 20 deg, posed to 120 deg: 95th percentile of the soft solids'
        volume change 75 %, where the optimisation of an untangled region takes it from about
        80 % to 24 %; this pass: 32 %; holding two rings around the inverted elements instead
        of the flat ones: 34 %, but on the 1M demo a flat element beyond them held everything
        and 68 % stayed). Runs when it moves at most ``options.tangle_pass_nodes`` nodes;
        kept when it leaves fewer elements below their aims; its settling takes no solid
        below the worst before it."""
        raise_if_cancelled(cancel, "relaxation cancelled")
        t = time.perf_counter()
        free = shortfall_region(
            x, self.blocks, self.aims, self.free, self.options.rings, crossing, cancel=cancel
        )
        free = np.setdiff1d(free, inverted, assume_unique=True)
        if not 0 < len(free) <= options.tangle_pass_nodes:
            return x, report
        held = np.union1d(inverted, self.flat_element_nodes(x, TANGLE_FLAT_BELOW, cancel))
        held = np.union1d(held, self._within_rings(held, 1, self.free))
        free = np.setdiff1d(free, held, assume_unique=True)
        region_seconds = time.perf_counter() - t
        if not len(free):
            return x, report
        floors = report.floors()
        try:
            out, more, _, _ = self._optimise_region(
                x, free, transforms, replace(options, settling_floors=floors), progress, cancel
            )
        except ValueError:
            return x, report
        if more.below_aim_after >= more.below_aim_before:
            return x, report
        return out, report.with_pass(
            more,
            region_seconds,
            free_nodes=report.free_nodes + more.free_nodes,
            below_aim_after=more.below_aim_after,
            worst_after=more.worst_after,
            collapse_below_aim_after=more.collapse_below_aim_after,
            collapse_worst_after=more.collapse_worst_after,
            max_displacement=max(report.max_displacement, more.max_displacement),
        )

    def _settle_in_bones(
        self,
        x: NDArray[np.float64],
        transforms: Mapping[str, RigidTransform],
        contact: NDArray[np.int64],
        constraints: ConstraintCallback,
        options: QualityOptions,
        report: QualityOptimisationReport,
        cancel: Callable[[], bool] | None,
        held: NDArray[np.int64] | None = None,
    ) -> tuple[NDArray[np.float64], QualityOptimisationReport]:
        """After the region's optimisation: the ``contact`` nodes it left deeper in a bone than
        its constraint tolerance are settled again on their own, the nodes within
        ``options.rings`` of them moving, no solid taken below the worst the optimisation left
        (``QualityOptions.settling_floors``), the nodes ``held`` (the elements the untangling
        left inverted) held. Each group of those nodes that no element or constraint ties to
        another is settled apart, and kept when the deepest of its nodes came out further; a
        group whose deepest came out by less than the tolerance is settled again, in place of
        that attempt, with every node of the nearly flat solids (below
        :data:`TANGLE_FLAT_BELOW`) and one ring around them held.

        The optimisation's settling moves every node past a constraint in one problem, and its
        line search refuses any step that takes a solid below its floor: one group of nodes
        that cannot move without that stalls every other group (the coarse mixed demo at
        120 deg: a ligament node 0.86 mm inside the femur stayed there through the settling's
        rounds while skin nodes 60 mm away could not meet their contour planes; settled alone,
        it came out in one round). The same holds within a group: on the 1M demo at 90 deg one
        group of 13,347 nodes around the crease held a solid at a corner Jacobian of 1e-5 and
        moved nothing; without that solid's nodes it moved 11,957 nodes up to 5.9 mm, and the
        export left 114 soft-tissue nodes in a bone instead of 173."""
        raise_if_cancelled(cancel, "relaxation cancelled")
        _, _, _, margin = self._contact_planes(x, contact, transforms, cancel)
        too_deep = margin < -options.constraint_tolerance
        if not too_deep.any():
            return x, report
        t = time.perf_counter()
        deep = contact[too_deep]
        free = shortfall_region(
            x, self.blocks, self.aims, self.free, self.options.rings, deep, misses=False
        )
        if held is not None:  # the inverted elements' nodes: the stage refuses to move one
            free = np.setdiff1d(free, held, assume_unique=True)
        in_free = np.zeros(self.n_nodes, dtype=bool)
        in_free[free] = True

        def around_nodes(mask: NDArray[np.bool_]) -> ConstraintCallback:
            def around(coords: NDArray[np.float64]) -> tuple[NDArray, ...]:
                nodes, normals, offsets, partners = with_partners(constraints(coords))
                keep = mask[nodes] | ((partners >= 0) & mask[np.maximum(partners, 0)])
                return nodes[keep], normals[keep], offsets[keep], partners[keep]

            return around

        around = around_nodes(in_free)
        # no solid below the worst the region's optimisation left (nor below its own worst
        # now, where that is lower): what the gate measures does not get worse
        settling = replace(options, rounds=0, gate_rounds=0, settling_floors=report.floors())

        def settle_group(
            coords: NDArray[np.float64], part: NDArray[np.int64]
        ) -> tuple[NDArray[np.float64], QualityOptimisationReport, float] | None:
            """The group settled, its report and how far its deepest node came out (None
            when an element there is inverted)."""
            raise_if_cancelled(cancel, "relaxation cancelled")
            mask = np.zeros(self.n_nodes, dtype=bool)
            mask[part] = True
            sunk = deep[mask[deep]]
            try:
                moved, settled = optimise_quality(
                    coords,
                    self.blocks,
                    part,
                    self.aims,
                    constraints=around_nodes(mask),
                    options=settling,
                    cancel=cancel,
                )
            except ValueError:
                return None
            _, _, _, before = self._contact_planes(coords, sunk, transforms, cancel)
            _, _, _, after = self._contact_planes(moved, sunk, transforms, cancel)
            return moved, settled, float(after.min()) - float(before.min())

        region_seconds = time.perf_counter() - t
        settled_nodes = 0
        out = x

        def keep(
            attempt: tuple[NDArray[np.float64], QualityOptimisationReport, float],
            nodes: NDArray[np.int64],
        ) -> None:
            nonlocal out, report, settled_nodes, region_seconds
            out, settled_nodes = attempt[0], settled_nodes + len(nodes)
            report = report.with_pass(attempt[1], region_seconds, bone_settled_nodes=settled_nodes)
            region_seconds = 0.0

        flat: NDArray[np.int64] | None = None
        for part in self._coupled_groups(x, free, around):
            if not np.isin(deep, part).any():
                continue
            tried = settle_group(out, part)
            if tried is not None and tried[2] >= options.constraint_tolerance:
                keep(tried, part)
                continue
            # stalled: a nearly flat solid holds the group's line search (any step of its nodes
            # takes it below its floor): again, in place of this attempt, with its nodes and
            # one ring around them held
            if flat is None:
                flat = self.flat_element_nodes(x, TANGLE_FLAT_BELOW, cancel)
                flat = np.union1d(flat, self._within_rings(flat, 1, self.free))
            rest = np.setdiff1d(part, flat, assume_unique=True)
            if not 0 < len(rest) < len(part):  # no such solid there, or nothing else
                if tried is not None and tried[2] > 0:
                    keep(tried, part)
                continue
            for sub in self._coupled_groups(out, rest, around):
                if np.isin(deep, sub).any():
                    again = settle_group(out, sub)
                    if again is not None and again[2] > 0:
                        keep(again, sub)
        return out, report

    def _coupled_groups(
        self,
        x: NDArray[np.float64],
        free: NDArray[np.int64],
        constraints: ConstraintCallback,
    ) -> list[NDArray[np.int64]]:
        """``free`` split into groups that no element and no constraint (at ``x``) ties
        together: each group's problem is apart from the others', and solved apart its line
        search is not held by another group's elements. Elements, not the corner edges of
        ``_adjacency``: two free nodes of one element are tied through its measures even where
        no free node joins them along an edge."""
        n = len(free)
        if n == 0:
            return []
        local = np.full(self.n_nodes, -1, dtype=np.int64)
        local[free] = np.arange(n)
        rows, cols = [], []
        for block in self.blocks.values():
            conn = local[block.conn]
            conn = conn[(conn >= 0).any(axis=1)]
            if not len(conn):
                continue
            first = conn.max(axis=1)
            for k in range(conn.shape[1]):
                ok = conn[:, k] >= 0
                rows.append(first[ok])
                cols.append(conn[ok, k])
        nodes, _, _, partners = with_partners(constraints(x))
        both = (partners >= 0) & (local[nodes] >= 0)
        both[both] &= local[partners[both]] >= 0
        rows.append(local[nodes[both]])
        cols.append(local[partners[both]])
        r, c = np.concatenate(rows), np.concatenate(cols)
        graph = coo_matrix((np.ones(len(r), dtype=bool), (r, c)), shape=(n, n))
        _, labels = connected_components(graph, directed=False)
        order = np.argsort(labels, kind="stable")
        cuts = np.flatnonzero(np.diff(labels[order])) + 1
        return np.split(free[order], cuts)

    def _mend_beyond(
        self,
        x: NDArray[np.float64],
        transforms: Mapping[str, RigidTransform] | None,
        options: QualityOptions,
        report: QualityOptimisationReport | None,
        cancel: Callable[[], bool] | None,
    ) -> tuple[NDArray[np.float64], QualityOptimisationReport | None]:
        """After the region's optimisation, apart from it: the ``beyond`` nodes around the
        elements the pose left past the gate's levels (:meth:`_beyond_region`) move so that
        those elements meet their aims, the region's nodes held where it left them. Apart, so
        that the region's result does not depend on them: moved together, the leg built at
        0 deg took 71 such nodes at 90 deg and its 95th percentile of volume change went from
        24.8 to 25.05 % (the region's path changed). Returns the coordinates and ``report``
        with the pass's nodes, time and iterations added (the pass's own report when
        ``report`` is None)."""
        t = time.perf_counter()
        beyond = self._beyond_region(x, transforms, options.beyond_margin)
        free = (
            shortfall_region(x, self.blocks, self.aims, beyond, self.options.rings)
            if len(beyond)
            else beyond
        )
        if len(free) == 0:
            return x, report
        planes = self._tangent_planes(x, free[self.is_skin[free]])
        # a skin node without a skin shell around it has no plane to slide in: it stays
        held = np.setdiff1d(free[self.is_skin[free]], planes[0])
        free = np.setdiff1d(free, held) if len(held) else free
        region_seconds = time.perf_counter() - t
        if len(free) == 0:
            return x, report
        try:
            out, far = optimise_quality(
                x,
                self.blocks,
                free,
                self.aims,
                constraints=lambda coords: planes,
                options=replace(options, margin=options.beyond_aim_margin),
                cancel=cancel,
            )
        except ValueError:  # an element there is inverted: the mapping's, the gate counts it
            return x, report
        in_free = np.zeros(self.n_nodes, dtype=bool)
        in_free[free] = True
        beyond = np.flatnonzero(self.is_beyond)
        out = _free_midside_nodes(self.blocks, in_free, beyond, self.rest).straighten(out)
        if report is None:
            return out, replace(far, region_seconds=region_seconds, beyond_region_nodes=len(free))
        return out, report.with_pass(far, region_seconds, beyond_region_nodes=len(free))

    def _tangent_planes(
        self, x: NDArray[np.float64], nodes: NDArray[np.int64]
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """Constraints that hold the skin ``nodes`` in their surface's tangent plane at ``x``
        (two opposite half-spaces each; the normal area-weighted over the skin shells around the
        node): they may slide along the skin, not leave it. A node with no skin shell around it
        gets none."""
        acc = np.zeros((self.n_nodes, 3))
        touching = np.zeros(self.n_nodes, dtype=bool)
        touching[nodes] = True
        for etype in ("quad4", "tri3"):
            shell = None if self.blocks is None else self.blocks.get(etype)
            if shell is None or len(shell) == 0 or len(nodes) == 0:
                continue
            conn = shell.conn[
                self.is_skin[shell.conn].all(axis=1) & touching[shell.conn].any(axis=1)
            ]
            p = x[conn]
            if etype == "quad4":
                normal = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])  # twice the area
            else:
                normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            for k in range(conn.shape[1]):
                np.add.at(acc, conn[:, k], normal)
        n = acc[nodes]
        length = np.linalg.norm(n, axis=1)
        ok = length > 0
        nodes, n = nodes[ok], n[ok] / length[ok, None]
        offset = np.einsum("ij,ij->i", n, x[nodes])
        return (
            np.concatenate([nodes, nodes]),
            np.concatenate([n, -n]),
            np.concatenate([offset, -offset]),
        )

    def _beyond_region(
        self,
        x: NDArray[np.float64],
        transforms: Mapping[str, RigidTransform] | None,
        margin: float,
    ) -> NDArray[np.int64]:
        """The ``beyond`` nodes within ``options.rings`` elements of a solid the pose left past
        one of the gate's levels (within ``margin``) and worse than at rest, farther than the
        contact band from every bone (sorted; empty when there is none)."""
        none = np.zeros(0, dtype=np.int64)
        if (
            self.blocks is None
            or self.aims is None
            or not self.aims.gate
            or self.initial_quality is None
            or not self.is_beyond.any()
        ):
            return none
        seeds = gate_shortfall_nodes(
            x, self.blocks, self.aims.gate, self.initial_quality, self.is_beyond, margin
        )
        if len(seeds) == 0:
            return none
        region = np.zeros(self.n_nodes, dtype=bool)
        region[seeds] = True
        conns = [
            b.conn[:, : CORNER_NODES[etype]]
            for etype, b in self.blocks.items()
            if etype in SOLID_CORNER_TYPES and len(b)
        ]
        for _ in range(self.options.rings):
            grown = region.copy()
            for conn in conns:
                grown[conn[region[conn].any(axis=1)]] = True
            region = grown
        nodes = np.flatnonzero(region & self.is_beyond)
        if len(nodes) and self.bones and transforms is not None:
            keep = np.ones(len(nodes), dtype=bool)
            for name, surface in self.bones.items():
                tr = transforms.get(name)
                if tr is not None:
                    depth = surface.query(tr.inverse().apply(x[nodes]))[0]
                    keep &= depth >= self.options.contact_band
            nodes = nodes[keep]
        return nodes


class RelaxedRegion:
    """An :class:`ElasticRelaxation` bound to one pose's bone motions: the region the chain
    (:func:`kneegui.meshopt.chain.improve_region`) untangles and optimises. ``smooth`` is the
    export's smoothing when given (``smooth(coords, options, progress, cancel)``); without it the
    chain must be run without a smoothing stage."""

    def __init__(
        self,
        relaxation: ElasticRelaxation,
        transforms: Mapping[str, RigidTransform] | None,
        smooth: Callable[..., tuple[NDArray[np.float64], SmoothingReport]] | None = None,
    ) -> None:
        self.relaxation = relaxation
        self.transforms = transforms
        self._smooth = smooth

    def untangle(self, coords, options, stop_when_untangled, progress, cancel, untangled=None):
        """Stage 1 (:meth:`ElasticRelaxation.untangle`; ``options`` are the relaxation's)."""
        if options != self.relaxation.options:
            raise ValueError("the relaxation was built with other RelaxOptions")
        return self.relaxation.untangle(
            coords, self.transforms, stop_when_untangled, progress, cancel, untangled
        )

    def optimise(self, coords, options, progress, cancel):
        """Stage 2 (:meth:`ElasticRelaxation.optimise`)."""
        return self.relaxation.optimise(coords, self.transforms, options, progress, cancel)

    def smooth(
        self,
        coords: NDArray[np.float64],
        options: SmoothOptions,
        progress: ProgressCallback,
        cancel: Callable[[], bool],
    ) -> tuple[NDArray[np.float64], SmoothingReport]:
        """Stage 3, the smoothing this region was given."""
        if self._smooth is None:
            raise ValueError("this region has no smoothing stage: run the chain with smooth=None")
        return self._smooth(coords, options, progress, cancel)
