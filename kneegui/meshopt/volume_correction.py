"""A volume-restoring step between the mapping and the relaxation: one linearised, smoothed solve.

The mapping (rigid bone motions blended through the tissue) changes the soft-tissue elements'
volumes smoothly over long distances: the 95th percentile of their volume change is 56 % at 90°
on the demo leg at 20k and at 177k elements alike. The quality stage's moves are local; on a
coarse mesh they remove most of it (18 %), on a fine one they would need many more iterations
per round (55.6 % at 177k). This step removes the long-wavelength part at once: the smooth
displacement ``u`` of the free nodes that minimises

    sum_e (g_e . u - r_e)^2 / V0_e^2  +  alpha * sum_edges |u_i - u_j|^2,

``g_e`` the gradient of element ``e``'s volume, ``r_e = V0_e - V_e`` its shortfall from the rest
volume (relative shortfalls clipped to :attr:`VolumeCorrectionOptions.clip`), the edge sum over
the soft elements' tetrahedra (an edge to a node that does not move pins it: bones stay where the
mapping put them). Elements the mapping has squeezed below :attr:`VolumeCorrectionOptions.floor`
times their rest volume (folded or nearly so) are left out of the residual: their recovery is
the untangling's.

On the 20k demo at 90° the step takes the 95th percentile of |ΔV| from 56.2 % to 14.6 % and
leaves 33 elements inverted against the mapping's 20 (a volume aim says nothing about shape);
the untangling that follows frees them. On the 177k demo, where the quality stage cannot remove
the mapping's volume change alone, the export's 95th percentile fell from 55.6 % to 22.1 %
(docs/repositioning.md, "The mapping's volume change restored before the relaxation").

The solve is a Jacobi-preconditioned conjugate gradient over ``3 F`` unknowns, matrix-free (the
normal matrix of a 1M-element region would take gigabytes), in compiled loops over fixed chunks
of rows: the same result for any number of threads.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from kneegui.errors import raise_if_cancelled
from kneegui.meshopt.lbfgs import dot_fixed_order
from kneegui.meshopt.parallel import PARALLEL_KERNEL_LOCK
from kneegui.model import ElementBlock
from kneegui.topology import sorted_unique

#: Each solid's volume as a sum of tetrahedra over its corner nodes (local indices). A 10-node
#: tet is its corner tetrahedron.
TET_SPLITS: dict[str, tuple[tuple[int, int, int, int], ...]] = {
    "hex8": ((0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6)),
    "wedge6": ((0, 1, 2, 3), (1, 2, 3, 4), (2, 3, 4, 5)),
    "pyramid5": ((0, 1, 2, 4), (0, 2, 3, 4)),
    "tet4": ((0, 1, 2, 3),),
    "tet10": ((0, 1, 2, 3),),
}
_SLOTS = 8  # corner nodes of the largest solid
_TETS = 6  # tetrahedra of the largest split


@dataclass(frozen=True)
class VolumeCorrectionOptions:
    """How the volume-restoring step weighs and solves.

    Attributes
    ----------
    smoothing : float
        ``alpha`` relative to the mean diagonal of the volume term per unit of node degree:
        larger spreads each correction wider and corrects less (the 20k demo at 90°: 95th
        percentile after the step 14.6 % with 0.3, 20.8 % with 1).
    clip : float
        Largest relative volume shortfall (or excess) one step aims to correct.
    floor : float
        Elements below this fraction of their rest volume (folded or nearly so) are left to the
        untangling (aimed at, an inverted element's shortfall is the whole clip).
    tolerance : float
        Relative residual of the conjugate gradients (the step is a start for the solvers
        that follow, not an end: 1e-3 moves nodes by hundredths of the step, 1e-6 by none).
    max_iterations : int
    """

    smoothing: float = 0.3
    clip: float = 1.0
    floor: float = 0.2
    tolerance: float = 1e-3
    max_iterations: int = 2000


@dataclass(frozen=True)
class VolumeCorrectionReport:
    """What one step did: elements aimed at, CG iterations, largest node move, seconds."""

    elements: int
    aimed: int
    iterations: int
    converged: bool
    largest_move: float
    seconds: float


class VolumeCorrection:
    """The step over chosen solids and free nodes, built once per model (module docstring).

    Parameters
    ----------
    blocks : mapping of str to ElementBlock
        The model's element blocks.
    rows : mapping of str to ndarray of int
        Per solid type, the block rows whose volume is restored (e.g. the soft tissue's).
    free : (N,) ndarray of bool
        The nodes the step may move (the others pin it).
    rest : (N, 3) ndarray
        The coordinates whose volumes are the aim.
    options : VolumeCorrectionOptions, optional
    cancel : callable, optional
        Asked between the set-up's steps; returning True raises
        :class:`kneegui.errors.Cancelled`.
    """

    def __init__(
        self,
        blocks: Mapping[str, ElementBlock],
        rows: Mapping[str, NDArray[np.int64]],
        free: NDArray[np.bool_],
        rest: NDArray[np.float64],
        options: VolumeCorrectionOptions | None = None,
        cancel: Callable[[], bool] | None = None,
    ) -> None:
        self.options = options or VolumeCorrectionOptions()

        def check() -> None:
            # between the set-up's steps: 2.9 s in all on the 1M demo, asked nothing before
            raise_if_cancelled(cancel, "cancelled while preparing the volume correction")

        nodes, tets = [], []
        for etype, split in TET_SPLITS.items():
            check()
            if etype not in blocks or etype not in rows or not len(rows[etype]):
                continue
            local = np.asarray(split, dtype=np.int64)
            conn = blocks[etype].conn[np.asarray(rows[etype], dtype=np.int64)][:, : local.max() + 1]
            padded = np.full((len(conn), _SLOTS), -1, dtype=np.int64)
            padded[:, : conn.shape[1]] = conn
            table = np.full((len(conn), _TETS, 4), -1, dtype=np.int64)
            table[:, : len(local)] = local
            # each tetrahedron oriented positive at rest, whatever the element's node order
            a, b, c, d = (rest[conn[:, local[:, k]]] for k in range(4))
            negative = np.einsum("eti,eti->et", np.cross(b - a, c - a), d - a) < 0.0
            swap = table[:, : len(local)]
            swap[negative, 2], swap[negative, 3] = swap[negative, 3], swap[negative, 2].copy()
            nodes.append(padded)
            tets.append(table)
        self.elem_nodes = np.concatenate(nodes) if nodes else np.zeros((0, _SLOTS), dtype=np.int64)
        self.elem_tets = np.concatenate(tets) if tets else np.zeros((0, _TETS, 4), dtype=np.int64)
        check()
        n = len(rest)
        used = np.unique(self.elem_nodes[self.elem_nodes >= 0])
        self.free = used[np.asarray(free, dtype=bool)[used]]
        self.row = np.full(n, -1, dtype=np.int64)
        self.row[self.free] = np.arange(len(self.free))
        self.rest_volume = _element_volumes(rest, self.elem_nodes, self.elem_tets)
        check()
        # free node -> (element, slot) incidence, in element order
        slot_row = self.row[np.maximum(self.elem_nodes, 0)]
        slot_row[self.elem_nodes < 0] = -1
        e_idx, s_idx = np.nonzero(slot_row >= 0)
        order = np.argsort(slot_row[e_idx, s_idx], kind="stable")
        self.inc_elem, self.inc_slot = e_idx[order], s_idx[order]
        self.inc_ptr = np.zeros(len(self.free) + 1, dtype=np.int64)
        counts = np.bincount(slot_row[e_idx, s_idx], minlength=len(self.free))
        np.cumsum(counts, out=self.inc_ptr[1:])
        check()
        # the tetrahedra's edges: each free node's degree and its free neighbours
        pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
        ends = []
        e_of = np.broadcast_to(np.arange(len(self.elem_nodes))[:, None], self.elem_tets.shape[:2])
        for p, q in pairs:
            slot_p, slot_q = self.elem_tets[..., p], self.elem_tets[..., q]
            valid = slot_p >= 0
            u = self.elem_nodes[e_of[valid], slot_p[valid]]
            v = self.elem_nodes[e_of[valid], slot_q[valid]]
            ends.append(np.minimum(u, v) * n + np.maximum(u, v))
        check()
        keys = sorted_unique(np.concatenate(ends)) if ends else np.zeros(0, np.int64)
        check()
        ra, rb = self.row[keys // n], self.row[keys % n]
        self.degree = np.bincount(
            np.concatenate([ra[ra >= 0], rb[rb >= 0]]), minlength=len(self.free)
        ).astype(np.float64)
        both = (ra >= 0) & (rb >= 0)
        src = np.concatenate([ra[both], rb[both]])
        dst = np.concatenate([rb[both], ra[both]])
        order = np.lexsort((dst, src))
        check()
        self.nb_idx = dst[order]
        self.nb_ptr = np.zeros(len(self.free) + 1, dtype=np.int64)
        np.cumsum(np.bincount(src, minlength=len(self.free)), out=self.nb_ptr[1:])

    def __len__(self) -> int:
        return len(self.elem_nodes)

    def __call__(
        self, x: NDArray[np.float64], cancel: Callable[[], bool] | None = None
    ) -> tuple[NDArray[np.float64], VolumeCorrectionReport]:
        """``x`` with the free nodes moved by the step (a new array), and its report."""
        t = time.perf_counter()
        opt = self.options
        n_free = len(self.free)
        if n_free == 0 or len(self) == 0:
            return np.array(x, copy=True), VolumeCorrectionReport(len(self), 0, 0, True, 0.0, 0.0)
        x = np.ascontiguousarray(x, dtype=np.float64)
        volume, grad = _element_gradients(x, self.elem_nodes, self.elem_tets)
        v0 = self.rest_volume
        aimed = volume >= opt.floor * v0
        weight = np.where(aimed, 1.0 / v0, 0.0)
        residual = np.clip((v0 - volume) / v0, -opt.clip, opt.clip) * aimed
        diag_volume = _jacobi_volume(grad, weight, self.inc_ptr, self.inc_elem, self.inc_slot)
        alpha = opt.smoothing * float(diag_volume.mean()) / max(float(self.degree.mean()), 1.0)
        diag = diag_volume + alpha * self.degree[:, None]
        rhs = _transpose_times(grad, weight, residual, self.inc_ptr, self.inc_elem, self.inc_slot)

        def times(v: NDArray[np.float64]) -> NDArray[np.float64]:
            s = _element_rates(grad, weight, self.elem_nodes, self.row, v)
            out = _transpose_times(grad, weight, s, self.inc_ptr, self.inc_elem, self.inc_slot)
            _add_laplacian(out, v, alpha, self.degree, self.nb_ptr, self.nb_idx)
            return out

        u, iterations, converged = _pcg(
            times, rhs, 1.0 / diag, opt.tolerance, opt.max_iterations, cancel
        )
        out = np.array(x, copy=True)
        out[self.free] += u
        moved = float(np.sqrt((u * u).sum(axis=1)).max())
        report = VolumeCorrectionReport(
            len(self), int(aimed.sum()), iterations, converged, moved, time.perf_counter() - t
        )
        return out, report


def _pcg(
    times: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    rhs: NDArray[np.float64],
    inv_diag: NDArray[np.float64],
    tolerance: float,
    max_iterations: int,
    cancel: Callable[[], bool] | None,
) -> tuple[NDArray[np.float64], int, bool]:
    """Jacobi-preconditioned CG from zero; every dot product a compiled fixed-chunk sum."""
    x = np.zeros_like(rhs)
    r = rhs.copy()
    z = inv_diag * r
    p = z.copy()
    with PARALLEL_KERNEL_LOCK:  # the compiled kernels run on numba's pool, one caller at a time
        target = tolerance * np.sqrt(_dot(rhs, rhs))
        rz = _dot(r, z)
    if target == 0.0:
        return x, 0, True
    for k in range(max_iterations):
        # every iteration: on the 1M demo 25 of them took 1.5-2.1 s between two questions
        raise_if_cancelled(cancel, "cancelled while restoring the tissue's volume")
        with PARALLEL_KERNEL_LOCK:
            ap = times(p)
            alpha = rz / _dot(p, ap)
            rr = _axpy_pair(x, r, p, ap, alpha)
            if np.sqrt(rr) <= target:
                return x, k + 1, True
            z = inv_diag * r
            rz_new = _dot(r, z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    return x, max_iterations, False


def _element_volumes(
    x: NDArray[np.float64], elem_nodes: NDArray[np.int64], elem_tets: NDArray[np.int64]
) -> NDArray[np.float64]:
    return _element_gradients(np.ascontiguousarray(x, dtype=np.float64), elem_nodes, elem_tets)[0]


@njit(cache=True, nogil=True, parallel=True)
def _element_gradients(x, elem_nodes, elem_tets):  # pragma: no cover - compiled
    """Each element's volume (sum of its oriented tetrahedra) and its gradient per slot."""
    m = elem_nodes.shape[0]
    volume = np.zeros(m)
    grad = np.zeros((m, _SLOTS, 3))
    for e in prange(m):
        total = 0.0
        for t in range(_TETS):
            if elem_tets[e, t, 0] < 0:
                break
            sa, sb = elem_tets[e, t, 0], elem_tets[e, t, 1]
            sc, sd = elem_tets[e, t, 2], elem_tets[e, t, 3]
            a, b, c, d = elem_nodes[e, sa], elem_nodes[e, sb], elem_nodes[e, sc], elem_nodes[e, sd]
            abx, aby, abz = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
            acx, acy, acz = x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2]
            adx, ady, adz = x[d, 0] - x[a, 0], x[d, 1] - x[a, 1], x[d, 2] - x[a, 2]
            # d V / d d = (ab x ac) / 6, d V / d b = (ac x ad) / 6, d V / d c = (ad x ab) / 6
            gdx, gdy, gdz = aby * acz - abz * acy, abz * acx - abx * acz, abx * acy - aby * acx
            gbx, gby, gbz = acy * adz - acz * ady, acz * adx - acx * adz, acx * ady - acy * adx
            gcx, gcy, gcz = ady * abz - adz * aby, adz * abx - adx * abz, adx * aby - ady * abx
            total += (gdx * adx + gdy * ady + gdz * adz) / 6.0
            grad[e, sb, 0] += gbx / 6.0
            grad[e, sb, 1] += gby / 6.0
            grad[e, sb, 2] += gbz / 6.0
            grad[e, sc, 0] += gcx / 6.0
            grad[e, sc, 1] += gcy / 6.0
            grad[e, sc, 2] += gcz / 6.0
            grad[e, sd, 0] += gdx / 6.0
            grad[e, sd, 1] += gdy / 6.0
            grad[e, sd, 2] += gdz / 6.0
            grad[e, sa, 0] -= (gbx + gcx + gdx) / 6.0
            grad[e, sa, 1] -= (gby + gcy + gdy) / 6.0
            grad[e, sa, 2] -= (gbz + gcz + gdz) / 6.0
        volume[e] = total
    return volume, grad


@njit(cache=True, nogil=True, parallel=True)
def _element_rates(grad, weight, elem_nodes, row, v):  # pragma: no cover - compiled
    """``weight_e * (g_e . v)`` per element (``v`` over the free rows)."""
    m = elem_nodes.shape[0]
    out = np.zeros(m)
    for e in prange(m):
        if weight[e] == 0.0:
            continue
        s = 0.0
        for k in range(_SLOTS):
            node = elem_nodes[e, k]
            if node < 0:
                continue
            r = row[node]
            if r < 0:
                continue
            s += grad[e, k, 0] * v[r, 0] + grad[e, k, 1] * v[r, 1] + grad[e, k, 2] * v[r, 2]
        out[e] = weight[e] * s
    return out


@njit(cache=True, nogil=True, parallel=True)
def _transpose_times(grad, weight, s, inc_ptr, inc_elem, inc_slot):  # pragma: no cover
    """Per free node, ``sum_e weight_e g_e,node s_e`` over its elements (in element order)."""
    n = inc_ptr.shape[0] - 1
    out = np.zeros((n, 3))
    for i in prange(n):
        for q in range(inc_ptr[i], inc_ptr[i + 1]):
            e, k = inc_elem[q], inc_slot[q]
            w = weight[e] * s[e]
            out[i, 0] += w * grad[e, k, 0]
            out[i, 1] += w * grad[e, k, 1]
            out[i, 2] += w * grad[e, k, 2]
    return out


@njit(cache=True, nogil=True, parallel=True)
def _jacobi_volume(grad, weight, inc_ptr, inc_elem, inc_slot):  # pragma: no cover
    """The volume term's diagonal per free node and axis."""
    n = inc_ptr.shape[0] - 1
    out = np.zeros((n, 3))
    for i in prange(n):
        for q in range(inc_ptr[i], inc_ptr[i + 1]):
            e, k = inc_elem[q], inc_slot[q]
            w = weight[e]
            for j in range(3):
                g = w * grad[e, k, j]
                out[i, j] += g * g
    return out


@njit(cache=True, nogil=True, parallel=True)
def _add_laplacian(out, v, alpha, degree, nb_ptr, nb_idx):  # pragma: no cover - compiled
    """``out += alpha (degree v - sum of the free neighbours' v)`` (fixed neighbours pin)."""
    n = out.shape[0]
    for i in prange(n):
        for j in range(3):
            acc = degree[i] * v[i, j]
            for q in range(nb_ptr[i], nb_ptr[i + 1]):
                acc -= v[nb_idx[q], j]
            out[i, j] += alpha * acc


def _dot(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """``sum(a * b)`` over (n, 3) arrays in an order fixed by the length alone (the L-BFGS's
    compiled dot; the caller holds :data:`PARALLEL_KERNEL_LOCK`)."""
    return float(dot_fixed_order(a.reshape(-1), b.reshape(-1)))


@njit(cache=True, nogil=True, parallel=True)
def _axpy(x, r, p, ap, alpha):  # pragma: no cover - compiled
    for i in prange(x.shape[0]):
        for j in range(3):
            x[i, j] += alpha * p[i, j]
            r[i, j] -= alpha * ap[i, j]


def _axpy_pair(x, r, p, ap, alpha: float) -> float:
    """``x += alpha p``, ``r -= alpha ap`` in place; returns ``|r|^2`` (fixed-chunk sum)."""
    _axpy(x, r, p, ap, alpha)
    return _dot(r, r)
