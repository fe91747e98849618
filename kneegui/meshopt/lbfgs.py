"""Unconstrained L-BFGS shared by the relaxation and the corner-Jacobian optimiser."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass
class _MinimizeResult:
    x: NDArray[np.float64]
    fun: float
    nit: int
    nfev: int


def _dot(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """Dot product of two vectors that does not depend on the BLAS thread count.

    ``a @ b`` goes to BLAS, which splits long vectors over threads and sums the parts in another
    order: the relaxation then followed other paths on machines with other core counts (the
    default demo at 120 degrees: 0 inverted elements with one OpenBLAS thread, 1 with two).
    """
    return float(np.einsum("i,i->", a, b))


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
    s_list: list[NDArray] = []
    y_list: list[NDArray] = []
    rho: list[float] = []
    it = 0
    for it in range(1, max_iterations + 1):
        q = g.copy()
        alpha = []
        for s_i, y_i, r_i in zip(reversed(s_list), reversed(y_list), reversed(rho), strict=True):
            a_i = r_i * _dot(s_i, q)
            alpha.append(a_i)
            q -= a_i * y_i
        if s_list:
            q *= _dot(s_list[-1], y_list[-1]) / _dot(y_list[-1], y_list[-1])
        else:
            q /= max(float(np.abs(g).max()), 1.0)
        for s_i, y_i, r_i, a_i in zip(s_list, y_list, rho, reversed(alpha), strict=True):
            q += (a_i - r_i * _dot(y_i, q)) * s_i
        d = -q
        slope = _dot(g, d)
        if slope >= 0:  # not a descent direction: forget the curvature pairs
            s_list.clear(), y_list.clear(), rho.clear()
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
            s_list.append(s_k), y_list.append(y_k), rho.append(1.0 / sy)
            if len(s_list) > memory:
                s_list.pop(0), y_list.pop(0), rho.pop(0)
        converged = (f - f_new) <= ftol * max(abs(f), abs(f_new), 1.0)
        x, f, g = x_new, f_new, g_new
        if converged:
            break
    return _MinimizeResult(x, f, it, nfev)
