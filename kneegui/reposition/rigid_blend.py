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

from collections.abc import Callable, Mapping, Sequence

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from kneegui.errors import Cancelled
from kneegui.geometry.transforms import RigidTransform
from kneegui.model import ElementBlock
from kneegui.topology import ELEMENT_EDGES

_SMALL = 1e-9
#: Largest number of free nodes whose weights are solved by a sparse LU (fastest up to there);
#: beyond, :func:`block_cg`.
DIRECT_SOLVE_MAX = 50_000


def mesh_edges(blocks: Mapping[str, ElementBlock], element_masks: Mapping[str, NDArray]) -> NDArray:
    """Unique undirected edges (E, 2) of the selected elements."""
    chunks = []
    for etype, block in blocks.items():
        mask = element_masks.get(etype)
        if mask is None or not mask.any():
            continue
        conn = block.conn[mask]
        for a, b in ELEMENT_EDGES[etype]:
            chunks.append(np.column_stack([conn[:, a], conn[:, b]]))
    if not chunks:
        return np.zeros((0, 2), dtype=np.int64)
    e = np.sort(np.concatenate(chunks), axis=1)
    e = e[e[:, 0] != e[:, 1]]
    return np.unique(e, axis=0)


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
    prior = _distance_prior(coords, free, anchor_surfaces or anchors)
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
        w = block_cg(lap, rhs, prior, 1.0 / diag, rtol=1e-8, max_iterations=5000, cancel=cancel)
    w = np.clip(w, 0.0, None)
    total = w.sum(axis=1, keepdims=True)
    return np.where(total > _SMALL, w / np.maximum(total, _SMALL), prior)


def block_cg(
    matrix: sp.csr_matrix,
    rhs: NDArray[np.float64],
    x0: NDArray[np.float64],
    inv_diag: NDArray[np.float64],
    rtol: float = 1e-8,
    max_iterations: int = 5000,
    cancel: Callable[[], bool] | None = None,
) -> NDArray[np.float64]:
    """Jacobi-preconditioned conjugate gradients for every column of ``rhs`` at once.

    The columns are independent CG runs (each with its own step lengths, stopping when its
    residual is below ``rtol`` times its right-hand side), advanced together so that one sparse
    product serves all of them: a near-linear solve for the large, well-conditioned Laplacians
    of the rigid blend, where a direct factorisation grows super-linearly. Column sums are
    einsum reductions, so the result does not depend on the BLAS thread count.

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
        Polled every 25 iterations; returning True raises :class:`kneegui.errors.Cancelled`.

    Returns
    -------
    (n, k) ndarray
    """
    a = sp.csr_matrix(matrix)
    x = np.array(x0, dtype=np.float64, copy=True)
    r = rhs - a @ x
    target = rtol * np.sqrt(np.einsum("ij,ij->j", rhs, rhs))
    active = np.sqrt(np.einsum("ij,ij->j", r, r)) > target
    m = inv_diag[:, None]
    z = m * r
    p = z.copy()
    rz = np.einsum("ij,ij->j", r, z)
    for iteration in range(max_iterations):
        if not active.any():
            break
        if cancel is not None and iteration % 25 == 0 and cancel():
            raise Cancelled("solve cancelled")
        cols = np.flatnonzero(active)
        pc = p[:, cols]
        ap = a @ pc
        alpha = rz[cols] / np.einsum("ij,ij->j", pc, ap)
        x[:, cols] += alpha * pc
        rc = r[:, cols] - alpha * ap
        r[:, cols] = rc
        done = np.sqrt(np.einsum("ij,ij->j", rc, rc)) <= target[cols]
        zc = m * rc
        rz_new = np.einsum("ij,ij->j", rc, zc)
        p[:, cols] = zc + (rz_new / rz[cols]) * pc
        rz[cols] = rz_new
        active[cols[done]] = False
    return x


def _distance_prior(
    coords: NDArray[np.float64], free: NDArray[np.int64], surfaces: Sequence[NDArray[np.int64]]
) -> NDArray[np.float64]:
    inv = np.zeros((len(free), len(surfaces)))
    for s, idx in enumerate(surfaces):
        if len(idx) == 0:
            continue
        d, _ = cKDTree(coords[idx]).query(coords[free])
        inv[:, s] = 1.0 / np.maximum(d, 1e-6) ** 2
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
    """Apply ``exp(twist_i)`` to ``points[i]`` for every row, vectorised.

    Parameters
    ----------
    twists : (M, 6) ndarray
        ``(omega, v)`` per point.
    points : (M, 3) ndarray
        Points to move.
    """
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
