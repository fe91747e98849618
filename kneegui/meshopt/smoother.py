"""Connectivity-preserving mesh smoothing, after the DARSS scheme of Jani et al. (2012).

Stage 1 moves free nodes towards the mean of their edge neighbours (a Laplacian step, tried
with relaxation 1, 1/2, 1/4); nodes that share no element move together (a colouring of the free
nodes), so each step is one vectorised evaluation. Stage 2 runs Nelder-Mead (one simplex per
node, the nodes of a colour at once, :mod:`kneegui.meshopt.batched`) on each node still next to
an element below its goal, maximising the summed normalised Jacobians of the elements sharing
it with extra weight on the worst one. Both stages keep a move only if, over the elements
sharing the node: the worst ordered quality J* (:func:`ordered_quality`) does not drop, the
summed J* rises, no more elements are invalid, no corner Jacobian falls below the region's
worst before smoothing, and the largest edge ratio stays below ``max(old, aspect_limit)``, and
an optional position guard accepts the node's new place.

Hence the model's worst corner Jacobian never decreases; fixed nodes never move; element count
and connectivity never change; and the result is deterministic.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kneegui.errors import GeometryError, raise_if_cancelled
from kneegui.meshopt.batched import build_problems, nelder_mead
from kneegui.meshopt.nodes import boundary_node_normals, unique_pairs
from kneegui.meshopt.smoother_kernel import QUAD_FACES, element_measures, greedy_colours
from kneegui.model import ElementBlock, Model
from kneegui.quality.kernels import (
    ratio_of_determinants,
    scaled_corner_determinants,
)
from kneegui.quality.thresholds import JACOBIAN_WARN
from kneegui.topology import CORNER_NODES, ELEMENT_EDGES, boundary_faces, sorted_unique
from kneegui.topology import CORNER_TRIPLES as TOPOLOGY_CORNER_TRIPLES

ProgressCallback = Callable[[float, str], None]
CancelCallback = Callable[[], bool]
PositionGuard = Callable[[NDArray[np.int64], NDArray[np.float64]], NDArray[np.bool_]]

#: :data:`kneegui.topology.CORNER_TRIPLES` of the smoothed types, as arrays.
CORNER_TRIPLES: dict[str, NDArray[np.int64]] = {
    etype: np.array(TOPOLOGY_CORNER_TRIPLES[etype])
    for etype in ("hex8", "wedge6", "pyramid5", "tet4", "quad4")
}
SMOOTHED_TYPES: tuple[str, ...] = tuple(CORNER_TRIPLES)


@dataclass(frozen=True)
class SmoothOptions:
    """Parameters of the smoother (:func:`smooth_mesh`) and of the region it works on
    (:func:`kneegui.meshopt.smooth_posed_model`).

    Attributes
    ----------
    max_sweeps : int
        Stage-1 (Laplacian) sweeps at most.
    relaxation : tuple of float
        Fractions of the Laplacian step tried in turn for each node, each in (0, 1].
    optimize : bool
        Run stage 2 (one Nelder-Mead simplex per node, all nodes of a colour at once,
        :mod:`kneegui.meshopt.batched`).
    max_optimized_nodes : int
        Stage 2 runs at most this many node optimisations in all.
    iterations : int
        Simplex iterations per node (4 trial points per iteration).
    passes : int
        Rounds of stage 1 + stage 2 (stops early when a round changes nothing, or when no
        element is invalid and every neighbourhood reaches its goal).
    sliding_feature_angle : float
        Degrees: a sliding node on boundary faces deviating more than this from its mean
        normal (a feature edge) stays fixed.
    aspect_limit : float
        A move may not raise the largest edge ratio (longest / shortest edge) of the elements
        sharing the node above ``max(its value before the move, aspect_limit)``.
    warpage_limit : float
        Likewise for the largest quad-face warpage (degrees) of the elements sharing the node.
    rings : int
        Element layers around the degraded elements whose nodes may move.
    slide_skin : bool
        Also let surface nodes of the soft tissue / skin slide tangentially.
    soft_interfaces : bool
        Also move nodes shared only by soft-tissue solids of different parts.
    """

    max_sweeps: int = 40
    relaxation: tuple[float, ...] = (1.0, 0.5, 0.25)
    optimize: bool = True
    max_optimized_nodes: int = 20000
    iterations: int = 10
    passes: int = 3
    sliding_feature_angle: float = 30.0
    aspect_limit: float = 5.0
    warpage_limit: float = 15.0
    rings: int = 2
    slide_skin: bool = False
    soft_interfaces: bool = False

    def __post_init__(self) -> None:
        problems = [
            f"{name} must be a whole number >= {low}, not {value!r}"
            for name, value, low in (
                ("max_sweeps", self.max_sweeps, 0),
                ("max_optimized_nodes", self.max_optimized_nodes, 0),
                ("iterations", self.iterations, 0),
                ("rings", self.rings, 0),
                ("passes", self.passes, 1),
            )
            if int(value) != value or value < low
        ]
        if not self.relaxation or not all(0 < r <= 1 for r in self.relaxation):
            problems.append(f"relaxation must be step fractions in (0, 1], not {self.relaxation}")
        if not 0 < self.sliding_feature_angle <= 180:
            problems.append("sliding_feature_angle must be in (0, 180] degrees")
        if not 0 < self.warpage_limit <= 180:
            problems.append("warpage_limit must be in (0, 180] degrees")
        if not self.aspect_limit >= 1:
            problems.append("aspect_limit must be >= 1")
        if problems:
            raise ValueError("SmoothOptions: " + "; ".join(problems))


@dataclass(frozen=True)
class SmoothingReport:
    """What the smoother did.

    Attributes
    ----------
    free_nodes, sliding_nodes : int
        Nodes allowed to move freely / tangentially on the surface.
    moved_nodes : int
        Nodes whose position changed.
    stage1_sweeps, stage1_moves : int
        Laplacian sweeps run and moves accepted.
    stage2_nodes, stage2_improved : int
        Nodes optimised by Nelder-Mead and how many of them improved.
    worst_jacobian_before, worst_jacobian_after : float
        Worst corner Jacobian of the elements touching a movable node.
    inverted_before, inverted_after : int
        Elements touching a movable node with corner Jacobian <= 0.
    inverted_out_of_reach : int
        Inverted elements none of whose nodes may move: smoothing cannot repair them (e.g.
        elements between bone and skin nodes).
    max_displacement : float
        Largest node displacement (model units).
    seconds : float
        Wall time.
    """

    free_nodes: int
    sliding_nodes: int
    moved_nodes: int
    stage1_sweeps: int
    stage1_moves: int
    stage2_nodes: int
    stage2_improved: int
    worst_jacobian_before: float
    worst_jacobian_after: float
    inverted_before: int
    inverted_after: int
    max_displacement: float
    seconds: float
    inverted_out_of_reach: int = 0

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return asdict(self)


# ---------------------------------------------------------------------- element quality
def corner_quality(
    points: NDArray[np.float64], etype: str
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Corner Jacobian ratio and worst scaled corner determinant of elements.

    Parameters
    ----------
    points : (m, k, 3) ndarray of float
        Node positions of ``m`` elements (corner nodes in the model's order).
    etype : str
        One of :data:`SMOOTHED_TYPES`.

    Returns
    -------
    jacobian : (m,) ndarray
        ``min/max`` of the corner determinants, ``-1`` when the largest is not positive (the
        ``jacobian_corner`` of :mod:`kneegui.quality`).
    scaled : (m,) ndarray
        Smallest ``det / (|a| |b| |c|)`` over the corners, in [-1, 1]: continuous, used to pull
        inverted corners back.
    """
    dets, ratios = scaled_corner_determinants(np.moveaxis(points, (1, 2), (0, 1)), etype)
    return ratio_of_determinants(dets), np.stack(ratios, axis=1).min(axis=1)


