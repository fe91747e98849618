"""Least-squares circle fit in the plane (used for the posterior femoral condyles).

An algebraic fit (Kåsa: ``x² + y² + D x + E y + F = 0`` by linear least squares, with the data
centred and scaled for conditioning) gives the start; a geometric refinement (Levenberg-Marquardt
on the orthogonal distances ``|p - c| - r``, :func:`scipy.optimize.least_squares`) gives the
answer. The geometric fit is unbiased for noisy points on a short arc, where Kåsa's radius is
known to shrink.
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


def fit_outer_profile(
    points2d: ArrayLike,
    rms_trigger: float = 0.5,
    tolerance: float = 0.25,
    max_iterations: int = 50,
) -> tuple[CircleFit, NDArray[np.bool_]]:
    """Circle through the outer boundary of a projected point cloud, when that is what fits.

    A condyle node set picked as a surface patch (not only its sagittal outline) projects to a
    filled crescent: the nodes on the condyle's rounded sides fall inside the circle and pull a
    plain fit in. The paper fits the circle to "the boundary nodes". This first fits all points;
    if their RMS exceeds ``rms_trigger``, it drops the points more than ``tolerance`` inside the
    current circle and refits, until the kept set no longer changes. The outer fit is used only
    if its RMS is within ``tolerance`` (a clean outline, not the outer half of a noisy cloud) and
    at most half the plain fit's, it keeps at least 10 % of the points (and 5) and half the arc;
    otherwise the plain fit is returned.

    Parameters
    ----------
    points2d : (M, 2) array_like of float
        Projected points (mm).
    rms_trigger, tolerance : float
        In the units of the points (mm).
    max_iterations : int
        Bound on the refits.

    Returns
    -------
    fit : CircleFit
        The fit used.
    used : (M,) ndarray of bool
        Which points it was fitted to.
    """
    pts = np.asarray(points2d, dtype=np.float64)
    full = fit_circle_2d(pts)
    everything = np.ones(len(pts), dtype=bool)
    if full.rms <= rms_trigger:
        return full, everything
    fit, keep = full, everything
    min_kept = max(5, int(np.ceil(0.1 * len(pts))))
    for _ in range(max_iterations):
        new_keep = fit.residuals(pts) >= -tolerance
        if new_keep.sum() < min_kept:
            return full, everything
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
        try:
            fit = fit_circle_2d(pts[keep])
        except GeometryError:
            return full, everything
    # a clean outline (not just the outer half of a noisy cloud) and a real improvement
    if (
        fit.rms <= tolerance
        and fit.rms <= 0.5 * full.rms
        and fit.arc_span_deg >= 0.5 * full.arc_span_deg
    ):
        return fit, keep
    return full, everything
