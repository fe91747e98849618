"""Joint axes of the knee (ALGORITHM.md §1) and the flexion angle.

Frame and signs
---------------
Everything is derived from the setup's landmarks, never from the model's global axes:

- *superior* ``f`` = unit(femur_axis proximal - distal) (the femoral anatomical axis);
- *medial-lateral* ``n`` = unit vector from the lateral to the medial condyle-set centroid, made
  orthogonal to ``f``. It is the normal of the sagittal plane;
- *left* = ``s * n`` with ``s = +1`` for a right knee, ``-1`` for a left one (the subject's left);
- *anterior* = left x superior (x = y x z of the subject frame x anterior, y left, z superior).

Circle fit: each condyle node set is projected on the sagittal plane (coordinates along anterior
and superior) and fitted with :func:`~kneegui.geometry.circle_fit.fit_circle_2d`; the 3-D centre
sits at the set's mean medial-lateral coordinate. The F-E axis (geometric centre axis, GCA) runs
through the two centres, directed lateral -> medial; its point is the mid-point of the centres
(the knee joint point P0). The L-R axis and the anatomical axes are directed distal -> proximal
(superior) and pass through their proximal landmark.

Flexion = signed angle from the femoral to the tibial anatomical axis (both directed superior),
projected on the sagittal plane, positive about *left*: the tibia's top tilting anteriorly, i.e.
the foot going posterior, is flexion, on either side.
"""

from __future__ import annotations

import csv
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kneegui.errors import GeometryError
from kneegui.geometry.axis_sensitivity import AxisSensitivity, axis_sensitivity
from kneegui.geometry.circle_fit import CircleFit, fit_circle_2d
from kneegui.geometry.transforms import unit
from kneegui.resources import RESOURCES_DIR


class TrackedPoint(Protocol):
    """An axis landmark that can be found in any pose: a node, or a point riding on a bone."""

    def position(self, coords: NDArray[np.float64]) -> NDArray[np.float64]:
        """Where the point is in the node coordinates ``coords`` (N, 3)."""
        ...


class KneeLandmarks(Protocol):
    """What the axes read from a joint setup; :class:`kneegui.setup.format.JointSetup` is one.

    Declared here rather than imported so that geometry stays below the setup in the engine's
    layer order (docs/architecture.md): the setup builds on geometry, never the reverse.
    """

    @property
    def n_nodes(self) -> int:
        """Node count of the model the landmarks index."""
        ...

    @property
    def side_sign(self) -> int:
        """+1 for a right knee, -1 for a left one."""
        ...

    @property
    def lateral_condyle(self) -> NDArray[np.int64]:
        """Node indices of the lateral posterior condyle set."""
        ...

    @property
    def medial_condyle(self) -> NDArray[np.int64]:
        """Node indices of the medial posterior condyle set."""
        ...

    @property
    def femur_axis(self) -> tuple[TrackedPoint, TrackedPoint]:
        """``(proximal, distal)`` points of the femoral anatomical axis."""
        ...

    @property
    def tibia_axis(self) -> tuple[TrackedPoint, TrackedPoint]:
        """``(proximal, distal)`` points of the tibial anatomical axis."""
        ...

    @property
    def lr_axis(self) -> tuple[TrackedPoint, TrackedPoint]:
        """``(proximal, distal)`` points of the longitudinal-rotation axis."""
        ...

    @property
    def segment_nodes(self) -> Mapping[str, NDArray[np.int64]]:
        """Node indices of each rigid group (``femur``, ``tibia``, ``patella``)."""
        ...


@lru_cache(maxsize=1)
def condyle_fit_limits() -> dict[str, float]:
    """Warning limits of the condyle fits and the axes
    (``resources/kinematics/condyle_fit_limits.csv``)."""
    with open(RESOURCES_DIR / "kinematics" / "condyle_fit_limits.csv", newline="") as fh:
        return {row["name"]: float(row["value"]) for row in csv.DictReader(fh)}


