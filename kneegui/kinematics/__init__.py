"""Bone kinematics: rigid posing of the femur, tibia and patella to a target flexion.

The kinematic tables that drive the coupled rotations are part of the joint setup
(:mod:`kneegui.setup.kinematic_tables`); this package turns a setup and its axes into bone
transforms.
"""

from kneegui.kinematics.posing import (
    BonePose,
    apply_bone_transforms,
    bone_transforms,
    pose_bones,
    solve_bone_pose,
)

__all__ = [
    "BonePose",
    "apply_bone_transforms",
    "bone_transforms",
    "pose_bones",
    "solve_bone_pose",
]
