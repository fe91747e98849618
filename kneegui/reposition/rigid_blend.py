"""Blending rigid bone motions smoothly through soft tissue (a remedy beyond the paper).

Each soft-tissue node gets weights ``w_s`` (one per rigid segment: femur, tibia group, patella,
fixed parts; they sum to 1), computed once as harmonic functions over the soft-tissue mesh: 1 on
the segment's own nodes, 0 on the other segments' nodes. A pose blends the segments' rigid
motions in the Lie algebra of rigid motions: ``x' = exp(sum_s w_s log T_s) x``. For motions about
one common axis (the knee's flexion about the F-E axis) this rotates a node about that axis by
the weighted angle, so tissue wraps around the joint instead of collapsing onto the chord as a
linear blend of positions would.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numba import njit, prange
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from kneegui.errors import Cancelled, raise_if_cancelled
from kneegui.geometry.transforms import RigidTransform
from kneegui.meshopt.parallel import PARALLEL_KERNEL_LOCK
from kneegui.model import ElementBlock
from kneegui.topology import ELEMENT_EDGES, sorted_unique

_SMALL = 1e-9
#: Largest number of free nodes whose weights are solved by a sparse LU (fastest up to there);
#: beyond, :func:`block_cg`.
DIRECT_SOLVE_MAX = 50_000


#: Edge keys sorted in one call up to this many; beyond, in pieces of about this many with a
#: question to ``cancel`` between them (a 1.76M-node model's soft tissue: 20M edge keys).
EDGE_SORT_PIECE = 4_000_000


def mesh_edges(
    blocks: Mapping[str, ElementBlock],
    element_masks: Mapping[str, NDArray],
    cancel: Callable[[], bool] | None = None,
) -> NDArray:
    """Unique undirected edges (E, 2) of the selected elements, rows sorted, each with its
    smaller node first; collapsed edges (one node twice) dropped.

    ``cancel`` is asked per element type and edge of it, and between the pieces of the final
    sort: seconds in all on a whole-body model.
    """
    lows, highs = [], []
    for etype, block in blocks.items():
        raise_if_cancelled(cancel, "cancelled while collecting the mesh's edges")
        mask = element_masks.get(etype)
        if mask is None or not mask.any():
            continue
        conn = block.conn[mask]
        for a, b in ELEMENT_EDGES[etype]:
            raise_if_cancelled(cancel, "cancelled while collecting the mesh's edges")
            low = np.minimum(conn[:, a], conn[:, b])
            high = np.maximum(conn[:, a], conn[:, b])
            kept = low != high
            lows.append(low[kept])
            highs.append(high[kept])
    if not lows:
        return np.zeros((0, 2), dtype=np.int64)
    low, high = np.concatenate(lows), np.concatenate(highs)
    del lows, highs
    if len(low) == 0 or int(high.max()) >= 2**31:
        return np.unique(np.column_stack([low, high]), axis=0)
    # one int64 key per edge: a 1-D unique sorts numbers, not rows (several times faster);
    # the keys sort as the rows would, so the result is the same array
    key = sorted_unique_in_pieces((low << 32) | high, cancel)
    return np.column_stack([key >> 32, key & 0xFFFFFFFF])


def sorted_unique_in_pieces(
    keys: NDArray[np.int64], cancel: Callable[[], bool] | None
) -> NDArray[np.int64]:
    """:func:`sorted_unique` of non-negative keys, in value ranges of equal width sorted one
    at a time (the same array: the ranges are disjoint and taken in order), ``cancel`` asked
    before each."""
    pieces = -(-len(keys) // EDGE_SORT_PIECE)
    if cancel is None or pieces <= 1:
        return sorted_unique(keys)
    lo, hi = int(keys.min()), int(keys.max()) + 1
    bounds = [lo + (hi - lo) * k // pieces for k in range(pieces + 1)]
    out = []
    for k in range(pieces):
        raise_if_cancelled(cancel, "cancelled while collecting the mesh's edges")
        out.append(sorted_unique(keys[(keys >= bounds[k]) & (keys < bounds[k + 1])]))
    return np.concatenate(out)


def harmonic_weights(
    n_nodes: int,
    edges: NDArray[np.int64],
    free: NDArray[np.int64],
    anchors: Sequence[NDArray[np.int64]],
    coords: NDArray[np.float64],
    anchor_surfaces: Sequence[NDArray[np.int64]] | None = None,
    regularisation: float = 1e-4,
    edge_weighting: str = "inverse_square_length",
    prior_strength: NDArray[np.float64] | None = None,
    cancel: Callable[[], bool] | None = None,
    surface_distance: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Harmonic partition-of-unity weights of ``free`` nodes with respect to anchor groups.

    Solves the graph Laplace equation over ``edges`` for each group ``s``: ``w_s = 1`` on
    ``anchors[s]``, ``0`` on the other anchors. A small pull towards a geometric prior
    (inverse-square distance to each group) keeps free nodes that no edge path connects to an
    anchor well defined.

    Parameters
    ----------
    n_nodes : int
        Number of model nodes.
    edges : (E, 2) ndarray of int
        Mesh edges (node indices).
    free : (F,) ndarray of int
        Nodes whose weights are wanted.
    anchors : sequence of (A_s,) ndarray of int
        Node indices of each rigid group.
    coords : (N, 3) ndarray of float
        Initial coordinates (for the prior).
    anchor_surfaces : sequence of ndarray of int, optional
        Subsets of the anchors used for the distance prior (default: the anchors).
    regularisation : float
        Strength of the prior relative to the mean node degree.
    prior_strength : (F,) ndarray, optional
        Extra pull of each free node towards its prior, relative to the mean node degree (e.g.
        strong for tissue lying on a bone away from the joint, zero in the joint).
    edge_weighting : str
        ``"inverse_square_length"`` (default: a discretisation of the continuous Laplacian that
        does not depend on how finely each region is meshed) or ``"uniform"`` (graph Laplacian).
    cancel : callable, optional
        Polled during the iterative solve; returning True raises
        :class:`kneegui.errors.Cancelled`.
    surface_distance : (F, S) ndarray, optional
        :func:`surface_distances` of ``free`` to the prior's surfaces, when the caller has
        measured them already (one nearest-point search per surface over every free node).

    Returns
    -------
    (F, S) ndarray of float
        Weights, rows summing to 1.
    """
    n_groups = len(anchors)
    free = np.asarray(free, dtype=np.int64)
    if len(free) == 0:
        return np.zeros((0, n_groups))
    value = np.full((n_nodes, n_groups), np.nan)
    for idx in anchors:
        value[idx] = 0.0
    for s, idx in enumerate(anchors):
        value[idx, s] = 1.0
    if surface_distance is None:
        surface_distance = surface_distances(coords, free, anchor_surfaces or anchors)
    prior = _distance_prior(surface_distance)
    pos = np.full(n_nodes, -1, dtype=np.int64)
    pos[free] = np.arange(len(free))
    a, b = edges[:, 0], edges[:, 1]
    keep = (pos[a] >= 0) | (pos[b] >= 0)
    a, b = a[keep], b[keep]
    if edge_weighting == "inverse_square_length":
        length2 = np.sum((coords[a] - coords[b]) ** 2, axis=1)
        ew = 1.0 / np.maximum(length2, 1e-12 * max(float(np.median(length2)), 1e-30))
        ew /= float(np.median(ew))
    else:
        ew = np.ones(len(a))
    deg = np.bincount(
        np.concatenate([a, b]), weights=np.concatenate([ew, ew]), minlength=n_nodes
    ).astype(np.float64)
    scale = max(float(deg[free].mean()), 1.0)
    eps = regularisation * scale * np.ones(len(free))
    if prior_strength is not None:
        eps = eps + scale * np.asarray(prior_strength, dtype=np.float64)
    rhs = eps[:, None] * prior
    rows, cols, vals = [], [], []
    for u, v in ((a, b), (b, a)):
        fu = pos[u] >= 0
        fv = pos[v] >= 0
        both = fu & fv
        rows.append(pos[u[both]])
        cols.append(pos[v[both]])
        vals.append(-ew[both])
        # edges to anchored (Dirichlet) nodes move to the right-hand side
        known = fu & ~fv
        known &= ~np.isnan(value[v, 0])
        np.add.at(rhs, pos[u[known]], ew[known][:, None] * value[v[known]])
    diag = deg[free] + eps
    lap = sp.csr_matrix(
        (
            np.concatenate([*vals, diag]),
            (
                np.concatenate([*rows, np.arange(len(free))]),
                np.concatenate([*cols, np.arange(len(free))]),
            ),
        ),
        shape=(len(free), len(free)),
    )
    if len(free) <= DIRECT_SOLVE_MAX:
        w = spla.splu(lap.tocsc()).solve(rhs)
    else:
        both = (pos[a] >= 0) & (pos[b] >= 0)
        lengths = np.linalg.norm(coords[a[both]] - coords[b[both]], axis=1)
        edge = float(np.median(lengths)) if len(lengths) else 0.0
        if not edge > 0.0:  # no edge between free nodes: cells of about 512 nodes each
            extent = np.ptp(coords[free], axis=0).max()
            edge = max(float(extent), 1e-12) / max(len(free), 1) ** (1.0 / 3.0)
        coarse = coarse_space(lap, coords[free], COARSE_CELL_EDGES * edge)
        raise_if_cancelled(cancel, "solve cancelled")
        w = block_cg(
            lap, rhs, prior, 1.0 / diag, rtol=1e-8, max_iterations=5000, cancel=cancel,
            coarse=coarse,
        )  # fmt: skip
    w = np.clip(w, 0.0, None)
    total = w.sum(axis=1, keepdims=True)
    return np.where(total > _SMALL, w / np.maximum(total, _SMALL), prior)


