"""Stage 2 of the smoother with one Nelder-Mead simplex per node, run for many nodes at once.

The nodes of one colour share no element, so their local problems are independent: each node
keeps its own simplex, and the objective of every node is evaluated in one vectorised call. The
objective and the acceptance rules are those of the per-node ``scipy.optimize.minimize`` path
(:func:`kneegui.meshopt.smoother._optimise_node`); the simplex moves are scipy's
(reflection 1, expansion 2, contraction 1/2, shrink 1/2).

Local problem of a node at ``x0`` moving by ``delta``: every corner determinant is affine,
``d = D0 + G . delta`` (a tetrahedron's volume is affine in each vertex; quad shells keep their
starting mean normal), so ``G`` is computed analytically once; edge ratios use the node's own
edges and the fixed extremes of the element's other edges.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kneegui.meshopt.batched_kernel import compiled_objective
from kneegui.topology import ELEMENT_EDGES

_W = 8  # corner determinants per element, padded (hex has 8)
_K = 4  # node edges per element, padded (a pyramid apex has 4)


@dataclass
class LocalProblems:
    """Padded local problems of ``n`` nodes with up to ``E`` elements each."""

    x0: NDArray  # (n, 3)
    projector: NDArray  # (n, 3, 3)
    scale: NDArray  # (n,) mean distance to the neighbours
    d0: NDArray  # (n, E, W)
    grad: NDArray  # (n, E, W, 3)
    size: NDArray  # (n, E) determinant scale
    element: NDArray  # (n, E) bool: real element (not padding)
    ends: NDArray  # (n, E, K, 3) far ends of the node's edges
    edge: NDArray  # (n, E, K) bool: real edge
    other_lo: NDArray  # (n, E) squared extremes of the element's other edges
    other_hi: NDArray
    count: NDArray  # (n,) elements
    old_worst: NDArray  # (n,) worst J* now
    old_inverted: NDArray  # (n,) invalid elements now
    aspect_cap: NDArray  # (n,) max(old worst edge ratio, limit)

    def __post_init__(self) -> None:
        n, e, w = self.d0.shape
        self.grad_flat = np.ascontiguousarray(self.grad.reshape(n, e * w, 3))
        self.ends_flat = np.ascontiguousarray(self.ends.reshape(n, e * _K, 3))
        self.ends_sq = np.einsum("nekc,nekc->nek", self.ends, self.ends)
        # what the compiled objective reads, contiguous and of one dtype each
        self.kernel_arrays = tuple(
            np.ascontiguousarray(a, dtype=bool if a.dtype == bool else np.float64)
            for a in (
                self.x0,
                self.projector,
                self.d0,
                self.grad,
                self.size,
                self.element,
                self.ends,
                self.ends_sq,
                self.edge,
                self.other_lo,
                self.other_hi,
                self.count,
                self.old_worst,
                self.old_inverted,
                self.aspect_cap,
            )
        )


def _cross(a: NDArray, b: NDArray) -> NDArray:
    return np.cross(a, b)


def build_problems(
    nodes: NDArray[np.int64],
    coords: NDArray[np.float64],
    handle_lists: list[tuple[str, NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]],
    triples: dict[str, NDArray[np.int64]],
    projector: NDArray[np.float64],
    old_worst: NDArray,
    old_inverted: NDArray,
    aspect_cap: NDArray,
    n_elements: NDArray[np.int64],
) -> LocalProblems:
    """Assemble the padded local problems.

    Parameters
    ----------
    nodes : (n,) int
        Node indices (into ``coords``).
    handle_lists : list of (etype, owner, slot, conn)
        Per element type: the owning node position (0..n-1), the element's slot in that node's
        list, and the element's corner connectivity.
    """
    n = len(nodes)
    e_max = int(n_elements.max()) if n else 0
    x0 = coords[nodes]
    d0 = np.zeros((n, e_max, _W))
    grad = np.zeros((n, e_max, _W, 3))
    size = np.ones((n, e_max))
    element = np.zeros((n, e_max), dtype=bool)
    ends = np.zeros((n, e_max, _K, 3))
    edge = np.zeros((n, e_max, _K), dtype=bool)
    other_lo = np.full((n, e_max), np.inf)
    other_hi = np.zeros((n, e_max))
    for etype, owner, slot, conn in handle_lists:
        m = len(conn)
        p = coords[conn]  # (m, k, 3)
        loc = np.argmax(conn == nodes[owner][:, None], axis=1)
        t = triples[etype]
        pi = p[:, t[:, 0]]
        va = p[:, t[:, 1]] - pi
        vb = p[:, t[:, 2]] - pi
        if etype == "quad4":
            normal = _cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
            vc = np.broadcast_to(normal[:, None, :], va.shape)
            g_a = _cross(vb, vc)
            g_b = _cross(vc, va)
            g_c = np.zeros_like(va)
        else:
            vc = p[:, t[:, 3]] - pi
            g_a = _cross(vb, vc)
            g_b = _cross(vc, va)
            g_c = _cross(va, vb)
        det = np.einsum("mtk,mtk->mt", _cross(va, vb), vc)
        g_i = -(g_a + g_b + g_c)
        lc = loc[:, None]
        g = (
            (t[:, 0][None, :] == lc)[..., None] * g_i
            + (t[:, 1][None, :] == lc)[..., None] * g_a
            + (t[:, 2][None, :] == lc)[..., None] * g_b
            + (t[:, 3][None, :] == lc)[..., None] * g_c
        )
        n_t = t.shape[0]
        if n_t < _W:  # pad with the first column: min and max unchanged
            det = np.concatenate([det, np.repeat(det[:, :1], _W - n_t, axis=1)], axis=1)
            g = np.concatenate([g, np.repeat(g[:, :1], _W - n_t, axis=1)], axis=1)
        d0[owner, slot] = det
        grad[owner, slot] = g
        size[owner, slot] = np.maximum(np.abs(det).max(axis=1), 1e-300)
        element[owner, slot] = True
        # edges: the node's own edges move, the others are fixed
        e = np.array(ELEMENT_EDGES[etype], dtype=np.int64)
        at_a = e[:, 0][None, :] == lc
        at_b = e[:, 1][None, :] == lc
        moving = at_a | at_b
        d = p[:, e[:, 1]] - p[:, e[:, 0]]
        sq = np.einsum("mek,mek->me", d, d)
        other_lo[owner, slot] = np.where(moving, np.inf, sq).min(axis=1)
        other_hi[owner, slot] = np.where(moving, 0.0, sq).max(axis=1)
        far = np.where(at_a, e[:, 1][None, :], e[:, 0][None, :])  # (m, n_edges)
        order = np.argsort(~moving, axis=1, kind="stable")[:, :_K]
        rows = np.arange(m)[:, None]
        k_used = order.shape[1]
        ends[owner, slot, :k_used] = p[rows, far[rows, order]]
        edge[owner, slot, :k_used] = moving[rows, order]
    dist = np.linalg.norm(ends - x0[:, None, None, :], axis=3)
    n_edges = np.maximum(edge.sum(axis=(1, 2)), 1)
    scale = np.where(edge, dist, 0.0).sum(axis=(1, 2)) / n_edges
    return LocalProblems(
        x0=x0,
        projector=projector,
        scale=np.where(scale > 0, scale, 1.0),
        d0=d0,
        grad=grad,
        size=size,
        element=element,
        ends=ends,
        edge=edge,
        other_lo=other_lo,
        other_hi=other_hi,
        count=n_elements.astype(float),
        old_worst=old_worst,
        old_inverted=old_inverted,
        aspect_cap=aspect_cap,
    )


def objective(pr: LocalProblems, u: NDArray[np.float64]) -> NDArray[np.float64]:
    """The negated objective of every node at ``P`` trial moves ``u`` (n, P, 3) -> (n, P).

    Compiled (:mod:`kneegui.meshopt.batched_kernel`); :func:`objective_numpy` is its reference.
    """
    return compiled_objective(pr.kernel_arrays, u)


def objective_numpy(pr: LocalProblems, u: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`objective` in NumPy: the reference the compiled objective is tested against."""
    n, e, w = pr.d0.shape
    p_count = u.shape[1]
    delta = u @ pr.projector.transpose(0, 2, 1)  # (n, P, 3)
    d = pr.d0[:, :, :, None] + (pr.grad_flat @ delta.transpose(0, 2, 1)).reshape(n, e, w, p_count)
    hi = d.max(axis=2)  # (n, E, P)
    lo = d.min(axis=2)
    valid = lo > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        star = np.where(
            valid, lo / np.where(valid, hi, 1.0), np.maximum(lo / pr.size[:, :, None], -1.0) - 1.0
        )
    element = pr.element[:, :, None]
    worst = np.where(element, star, np.inf).min(axis=1)  # (n, P)
    value = np.where(element, star, 0.0).sum(axis=1) + pr.count[:, None] * worst
    penalty = 10.0 * pr.count[:, None] * np.maximum(pr.old_worst[:, None] - worst, 0.0)
    invalid = np.count_nonzero(~valid & element, axis=1)
    penalty += 10.0 * np.maximum(invalid - pr.old_inverted[:, None], 0.0)
    # squared node-edge lengths |end - x|^2 = |end|^2 - 2 end.x + |x|^2, x = x0 + delta
    x = pr.x0[:, None, :] + delta  # (n, P, 3)
    cross_term = (pr.ends_flat @ x.transpose(0, 2, 1)).reshape(n, e, _K, p_count)
    sq = pr.ends_sq[..., None] - 2.0 * cross_term + np.einsum("npc,npc->np", x, x)[:, None, None]
    edge = pr.edge[..., None]
    e_hi = np.maximum(pr.other_hi[..., None], np.where(edge, sq, 0.0).max(axis=2))  # (n, E, P)
    e_lo = np.minimum(pr.other_lo[..., None], np.where(edge, sq, np.inf).min(axis=2))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.sqrt(np.where(element, e_hi / np.maximum(e_lo, 1e-300), 0.0).max(axis=1))
    cap = pr.aspect_cap[:, None]
    penalty += 10.0 * pr.count[:, None] * np.maximum(ratio - cap, 0.0) / cap
    return -(value - penalty)


