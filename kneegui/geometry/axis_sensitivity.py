"""How much the flexion-extension axis depends on the picked condyle nodes.

Real condyles are not circles (their sagittal radius decreases from the distal to the posterior
arc), so the fitted circle, and with it the F-E axis (GCA), moves with the nodes picked. This
module measures that: it refits both condyles on ``n_subsets`` random subsets, each leaving out
a fixed fraction (default a fifth) of each condyle's nodes, and reports how far the axis
direction, the two centres and the radii move from the fit of all the nodes. The subsets come
from a fixed seed, so the same nodes give the same numbers.

Each subset goes through the same estimator as the full set: geometric least-squares circles
(:func:`~kneegui.geometry.circle_fit.fit_circles_2d_subsets`, batched) in the sagittal plane,
each 3-D centre at the subset's mean medial-lateral coordinate and, with ``frame_refinements``
(what :func:`~kneegui.geometry.axes.compute_joint_axes` passes), the sagittal normal re-aimed at
the subset's own fitted axis and the circles refitted. A node set spread across the condyle's
width projects differently when the normal turns, so the refinement is part of what moves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kneegui.errors import GeometryError
from kneegui.geometry.circle_fit import (
    SUBSET_FIT_MAX_ITERATIONS,
    SUBSET_FIT_TOLERANCE,
    CircleFit,
    fit_circle_2d,
    fit_circles_2d_subsets,
)

#: A subset's re-aimed sagittal normal is taken as settled when it moves less than this (a
#: unit-vector change, ~radians: 6e-8 degrees).
FRAME_TOLERANCE = 1e-9


@dataclass(frozen=True)
class SensitivitySettings:
    """How the condyle node sets are resampled.

    Attributes
    ----------
    n_subsets : int
        Number of random subsets (>= 10).
    leave_out_fraction : float
        Fraction of each condyle's nodes left out of each subset, in (0, 0.5].
    seed : int
        Seed of the random subsets (the same seed gives the same subsets).
    percentile : float
        Percentile reported as "the spread", in (50, 100].
    """

    n_subsets: int = 200
    leave_out_fraction: float = 0.2
    seed: int = 0
    percentile: float = 95.0

    def __post_init__(self) -> None:
        if isinstance(self.n_subsets, bool) or int(self.n_subsets) != self.n_subsets:
            raise ValueError(f"n_subsets must be an integer, got {self.n_subsets!r}")
        if self.n_subsets < 10:
            raise ValueError(f"n_subsets must be at least 10, got {self.n_subsets}")
        if not 0.0 < self.leave_out_fraction <= 0.5:
            raise ValueError(
                f"leave_out_fraction must be in (0, 0.5], got {self.leave_out_fraction}"
            )
        if not 50.0 < self.percentile <= 100.0:
            raise ValueError(f"percentile must be in (50, 100], got {self.percentile}")


@dataclass(frozen=True, eq=False)
class AxisSensitivity:
    """Spread of the F-E axis and of the condyle circles over random node subsets.

    Attributes
    ----------
    settings : SensitivitySettings
        How the subsets were drawn.
    direction_deg : (S,) ndarray of float
        Angle (degrees) between each subset's F-E axis and the full-set axis.
    lateral_center_mm, medial_center_mm : (S,) ndarray of float
        Distance (mm) of each subset's circle centre from the full-set centre, across the
        full-set axis (a shift along the axis, e.g. from the subset's mean medial-lateral
        coordinate, does not move the axis and is not counted).
    lateral_radius_mm, medial_radius_mm : (S,) ndarray of float
        Each subset's radius minus the full-set radius (mm).

    A subset whose circles are not determined (nearly collinear projected nodes, or a fit that
    does not converge) has ``inf`` in every array: the axis is unstable for that choice of
    nodes, and it counts in the percentiles (``n_failed`` says how many).
    """

    settings: SensitivitySettings
    direction_deg: NDArray[np.float64]
    lateral_center_mm: NDArray[np.float64]
    medial_center_mm: NDArray[np.float64]
    lateral_radius_mm: NDArray[np.float64]
    medial_radius_mm: NDArray[np.float64]

    def _spread(self, values: NDArray[np.float64]) -> float:
        # "higher": an observed value, never an interpolation towards a failed subset's inf
        return float(np.percentile(np.abs(values), self.settings.percentile, method="higher"))

    @property
    def n_failed(self) -> int:
        """Subsets whose circles were not determined (their values are ``inf``)."""
        return int(np.count_nonzero(~np.isfinite(self.direction_deg)))

    @property
    def direction_spread_deg(self) -> float:
        """Percentile (default 95th) of the axis direction change, degrees."""
        return self._spread(self.direction_deg)

    @property
    def lateral_center_spread_mm(self) -> float:
        """Percentile of the lateral centre's displacement across the axis, mm."""
        return self._spread(self.lateral_center_mm)

    @property
    def medial_center_spread_mm(self) -> float:
        """Percentile of the medial centre's displacement across the axis, mm."""
        return self._spread(self.medial_center_mm)

    @property
    def lateral_radius_spread_mm(self) -> float:
        """Percentile of the lateral radius change (absolute), mm."""
        return self._spread(self.lateral_radius_mm)

    @property
    def medial_radius_spread_mm(self) -> float:
        """Percentile of the medial radius change (absolute), mm."""
        return self._spread(self.medial_radius_mm)

    def summary(self) -> str:
        """One line for the CLI, the GUI and the pose report."""
        s = self.settings
        failed = (
            f"; {self.n_failed} of {s.n_subsets} subsets gave no determined circle"
            if self.n_failed
            else ""
        )
        if not np.isfinite(self.direction_spread_deg):
            return (
                f"F-E axis unstable: more than {100 - s.percentile:g} % of the subsets leaving "
                f"out {100 * s.leave_out_fraction:g} % of each condyle's nodes gave no "
                f"determined circle{failed}"
            )
        return (
            f"F-E axis within {self.direction_spread_deg:.2f} deg, centres within "
            f"{self.lateral_center_spread_mm:.2f} / {self.medial_center_spread_mm:.2f} mm, "
            f"radii within {self.lateral_radius_spread_mm:.2f} / "
            f"{self.medial_radius_spread_mm:.2f} mm (lateral / medial; {s.percentile:g}th "
            f"percentile over {s.n_subsets} subsets leaving out {100 * s.leave_out_fraction:g} % "
            f"of each condyle's nodes{failed})"
        )

    def to_dict(self) -> dict[str, float | int | None]:
        """JSON-ready summary (the spreads and how they were measured; None for infinite)."""
        s = self.settings

        def finite(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        return {
            "direction_spread_deg": finite(self.direction_spread_deg),
            "lateral_center_spread_mm": finite(self.lateral_center_spread_mm),
            "medial_center_spread_mm": finite(self.medial_center_spread_mm),
            "lateral_radius_spread_mm": finite(self.lateral_radius_spread_mm),
            "medial_radius_spread_mm": finite(self.medial_radius_spread_mm),
            "direction_max_deg": finite(self.direction_deg.max()),
            "failed_subsets": self.n_failed,
            "percentile": float(s.percentile),
            "n_subsets": int(s.n_subsets),
            "leave_out_fraction": float(s.leave_out_fraction),
            "seed": int(s.seed),
        }


def _frozen(a: NDArray[np.float64]) -> NDArray[np.float64]:
    out = np.array(a, dtype=np.float64)
    out.flags.writeable = False
    return out


def _subsets(rng: np.random.Generator, n_points: int, settings: SensitivitySettings):
    """(S, M) masks, each leaving out ``round(fraction * M)`` points (at least one)."""
    n_out = max(1, round(settings.leave_out_fraction * n_points))
    if n_points - n_out < 3:
        raise GeometryError(f"axis sensitivity: {n_points} nodes are too few to leave {n_out} out")
    order = np.argsort(rng.random((settings.n_subsets, n_points)), axis=1)
    keep = np.ones((settings.n_subsets, n_points), dtype=bool)
    np.put_along_axis(keep, order[:, :n_out], False, axis=1)
    return keep


def _unit_rows(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rows made unit; NaN rows where a row is zero or NaN (a failed subset)."""
    norm = np.linalg.norm(v, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where((norm > 0)[:, None], v / norm[:, None], np.nan)


def axis_sensitivity(
    lateral_points: ArrayLike,
    medial_points: ArrayLike,
    anterior: ArrayLike,
    superior: ArrayLike,
    lateral_to_medial: ArrayLike,
    origin: ArrayLike,
    settings: SensitivitySettings | None = None,
    fits: tuple[CircleFit, CircleFit] | None = None,
    frame_refinements: int = 5,
) -> AxisSensitivity:
    """Resample the condyle node sets and measure how the F-E axis moves.

    Parameters
    ----------
    lateral_points, medial_points : (M, 3) array_like of float
        Condyle node coordinates (mm), M >= 4 each.
    anterior, superior, lateral_to_medial : (3,) array_like of float
        Orthonormal sagittal frame of the full fit (as in
        :class:`~kneegui.geometry.axes.JointAxes`); ``superior`` is the femoral axis.
    origin : (3,) array_like of float
        Origin of the 2-D fit coordinates.
    settings : SensitivitySettings, optional
        Subsets; default 200 leaving out a fifth, seed 0, 95th percentile.
    fits : (CircleFit, CircleFit), optional
        The full-set fits (lateral, medial) in this frame, if already known (used as the start
        and the reference); fitted here otherwise.
    frame_refinements : int
        As :func:`~kneegui.geometry.axes.compute_joint_axes` does (``SAGITTAL_REFINEMENTS``, 5),
        re-aim each subset's sagittal normal at its own fitted axis (made orthogonal to
        ``superior``) and refit, at most this many times; 0 keeps the given frame for every
        subset.

    Returns
    -------
    AxisSensitivity

    Raises
    ------
    GeometryError
        Too few nodes, or degenerate subsets.
    """
    settings = SensitivitySettings() if settings is None else settings
    f = np.asarray(superior, dtype=np.float64)
    n0 = np.asarray(lateral_to_medial, dtype=np.float64)
    a0 = np.asarray(anterior, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    basis0 = np.stack([a0, f, n0])
    # the anterior of a re-aimed frame keeps the sign of the given one (left or right knee)
    handed = 1.0 if np.cross(n0, f) @ a0 > 0 else -1.0
    rng = np.random.default_rng(settings.seed)
    rel, keeps, starts, centres_full, full_radii = [], [], [], [], []
    for k, pts in enumerate((lateral_points, medial_points)):
        r = np.asarray(pts, dtype=np.float64) - origin
        local = r @ basis0.T
        full = fits[k] if fits is not None else fit_circle_2d(local[:, :2])
        keep = _subsets(rng, len(r), settings)
        rel.append(r)
        keeps.append(keep)
        starts.append(np.tile([full.center[0], full.center[1], full.radius], (len(keep), 1)))
        centres_full.append(origin + np.array([*full.center, local[:, 2].mean()]) @ basis0)
        full_radii.append(full.radius)
    n_sub = np.tile(n0, (settings.n_subsets, 1))
    refined, last = 0, frame_refinements == 0
    while True:
        ant = handed * _unit_rows(np.cross(n_sub, f))
        basis = np.stack([ant, np.broadcast_to(f, ant.shape), n_sub], axis=1)  # (S, 3, 3)
        centres, radii_sub = [], []
        for k in range(2):
            local = rel[k] @ basis.transpose(0, 2, 1)  # (S, M, 3)
            # while the frame still moves the circles are fitted loosely (a subset not settled
            # in 10 iterations keeps its frame and restarts from its Kasa circle); the last fit,
            # in the settled frame, is the full one
            c2, radii = fit_circles_2d_subsets(
                local[:, :, :2],
                keeps[k],
                starts[k],
                tolerance=SUBSET_FIT_TOLERANCE if last else 1e-7,
                max_iterations=SUBSET_FIT_MAX_ITERATIONS if last else 10,
            )
            starts[k] = np.column_stack([c2, radii])
            radii_sub.append(radii)
            ml = (keeps[k] * local[:, :, 2]).sum(axis=1) / keeps[k].sum(axis=1)
            coeffs = np.column_stack([c2, ml])[:, None, :]
            centres.append(origin + (coeffs @ basis)[:, 0, :])
        if last:
            break
        across = centres[1] - centres[0]
        across -= np.outer(across @ f, f)
        n_new = _unit_rows(across)
        # as compute_joint_axes: a normal far from the provisional one is not followed
        with np.errstate(invalid="ignore"):
            follow = np.einsum("si,si->s", n_new, n_sub) >= 0.9  # False for a failed subset
            moved = np.abs(n_new - n_sub).max(axis=1) > FRAME_TOLERANCE
        n_sub = np.where(follow[:, None], n_new, n_sub)
        refined += 1
        last = refined == frame_refinements or not np.any(follow & moved)
    axis_full = _unit_rows((centres_full[1] - centres_full[0])[None, :])[0]
    axes_sub = _unit_rows(centres[1] - centres[0])
    # angle from the cross and dot products: accurate for small angles too
    sin = np.linalg.norm(np.cross(axes_sub, axis_full), axis=1)
    angle = np.degrees(np.arctan2(sin, axes_sub @ axis_full))
    shifts = []
    for k in range(2):
        d = centres[k] - centres_full[k]
        shifts.append(np.linalg.norm(d - np.outer(d @ axis_full, axis_full), axis=1))
    changes = [radii_sub[0] - full_radii[0], radii_sub[1] - full_radii[1]]
    # a subset without a determined circle: infinitely far (it counts in the percentiles)
    failed = ~np.isfinite(angle)
    for values in (angle, *shifts, *changes):
        failed |= ~np.isfinite(values)
    for values in (angle, *shifts, *changes):
        values[failed] = np.inf
    return AxisSensitivity(
        settings=settings,
        direction_deg=_frozen(angle),
        lateral_center_mm=_frozen(shifts[0]),
        medial_center_mm=_frozen(shifts[1]),
        lateral_radius_mm=_frozen(changes[0]),
        medial_radius_mm=_frozen(changes[1]),
    )