#: Side of the cubic cells that group the blend's unknowns into the coarse space of
#: :func:`block_cg`, in median mesh edges: the 1M demo's 739,322 soft nodes fall into 4,291
#: cells. Smaller cells (6 edges: 9,329) saved iterations (140 instead of 168) but not time,
#: their coarse solve costing four times as much.
COARSE_CELL_EDGES = 8.0


@dataclass(frozen=True)
class CoarseSpace:
    """A coarse space for :func:`block_cg`: the unknowns grouped into aggregates, and the
    factorised Galerkin matrix ``P.T @ A @ P`` of the aggregates' indicator columns ``P``.

    Attributes
    ----------
    aggregate : (n,) ndarray of int
        The aggregate of each unknown (0 to ``count - 1``, every one non-empty).
    count : int
    factor : scipy.sparse.linalg.SuperLU
        LU factors of the coarse matrix (symmetric positive definite when the matrix is).
    """

    aggregate: NDArray[np.int64]
    count: int
    factor: spla.SuperLU


def coarse_space(matrix: sp.spmatrix, coords: NDArray[np.float64], cell: float) -> CoarseSpace:
    """Aggregates of the unknowns of ``matrix`` by cubic cells of side ``cell`` over their
    ``coords`` (one row per unknown), and the factorised coarse matrix over them.

    Cells, not graph aggregation: one vectorised pass over the coordinates. Unknowns of one
    cell that the matrix does not connect (two sides of a sliding interface) share an aggregate;
    the preconditioner stays symmetric positive definite, only a little less effective there.
    """
    coords = np.asarray(coords, dtype=np.float64)
    key = np.floor((coords - coords.min(axis=0)) / max(cell, 1e-300)).astype(np.int64)
    dims = key.max(axis=0) + 1
    flat = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
    _, aggregate = np.unique(flat, return_inverse=True)
    aggregate = aggregate.astype(np.int64).ravel()
    count = int(aggregate.max()) + 1 if len(aggregate) else 0
    n = len(aggregate)
    indicator = sp.csr_matrix((np.ones(n), (np.arange(n), aggregate)), shape=(n, count))
    galerkin = (indicator.T @ sp.csr_matrix(matrix) @ indicator).tocsc()
    return CoarseSpace(aggregate, count, spla.splu(galerkin))


