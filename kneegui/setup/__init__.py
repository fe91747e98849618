"""The joint setup: roles, landmarks, side, moving segment and kinematic tables of a model."""

from kneegui.setup.condyles import femur_frame, suggest_condyle_nodes, surface_node_indices
from kneegui.setup.format import (
    ROLES,
    JointSetup,
    LandmarkPoint,
    load_setup,
    save_setup,
    setup_to_json,
)
from kneegui.setup.landmarks import suggest_axis_landmarks, suggest_setup
from kneegui.setup.roles import suggest_roles

__all__ = [
    "ROLES",
    "JointSetup",
    "LandmarkPoint",
    "femur_frame",
    "load_setup",
    "save_setup",
    "setup_to_json",
    "suggest_axis_landmarks",
    "suggest_condyle_nodes",
    "suggest_roles",
    "suggest_setup",
    "surface_node_indices",
]
