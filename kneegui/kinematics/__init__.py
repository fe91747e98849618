"""Bone kinematics: kinematic tables and rigid posing of the femur, tibia and patella."""

from kneegui.kinematics.posing import (
    BonePose,
    apply_bone_transforms,
    bone_transforms,
    pose_bones,
    solve_bone_pose,
)
from kneegui.kinematics.tables import (
    QUANTITIES,
    SUPPORTED_FLEXION_DEG,
    VALIDATED_FLEXION_DEG,
    KinematicTable,
    read_table_csv,
    resolve_table,
    shipped_tables,
    table_names,
)

__all__ = [
    "QUANTITIES",
    "SUPPORTED_FLEXION_DEG",
    "VALIDATED_FLEXION_DEG",
    "BonePose",
    "KinematicTable",
    "apply_bone_transforms",
    "bone_transforms",
    "pose_bones",
    "read_table_csv",
    "resolve_table",
    "shipped_tables",
    "solve_bone_pose",
    "table_names",
]