def block_cg(
    matrix: sp.csr_matrix,
    rhs: NDArray[np.float64],
    x0: NDArray[np.float64],
    inv_diag: NDArray[np.float64],
    rtol: float = 1e-8,
    max_iterations: int = 5000,
    cancel: Callable[[], bool] | None = None,
    coarse: CoarseSpace | None = None,
) -> NDArray[np.float64]:
    """Jacobi-preconditioned conjugate gradients for every column of ``rhs`` at once.

    The columns are independent CG runs (each with its own step lengths, stopping when its
    residual is below ``rtol`` times its right-hand side), advanced together so that one sparse
    product serves all of them: a near-linear solve for the large, well-conditioned Laplacians
    of the rigid blend, where a direct factorisation grows super-linearly. The iterations are
    one compiled, sequential loop (no temporaries, one pass over the matrix per iteration for
    all columns), so the result does not depend on the thread count.

    Parameters
    ----------
    matrix : (n, n) sparse matrix
        Symmetric positive definite.
    rhs, x0 : (n, k) ndarray
        Right-hand sides and initial guesses.
    inv_diag : (n,) ndarray
        Inverse of the matrix diagonal.
    rtol : float
    max_iterations : int
    cancel : callable, optional
        Polled before the first iteration and every 25 after; returning True raises
        :class:`kneegui.errors.Cancelled`.
    coarse : CoarseSpace, optional
        Adds a coarse-grid correction to the Jacobi preconditioner (two-level additive:
        ``M^-1 r = D^-1 r + P (P^T A P)^-1 P^T r``, :func:`coarse_space`). Jacobi alone removes
        an error smooth over the model only in hundreds of iterations, each streaming the
        matrix (the 1M demo's weights: 488); the coarse solve removes it at once (168).

    Returns
    -------
    (n, k) ndarray
    """
    if coarse is not None:
        return _two_level_cg(matrix, rhs, x0, inv_diag, coarse, rtol, max_iterations, cancel)
    a = sp.csr_matrix(matrix)
    a.sort_indices()
    x = np.array(x0, dtype=np.float64, copy=True, order="C")
    rhs = np.ascontiguousarray(rhs, dtype=np.float64)
    inv_diag = np.ascontiguousarray(inv_diag, dtype=np.float64)
    indptr = a.indptr.astype(np.int64)
    # 32-bit column indices where they fit: the product streams the matrix every iteration,
    # and its indices are a third of that (the arithmetic is the same)
    index_type = np.int32 if a.shape[1] < 2**31 else np.int64
    indices = a.indices.astype(index_type)
    data = a.data.astype(np.float64)
    r = rhs - _csr_times(indptr, indices, data, x)
    target = rtol * np.sqrt(_column_dots(rhs, rhs))
    active = np.sqrt(_column_dots(r, r)) > target
    p = inv_diag[:, None] * r
    rz = _column_dots(r, p)
    done = 0

    def packed(cols: NDArray[np.int64]) -> tuple[NDArray, ...]:
        # the columns still iterating, packed: a converged (or zero) column costs nothing
        xc, rc, pc = (np.ascontiguousarray(v[:, cols]) for v in (x, r, p))
        return xc, rc, pc, rz[cols], active[cols], target[cols]

    cols = np.flatnonzero(active)
    xc, rc, pc, rzc, activec, target_c = packed(cols)
    while done < max_iterations and active.any():
        if cancel is not None and cancel():
            raise Cancelled("solve cancelled")
        steps = min(_CANCEL_EVERY, max_iterations - done)
        with PARALLEL_KERNEL_LOCK:
            done += _cg_iterations(
                indptr, indices, data, inv_diag, xc, rc, pc, rzc, activec, target_c, steps
            )
        active[cols] = activec
        if active.any() and not activec.all():  # a column converged: repack the others
            x[:, cols], r[:, cols], p[:, cols], rz[cols] = xc, rc, pc, rzc
            cols = np.flatnonzero(active)
            xc, rc, pc, rzc, activec, target_c = packed(cols)
    x[:, cols] = xc
    return x