@dataclass(frozen=True, eq=False)
class Axis:
    """A directed line: ``point`` (3,) and unit ``direction`` (3,)."""

    point: NDArray[np.float64]
    direction: NDArray[np.float64]

    def to_dict(self) -> dict[str, list[float]]:
        """``{"point": [x, y, z], "direction": [dx, dy, dz]}``."""
        return {
            "point": [float(v) for v in self.point],
            "direction": [float(v) for v in self.direction],
        }


@dataclass(frozen=True, eq=False)
class JointAxes:
    """The knee's axes in one pose.

    Attributes
    ----------
    lateral_fit, medial_fit : CircleFit
        Sagittal circle fits (2-D centre in the (anterior, superior) plane coordinates about
        ``origin``), radius (mm), RMS (mm), arc span (degrees).
    lateral_center, medial_center : (3,) ndarray
        The circle centres in model coordinates.
    fe_axis : Axis
        Flexion-extension axis (GCA): mid-point of the centres, direction lateral -> medial.
    lr_axis, femur_axis, tibia_axis : Axis
        Through the proximal landmark, direction distal -> proximal.
    sagittal_normal : (3,) ndarray
        Lateral -> medial unit normal of the sagittal plane (orthogonal to the femoral axis).
    anterior, superior : (3,) ndarray
        The rest of the femoral frame (see module docstring).
    origin : (3,) ndarray
        Mid-point of the two condyle-set centroids (origin of the 2-D fit coordinates).
    side_sign : int
        +1 right, -1 left.
    initial_flexion_deg : float
        Flexion measured in this pose (degrees).
    patella_center : (3,) ndarray or None
        Centroid of the patella nodes (None without a patella role).
    warnings : tuple of str
        Fit quality findings (radius outside limits, RMS too large, short arc, ...).
    setup : KneeLandmarks
        The setup the axes were computed from (a :class:`~kneegui.setup.format.JointSetup`).
    sensitivity : AxisSensitivity or None
        How much the F-E axis, centres and radii move when a fifth of each condyle's nodes is
        left out at random (:func:`~kneegui.geometry.axis_sensitivity.axis_sensitivity`); None
        if the node sets are too small to resample.
    """

    lateral_fit: CircleFit
    medial_fit: CircleFit
    lateral_center: NDArray[np.float64]
    medial_center: NDArray[np.float64]
    fe_axis: Axis
    lr_axis: Axis
    femur_axis: Axis
    tibia_axis: Axis
    sagittal_normal: NDArray[np.float64]
    anterior: NDArray[np.float64]
    superior: NDArray[np.float64]
    origin: NDArray[np.float64]
    side_sign: int
    initial_flexion_deg: float
    patella_center: NDArray[np.float64] | None
    warnings: tuple[str, ...]
    setup: KneeLandmarks = field(repr=False, compare=False)
    sensitivity: AxisSensitivity | None = field(default=None, repr=False, compare=False)

    @property
    def left(self) -> NDArray[np.float64]:
        """The subject's left (unit): ``side_sign * sagittal_normal``."""
        return self.side_sign * self.sagittal_normal

    @property
    def knee_center(self) -> NDArray[np.float64]:
        """The knee joint point P0 (mid-way between the condyle centres)."""
        return self.fe_axis.point

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (what ``kneegui axes --json`` prints)."""
        return {
            "side": "right" if self.side_sign > 0 else "left",
            "lateral_radius": self.lateral_fit.radius,
            "medial_radius": self.medial_fit.radius,
            "lateral_rms": self.lateral_fit.rms,
            "medial_rms": self.medial_fit.rms,
            "lateral_arc_span_deg": self.lateral_fit.arc_span_deg,
            "medial_arc_span_deg": self.medial_fit.arc_span_deg,
            "lateral_center": [float(v) for v in self.lateral_center],
            "medial_center": [float(v) for v in self.medial_center],
            "fe_axis": self.fe_axis.to_dict(),
            "lr_axis": self.lr_axis.to_dict(),
            "femur_axis": self.femur_axis.to_dict(),
            "tibia_axis": self.tibia_axis.to_dict(),
            "sagittal_normal": [float(v) for v in self.sagittal_normal],
            "anterior": [float(v) for v in self.anterior],
            "superior": [float(v) for v in self.superior],
            "initial_flexion": self.initial_flexion_deg,
            "warnings": list(self.warnings),
            "sensitivity": None if self.sensitivity is None else self.sensitivity.to_dict(),
        }


def _frozen(v: ArrayLike) -> NDArray[np.float64]:
    out = np.array(v, dtype=np.float64)
    out.flags.writeable = False
    return out


def sagittal_normal_from(
    femur_superior: ArrayLike, lateral_centroid: ArrayLike, medial_centroid: ArrayLike
) -> NDArray[np.float64]:
    """Lateral -> medial unit vector orthogonal to the femoral axis.

    Raises
    ------
    GeometryError
        If the condyle centroids coincide or lie along the femoral axis.
    """
    f = unit(femur_superior, "femoral axis")
    ml = np.asarray(medial_centroid, dtype=np.float64) - np.asarray(lateral_centroid, np.float64)
    ml_perp = ml - (ml @ f) * f
    if np.linalg.norm(ml_perp) <= 1e-6 * max(np.linalg.norm(ml), 1e-300):
        raise GeometryError(
            "the lateral and medial condyle sets are not side by side across the femoral axis"
        )
    return unit(ml_perp, "medial-lateral direction")


def flexion_angle_deg(
    femur_superior: ArrayLike,
    tibia_superior: ArrayLike,
    lateral_to_medial: ArrayLike,
    side_sign: int,
) -> float:
    """Knee flexion (degrees) between two anatomical axis directions.

    Parameters
    ----------
    femur_superior, tibia_superior : (3,) array_like
        Directions of the femoral and tibial anatomical axes, distal -> proximal.
    lateral_to_medial : (3,) array_like
        Sagittal-plane normal, lateral -> medial.
    side_sign : int
        +1 right knee, -1 left knee.

    Returns
    -------
    float
        Signed angle in (-180, 180]; positive = flexion (foot posterior).
    """
    n = unit(lateral_to_medial, "sagittal normal")
    f = np.asarray(femur_superior, dtype=np.float64)
    t = np.asarray(tibia_superior, dtype=np.float64)
    f = f - (f @ n) * n
    t = t - (t @ n) * n
    if np.linalg.norm(f) == 0 or np.linalg.norm(t) == 0:
        raise GeometryError("an anatomical axis is perpendicular to the sagittal plane")
    left = side_sign * n
    return float(np.degrees(np.arctan2(np.cross(f, t) @ left, f @ t)))


@dataclass(frozen=True, eq=False)
class _LandmarkPositions:
    lateral: NDArray[np.float64]
    medial: NDArray[np.float64]
    femur: tuple[NDArray[np.float64], NDArray[np.float64]]
    tibia: tuple[NDArray[np.float64], NDArray[np.float64]]
    lr: tuple[NDArray[np.float64], NDArray[np.float64]]


def _positions(coords: NDArray[np.float64], setup: KneeLandmarks) -> _LandmarkPositions:
    coords = np.asarray(coords, dtype=np.float64)
    if coords.shape != (setup.n_nodes, 3):
        raise GeometryError(
            f"coordinates have shape {coords.shape}, the setup's model has {setup.n_nodes} nodes"
        )
    lat = coords[setup.lateral_condyle]
    med = coords[setup.medial_condyle]
    if not (np.all(np.isfinite(lat)) and np.all(np.isfinite(med))):
        raise GeometryError("non-finite condyle node coordinates")

    def pair(points: tuple[TrackedPoint, TrackedPoint]):
        a, b = (p.position(coords) for p in points)
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            raise GeometryError("non-finite axis landmark coordinates")
        return a, b

    return _LandmarkPositions(
        lat, med, pair(setup.femur_axis), pair(setup.tibia_axis), pair(setup.lr_axis)
    )


def measure_flexion(coords: ArrayLike, reference: KneeLandmarks | JointAxes) -> float:
    """Knee flexion (degrees) of a pose.

    Parameters
    ----------
    coords : (N, 3) array_like of float
        Node coordinates of the model (initial or posed).
    reference : KneeLandmarks or JointAxes
        The setup (a :class:`~kneegui.setup.format.JointSetup`), or axes computed from it, naming
        the landmarks. The landmarks are read from ``coords`` (coordinate landmarks follow their
        bone), so the measure is that of the pose.

    Returns
    -------
    float
        Angle between the femoral and tibial anatomical axes projected on the sagittal plane,
        positive in flexion for both sides.
    """
    setup = reference.setup if isinstance(reference, JointAxes) else reference
    pos = _positions(np.asarray(coords, dtype=np.float64), setup)
    frame = _sagittal_frame(pos, setup.side_sign)
    t = unit(pos.tibia[0] - pos.tibia[1], "tibial axis")
    return flexion_angle_deg(frame.superior, t, frame.normal, setup.side_sign)


#: Refinements of the sagittal normal (centroid direction -> F-E axis direction).
SAGITTAL_REFINEMENTS = 5


@dataclass(frozen=True, eq=False)
class _SagittalFrame:
    superior: NDArray[np.float64]
    normal: NDArray[np.float64]
    anterior: NDArray[np.float64]
    origin: NDArray[np.float64]
    fits: tuple[CircleFit, CircleFit]
    centres: tuple[NDArray[np.float64], NDArray[np.float64]]


def _fit_condyles(pos: _LandmarkPositions, f, n, anterior, origin):
    basis = np.stack([anterior, f, n])  # rows: anterior, superior, lateral->medial
    fits, centres = [], []
    for name, pts in (("lateral", pos.lateral), ("medial", pos.medial)):
        local = (pts - origin) @ basis.T
        try:
            fit = fit_circle_2d(local[:, :2])
        except GeometryError as exc:
            raise GeometryError(f"{name} condyle: {exc}") from None
        fits.append(fit)
        centres.append(
            origin + fit.center[0] * anterior + fit.center[1] * f + local[:, 2].mean() * n
        )
    return fits, centres


def _sagittal_frame(pos: _LandmarkPositions, side_sign: int) -> _SagittalFrame:
    """Femoral frame; the sagittal normal starts from the condyle-set centroids and is refined
    to the fitted F-E axis direction (made orthogonal to the femoral axis)."""
    f = unit(pos.femur[0] - pos.femur[1], "femoral axis")
    n = sagittal_normal_from(f, pos.lateral.mean(axis=0), pos.medial.mean(axis=0))
    origin = 0.5 * (pos.lateral.mean(axis=0) + pos.medial.mean(axis=0))
    for i in range(SAGITTAL_REFINEMENTS + 1):
        anterior = unit(np.cross(side_sign * n, f), "anterior direction")
        fits, centres = _fit_condyles(pos, f, n, anterior, origin)
        if i == SAGITTAL_REFINEMENTS:
            break
        try:
            n_new = sagittal_normal_from(f, centres[0], centres[1])
        except GeometryError:
            break
        if n_new @ n < 0.9:  # centres far from the centroid direction: keep the provisional one
            break
        converged = np.linalg.norm(n_new - n) < 1e-12
        n = n_new
        if converged:
            anterior = unit(np.cross(side_sign * n, f), "anterior direction")
            fits, centres = _fit_condyles(pos, f, n, anterior, origin)
            break
    return _SagittalFrame(f, n, anterior, origin, (fits[0], fits[1]), (centres[0], centres[1]))


def _sensitivity(pos: _LandmarkPositions, frame: _SagittalFrame) -> AxisSensitivity | None:
    """Axis spread over node subsets, None when a set is too small to resample."""
    try:
        return axis_sensitivity(
            pos.lateral,
            pos.medial,
            frame.anterior,
            frame.superior,
            frame.normal,
            frame.origin,
            fits=frame.fits,
            frame_refinements=SAGITTAL_REFINEMENTS,
        )
    except GeometryError:
        return None


def compute_joint_axes(model_coords: ArrayLike, setup: KneeLandmarks) -> JointAxes:
    """Fit the condyle circles and build the F-E, L-R and anatomical axes.

    Parameters
    ----------
    model_coords : (N, 3) array_like of float
        Node coordinates (mm) of the model the setup was validated on (or of a pose of it).
    setup : KneeLandmarks
        Landmarks and side: a :class:`~kneegui.setup.format.JointSetup`.

    Returns
    -------
    JointAxes

    Raises
    ------
    GeometryError
        Degenerate landmarks (coincident condyle sets, collinear condyle points, ...).
    """
    pos = _positions(np.asarray(model_coords, dtype=np.float64), setup)
    s = setup.side_sign
    frame = _sagittal_frame(pos, s)
    f, n, anterior, origin = frame.superior, frame.normal, frame.anterior, frame.origin
    fits = frame.fits
    lat_c, med_c = frame.centres
    fe_dir = unit(med_c - lat_c, "F-E axis")
    tib_dir = unit(pos.tibia[0] - pos.tibia[1], "tibial axis")
    lr_dir = unit(pos.lr[0] - pos.lr[1], "L-R axis")

    limits = condyle_fit_limits()
    warnings = []
    for name, fit in (("lateral", fits[0]), ("medial", fits[1])):
        if not limits["radius_min"] <= fit.radius <= limits["radius_max"]:
            warnings.append(
                f"{name} condyle radius {fit.radius:.2f} mm is outside "
                f"{limits['radius_min']:g}-{limits['radius_max']:g} mm"
            )
        if fit.rms > limits["rms_max"]:
            warnings.append(
                f"{name} condyle fit RMS {fit.rms:.2f} mm exceeds {limits['rms_max']:g} mm "
                "(nodes off the posterior outline, e.g. a picked surface patch?)"
            )
        if fit.arc_span_deg < limits["arc_span_min"]:
            warnings.append(
                f"{name} condyle nodes span only {fit.arc_span_deg:.0f} deg of arc "
                f"(< {limits['arc_span_min']:g} deg): the radius is poorly determined"
            )
    lr_angle = float(np.degrees(np.arccos(np.clip(lr_dir @ tib_dir, -1.0, 1.0))))
    if lr_angle > limits["lr_to_tibia_axis_max"]:
        warnings.append(f"the L-R axis is {lr_angle:.0f} deg away from the tibial axis")
    flexion = flexion_angle_deg(f, tib_dir, n, s)
    patella_nodes = setup.segment_nodes["patella"]
    coords = np.asarray(model_coords, dtype=np.float64)
    patella_center = _frozen(coords[patella_nodes].mean(axis=0)) if len(patella_nodes) else None
    if not limits["initial_flexion_min"] <= flexion <= limits["initial_flexion_max"]:
        warnings.append(
            f"initial flexion {flexion:.1f} deg is implausible: check 'side' and the axis points"
        )
    return JointAxes(
        lateral_fit=fits[0],
        medial_fit=fits[1],
        lateral_center=_frozen(lat_c),
        medial_center=_frozen(med_c),
        fe_axis=Axis(_frozen(0.5 * (lat_c + med_c)), _frozen(fe_dir)),
        lr_axis=Axis(_frozen(pos.lr[0]), _frozen(lr_dir)),
        femur_axis=Axis(_frozen(pos.femur[0]), _frozen(f)),
        tibia_axis=Axis(_frozen(pos.tibia[0]), _frozen(tib_dir)),
        sagittal_normal=_frozen(n),
        anterior=_frozen(anterior),
        superior=_frozen(f),
        origin=_frozen(origin),
        side_sign=s,
        initial_flexion_deg=flexion,
        patella_center=patella_center,
        warnings=tuple(warnings),
        setup=setup,
        sensitivity=_sensitivity(pos, frame),
    )
