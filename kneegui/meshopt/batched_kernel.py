"""Compiled objective of the smoother's batched Nelder-Mead (stage 2).

:func:`kneegui.meshopt.batched.objective_numpy` is the reference (tests check the two agree);
this is the same objective node by node and trial by trial, without the NumPy version's
``(n, E, 8, P)`` temporaries: 2.7 s of the 177k demo's smoothing at 90 degrees in NumPy.
Every node's values are computed on their own, so the thread count cannot change them.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from kneegui.meshopt.parallel import PARALLEL_KERNEL_LOCK, PARALLEL_MIN_ELEMENTS


@njit(cache=True, nogil=True)
def _node_objective(n, u, arrays, out):  # pragma: no cover - compiled
    """Node ``n``'s objective at its trial moves ``u[n]`` into ``out[n]``."""
    (
        x0,
        projector,
        d0,
        grad,
        size,
        element,
        ends,
        ends_sq,
        edge,
        other_lo,
        other_hi,
        count,
        old_worst,
        old_inverted,
        aspect_cap,
    ) = arrays
    n_elements, n_dets = d0.shape[1], d0.shape[2]
    for p in range(u.shape[1]):
        # the move, kept in the node's plane (sliding) or free
        m0 = u[n, p, 0] * projector[n, 0, 0] + u[n, p, 1] * projector[n, 0, 1]
        m0 += u[n, p, 2] * projector[n, 0, 2]
        m1 = u[n, p, 0] * projector[n, 1, 0] + u[n, p, 1] * projector[n, 1, 1]
        m1 += u[n, p, 2] * projector[n, 1, 2]
        m2 = u[n, p, 0] * projector[n, 2, 0] + u[n, p, 1] * projector[n, 2, 1]
        m2 += u[n, p, 2] * projector[n, 2, 2]
        x_0 = x0[n, 0] + m0
        x_1 = x0[n, 1] + m1
        x_2 = x0[n, 2] + m2
        xx = x_0 * x_0 + x_1 * x_1 + x_2 * x_2
        worst = math.inf
        total = 0.0
        invalid = 0
        ratio_sq = 0.0
        for e in range(n_elements):
            if not element[n, e]:
                continue
            lo = math.inf
            hi = -math.inf
            for w in range(n_dets):
                g = grad[n, e, w]
                d = d0[n, e, w] + (g[0] * m0 + g[1] * m1 + g[2] * m2)
                lo = min(lo, d)
                hi = max(hi, d)
            if lo > 0.0:
                star = lo / hi
            else:
                star = max(lo / size[n, e], -1.0) - 1.0
                invalid += 1
            worst = min(worst, star)
            total += star
            e_lo = other_lo[n, e]
            e_hi = other_hi[n, e]
            for k in range(ends.shape[2]):
                if edge[n, e, k]:
                    cross = ends[n, e, k, 0] * x_0 + ends[n, e, k, 1] * x_1
                    cross += ends[n, e, k, 2] * x_2
                    sq = ends_sq[n, e, k] - 2.0 * cross + xx
                    e_lo = min(e_lo, sq)
                    e_hi = max(e_hi, sq)
            ratio_sq = max(ratio_sq, e_hi / max(e_lo, 1e-300))
        value = total + count[n] * worst
        penalty = 10.0 * count[n] * max(old_worst[n] - worst, 0.0)
        penalty += 10.0 * max(invalid - old_inverted[n], 0.0)
        ratio = math.sqrt(ratio_sq)
        cap = aspect_cap[n]
        penalty += 10.0 * count[n] * max(ratio - cap, 0.0) / cap
        out[n, p] = -(value - penalty)


@njit(cache=True, nogil=True)
def _objective_serial(u, arrays, out):  # pragma: no cover - compiled
    for n in range(u.shape[0]):
        _node_objective(n, u, arrays, out)


@njit(cache=True, nogil=True, parallel=True)
def _objective_parallel(u, arrays, out):  # pragma: no cover - compiled
    for n in prange(u.shape[0]):
        _node_objective(n, u, arrays, out)


def compiled_objective(arrays: tuple[NDArray, ...], u: NDArray[np.float64]) -> NDArray[np.float64]:
    """The negated objective of every node at ``P`` trial moves ``u`` (n, P, 3) -> (n, P).

    ``arrays`` are the local problems' ``x0, projector, d0, grad, size, element, ends, ends_sq,
    edge, other_lo, other_hi, count, old_worst, old_inverted, aspect_cap`` (contiguous, as
    :class:`kneegui.meshopt.batched.LocalProblems` keeps them).
    """
    u = np.ascontiguousarray(u, dtype=np.float64)
    out = np.empty(u.shape[:2])
    n, n_elements = arrays[2].shape[:2]
    if n * n_elements >= PARALLEL_MIN_ELEMENTS:
        with PARALLEL_KERNEL_LOCK:
            _objective_parallel(u, arrays, out)
    else:
        _objective_serial(u, arrays, out)
    return out