def ordered_quality(jac: NDArray, scaled: NDArray) -> NDArray:
    """A quality that orders valid and invalid elements: J* = J if J > 0, else scaled - 1.

    Valid elements keep their corner Jacobian (0, 1]; an invalid element scores its worst
    scaled corner determinant minus one, in [-2, -1], which rises steadily while it is being
    untangled (the ratio J itself jumps between -1 and -infinity on the way).
    """
    return np.where(jac > 0, jac, np.minimum(scaled, 0.0) - 1.0)


_EDGE_INDEX = {t: np.array(e, dtype=np.int64) for t, e in ELEMENT_EDGES.items()}


def edge_ratio(points: NDArray[np.float64], etype: str) -> NDArray[np.float64]:
    """Longest / shortest edge of each element (all its edges; ``inf`` for a zero edge).

    Parameters
    ----------
    points : (m, k, 3) ndarray of float
        Node positions of ``m`` elements.
    etype : str
        Element type.
    """
    e = _EDGE_INDEX[etype]
    d = points[:, e[:, 1]] - points[:, e[:, 0]]
    # summed x, y, z in that order, as the compiled kernel does (einsum adds x + z first)
    sq = (d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]) + d[..., 2] * d[..., 2]
    lo = sq.min(axis=1)
    out = np.full(len(sq), np.inf)
    np.divide(sq.max(axis=1), lo, out=out, where=lo > 0)
    return np.sqrt(out)


