"""Unconstrained L-BFGS shared by the relaxation and the corner-Jacobian optimiser."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from kneegui.errors import raise_if_cancelled
from kneegui.meshopt.parallel import PARALLEL_KERNEL_LOCK


@dataclass
class _MinimizeResult:
    x: NDArray[np.float64]
    fun: float
    nit: int
    nfev: int


#: Vector sums run over fixed chunks of this many entries, each chunk over four interleaved
#: partial sums, then the chunks in index order: the order depends only on the vector's length,
#: never on the CPU or the thread count, so every machine gets the same bits. Four partial sums
#: instead of one running total let the compiler use SIMD (a running total is one long chain of
#: dependent additions: 0.13 ms per dot of 157,000 entries against 0.05), and the chunks can be
#: summed on both cores.
CHUNK = 4096
#: Vectors at least this long run their chunks in parallel (shorter ones in one thread: the
#: thread pool's start costs more than it saves). Both give the same bits.
PARALLEL_MIN_LENGTH = 32_768


@njit(cache=True, nogil=True)
def _chunk_update(q, a, x, scale, v, want_dot):  # pragma: no cover - compiled
    """``q[i] = (q[i] + a * x[i]) * scale``, then (``want_dot``) the sum of ``v[i] * q[i]``
    over four interleaved partial sums, added at the end in a fixed order. Called on slices
    of one chunk (starting at index 0, the compiler vectorises the sum: twice as fast as
    the same loop over ``lo:hi`` of the whole vector)."""
    n = q.shape[0]
    if a != 0.0 or scale != 1.0:
        for i in range(n):
            q[i] = (q[i] + a * x[i]) * scale
    if not want_dot:
        return 0.0
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    m = n - n % 4
    for i in range(0, m, 4):
        s0 += v[i] * q[i]
        s1 += v[i + 1] * q[i + 1]
        s2 += v[i + 2] * q[i + 2]
        s3 += v[i + 3] * q[i + 3]
    for i in range(m, n):
        s0 += v[i] * q[i]
    return (s0 + s1) + (s2 + s3)


@njit(cache=True, nogil=True)
def _update_serial(q, a, x, scale, v, want_dot):  # pragma: no cover - compiled
    n = q.shape[0]
    total = 0.0
    for lo in range(0, n, CHUNK):
        hi = min(n, lo + CHUNK)
        total += _chunk_update(q[lo:hi], a, x[lo:hi], scale, v[lo:hi], want_dot)
    return total


@njit(cache=True, nogil=True, parallel=True)
def _update_parallel(q, a, x, scale, v, want_dot):  # pragma: no cover - compiled
    n = q.shape[0]
    count = (n + CHUNK - 1) // CHUNK
    parts = np.empty(count)
    for c in prange(count):
        lo = c * CHUNK
        hi = min(n, lo + CHUNK)
        parts[c] = _chunk_update(q[lo:hi], a, x[lo:hi], scale, v[lo:hi], want_dot)
    total = 0.0
    for c in range(count):
        total += parts[c]
    return total


@njit(cache=True, nogil=True)
def _update(q, a, x, scale, v, want_dot):  # pragma: no cover - compiled
    """:func:`_chunk_update` over the whole vector, the chunks' sums added in order; in
    parallel for long vectors (the same bits either way)."""
    if q.shape[0] >= PARALLEL_MIN_LENGTH:
        return _update_parallel(q, a, x, scale, v, want_dot)
    return _update_serial(q, a, x, scale, v, want_dot)


@njit(cache=True, nogil=True)
def dot_fixed_order(a, b):  # pragma: no cover - compiled
    """``a . b`` of 1-D arrays, summed in an order fixed by the length alone (:data:`CHUNK`),
    on numba's pool for long vectors: the caller holds
    :data:`~kneegui.meshopt.parallel.PARALLEL_KERNEL_LOCK` (:func:`_dot` takes it)."""
    return _update(a, 0.0, a, 1.0, b, True)


def _dot(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """Dot product of two vectors that does not depend on the BLAS or numba thread count or
    the CPU.

    ``a @ b`` goes to BLAS, which splits long vectors over threads and sums the parts in another
    order: the relaxation then followed other paths on machines with other core counts (the
    default demo at 120 degrees: 0 inverted elements with one OpenBLAS thread, 1 with two). The
    compiled sum adds in an order fixed by the length alone (:data:`CHUNK`; no fast-math: the
    compiler may not reorder it).
    """
    with PARALLEL_KERNEL_LOCK:
        return float(dot_fixed_order(a, b))


@njit(cache=True, nogil=True)
def _two_loop(g, s_mem, y_mem, rho, order):  # pragma: no cover - compiled
    """The L-BFGS direction ``-H g`` (Nocedal & Wright, algorithm 7.4) from the correction
    pairs ``s_mem[order[k]], y_mem[order[k]]``, oldest first. Each pass over the vector does the
    update of one step and the dot product of the next (:func:`_update`), so the direction
    costs ``2 * count + 1`` passes."""
    q = g.copy()
    count = order.shape[0]
    if count == 0:
        scale = 1.0
        for j in range(g.shape[0]):
            scale = max(scale, abs(g[j]))
        for j in range(q.shape[0]):
            q[j] = -(q[j] / scale)
        return q
    alpha = np.empty(count)
    a = 0.0
    previous = order[count - 1]
    for k in range(count - 1, -1, -1):
        i = order[k]
        # q -= alpha[k + 1] * y[k + 1], then s[k] . q
        alpha[k] = rho[i] * _update(q, a, y_mem[previous], 1.0, s_mem[i], True)
        a = -alpha[k]
        previous = i
    newest = order[count - 1]
    gamma = dot_fixed_order(y_mem[newest], s_mem[newest]) / dot_fixed_order(
        y_mem[newest], y_mem[newest]
    )
    # q = (q - alpha[0] * y[0]) * gamma, then the second loop
    b = 0.0
    x = y_mem[previous]
    scale = gamma
    for k in range(count):
        i = order[k]
        b_next = alpha[k] - rho[i] * _update(q, a if k == 0 else b, x, scale, y_mem[i], True)
        x = s_mem[i]
        scale = 1.0
        b = b_next
    _update(q, b, x, -1.0, x, False)  # q += b * s[last], then negated
    return q


#: Least time between two progress reports from inside a solver round (seconds): a window
#: redraws its progress bar on each report, and a round at paper scale runs about a thousand
#: iterations a second.
PROGRESS_INTERVAL_S = 0.25


def round_monitor(
    cancel: Callable[[], bool],
    progress: Callable[[float, str], None],
    fraction: Callable[[float], float],
    message: str,
    cancelled: str,
) -> Callable[[int, int], None]:
    """An ``each_iteration`` hook for :func:`minimize_lbfgs`: stop and report within a round.

    A round on a whole-body model's region runs for tens of seconds; checked only between
    rounds, a cancel waited that long (the 1M demo: up to 21.9 s without asking).

    Parameters
    ----------
    cancel : callable
        ``cancel()`` returning True raises :class:`kneegui.errors.Cancelled` with the message
        ``cancelled``; asked after every iteration.
    progress : callable
        ``progress(fraction, message)``, called at most every :data:`PROGRESS_INTERVAL_S`.
    fraction : callable
        The overall fraction done, given the fraction of this round's iterations done.
    message, cancelled : str
        The progress message, and the message of the :class:`Cancelled` raised.
    """
    last = time.perf_counter()

    def each_iteration(done: int, limit: int) -> None:
        nonlocal last
        raise_if_cancelled(cancel, cancelled)
        now = time.perf_counter()
        if now - last >= PROGRESS_INTERVAL_S:
            last = now
            progress(fraction(done / limit), message)

    return each_iteration


def minimize_lbfgs(
    fun: Callable[[NDArray[np.float64]], tuple[float, NDArray[np.float64]]],
    x0: NDArray[np.float64],
    max_iterations: int,
    memory: int = 10,
    ftol: float = 2.2e-9,
    each_iteration: Callable[[int, int], None] | None = None,
) -> _MinimizeResult:
    """Unconstrained L-BFGS (Nocedal & Wright, algorithm 7.4/7.5) with Armijo backtracking.

    A step that meets an infinite or NaN energy (a barrier) is halved like any other rejected
    step. SciPy's L-BFGS-B spent more time in its bound handling than this problem spends in
    its energy; this loop costs a few vector operations per iteration.

    Parameters
    ----------
    fun : callable
        ``fun(x) -> (f, gradient)``.
    x0 : (n,) ndarray
    max_iterations : int
    memory : int
        Number of correction pairs kept.
    ftol : float
        Stops when ``(f_k - f_{k+1}) / max(|f_k|, |f_{k+1}|, 1) <= ftol``.
    each_iteration : callable, optional
        ``each_iteration(done, max_iterations)`` after every iteration; it may raise (e.g.
        :class:`kneegui.errors.Cancelled`, :func:`round_monitor`) and cannot change the
        iterates.
    """
    x = np.array(x0, dtype=np.float64, copy=True)
    f, g = fun(x)
    nfev = 1
    # correction pairs in a ring buffer; ``order`` lists the live slots, oldest first
    s_mem = np.zeros((memory, len(x)))
    y_mem = np.zeros((memory, len(x)))
    rho = np.zeros(memory)
    order: list[int] = []
    it = 0
    for it in range(1, max_iterations + 1):
        with PARALLEL_KERNEL_LOCK:
            d = _two_loop(g, s_mem, y_mem, rho, np.array(order, dtype=np.int64))
        slope = _dot(g, d)
        if slope >= 0:  # not a descent direction: forget the curvature pairs
            order.clear()
            d = -g / max(float(np.abs(g).max()), 1.0)
            slope = _dot(g, d)
        if slope == 0:
            break
        step = 1.0
        while True:
            x_new = x + step * d
            f_new, g_new = fun(x_new)
            nfev += 1
            if np.isfinite(f_new) and f_new <= f + 1e-4 * step * slope:
                break
            step *= 0.5
            if step < 1e-10:
                return _MinimizeResult(x, f, it, nfev)
        s_k, y_k = x_new - x, g_new - g
        sy = _dot(s_k, y_k)
        if sy > 1e-12 * np.sqrt(_dot(s_k, s_k) * _dot(y_k, y_k)):
            slot = order.pop(0) if len(order) == memory else len(order)
            s_mem[slot], y_mem[slot], rho[slot] = s_k, y_k, 1.0 / sy
            order.append(slot)
        converged = (f - f_new) <= ftol * max(abs(f), abs(f_new), 1.0)
        x, f, g = x_new, f_new, g_new
        if each_iteration is not None:
            each_iteration(it, max_iterations)
        if converged:
            break
    return _MinimizeResult(x, f, it, nfev)
