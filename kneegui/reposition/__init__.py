"""Whole-model repositioning: bones, skin contours and soft tissue (ALGORITHM.md §2-4)."""

from kneegui.reposition.repositioner import (
    METHODS,
    NodeGroups,
    PoseResult,
    Repositioner,
    RepositionOptions,
    classify_nodes,
)

__all__ = [
    "METHODS",
    "NodeGroups",
    "PoseResult",
    "RepositionOptions",
    "Repositioner",
    "classify_nodes",
]
