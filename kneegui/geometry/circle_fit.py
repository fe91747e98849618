"""Least-squares circle fit in the plane (used for the posterior femoral condyles).

An algebraic fit (Kåsa: ``x² + y² + D x + E y + F = 0`` by linear least squares, with the data
centred and scaled for conditioning) gives the start; a geometric refinement (Levenberg-Marquardt
on the orthogonal distances ``|p - c| - r``, :func:`scipy.optimize.least_squares`) gives the
answer. The geometric fit is unbiased for noisy points on a short arc, where Kåsa's radius is
known to shrink.

:func:`fit_circles_2d_subsets` fits many subsets of one point set at once (the same two
stages, batched), for the resampling in :mod:`kneegui.geometry.axis_sensitivity`; it is
checked against :func:`fit_circle_2d` subset by subset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from kneegui.errors import GeometryError


@dataclass(frozen=True, eq=False)
class CircleFit:
    """A fitted circle.

    Attributes
    ----------
    center : (2,) ndarray of float
        Centre, in the units and frame of the input points.
    radius : float
        Radius (same units).
    rms : float
        Root-mean-square orthogonal distance of the points to the circle.
    arc_span_deg : float
        Angular extent covered by the points seen from the centre, in degrees: 360 minus the
        largest angular gap between consecutive points.
    """

    center: NDArray[np.float64]
    radius: float
    rms: float
    arc_span_deg: float

    def residuals(self, points2d: ArrayLike) -> NDArray[np.float64]:
        """Signed orthogonal distance ``|p - center| - radius`` of each point, (M,)."""
        pts = np.asarray(points2d, dtype=np.float64)
        return np.linalg.norm(pts - self.center, axis=1) - self.radius


def _algebraic_start(pts: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """Kåsa fit on centred, scaled points; returns centre and radius in the input frame."""
    mean = pts.mean(axis=0)
    q = pts - mean
    scale = float(np.sqrt((q**2).sum(axis=1).mean()))
    if not np.isfinite(scale) or scale == 0.0:
        raise GeometryError("circle fit: all points coincide")
    q = q / scale
    a = np.column_stack([q, np.ones(len(q))])
    b = -(q**2).sum(axis=1)
    sol, _, rank, _ = np.linalg.lstsq(a, b, rcond=None)
    if rank < 3:
        raise GeometryError("circle fit: the points are degenerate (collinear or coincident)")
    d, e, f = sol
    centre = np.array([-d / 2.0, -e / 2.0])
    r2 = centre @ centre - f
    if not np.isfinite(r2) or r2 <= 0:
        raise GeometryError("circle fit: no real circle through the points")
    return mean + scale * centre, float(scale * np.sqrt(r2))


def arc_span_deg(points2d: ArrayLike, center: ArrayLike) -> float:
    """Angular extent (degrees) of points seen from ``center``: 360 minus the largest gap."""
    pts = np.asarray(points2d, dtype=np.float64) - np.asarray(center, dtype=np.float64)
    ang = np.sort(np.arctan2(pts[:, 1], pts[:, 0]))
    if len(ang) < 2:
        return 0.0
    gaps = np.diff(np.concatenate([ang, ang[:1] + 2 * np.pi]))
    return float(np.degrees(2 * np.pi - gaps.max()))


def fit_circle_2d(points2d: ArrayLike) -> CircleFit:
    """Fit a circle to points in a plane.

    Parameters
    ----------
    points2d : (M, 2) array_like of float
        Point coordinates (e.g. mm), M >= 3, not all collinear.

    Returns
    -------
    CircleFit
        Centre, radius, RMS orthogonal residual and arc span.

    Raises
    ------
    GeometryError
        Fewer than 3 points, non-finite coordinates, or collinear / coincident points.
    """
    pts = np.asarray(points2d, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise GeometryError(f"circle fit: expected (M, 2) points, got shape {pts.shape}")
    if len(pts) < 3:
        raise GeometryError(f"circle fit: needs at least 3 points, got {len(pts)}")
    if not np.all(np.isfinite(pts)):
        raise GeometryError("circle fit: non-finite coordinates")
    centre0, radius0 = _algebraic_start(pts)
    extent = float(np.ptp(pts, axis=0).max())
    if radius0 > 1e6 * max(extent, 1e-300):
        raise GeometryError("circle fit: the points are collinear")

    def residual(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.hypot(pts[:, 0] - p[0], pts[:, 1] - p[1]) - p[2]

    def jacobian(p: NDArray[np.float64]) -> NDArray[np.float64]:
        dx, dy = pts[:, 0] - p[0], pts[:, 1] - p[1]
        dist = np.maximum(np.hypot(dx, dy), 1e-300)
        return np.column_stack([-dx / dist, -dy / dist, -np.ones(len(pts))])

    x0 = np.array([centre0[0], centre0[1], radius0])
    method = "lm" if len(pts) >= 3 else "trf"
    sol = least_squares(residual, x0, jac=jacobian, method=method, xtol=1e-14, ftol=1e-14)
    centre = sol.x[:2].copy()
    radius = float(abs(sol.x[2]))
    res = np.hypot(pts[:, 0] - centre[0], pts[:, 1] - centre[1]) - radius
    centre.flags.writeable = False
    return CircleFit(
        center=centre,
        radius=radius,
        rms=float(np.sqrt(np.mean(res**2))),
        arc_span_deg=arc_span_deg(pts, centre),
    )


_EYE3 = np.eye(3)


def _normal_equations(params, pts, w):
    """Gauss-Newton normal matrix (S, 3, 3), gradient (S, 3) and cost (S,) of weighted circle
    fits: residual ``|p - c| - r``, Jacobian rows ``(-dx/dist, -dy/dist, -1)``.
    """
    dx = pts[:, :, 0] - params[:, 0, None]
    dy = pts[:, :, 1] - params[:, 1, None]
    dist = np.maximum(np.hypot(dx, dy), 1e-300)
    res = dist - params[:, 2, None]
    cols = np.stack([-dx / dist, -dy / dist, -np.ones_like(dist), res], axis=2)  # (S, M, 4)
    # one batched product gives J^T W J and J^T W r (a batched einsum is several times slower)
    prod = (cols[:, :, :3] * w[:, :, None]).transpose(0, 2, 1) @ cols  # (S, 3, 4)
    return prod[:, :, :3], prod[:, :, 3], (w * res**2).sum(1)


#: Levenberg-Marquardt iterations allowed in :func:`fit_circles_2d_subsets` (it converges in
#: 3-8 from its algebraic start; more means a subset whose circle is not determined).
SUBSET_FIT_MAX_ITERATIONS = 50
#: Convergence of :func:`fit_circles_2d_subsets`: the last step, relative to the radius.
SUBSET_FIT_TOLERANCE = 1e-10


def _algebraic_starts(pts: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]:
    """Kåsa circles ``(cx, cy, r)`` (S, 3) of weighted point sets (S, M, 2), centred and scaled
    per set for conditioning (as :func:`_algebraic_start`); NaN rows where there is none."""
    sw = w.sum(1)
    mean = (w[:, :, None] * pts).sum(1) / sw[:, None]
    q = pts - mean[:, None, :]
    q2 = (q**2).sum(2)
    scale = np.sqrt((w * q2).sum(1) / sw)
    bad = ~(scale > 0)  # all points of a subset coincide
    scale = np.where(bad, 1.0, scale)
    q = q / scale[:, None, None]
    q2 = q2 / scale[:, None] ** 2
    a = np.concatenate([q, np.ones_like(q[:, :, :1])], axis=2)  # (S, M, 3)
    wa = a * w[:, :, None]
    lhs = wa.transpose(0, 2, 1) @ a
    rhs = -(wa * q2[:, :, None]).sum(1)
    lhs += 1e-12 * np.eye(3) * np.trace(lhs, axis1=1, axis2=2)[:, None, None]
    lhs[bad] = np.eye(3)  # coincident points: any solvable system, the row becomes NaN below
    d, e, f = np.linalg.solve(lhs, rhs[:, :, None])[:, :, 0].T
    r2 = 0.25 * (d**2 + e**2) - f
    r2 = np.where((r2 > 0) & ~bad, r2, np.nan)  # no real circle through the subset: NaN
    centre = mean + scale[:, None] * np.column_stack([-0.5 * d, -0.5 * e])
    return np.column_stack([centre, scale * np.sqrt(r2)])


def fit_circles_2d_subsets(
    points2d: ArrayLike,
    keep: ArrayLike,
    start: ArrayLike | None = None,
    tolerance: float = SUBSET_FIT_TOLERANCE,
    max_iterations: int = SUBSET_FIT_MAX_ITERATIONS,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Geometric least-squares circles of many subsets of a point set, in one batch.

    Each subset's circle minimises the sum of squared orthogonal distances ``|p - c| - r`` of its
    points, as :func:`fit_circle_2d` does: from a start (its algebraic Kåsa circle unless given)
    it is refined by Levenberg-Marquardt (a damping per subset), all subsets together.

    Parameters
    ----------
    points2d : (M, 2) or (S, M, 2) array_like of float
        The points (mm): one set shared by the subsets, or one projection per subset.
    keep : (S, M) array_like of bool
        Which points each of the S subsets holds (at least 3 each).
    start : (S, 3) array_like of float, optional
        Starting circles as rows ``(cx, cy, r)`` (e.g. the fit of all the points); a row with a
        NaN starts from its algebraic circle.
    tolerance : float
        A subset is converged when its last step is below ``tolerance`` times its radius.
    max_iterations : int
        Levenberg-Marquardt iterations allowed.

    Returns
    -------
    centers : (S, 2) ndarray of float
    radii : (S,) ndarray of float
        NaN for a subset whose circle is not determined (nearly collinear points, or no
        convergence in ``max_iterations``).

    Raises
    ------
    GeometryError
        Shapes that do not match, or a subset with fewer than 3 points.
    """
    w = np.asarray(keep, dtype=bool)
    pts = np.asarray(points2d, dtype=np.float64)
    if pts.ndim == 2:
        pts = np.broadcast_to(pts, (len(w), *pts.shape))
    if pts.ndim != 3 or pts.shape[2] != 2 or w.ndim != 2 or pts.shape[:2] != w.shape:
        raise GeometryError(
            f"subset circle fit: points {pts.shape} and subsets {w.shape} do not match"
        )
    if (w.sum(axis=1) < 3).any():
        raise GeometryError("subset circle fit: a subset has fewer than 3 points")
    wf = w.astype(np.float64)
    n_sub = len(w)
    if start is None:
        params = np.full((n_sub, 3), np.nan)
    else:
        params = np.array(start, dtype=np.float64).reshape(n_sub, 3)
    cold = ~np.isfinite(params).all(axis=1)
    if cold.any():
        params[cold] = _algebraic_starts(pts[cold], wf[cold])
    # collinear subsets (the smaller principal variance vanishing) have no circle
    sw = wf.sum(1)
    q = pts - ((wf[:, :, None] * pts).sum(1) / sw[:, None])[:, None, :]
    cxx, cyy = (wf * q[:, :, 0] ** 2).sum(1), (wf * q[:, :, 1] ** 2).sum(1)
    cxy = (wf * q[:, :, 0] * q[:, :, 1]).sum(1)
    half, det = 0.5 * (cxx + cyy), cxx * cyy - cxy**2
    major = half + np.sqrt(np.maximum(half**2 - det, 0.0))
    minor = det / np.maximum(major, 1e-300)
    params[~(minor > 1e-14 * major)] = np.nan
    active = np.isfinite(params).all(axis=1)
    normal, grad, cost = _normal_equations(params, pts, wf)
    damping = np.full(n_sub, 1e-3)
    for _ in range(max_iterations):
        if not active.any():
            break
        broken = active & ~(np.isfinite(normal).all(axis=(1, 2)) & np.isfinite(grad).all(axis=1))
        params[broken] = np.nan  # overflowed on its way to an infinite radius
        active &= ~broken
        if not active.any():
            break
        idx = np.flatnonzero(active)
        every = len(idx) == n_sub  # no fancy-index copies while every subset iterates
        n_a, g_a = (normal, grad) if every else (normal[idx], grad[idx])
        diag = n_a * _EYE3
        lhs = n_a + (damping[idx, None, None] + 1e-12) * diag + 1e-300 * _EYE3
        step = -np.linalg.solve(lhs, g_a[:, :, None])[:, :, 0]
        trial = params[idx] + step
        n_t, g_t, c_t = _normal_equations(
            trial, pts if every else pts[idx], wf if every else wf[idx]
        )
        # Levenberg-Marquardt: keep a step that lowers the cost, else damp more and retry
        better = np.isfinite(c_t) & (c_t <= cost[idx])
        acc = idx[better]
        params[acc], normal[acc], grad[acc], cost[acc] = (
            trial[better],
            n_t[better],
            g_t[better],
            c_t[better],
        )
        damping[idx] = np.where(better, np.maximum(damping[idx] / 3.0, 1e-9), damping[idx] * 4.0)
        size = np.maximum(np.abs(params[idx, 2]), 1e-300)
        small = np.abs(step).max(axis=1) <= tolerance * size
        active[idx[small | (damping[idx] > 1e12)]] = False
    params[active] = np.nan  # not converged
    # a radius a thousand times the points' spread: the points are (nearly) collinear
    params[np.abs(params[:, 2]) > 1e3 * np.sqrt(major / sw)] = np.nan
    return params[:, :2].copy(), np.abs(params[:, 2])