def nelder_mead(
    pr: LocalProblems,
    iterations: int,
    check_cancel: Callable[[], None] | None = None,
) -> NDArray[np.float64]:
    """Minimise :func:`objective` for every node at once; returns the best moves (n, 3)."""
    n = len(pr.x0)
    simplex = np.zeros((n, 4, 3))
    simplex[:, 1:] = 0.2 * pr.scale[:, None, None] * np.eye(3)[None]
    values = objective(pr, simplex)
    rows = np.arange(n)
    tolerance = (1e-3 * pr.scale)[:, None]
    for _ in range(iterations):
        if check_cancel is not None:
            check_cancel()
        spread = np.abs(simplex[:, 1:] - simplex[:, :1]).max(axis=2)
        if np.all(spread <= tolerance):
            break  # every simplex has collapsed
        order = np.argsort(values, axis=1, kind="stable")
        simplex = np.take_along_axis(simplex, order[:, :, None], axis=1)
        values = np.take_along_axis(values, order, axis=1)
        centre = simplex[:, :3].mean(axis=1)
        worst = simplex[:, 3]
        trials = np.stack(
            [
                2.0 * centre - worst,  # reflection
                3.0 * centre - 2.0 * worst,  # expansion
                1.5 * centre - 0.5 * worst,  # outside contraction
                0.5 * centre + 0.5 * worst,  # inside contraction
            ],
            axis=1,
        )
        f = objective(pr, trials)
        fr, fe, fc, fcc = f[:, 0], f[:, 1], f[:, 2], f[:, 3]
        f_best, f_second, f_worst = values[:, 0], values[:, 2], values[:, 3]
        expand = fr < f_best
        reflect = ~expand & (fr < f_second)
        outside = ~expand & ~reflect & (fr < f_worst)
        inside = ~expand & ~reflect & ~outside
        choice = np.full(n, -1)
        choice[expand] = np.where(fe[expand] < fr[expand], 1, 0)
        choice[reflect] = 0
        choice[outside & (fc <= fr)] = 2
        choice[inside & (fcc < f_worst)] = 3
        replace = choice >= 0
        simplex[replace, 3] = trials[rows[replace], choice[replace]]
        values[replace, 3] = f[rows[replace], choice[replace]]
        shrink = ~replace
        if shrink.any():
            best = simplex[shrink, :1]
            simplex[shrink, 1:] = best + 0.5 * (simplex[shrink, 1:] - best)
            values[shrink] = objective(pr, simplex)[shrink]
    best = np.argmin(values, axis=1)
    return simplex[rows, best]
