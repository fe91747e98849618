"""How much the flexion-extension axis depends on the picked condyle nodes.

Real condyles are not circles (their sagittal radius decreases from the distal to the posterior
arc), so the fitted circle, and with it the F-E axis (GCA), moves with the nodes picked. This
module measures that: it refits both condyles on ``n_subsets`` random subsets, each leaving out
a fixed fraction (default a fifth) of each condyle's nodes, and reports how far the axis
direction, the two centres and the radii move from the fit of all the nodes. The subsets come
from a fixed seed, so the same nodes give the same numbers.

The sagittal frame (anterior, superior, lateral -> medial) is held at the one of the full fit:
the resampling measures the fit, not the frame refinement of
:func:`~kneegui.geometry.axes.compute_joint_axes` (a change of the frame by a fraction of a
degree changes the projected centres by far less than the node choice does). Each subset's
circles are geometric least-squares fits (:func:`~kneegui.geometry.circle_fit.
fit_circles_2d_subsets`), each 3-D centre at the subset's mean medial-lateral coordinate, as for
the full fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kneegui.errors import GeometryError
from kneegui.geometry.circle_fit import CircleFit, fit_circle_2d, fit_circles_2d_subsets


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
        Distance (mm) of each subset's circle centre from the full-set centre in the sagittal
        plane (a shift along the medial-lateral direction, from the subset's mean medial-lateral
        coordinate, slides the centre along the axis and is not counted).
    lateral_radius_mm, medial_radius_mm : (S,) ndarray of float
        Each subset's radius minus the full-set radius (mm).
    """

    settings: SensitivitySettings
    direction_deg: NDArray[np.float64]
    lateral_center_mm: NDArray[np.float64]
    medial_center_mm: NDArray[np.float64]
    lateral_radius_mm: NDArray[np.float64]
    medial_radius_mm: NDArray[np.float64]

    def _spread(self, values: NDArray[np.float64]) -> float:
        return float(np.percentile(np.abs(values), self.settings.percentile))

    @property
    def direction_spread_deg(self) -> float:
        """Percentile (default 95th) of the axis direction change, degrees."""
        return self._spread(self.direction_deg)

    @property
    def lateral_center_spread_mm(self) -> float:
        """Percentile of the lateral centre's displacement in the sagittal plane, mm."""
        return self._spread(self.lateral_center_mm)

    @property
    def medial_center_spread_mm(self) -> float:
        """Percentile of the medial centre's displacement in the sagittal plane, mm."""
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
        return (
            f"F-E axis within {self.direction_spread_deg:.2f} deg, centres within "
            f"{self.lateral_center_spread_mm:.2f} / {self.medial_center_spread_mm:.2f} mm, "
            f"radii within {self.lateral_radius_spread_mm:.2f} / "
            f"{self.medial_radius_spread_mm:.2f} mm (lateral / medial; {s.percentile:g}th "
            f"percentile over {s.n_subsets} subsets leaving out {100 * s.leave_out_fraction:g} % "
            f"of each condyle's nodes)"
        )

    def to_dict(self) -> dict[str, float | int]:
        """JSON-ready summary (the spreads and how they were measured)."""
        s = self.settings
        return {
            "direction_spread_deg": self.direction_spread_deg,
            "lateral_center_spread_mm": self.lateral_center_spread_mm,
            "medial_center_spread_mm": self.medial_center_spread_mm,
            "lateral_radius_spread_mm": self.lateral_radius_spread_mm,
            "medial_radius_spread_mm": self.medial_radius_spread_mm,
            "direction_max_deg": float(self.direction_deg.max()),
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


def axis_sensitivity(
    lateral_points: ArrayLike,
    medial_points: ArrayLike,
    anterior: ArrayLike,
    superior: ArrayLike,
    lateral_to_medial: ArrayLike,
    origin: ArrayLike,
    settings: SensitivitySettings | None = None,
    fits: tuple[CircleFit, CircleFit] | None = None,
) -> AxisSensitivity:
    """Resample the condyle node sets and measure how the F-E axis moves.

    Parameters
    ----------
    lateral_points, medial_points : (M, 3) array_like of float
        Condyle node coordinates (mm), M >= 4 each.
    anterior, superior, lateral_to_medial : (3,) array_like of float
        Orthonormal sagittal frame (as in :class:`~kneegui.geometry.axes.JointAxes`).
    origin : (3,) array_like of float
        Origin of the 2-D fit coordinates.
    settings : SensitivitySettings, optional
        Subsets; default 200 leaving out a fifth, seed 0, 95th percentile.
    fits : (CircleFit, CircleFit), optional
        The full-set fits (lateral, medial) in this frame, if already known (used as the start
        and the reference); fitted here otherwise.

    Returns
    -------
    AxisSensitivity

    Raises
    ------
    GeometryError
        Too few nodes, or degenerate subsets.
    """
    settings = SensitivitySettings() if settings is None else settings
    basis = np.stack(
        [
            np.asarray(anterior, dtype=np.float64),
            np.asarray(superior, dtype=np.float64),
            np.asarray(lateral_to_medial, dtype=np.float64),
        ]
    )
    origin = np.asarray(origin, dtype=np.float64)
    rng = np.random.default_rng(settings.seed)
    centres_full, centres_sub, radius_change, centre_shift = [], [], [], []
    for k, pts in enumerate((lateral_points, medial_points)):
        local = (np.asarray(pts, dtype=np.float64) - origin) @ basis.T
        full = fits[k] if fits is not None else fit_circle_2d(local[:, :2])
        keep = _subsets(rng, len(local), settings)
        centres2d, radii = fit_circles_2d_subsets(local[:, :2], keep, full)
        ml = (keep * local[None, :, 2]).sum(axis=1) / keep.sum(axis=1)
        centres_sub.append(origin + np.column_stack([centres2d, ml]) @ basis)
        centres_full.append(origin + np.array([*full.center, local[:, 2].mean()]) @ basis)
        radius_change.append(radii - full.radius)
        centre_shift.append(np.linalg.norm(centres2d - full.center, axis=1))
    axis_full = centres_full[1] - centres_full[0]
    axis_full /= np.linalg.norm(axis_full)
    axes_sub = centres_sub[1] - centres_sub[0]
    axes_sub /= np.linalg.norm(axes_sub, axis=1)[:, None]
    # angle from the cross and dot products: accurate for small angles too
    sin = np.linalg.norm(np.cross(axes_sub, axis_full), axis=1)
    angle = np.degrees(np.arctan2(sin, axes_sub @ axis_full))
    return AxisSensitivity(
        settings=settings,
        direction_deg=_frozen(angle),
        lateral_center_mm=_frozen(centre_shift[0]),
        medial_center_mm=_frozen(centre_shift[1]),
        lateral_radius_mm=_frozen(radius_change[0]),
        medial_radius_mm=_frozen(radius_change[1]),
    )
