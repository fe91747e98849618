"""Unconstrained L-BFGS shared by the relaxation and the corner-Jacobian optimiser."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray


@dataclass
class _MinimizeResult:
    x: NDArray[np.float64]
    fun: float
    nit: int
    nfev: int


@njit(cache=True, nogil=True)
def _dot_compiled(a, b):  # pragma: no cover - compiled
    total = 0.0
    for i in range(a.shape[0]):
        total += a[i] * b[i]
    return total


def _dot(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """Dot product of two vectors that does not depend on the BLAS thread count or the CPU.

    ``a @ b`` goes to BLAS, which splits long vectors over threads and sums the parts in another
    order: the relaxation then followed other paths on machines with other core counts (the
    default demo at 120 degrees: 0 inverted elements with one OpenBLAS thread, 1 with two). A
    compiled loop adds in index order (no fast-math: the compiler may not reorder the sum).
    """
    return float(_dot_compiled(a, b))


@njit(cache=True, nogil=True)
def _two_loop(g, s_mem, y_mem, rho, order):  # pragma: no cover - compiled
    """The L-BFGS direction ``-H g`` (Nocedal & Wright, algorithm 7.4) from the correction
    pairs ``s_mem[order[k]], y_mem[order[k]]``, oldest first; every sum in index order."""
    q = g.copy()
    count = order.shape[0]
    alpha = np.empty(count)
    for k in range(count - 1, -1, -1):
        i = order[k]
        a = rho[i] * _dot_compiled(s_mem[i], q)
        alpha[k] = a
        for j in range(q.shape[0]):
            q[j] -= a * y_mem[i, j]
    if count:
        i = order[count - 1]
        gamma = _dot_compiled(s_mem[i], y_mem[i]) / _dot_compiled(y_mem[i], y_mem[i])
        for j in range(q.shape[0]):
            q[j] *= gamma
    else:
        scale = 1.0
        for j in range(g.shape[0]):
            scale = max(scale, abs(g[j]))
        for j in range(q.shape[0]):
            q[j] /= scale
    for k in range(count):
        i = order[k]
        b = alpha[k] - rho[i] * _dot_compiled(y_mem[i], q)
        for j in range(q.shape[0]):
            q[j] += b * s_mem[i, j]
    for j in range(q.shape[0]):
        q[j] = -q[j]
    return q


def minimize_lbfgs(
    fun: Callable[[NDArray[np.float64]], tuple[float, NDArray[np.float64]]],
    x0: NDArray[np.float64],
    max_iterations: int,
    memory: int = 10,
    ftol: float = 2.2e-9,
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
        if converged:
            break
    return _MinimizeResult(x, f, it, nfev)
