"""Rigid bone motion to a target flexion (ALGORITHM.md §2).

Relative to the femur, the tibia group (tibia + fibula) is rotated

1. about the F-E axis (GCA) by ``s * delta`` - flexion; ``delta`` starts at ``phi - phi0`` and is
   iterated until the re-measured flexion equals ``phi``;
2. then about the L-R axis, carried along by step 1, by ``s * (R(phi) - R(phi0))`` - the coupled
   tibial internal rotation (screw-home), ``R`` from the ``tibial_rotation`` table.

The patella is flexed about the F-E axis by ``s * (P(phi) - P(phi0))`` and then tilted about its
own proximal-distal axis (through its flexed centroid, along the flexed femoral axis direction)
by ``s * (T(phi) - T(phi0))``. ``phi0`` is the measured initial flexion and ``s`` is +1 for a right
knee, -1 for a left one; the F-E axis is directed lateral -> medial and the L-R and patellar axes
distal -> proximal, so with ``s`` every sign mirrors for a left knee (see
:mod:`kneegui.setup.kinematic_tables` for the convention).

When the femur is the moving segment, the femur (and the patella, which rides on it) take the
inverse of the tibia's relative motion and the tibia stays: the relative pose is the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import GeometryError
from kneegui.geometry.axes import JointAxes, compute_joint_axes, flexion_angle_deg
from kneegui.geometry.transforms import RigidTransform
from kneegui.model import Model
from kneegui.setup.format import JointSetup

#: Newton iteration on the F-E rotation: stop below this flexion error (degrees).
FLEXION_TOLERANCE_DEG = 1e-9
MAX_ITERATIONS = 50


@dataclass(frozen=True, eq=False)
class BonePose:
    """The rigid motion of the bones for one target flexion.

    Attributes
    ----------
    transforms : dict of str to RigidTransform
        ``femur``, ``tibia`` (tibia + fibula) and ``patella``, from the initial pose; the fixed
        segment's transform is the identity.
    target_flexion_deg, initial_flexion_deg, measured_flexion_deg : float
        Target, initial and re-measured flexion (degrees).
    fe_rotation_deg : float
        Rotation about the F-E axis actually applied (after iteration), as a flexion change.
    tibial_rotation_deg, patellar_flexion_deg, patellar_tilt_deg : float
        Table changes applied (internal rotation, patellar flexion, medial tilt), degrees.
    iterations : int
        Newton iterations used.
    patellar_lift : float
        How far the patella was lifted off the femur after its tables, radially from the F-E
        axis (model units; set by :class:`kneegui.reposition.Repositioner`'s patellar
        seating, 0 here).
    """

    transforms: dict[str, RigidTransform]
    target_flexion_deg: float
    initial_flexion_deg: float
    measured_flexion_deg: float
    fe_rotation_deg: float
    tibial_rotation_deg: float
    patellar_flexion_deg: float
    patellar_tilt_deg: float
    iterations: int
    patellar_lift: float = 0.0


def _tibia_relative(axes: JointAxes, fe_deg: float, rot_deg: float) -> RigidTransform:
    """Tibia motion relative to the femur: L-R rotation (initial axis), then F-E rotation."""
    s = axes.side_sign
    lr = RigidTransform.about_axis(axes.lr_axis.point, axes.lr_axis.direction, s * rot_deg)
    fe = RigidTransform.about_axis(axes.fe_axis.point, axes.fe_axis.direction, s * fe_deg)
    return lr.then(fe)


def _wrap(angle_deg: float) -> float:
    return (angle_deg + 180.0) % 360.0 - 180.0


def solve_bone_pose(axes: JointAxes, setup: JointSetup, flexion_deg: float) -> BonePose:
    """Bone transforms that bring the knee to ``flexion_deg`` (measured), with the coupled motion.

    Parameters
    ----------
    axes : JointAxes
        Axes of the initial pose (:func:`~kneegui.geometry.axes.compute_joint_axes`).
    setup : JointSetup
        Side, moving segment and kinematic tables.
    flexion_deg : float
        Target knee flexion (degrees, e.g. -5 ... 140).

    Raises
    ------
    GeometryError
        If the target flexion cannot be reached by rotating about the F-E axis.
    """
    phi = float(flexion_deg)
    if not np.isfinite(phi):
        raise GeometryError(f"target flexion {flexion_deg!r} is not finite")
    phi0 = axes.initial_flexion_deg
    s = axes.side_sign
    rot = setup.tables["tibial_rotation"].change(phi0, phi)
    pflex = setup.tables["patellar_flexion"].change(phi0, phi)
    tilt = setup.tables["patellar_tilt"].change(phi0, phi)

    femur_dir, tibia_dir, normal = axes.superior, axes.tibia_axis.direction, axes.sagittal_normal

    def measured(fe_deg: float) -> float:
        moved = _tibia_relative(axes, fe_deg, rot).apply_vector(tibia_dir)
        return flexion_angle_deg(femur_dir, moved, normal, s)

    delta = _wrap(phi - phi0)
    err = _wrap(measured(delta) - phi)
    iterations = 0
    step = 1e-3
    while abs(err) > FLEXION_TOLERANCE_DEG and iterations < MAX_ITERATIONS:
        slope = (_wrap(measured(delta + step) - phi) - err) / step
        if not np.isfinite(slope) or abs(slope) < 1e-6:
            break
        delta = delta - err / slope
        err = _wrap(measured(delta) - phi)
        iterations += 1
        step = min(1e-3, max(abs(err), 1e-7))
    if abs(err) > 1e-6:
        raise GeometryError(
            f"cannot reach {phi:.2f} deg of flexion by rotating about the F-E axis "
            f"(residual {err:.3g} deg): the F-E axis may lie in the sagittal plane"
        )
    tibia_rel = _tibia_relative(axes, delta, rot)

    identity = RigidTransform.identity()
    patella_rel = identity
    if axes.patella_center is not None:
        flex_t = RigidTransform.about_axis(axes.fe_axis.point, axes.fe_axis.direction, s * pflex)
        tilt_t = RigidTransform.about_axis(
            flex_t.apply(axes.patella_center), flex_t.apply_vector(axes.superior), s * tilt
        )
        patella_rel = flex_t.then(tilt_t)
    if setup.moving_segment == "tibia":
        transforms = {"femur": identity, "tibia": tibia_rel, "patella": patella_rel}
    else:
        femur_t = tibia_rel.inverse()
        transforms = {"femur": femur_t, "tibia": identity, "patella": patella_rel.then(femur_t)}
    return BonePose(
        transforms=transforms,
        target_flexion_deg=phi,
        initial_flexion_deg=phi0,
        measured_flexion_deg=phi + err,
        fe_rotation_deg=delta,
        tibial_rotation_deg=rot,
        patellar_flexion_deg=pflex,
        patellar_tilt_deg=tilt,
        iterations=iterations,
    )


def bone_transforms(
    axes: JointAxes, setup: JointSetup, flexion_deg: float
) -> dict[str, RigidTransform]:
    """Rigid transforms of ``femur``, ``tibia`` (tibia + fibula) and ``patella`` groups.

    Each maps initial-pose coordinates to the pose at ``flexion_deg``; the segment that does not
    move gets the identity. See :func:`solve_bone_pose`.
    """
    return solve_bone_pose(axes, setup, flexion_deg).transforms


def apply_bone_transforms(
    coords: NDArray[np.float64], setup: JointSetup, transforms: dict[str, RigidTransform]
) -> NDArray[np.float64]:
    """New (N, 3) coordinates: each rigid group's nodes moved by its transform, others copied.

    A node shared by two groups follows the later of ``femur``, ``tibia``, ``patella``.
    """
    out = np.array(coords, dtype=np.float64, copy=True)
    for segment in ("femur", "tibia", "patella"):
        idx = setup.segment_nodes[segment]
        t = transforms[segment]
        if len(idx) and not (np.array_equal(t.rotation, np.eye(3)) and not t.translation.any()):
            out[idx] = t.apply(coords[idx])
    return out


def pose_bones(
    model: Model, setup: JointSetup, flexion_deg: float, axes: JointAxes | None = None
) -> NDArray[np.float64]:
    """Coordinates of every node with the bones posed at ``flexion_deg``.

    Parameters
    ----------
    model : Model
        The model in its initial pose (the one the setup was validated on).
    setup : JointSetup
        Roles, landmarks, side, moving segment and tables.
    flexion_deg : float
        Target flexion (degrees), as measured between the anatomical axes.
    axes : JointAxes, optional
        Axes of the initial pose; computed from ``model.coords`` when omitted.

    Returns
    -------
    (N, 3) ndarray of float
        New coordinates. Only the nodes of the moving segment's bones and of the patella differ
        from ``model.coords``; every bone moves rigidly.
    """
    if model.n_nodes != setup.n_nodes:
        raise GeometryError(
            f"the model has {model.n_nodes} nodes but the setup was validated on {setup.n_nodes}"
        )
    if axes is None:
        axes = compute_joint_axes(model.coords, setup)
    return apply_bone_transforms(model.coords, setup, bone_transforms(axes, setup, flexion_deg))