def warp_cosine(points: NDArray[np.float64], etype: str) -> NDArray[np.float64]:
    """Cosine of the worst quad-face warpage of each element (1: flat faces or none).

    Same definition as the reported warpage (both diagonal splits of every quad face).
    """
    faces = QUAD_FACES.get(etype)
    if faces is None or len(faces) == 0:
        return np.ones(len(points))
    p = np.moveaxis(points[:, faces], 3, 0)  # (3, m, F, 4)
    p0, p1, p2, p3 = p[..., 0], p[..., 1], p[..., 2], p[..., 3]

    def cross(a, b):
        return np.stack(
            [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
        )

    d01, d02, d03 = p1 - p0, p2 - p0, p3 - p0
    area2 = cross(d02, p3 - p1)
    n012 = cross(d01, d02)
    n013 = cross(d01, d03)
    worst = np.ones(points.shape[0])
    for a in (n012, n013):
        b = area2 - a
        den = np.sqrt((a * a).sum(axis=0) * (b * b).sum(axis=0))
        cos = np.ones_like(den)
        np.divide((a * b).sum(axis=0), den, out=cos, where=den > 0)
        worst = np.minimum(worst, cos.min(axis=1))
    return worst


@dataclass(frozen=True)
class _NeighbourhoodScore:
    """Per-node summary of the elements sharing the node."""

    worst: NDArray  # smallest ordered quality J*
    total: NDArray  # sum of J* plus (count x worst): raise the minimum first
    inverted: NDArray  # number of elements with Jacobian <= 0
    worst_jacobian: NDArray  # smallest corner Jacobian (the reported measure)
    worst_aspect: NDArray  # largest edge ratio
    worst_warp: NDArray  # smallest warpage cosine (largest warpage)


def _score(
    jac: NDArray, scaled: NDArray, aspect: NDArray, warp: NDArray, owner: NDArray, n: int
) -> _NeighbourhoodScore:
    star = ordered_quality(jac, scaled)
    worst = np.full(n, np.inf)
    np.minimum.at(worst, owner, star)
    worst_jacobian = np.full(n, np.inf)
    np.minimum.at(worst_jacobian, owner, jac)
    count = np.bincount(owner, minlength=n)
    total = np.bincount(owner, star, minlength=n) + count * np.where(count > 0, worst, 0.0)
    worst_aspect = np.zeros(n)
    np.maximum.at(worst_aspect, owner, aspect)
    worst_warp = np.ones(n)
    np.minimum.at(worst_warp, owner, warp)
    return _NeighbourhoodScore(
        worst_aspect=worst_aspect,
        worst_warp=worst_warp,
        worst=worst,
        total=total,
        inverted=np.bincount(owner, (jac <= 0).astype(float), minlength=n),
        worst_jacobian=worst_jacobian,
    )


def _accept(
    old: _NeighbourhoodScore,
    new: _NeighbourhoodScore,
    floor: float,
    aspect_limit: float,
    warp_limit_cos: float,
) -> NDArray:
    """Which moves to keep: the worst J* around the node does not drop, the summed J* rises,
    no more elements are invalid, no corner Jacobian falls below ``floor`` (the worst of the
    region before smoothing, so that value can never get worse), and the largest edge ratio
    stays below ``max(its old value, aspect_limit)``. (Single elements other than the worst may
    lose quality: forbidding it stops untangling.)"""
    eps = 1e-12 * np.maximum(np.abs(old.total), 1.0)
    return (
        (new.worst >= old.worst)
        & (new.total > old.total + eps)
        & (new.inverted <= old.inverted)
        & (new.worst_jacobian >= floor)
        & (new.worst_aspect <= np.maximum(old.worst_aspect, aspect_limit))
        & (new.worst_warp >= np.minimum(old.worst_warp, warp_limit_cos))
    )


# ---------------------------------------------------------------------- neighbourhoods
@dataclass
class _Neighbourhood:
    """Elements touching the movable nodes and the incidence between them."""

    types: list[str]
    conn: list[NDArray[np.int64]]  # per type, corner connectivity of the touching elements
    offset: NDArray[np.int64]  # handle offset of each type
    handle_type: NDArray[np.int64]  # per handle: index into types
    handle_row: NDArray[np.int64]  # per handle: row into conn[type]
    node_ptr: NDArray[np.int64]  # CSR over movable nodes (compressed) -> handles
    node_handles: NDArray[np.int64]
    nbr_ptr: NDArray[np.int64]  # CSR over movable nodes -> edge-neighbour node indices
    nbr: NDArray[np.int64]
    block_rows: list[NDArray[np.int64]]  # per type, rows of the touching elements in the block


def _build_neighbourhood(
    blocks: Mapping[str, ElementBlock],
    movable: NDArray[np.int64],
    n_nodes: int,
    check_cancel: Callable[[], None] = lambda: None,
) -> _Neighbourhood:
    """The elements, handles and edge neighbours of the movable nodes; ``check_cancel()``
    between the steps (a whole-body model's smoothing region: a second in all at 1M)."""
    is_movable = np.zeros(n_nodes, dtype=bool)
    is_movable[movable] = True
    compressed = np.full(n_nodes, -1, dtype=np.int64)
    compressed[movable] = np.arange(len(movable))
    types, conns, offsets, block_rows = [], [], [0], []
    pair_node, pair_handle, edge_a, edge_b = [], [], [], []
    for etype in SMOOTHED_TYPES:
        block = blocks.get(etype)
        if block is None or len(block) == 0:
            continue
        check_cancel()
        k = CORNER_NODES[etype]
        conn = block.conn[:, :k]
        touching = is_movable[conn].any(axis=1)
        if not touching.any():
            continue
        conn = np.ascontiguousarray(conn[touching])
        block_rows.append(np.flatnonzero(touching))
        base = offsets[-1]
        handles = base + np.arange(len(conn))
        hit = is_movable[conn]
        pair_node.append(compressed[conn[hit]])
        pair_handle.append(np.broadcast_to(handles[:, None], conn.shape)[hit])
        for a, b in ELEMENT_EDGES[etype]:
            edge_a.append(conn[:, a])
            edge_b.append(conn[:, b])
        types.append(etype)
        conns.append(conn)
        offsets.append(base + len(conn))
    n_handles = offsets[-1]
    handle_type = np.zeros(n_handles, dtype=np.int64)
    handle_row = np.zeros(n_handles, dtype=np.int64)
    for ti in range(len(types)):
        handle_type[offsets[ti] : offsets[ti + 1]] = ti
        handle_row[offsets[ti] : offsets[ti + 1]] = np.arange(offsets[ti + 1] - offsets[ti])
    pn = np.concatenate(pair_node) if pair_node else np.zeros(0, dtype=np.int64)
    ph = np.concatenate(pair_handle) if pair_handle else np.zeros(0, dtype=np.int64)
    check_cancel()
    order = np.lexsort((ph, pn))
    node_ptr = np.searchsorted(pn[order], np.arange(len(movable) + 1))
    # edge neighbours of the movable nodes
    ea = np.concatenate(edge_a) if edge_a else np.zeros(0, dtype=np.int64)
    eb = np.concatenate(edge_b) if edge_b else np.zeros(0, dtype=np.int64)
    src = np.concatenate([ea, eb])
    dst = np.concatenate([eb, ea])
    keep = is_movable[src]
    check_cancel()
    pairs = unique_pairs(compressed[src[keep]], dst[keep], n_nodes)
    nbr_ptr = np.searchsorted(pairs[:, 0], np.arange(len(movable) + 1))
    return _Neighbourhood(
        types=types,
        conn=conns,
        offset=np.array(offsets, dtype=np.int64),
        handle_type=handle_type,
        handle_row=handle_row,
        node_ptr=node_ptr,
        node_handles=ph[order],
        nbr_ptr=nbr_ptr,
        nbr=pairs[:, 1],
        block_rows=block_rows,
    )


def _csr_gather(ptr: NDArray, values: NDArray, rows: NDArray) -> tuple[NDArray, NDArray]:
    """Concatenated ``values[ptr[r]:ptr[r+1]]`` for each row, and the row position of each."""
    starts, stops = ptr[rows], ptr[rows + 1]
    lengths = stops - starts
    owner = np.repeat(np.arange(len(rows)), lengths)
    within = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    return values[np.repeat(starts, lengths) + within], owner


def _evaluate(
    nb: _Neighbourhood, coords: NDArray[np.float64], handles: NDArray[np.int64]
) -> tuple[NDArray, NDArray, NDArray]:
    """Corner Jacobian, worst scaled corner and edge ratio of the given elements."""
    jac = np.empty(len(handles))
    scaled = np.empty(len(handles))
    aspect = np.empty(len(handles))
    warp = np.empty(len(handles))
    types = nb.handle_type[handles]
    for ti, etype in enumerate(nb.types):
        sel = np.flatnonzero(types == ti)
        if len(sel):
            measures = element_measures(coords, nb.conn[ti], nb.handle_row[handles[sel]], etype)
            jac[sel], scaled[sel], aspect[sel], warp[sel] = measures
    return jac, scaled, aspect, warp


def _colour(
    nb: _Neighbourhood, compressed: NDArray[np.int64], n_movable: int
) -> tuple[list[NDArray[np.int64]], NDArray[np.int64], NDArray[np.int64]]:
    """Split the movable nodes into groups of nodes that share no element (deterministic).

    Returns the groups and the conflict graph (CSR ``ptr``, ``neighbours``) between movable
    nodes that share an element.
    """
    # conflict pairs: movable nodes sharing an element, as packed keys merged corner by corner
    # (all 56 corner pairs of every hex at once were 0.4 GB around the 1M demo's knee)
    keys = np.zeros(0, dtype=np.int64)
    for conn in nb.conn:
        local = compressed[conn]
        k = conn.shape[1]
        for i in range(k):
            new = [keys]
            for j in range(k):
                if i != j:
                    both = (local[:, i] >= 0) & (local[:, j] >= 0)
                    new.append(local[both, i] * n_movable + local[both, j])
            keys = sorted_unique(np.concatenate(new))
    pairs = np.stack([keys // max(n_movable, 1), keys % max(n_movable, 1)], 1)
    ptr = np.searchsorted(pairs[:, 0], np.arange(n_movable + 1))
    nbrs = pairs[:, 1]
    # deterministic priorities; the colouring of the Jones-Plassmann rounds, compiled
    priority = np.random.default_rng(12345).permutation(n_movable)
    colour = greedy_colours(ptr, nbrs, priority)
    colours = [np.flatnonzero(colour == c) for c in range(int(colour.max()) + 1)]
    colours = [c for c in colours if len(c)]
    return colours, ptr, nbrs


# ---------------------------------------------------------------------- the smoother
def smooth_mesh(
    model_or_coords: Model | ArrayLike,
    blocks: Mapping[str, ElementBlock] | None,
    free_nodes: ArrayLike,
    *,
    sliding_nodes: ArrayLike | None = None,
    target: float | Mapping[str, ArrayLike] = JACOBIAN_WARN,
    options: SmoothOptions | None = None,
    position_guard: PositionGuard | None = None,
    progress: ProgressCallback | None = None,
    cancel: CancelCallback | None = None,
) -> tuple[NDArray[np.float64], SmoothingReport]:
    """Improve element quality by moving free nodes; connectivity never changes.

    Parameters
    ----------
    model_or_coords : Model or (N, 3) array_like of float
        The mesh (or its node coordinates). Never modified.
    blocks : mapping of str to ElementBlock or None
        Element blocks; ``None`` to use the model's.
    free_nodes : (N,) array_like of bool, or array_like of int
        Nodes allowed to move in any direction (mask or indices), e.g. from
        :func:`kneegui.meshopt.smoothing_free_nodes`.
    sliding_nodes : (N,) bool or int array_like, optional
        Surface nodes allowed to move only in the tangent plane of the solid mesh's boundary
        (e.g. skin nodes). Nodes on a feature edge (boundary faces deviating more than
        ``options.sliding_feature_angle`` degrees from the mean normal) stay fixed.
    target : float or mapping of str to (m,) array_like
        Quality goal: both stages work on the nodes sharing an element whose corner Jacobian is
        below its goal (stage 1 also on their neighbours). A float applies to every element; a
        mapping gives one goal per element of a block (aligned with its rows; types not in the
        mapping use the warn level), e.g. ``min(warn, initial Jacobian)`` so that elements are
        brought back to their initial quality rather than above it.
    options : SmoothOptions, optional
        Sweeps, stage 2 and the acceptance limits (default: :class:`SmoothOptions`).
    position_guard : callable(nodes, coords) -> (k,) bool, optional
        An extra rule on where a node may go: called with the indices of the nodes about to
        move and the full coordinate array holding their trial positions; a move is kept only
        where it returns true (e.g. "not deeper inside a bone", see
        :meth:`kneegui.reposition.relax.ElasticRelaxation.relax`).
    progress : callable(fraction, message), optional
        Called with the fraction done (0-1) and a short message.
    cancel : callable() -> bool, optional
        Polled between steps; when it returns true the smoother raises
        :class:`kneegui.errors.Cancelled` (the input is untouched, so nothing is lost).

    Returns
    -------
    new_coords : (N, 3) ndarray of float
        Smoothed coordinates (a new array).
    report : SmoothingReport

    Raises
    ------
    Cancelled
        If ``cancel()`` returned true.
    GeometryError
        If the coordinates contain NaN or infinity.
    """
    started = time.perf_counter()
    opt = options or SmoothOptions()
    if isinstance(model_or_coords, Model):
        coords0 = model_or_coords.coords
        blocks = model_or_coords.blocks if blocks is None else blocks
    else:
        coords0 = np.asarray(model_or_coords, dtype=np.float64)
        if blocks is None:
            raise ValueError("blocks are required when coordinates are given")
    n_nodes = len(coords0)
    if not np.all(np.isfinite(coords0)):
        raise GeometryError("node coordinates contain NaN or infinity")
    coords = np.array(coords0, dtype=np.float64, copy=True)

    def as_mask(sel) -> NDArray[np.bool_]:
        arr = np.asarray(sel)
        if arr.dtype == bool:
            if arr.shape != (n_nodes,):
                raise ValueError(f"node mask has shape {arr.shape}, expected ({n_nodes},)")
            return arr.copy()
        mask = np.zeros(n_nodes, dtype=bool)
        mask[arr.astype(np.int64)] = True
        return mask

    free = as_mask(free_nodes)
    sliding = as_mask(sliding_nodes) & ~free if sliding_nodes is not None else free & False
    # tangent bases of the sliding nodes (feature nodes stay put)
    basis = {}
    if sliding.any():
        quads, tris = boundary_faces(blocks)
        normals = boundary_node_normals(coords, quads, tris)
        cos_limit = np.cos(np.radians(opt.sliding_feature_angle))
        worst_cos = np.ones(n_nodes)
        for faces in (quads, tris):
            if len(faces):
                p = coords[faces]
                fn = (
                    np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
                    if faces.shape[1] == 4
                    else np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
                )
                fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
                for k in range(faces.shape[1]):
                    c = np.einsum("ij,ij->i", fn, normals[faces[:, k]])
                    np.minimum.at(worst_cos, faces[:, k], c)
        sliding &= (worst_cos >= cos_limit) & (np.linalg.norm(normals, axis=1) > 0)
        for node in np.flatnonzero(sliding):
            n = normals[node]
            helper = np.eye(3)[np.argmin(np.abs(n))]
            t1 = np.cross(n, helper)
            t1 /= np.linalg.norm(t1)
            basis[int(node)] = np.stack([t1, np.cross(n, t1)], 1)  # (3, 2)
    movable = np.flatnonzero(free | sliding)
    raise_if_cancelled(cancel, "smoothing cancelled")
    nb = _build_neighbourhood(
        blocks, movable, n_nodes, lambda: raise_if_cancelled(cancel, "smoothing cancelled")
    )
    raise_if_cancelled(cancel, "smoothing cancelled")
    n_mov = len(movable)
    all_handles = np.arange(nb.offset[-1])
    jac, scaled, aspect, warp = _evaluate(nb, coords, all_handles)
    worst_before = float(jac.min()) if len(jac) else float("nan")
    inverted_before = int(np.count_nonzero(jac <= 0))
    # per-node projector onto the allowed directions (identity for free nodes)
    projector = np.broadcast_to(np.eye(3), (n_mov, 3, 3)).copy()
    slide_pos = [i for i, node in enumerate(movable) if int(node) in basis]
    for i in slide_pos:
        b = basis[int(movable[i])]
        projector[i] = b @ b.T

    def check_cancel() -> None:
        raise_if_cancelled(cancel, "smoothing cancelled")

    def report_progress(fraction: float, message: str) -> None:
        if progress is not None:
            progress(float(min(max(fraction, 0.0), 1.0)), message)

    # ------------------------------------------------------------------ stages 1 and 2
    compressed = np.full(n_nodes, -1, dtype=np.int64)
    compressed[movable] = np.arange(n_mov)
    raise_if_cancelled(cancel, "smoothing cancelled")
    if n_mov:
        colours, conflict_ptr, conflict_nbrs = _colour(nb, compressed, n_mov)
        raise_if_cancelled(cancel, "smoothing cancelled")
    else:
        colours, conflict_ptr, conflict_nbrs = [], np.zeros(1, np.int64), np.zeros(0, np.int64)
    scale = 1.0
    if n_mov and len(nb.nbr):
        edge_len = np.linalg.norm(
            coords[movable[np.repeat(np.arange(n_mov), np.diff(nb.nbr_ptr))]] - coords[nb.nbr],
            axis=1,
        )
        scale = float(np.median(edge_len)) if len(edge_len) else 1.0
    goal = np.full(len(jac), JACOBIAN_WARN)
    for ti, etype in enumerate(nb.types):
        span = slice(nb.offset[ti], nb.offset[ti + 1])
        if isinstance(target, Mapping):
            if etype in target:
                goal[span] = np.asarray(target[etype], dtype=float)[nb.block_rows[ti]]
        else:
            goal[span] = float(target)
    state = _State(
        nb, coords, jac, scaled, aspect, warp, movable, projector, basis, worst_before, scale,
        float(opt.aspect_limit), float(np.cos(np.radians(opt.warpage_limit))), goal,
        position_guard,
    )  # fmt: skip
    moves = sweeps = optimized = improved = 0
    n_passes = max(int(opt.passes), 1) if n_mov else 0
    dirty = np.ones(n_mov, dtype=bool)  # nodes whose neighbourhood changed since last tried
    for p in range(n_passes):
        before = (int(np.count_nonzero(jac <= 0)), float(jac.min()), float(jac.sum()))
        snapshot = coords[movable].copy()

        def sweep_progress(fraction: float, message: str, p=p) -> None:
            report_progress((p + 0.5 * fraction) / n_passes, message)

        def node_progress(fraction: float, message: str, p=p) -> None:
            report_progress((p + 0.5 + 0.5 * fraction) / n_passes, message)

        m, s_ = _laplacian_stage(
            state, colours, (conflict_ptr, conflict_nbrs), opt.max_sweeps, opt.relaxation,
            sweep_progress, check_cancel,
        )  # fmt: skip
        moves += m
        sweeps += s_
        if opt.optimize and optimized < opt.max_optimized_nodes:
            o, i_ = _batched_stage(
                state, colours, opt.max_optimized_nodes - optimized, opt.iterations,
                node_progress, check_cancel, dirty,
            )  # fmt: skip
            optimized += o
            improved += i_
        after = (int(np.count_nonzero(jac <= 0)), float(jac.min()), float(jac.sum()))
        moved = np.any(coords[movable] != snapshot, axis=1)
        dirty = moved.copy()
        if moved.any() and len(conflict_nbrs):
            owner = np.repeat(np.arange(n_mov), np.diff(conflict_ptr))
            dirty[owner[moved[conflict_nbrs]]] = True
        if after[0] == 0 and np.all(state.deficit(all_handles) >= 0):
            break
        if after[0] >= before[0] and after[1] <= before[1] + 1e-9 and after[2] <= before[2] + 1e-6:
            break
    report_progress(1.0, "smoothing done")
    displacement = np.linalg.norm(coords - coords0, axis=1)
    report = SmoothingReport(
        free_nodes=int(free.sum()),
        sliding_nodes=int(sliding.sum()),
        moved_nodes=int(np.count_nonzero(displacement > 0)),
        stage1_sweeps=sweeps,
        stage1_moves=moves,
        stage2_nodes=optimized,
        stage2_improved=improved,
        worst_jacobian_before=worst_before,
        worst_jacobian_after=float(jac.min()) if len(jac) else float("nan"),
        inverted_before=inverted_before,
        inverted_after=int(np.count_nonzero(jac <= 0)),
        max_displacement=float(displacement.max()) if n_nodes else 0.0,
        seconds=time.perf_counter() - started,
        inverted_out_of_reach=_inverted_out_of_reach(blocks, coords, free | sliding, check_cancel),
    )
    return coords, report


@dataclass
class _State:
    """What the two stages share (arrays updated in place)."""

    nb: _Neighbourhood
    coords: NDArray[np.float64]
    jac: NDArray[np.float64]
    scaled: NDArray[np.float64]
    aspect: NDArray[np.float64]
    warp: NDArray[np.float64]
    movable: NDArray[np.int64]
    projector: NDArray[np.float64]
    basis: dict[int, NDArray[np.float64]]
    floor: float
    scale: float
    aspect_limit: float
    warp_limit_cos: float
    goal: NDArray[np.float64]  # per element (handle): the quality it should reach
    guard: PositionGuard | None = None

    def allowed(self, nodes: NDArray[np.int64], accept: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """``accept`` narrowed by the position guard (nodes at their trial positions)."""
        if self.guard is None or not accept.any():
            return accept
        out = accept.copy()
        out[accept] = self.guard(nodes[accept], self.coords)
        return out

    def deficit(self, handles: NDArray[np.int64]) -> NDArray[np.float64]:
        """J* minus the goal of the given elements (negative: below the goal)."""
        return ordered_quality(self.jac[handles], self.scaled[handles]) - self.goal[handles]


def _laplacian_stage(
    st: _State,
    colours: list[NDArray[np.int64]],
    conflicts: tuple[NDArray[np.int64], NDArray[np.int64]],
    max_sweeps: int,
    relaxation: tuple[float, ...],
    progress: ProgressCallback,
    check_cancel: Callable[[], None],
) -> tuple[int, int]:
    """Stage 1: guarded Laplacian sweeps. Returns (accepted moves, sweeps run).

    Each sweep works on the nodes sharing an element below its goal and the nodes sharing an
    element with them.
    """
    nb, coords, jac, scaled, aspect, warp = st.nb, st.coords, st.jac, st.scaled, st.aspect, st.warp
    n_mov = len(st.movable)
    all_handles, all_owner = _csr_gather(nb.node_ptr, nb.node_handles, np.arange(n_mov))
    conflict_ptr, conflict_nbrs = conflicts
    conflict_owner = np.repeat(np.arange(n_mov), np.diff(conflict_ptr))
    tolerance = 1e-4 * st.scale  # smaller Laplacian steps are not tried
    converged = 1e-3 * st.scale  # a sweep whose largest accepted move is smaller ends stage 1
    moves = sweeps = 0
    best = (int(np.count_nonzero(jac <= 0)), float(jac.min()) if len(jac) else 0.0)
    stalled = 0
    for sweep in range(max_sweeps):
        check_cancel()
        sweeps += 1
        moved_this_sweep = 0
        largest_move = 0.0
        node_deficit = np.full(n_mov, np.inf)
        np.minimum.at(node_deficit, all_owner, st.deficit(all_handles))
        poor = node_deficit < 0
        working = poor.copy()
        working[conflict_owner[poor[conflict_nbrs]]] = True
        if not working.any():
            break
        for full_group in colours:
            group = full_group[working[full_group]]
            if len(group) == 0:
                continue
            check_cancel()  # a sweep over a whole-body model's region: a second at 1M
            nodes = st.movable[group]
            nbr_idx, owner = _csr_gather(nb.nbr_ptr, nb.nbr, group)
            counts = np.bincount(owner, minlength=len(group))
            mean = np.zeros((len(group), 3))
            np.add.at(mean, owner, coords[nbr_idx])
            mean /= np.maximum(counts, 1)[:, None]
            step = np.einsum("nij,nj->ni", st.projector[group], mean - coords[nodes])
            active = np.linalg.norm(step, axis=1) > tolerance
            handles, h_owner = _csr_gather(nb.node_ptr, nb.node_handles, group)
            old = _score(
                jac[handles], scaled[handles], aspect[handles], warp[handles], h_owner, len(group)
            )
            start = coords[nodes].copy()
            for omega in relaxation:
                if not active.any():
                    break
                coords[nodes[active]] = start[active] + omega * step[active]
                sel = active[h_owner]
                new_j, new_s, new_a, new_w = _evaluate(nb, coords, handles[sel])
                new = _score(new_j, new_s, new_a, new_w, h_owner[sel], len(group))
                accept = active & _accept(old, new, st.floor, st.aspect_limit, st.warp_limit_cos)
                accept = st.allowed(nodes, accept)
                reject = active & ~accept
                coords[nodes[reject]] = start[reject]  # put rejected nodes back
                kept = accept[h_owner[sel]]
                jac[handles[sel][kept]] = new_j[kept]
                scaled[handles[sel][kept]] = new_s[kept]
                aspect[handles[sel][kept]] = new_a[kept]
                warp[handles[sel][kept]] = new_w[kept]
                moved_this_sweep += int(accept.sum())
                if accept.any():
                    largest_move = max(largest_move, omega * float(np.abs(step[accept]).max()))
                active = reject
        moves += moved_this_sweep
        progress((sweep + 1) / max_sweeps, f"smoothing sweep {sweep + 1}")
        if moved_this_sweep == 0 or largest_move < converged:
            break
        # stop when neither the invalid count nor the worst value improved for 3 sweeps
        now = (int(np.count_nonzero(jac <= 0)), float(jac.min()))
        if now[0] < best[0] or now[1] > best[1] + 1e-4:
            best = (min(now[0], best[0]), max(now[1], best[1]))
            stalled = 0
        else:
            stalled += 1
            if stalled >= 3:
                break
    return moves, sweeps


def _batched_stage(
    st: _State,
    colours: list[NDArray[np.int64]],
    max_nodes: int,
    iterations: int,
    progress: ProgressCallback,
    check_cancel: Callable[[], None],
    dirty: NDArray[np.bool_],
) -> tuple[int, int]:
    """Stage 2 with one Nelder-Mead simplex per node, all nodes of a colour at once.

    Returns (nodes tried, nodes improved). Same objective and acceptance as the per-node
    scipy path; see :mod:`kneegui.meshopt.batched`.
    """
    nb = st.nb
    tried = improved = 0
    for gi, group in enumerate(colours):
        check_cancel()
        progress(gi / max(len(colours), 1), "optimising nodes")
        if tried >= max_nodes:
            break
        handles, owner = _csr_gather(nb.node_ptr, nb.node_handles, group)
        deficit = np.full(len(group), np.inf)
        np.minimum.at(deficit, owner, st.deficit(handles))
        pick = (deficit < 0) & dirty[group]
        if not pick.any():
            continue
        sub = group[pick][: max_nodes - tried]
        handles, owner = _csr_gather(nb.node_ptr, nb.node_handles, sub)
        n = len(sub)
        counts = np.bincount(owner, minlength=n)
        slot = np.arange(len(handles)) - np.repeat(np.cumsum(counts) - counts, counts)
        old = _score(
            st.jac[handles], st.scaled[handles], st.aspect[handles], st.warp[handles], owner, n
        )
        types = nb.handle_type[handles]
        handle_lists = []
        for ti, etype in enumerate(nb.types):
            sel = np.flatnonzero(types == ti)
            if len(sel):
                conn = nb.conn[ti][nb.handle_row[handles[sel]]]
                handle_lists.append((etype, owner[sel], slot[sel], conn))
        nodes = st.movable[sub]
        problems = build_problems(
            nodes, st.coords, handle_lists, CORNER_TRIPLES, st.projector[sub], old.worst,
            old.inverted, np.maximum(old.worst_aspect, st.aspect_limit), counts,
        )  # fmt: skip
        u = nelder_mead(problems, iterations, check_cancel)
        start = st.coords[nodes].copy()
        st.coords[nodes] = problems.x0 + np.einsum("nij,nj->ni", problems.projector, u)
        new_j, new_s, new_a, new_w = _evaluate(nb, st.coords, handles)
        new = _score(new_j, new_s, new_a, new_w, owner, n)
        accept = _accept(old, new, st.floor, st.aspect_limit, st.warp_limit_cos)
        accept = st.allowed(nodes, accept)
        st.coords[nodes[~accept]] = start[~accept]
        kept = accept[owner]
        st.jac[handles[kept]] = new_j[kept]
        st.scaled[handles[kept]] = new_s[kept]
        st.aspect[handles[kept]] = new_a[kept]
        st.warp[handles[kept]] = new_w[kept]
        tried += n
        improved += int(accept.sum())
    return tried, improved


def _inverted_out_of_reach(
    blocks: Mapping[str, ElementBlock],
    coords: NDArray[np.float64],
    movable: NDArray[np.bool_],
    check_cancel: Callable[[], None] | None = None,
) -> int:
    """Inverted solid/quad elements with no movable node (unchanged by smoothing);
    ``check_cancel()`` before every chunk (a whole-body model: seconds in all)."""
    count = 0
    for etype in SMOOTHED_TYPES:
        block = blocks.get(etype)
        if block is None or len(block) == 0:
            continue
        conn = block.conn[:, : CORNER_NODES[etype]]
        out = conn[~movable[conn].any(axis=1)]
        for start in range(0, len(out), 65536):
            if check_cancel is not None:
                check_cancel()
            jac, _ = corner_quality(coords[out[start : start + 65536]], etype)
            count += int(np.count_nonzero(jac <= 0))
    return count
