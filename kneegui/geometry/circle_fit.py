"""Least-squares circle fit in the plane (used for the posterior femoral condyles).

An algebraic fit (Kåsa: ``x² + y² + D x + E y + F = 0`` by linear least squares, with the data
centred and scaled for conditioning) gives the start; a geometric refinement (Levenberg-Marquardt
on the orthogonal distances ``|p - c| - r``, :func:`scipy.optimize.least_squares`) gives the
answer. The geometric fit is unbiased for noisy points on a short arc, where Kåsa's radius is
known to shrink.

:func:`fit_circles_2d_subsets` fits many subsets of one point set at once (batched Gauss-Newton
from a common start), for the resampling in :mod:`kneegui.geometry.axis_sensitivity`; it is
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


#: Gauss-Newton iterations allowed in :func:`fit_circles_2d_subsets` (it converges in 3-6 from a
#: full-set fit; more means a subset whose circle is not determined).
SUBSET_FIT_MAX_ITERATIONS = 50


def fit_circles_2d_subsets(
    points2d: ArrayLike, keep: ArrayLike, start: CircleFit
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Geometric least-squares circles of many subsets of one point set, in one batch.

    Each subset's circle minimises the sum of squared orthogonal distances ``|p - c| - r`` of its
    points, as :func:`fit_circle_2d` does; all subsets iterate together (Gauss-Newton with a
    small Levenberg-Marquardt damping, vectorised over the subsets), starting from ``start``
    (usually the fit of all the points, which every subset's answer is near).

    Parameters
    ----------
    points2d : (M, 2) array_like of float
        All points (mm).
    keep : (S, M) array_like of bool
        Which points each of the S subsets holds (at least 3 each).
    start : CircleFit
        Starting circle.

    Returns
    -------
    centers : (S, 2) ndarray of float
    radii : (S,) ndarray of float

    Raises
    ------
    GeometryError
        A subset with fewer than 3 points, or one whose fit does not converge.
    """
    pts = np.asarray(points2d, dtype=np.float64)
    w = np.asarray(keep, dtype=bool)
    if pts.ndim != 2 or pts.shape[1] != 2 or w.ndim != 2 or w.shape[1] != len(pts):
        raise GeometryError(
            f"subset circle fit: points {pts.shape} and subsets {w.shape} do not match"
        )
    if (w.sum(axis=1) < 3).any():
        raise GeometryError("subset circle fit: a subset has fewer than 3 points")
    wf = w.astype(np.float64)
    n_sub = len(w)
    params = np.tile([start.center[0], start.center[1], start.radius], (n_sub, 1))
    scale = max(float(start.radius), 1e-300)
    active = np.ones(n_sub, dtype=bool)
    for _ in range(SUBSET_FIT_MAX_ITERATIONS):
        p = params[active]
        dx = pts[None, :, 0] - p[:, 0, None]
        dy = pts[None, :, 1] - p[:, 1, None]
        dist = np.maximum(np.hypot(dx, dy), 1e-300)
        res = dist - p[:, 2, None]
        jac = np.stack([-dx / dist, -dy / dist, -np.ones_like(dist)], axis=2)  # (S, M, 3)
        wj = jac * wf[active][:, :, None]
        normal = np.einsum("smi,smj->sij", wj, jac)
        normal += 1e-12 * np.eye(3) * np.trace(normal, axis1=1, axis2=2)[:, None, None]
        grad = np.einsum("smi,sm->si", wj, res)
        step = -np.linalg.solve(normal, grad[:, :, None])[:, :, 0]
        params[active] = p + step
        done = np.abs(step).max(axis=1) <= 1e-12 * scale
        idx = np.flatnonzero(active)
        active[idx[done]] = False
        if not active.any():
            break
    if active.any() or not np.all(np.isfinite(params)):
        raise GeometryError("subset circle fit: did not converge (an arc too short or too noisy)")
    centers = params[:, :2].copy()
    radii = np.abs(params[:, 2])
    return centers, radii
