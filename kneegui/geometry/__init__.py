"""Geometry of the knee: circle fit, rigid transforms, joint axes and the flexion angle."""

from kneegui.geometry.axes import (
    Axis,
    JointAxes,
    compute_joint_axes,
    flexion_angle_deg,
    measure_flexion,
)
from kneegui.geometry.circle_fit import CircleFit, fit_circle_2d
from kneegui.geometry.transforms import RigidTransform, best_fit_transform, rotation_matrix

__all__ = [
    "Axis",
    "CircleFit",
    "JointAxes",
    "RigidTransform",
    "best_fit_transform",
    "compute_joint_axes",
    "fit_circle_2d",
    "flexion_angle_deg",
    "measure_flexion",
    "rotation_matrix",
]