#: Iterations of :func:`block_cg` between two polls of its ``cancel`` callable.
_CANCEL_EVERY = 25


def _two_level_cg(
    matrix: sp.spmatrix,
    rhs: NDArray[np.float64],
    x0: NDArray[np.float64],
    inv_diag: NDArray[np.float64],
    coarse: CoarseSpace,
    rtol: float,
    max_iterations: int,
    cancel: Callable[[], bool] | None,
) -> NDArray[np.float64]:
    """:func:`block_cg` with the coarse-grid correction of ``coarse``: the same stopping test
    (each column's residual below ``rtol`` times its right-hand side); a converged column takes
    zero steps from then on. Every pass over the rows runs in fixed chunks and the restriction
    to the aggregates in row order, so the result does not depend on the thread count."""
    a = sp.csr_matrix(matrix)
    a.sort_indices()
    indptr = a.indptr.astype(np.int64)
    indices = a.indices.astype(np.int32 if a.shape[1] < 2**31 else np.int64)
    data = a.data.astype(np.float64)
    x = np.array(x0, dtype=np.float64, copy=True, order="C")
    rhs = np.ascontiguousarray(rhs, dtype=np.float64)
    inv_diag = np.ascontiguousarray(inv_diag, dtype=np.float64)
    aggregate = coarse.aggregate
    n, k = rhs.shape
    parts = np.zeros(((n + _CG_CHUNK_ROWS - 1) // _CG_CHUNK_ROWS, k))
    r = rhs - _csr_times(indptr, indices, data, x)
    target = rtol * np.sqrt(_column_dots(rhs, rhs))
    active = np.sqrt(_column_dots(r, r)) > target
    if not active.any():
        return x

    def corrected_dots() -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        # the coarse correction of r, and r . M^-1 r per column
        correction = coarse.factor.solve(_restrict(r, aggregate, coarse.count))
        _preconditioned_dots(r, inv_diag, aggregate, correction, parts)
        return correction, _chunk_sums(parts)

    p = np.zeros_like(r)
    ap = np.empty_like(r)
    with PARALLEL_KERNEL_LOCK:
        correction, rz = corrected_dots()
        _update_directions(p, r, inv_diag, aggregate, correction, np.zeros(k), active)
    done = 0
    while done < max_iterations and active.any():
        if cancel is not None and cancel():
            raise Cancelled("solve cancelled")
        with PARALLEL_KERNEL_LOCK:
            for _ in range(min(_CANCEL_EVERY, max_iterations - done)):
                _product_dots(indptr, indices, data, p, ap, parts)
                alpha = np.where(active, rz / np.where(active, _chunk_sums(parts), 1.0), 0.0)
                _step(x, r, p, ap, alpha, parts)
                converged = np.sqrt(_chunk_sums(parts)) <= target
                correction, rz_new = corrected_dots()
                beta = np.where(active, rz_new / np.where(active, rz, 1.0), 0.0)
                rz = np.where(active, rz_new, rz)
                _update_directions(p, r, inv_diag, aggregate, correction, beta, active)
                active &= ~converged
                done += 1
                if not active.any():
                    break
    return x


@njit(cache=True, nogil=True)
def _chunk_sums(parts):  # pragma: no cover - compiled
    """The chunks' partial sums (C, k) added in chunk order."""
    out = np.zeros(parts.shape[1])
    for c in range(parts.shape[0]):
        for j in range(parts.shape[1]):
            out[j] += parts[c, j]
    return out


@njit(cache=True, nogil=True, parallel=True)
def _product_dots(indptr, indices, data, p, ap, parts):  # pragma: no cover - compiled
    """``ap = A @ p`` and each chunk's sums of ``p * ap`` per column into ``parts``."""
    n, k = p.shape
    for chunk in prange(parts.shape[0]):
        acc = np.empty(k)
        sums = np.zeros(k)
        for i in range(chunk * _CG_CHUNK_ROWS, min(n, (chunk + 1) * _CG_CHUNK_ROWS)):
            acc[:] = 0.0
            for q in range(indptr[i], indptr[i + 1]):
                c, w = indices[q], data[q]
                for j in range(k):
                    acc[j] += w * p[c, j]
            for j in range(k):
                ap[i, j] = acc[j]
                sums[j] += p[i, j] * acc[j]
        parts[chunk, :] = sums


@njit(cache=True, nogil=True, parallel=True)
def _step(x, r, p, ap, alpha, parts):  # pragma: no cover - compiled
    """``x += alpha p``, ``r -= alpha ap``, and each chunk's ``r . r`` per column."""
    n, k = x.shape
    for chunk in prange(parts.shape[0]):
        rr = np.zeros(k)
        for i in range(chunk * _CG_CHUNK_ROWS, min(n, (chunk + 1) * _CG_CHUNK_ROWS)):
            for j in range(k):
                x[i, j] += alpha[j] * p[i, j]
                r[i, j] -= alpha[j] * ap[i, j]
                rr[j] += r[i, j] * r[i, j]
        parts[chunk, :] = rr


@njit(cache=True, nogil=True)
def _restrict(r, aggregate, count):  # pragma: no cover - compiled
    """``P.T @ r``: each aggregate's rows summed, in row order."""
    out = np.zeros((count, r.shape[1]))
    for i in range(r.shape[0]):
        for j in range(r.shape[1]):
            out[aggregate[i], j] += r[i, j]
    return out


@njit(cache=True, nogil=True, parallel=True)
def _preconditioned_dots(r, inv_diag, aggregate, correction, parts):  # pragma: no cover
    """Each chunk's ``r . z`` per column, ``z = inv_diag r + correction[aggregate]``."""
    n, k = r.shape
    for chunk in prange(parts.shape[0]):
        sums = np.zeros(k)
        for i in range(chunk * _CG_CHUNK_ROWS, min(n, (chunk + 1) * _CG_CHUNK_ROWS)):
            d = inv_diag[i]
            g = aggregate[i]
            for j in range(k):
                sums[j] += r[i, j] * (d * r[i, j] + correction[g, j])
        parts[chunk, :] = sums


@njit(cache=True, nogil=True, parallel=True)
def _update_directions(p, r, inv_diag, aggregate, correction, beta, active):  # pragma: no cover
    """``p = z + beta p`` for the active columns, ``z`` as in :func:`_preconditioned_dots`
    (computed again rather than stored: one pass less over memory)."""
    n, k = p.shape
    for chunk in prange((n + _CG_CHUNK_ROWS - 1) // _CG_CHUNK_ROWS):
        for i in range(chunk * _CG_CHUNK_ROWS, min(n, (chunk + 1) * _CG_CHUNK_ROWS)):
            d = inv_diag[i]
            g = aggregate[i]
            for j in range(k):
                if active[j]:
                    p[i, j] = (d * r[i, j] + correction[g, j]) + beta[j] * p[i, j]


@njit(cache=True, nogil=True)
def _csr_times(indptr, indices, data, v):  # pragma: no cover - compiled
    n, k = len(indptr) - 1, v.shape[1]
    out = np.zeros((n, k))
    for i in range(n):
        for q in range(indptr[i], indptr[i + 1]):
            c, w = indices[q], data[q]
            for j in range(k):
                out[i, j] += w * v[c, j]
    return out


@njit(cache=True, nogil=True)
def _column_dots(u, v):  # pragma: no cover - compiled
    out = np.zeros(u.shape[1])
    for i in range(u.shape[0]):
        for j in range(u.shape[1]):
            out[j] += u[i, j] * v[i, j]
    return out


#: Rows per chunk of the compiled CG's parallel passes. The chunking, and so every sum's order,
#: is fixed by the matrix size alone, never by the thread count.
_CG_CHUNK_ROWS = 4096


@njit(cache=True, nogil=True, parallel=True)
def _cg_iterations(
    indptr, indices, data, inv_diag, x, r, p, rz, active, target, steps
):  # pragma: no cover - compiled
    """Up to ``steps`` Jacobi-preconditioned CG iterations of the active columns, in place.

    A converged column is carried along with a zero step (its ``x``, ``r`` and ``p`` do not
    change), so every loop runs over all columns without indirection. The passes over the rows
    run in parallel over fixed chunks; each chunk sums its own rows in order and the chunks'
    sums are added in chunk order, so the result is the same for any number of threads.
    Returns the iterations done (fewer once every column has converged).
    """
    n, k = x.shape
    n_chunks = (n + _CG_CHUNK_ROWS - 1) // _CG_CHUNK_ROWS
    ap = np.empty((n, k))
    part_a = np.zeros((n_chunks, k))
    part_b = np.zeros((n_chunks, k))
    part_c = np.zeros((n_chunks, k))
    alpha = np.empty(k)
    beta = np.empty(k)
    for step in range(steps):
        if not active.any():
            return step
        _product_dots(indptr, indices, data, p, ap, part_a)
        for j in range(k):
            p_ap = 0.0
            for chunk in range(n_chunks):
                p_ap += part_a[chunk, j]
            alpha[j] = rz[j] / p_ap if active[j] else 0.0
        for chunk in prange(n_chunks):
            rr = np.zeros(k)
            rz_new = np.zeros(k)
            for i in range(chunk * _CG_CHUNK_ROWS, min(n, (chunk + 1) * _CG_CHUNK_ROWS)):
                d = inv_diag[i]
                for j in range(k):
                    x[i, j] += alpha[j] * p[i, j]
                    r[i, j] -= alpha[j] * ap[i, j]
                    rr[j] += r[i, j] * r[i, j]
                    rz_new[j] += r[i, j] * (d * r[i, j])
            part_b[chunk, :] = rr
            part_c[chunk, :] = rz_new
        converged = np.zeros(k, dtype=np.bool_)
        for j in range(k):
            rr_j = 0.0
            rz_j = 0.0
            for chunk in range(n_chunks):
                rr_j += part_b[chunk, j]
                rz_j += part_c[chunk, j]
            if active[j]:
                beta[j] = rz_j / rz[j]
                rz[j] = rz_j
                converged[j] = np.sqrt(rr_j) <= target[j]
            else:
                beta[j] = 1.0
        for chunk in prange(n_chunks):
            for i in range(chunk * _CG_CHUNK_ROWS, min(n, (chunk + 1) * _CG_CHUNK_ROWS)):
                d = inv_diag[i]
                for j in range(k):
                    if active[j]:
                        p[i, j] = d * r[i, j] + beta[j] * p[i, j]
        for j in range(k):
            if converged[j]:
                active[j] = False
    return steps


def surface_distances(
    coords: NDArray[np.float64], nodes: NDArray[np.int64], surfaces: Sequence[NDArray[np.int64]]
) -> NDArray[np.float64]:
    """Distance of each of ``nodes`` to the nearest node of each surface (``inf`` where a
    surface has no nodes), shape (len(nodes), len(surfaces)).

    The nearest of several surfaces' columns is the distance to their union, to the bit (a
    node pair's distance is computed the same way whichever tree holds it).
    """
    out = np.full((len(nodes), len(surfaces)), np.inf)
    for s, idx in enumerate(surfaces):
        if len(idx):
            out[:, s] = cKDTree(coords[idx]).query(coords[nodes], workers=-1)[0]
    return out


def _distance_prior(distance: NDArray[np.float64]) -> NDArray[np.float64]:
    """Inverse-square-distance weights of :func:`surface_distances`, rows summing to 1."""
    inv = np.zeros(distance.shape)
    measured = np.isfinite(distance)
    inv[measured] = 1.0 / np.maximum(distance[measured], 1e-6) ** 2
    total = inv.sum(axis=1, keepdims=True)
    return inv / np.maximum(total, _SMALL)


# ------------------------------------------------------------------------------ Lie algebra
def _hat(w: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def log_rigid(transform: RigidTransform) -> NDArray[np.float64]:
    """Twist ``(omega, v)`` (6,) with ``exp`` equal to the transform (rotation angle < 180°)."""
    r, t = transform.rotation, transform.translation
    c = np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(c))
    if theta < 1e-8:
        return np.concatenate([np.zeros(3), t])
    omega = (
        theta
        / (2.0 * np.sin(theta))
        * np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    )
    wx = _hat(omega)
    v_inv = (
        np.eye(3)
        - 0.5 * wx
        + (1.0 / theta**2) * (1.0 - theta * np.sin(theta) / (2.0 * (1.0 - np.cos(theta)))) * wx @ wx
    )
    return np.concatenate([omega, v_inv @ t])


def exp_twists_apply(twists: NDArray[np.float64], points: NDArray[np.float64]) -> NDArray:
    """Apply ``exp(twist_i)`` to ``points[i]`` for every row (one compiled pass).

    Parameters
    ----------
    twists : (M, 6) ndarray
        ``(omega, v)`` per point.
    points : (M, 3) ndarray
        Points to move.

    Returns
    -------
    (M, 3) ndarray
        The moved points: the same bits as :func:`exp_twists_apply_numpy`, the reference,
        wherever NumPy's ``sin``, ``cos`` and ``pow`` are the C library's (every x86-64 machine
        with AVX2 under :mod:`kneegui.reproducible`'s pin).
    """
    twists = np.ascontiguousarray(twists, dtype=np.float64)
    points = np.ascontiguousarray(points, dtype=np.float64)
    out = np.empty_like(points)
    _exp_twists_kernel(twists, points, 3.0, out)
    return out


@njit(cache=True, nogil=True)
def _exp_twists_kernel(twists, points, cube, out):  # pragma: no cover - compiled
    """:func:`exp_twists_apply_numpy`, node by node: every operation in NumPy's order
    (``theta ** 2`` is NumPy's square, ``th ** 3`` its ``pow``, which ``cube``, an argument
    rather than a constant, keeps the compiler from turning into two products). One thread:
    a slider pose must not wait for the solvers' parallel kernels."""
    for i in range(twists.shape[0]):
        ox = twists[i, 0]
        oy = twists[i, 1]
        oz = twists[i, 2]
        vx = twists[i, 3]
        vy = twists[i, 4]
        vz = twists[i, 5]
        px = points[i, 0]
        py = points[i, 1]
        pz = points[i, 2]
        theta = math.sqrt((ox * ox + oy * oy) + oz * oz)
        if theta < 1e-6:  # series for small angles keep the coefficients accurate
            t2 = theta * theta
            a = 1.0 - t2 / 6.0  # sin(t)/t
            b = 0.5 - t2 / 24.0  # (1-cos t)/t^2
            d = 1.0 / 6.0 - t2 / 120.0  # (t-sin t)/t^3
        else:
            s = math.sin(theta)
            a = s / theta
            b = (1.0 - math.cos(theta)) / (theta * theta)
            d = (theta - s) / math.pow(theta, cube)
        # omega x p, then omega x (omega x p)
        w0 = oy * pz - oz * py
        w1 = oz * px - ox * pz
        w2 = ox * py - oy * px
        u0 = oy * w2 - oz * w1
        u1 = oz * w0 - ox * w2
        u2 = ox * w1 - oy * w0
        # omega x v, then omega x (omega x v)
        g0 = oy * vz - oz * vy
        g1 = oz * vx - ox * vz
        g2 = ox * vy - oy * vx
        h0 = oy * g2 - oz * g1
        h1 = oz * g0 - ox * g2
        h2 = ox * g1 - oy * g0
        out[i, 0] = (px + a * w0 + b * u0) + (vx + b * g0 + d * h0)
        out[i, 1] = (py + a * w1 + b * u1) + (vy + b * g1 + d * h1)
        out[i, 2] = (pz + a * w2 + b * u2) + (vz + b * g2 + d * h2)


def exp_twists_apply_numpy(twists: NDArray[np.float64], points: NDArray[np.float64]) -> NDArray:
    """:func:`exp_twists_apply` in NumPy (the reference the compiled pass is tested against)."""
    omega, v = twists[:, :3], twists[:, 3:]
    theta = np.linalg.norm(omega, axis=1)
    small = theta < 1e-6
    th = np.where(small, 1.0, theta)
    s, c = np.sin(th), np.cos(th)
    # series for small angles keep the coefficients accurate
    a = np.where(small, 1.0 - theta**2 / 6.0, s / th)  # sin(t)/t
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - c) / th**2)  # (1-cos t)/t^2
    d = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (th - s) / th**3)  # (t-sin t)/t^3
    wxp = np.cross(omega, points)
    rp = points + a[:, None] * wxp + b[:, None] * np.cross(omega, wxp)
    wxv = np.cross(omega, v)
    vv = v + b[:, None] * wxv + d[:, None] * np.cross(omega, wxv)
    return rp + vv
