"""Connectivity-preserving smoothing of the soft tissue after posing (ALGORITHM.md §5).

- :func:`smoothing_free_nodes` / :func:`smoothing_sliding_nodes`: which nodes may move.
- :func:`degraded_elements`: the elements to work on (inverted, or below the warn level and
  worse than in the initial model).
- :func:`smooth_mesh`: stage 1 guarded Laplacian moves + stage 2 Nelder-Mead per node.
- :func:`smooth_posed_model`: all of the above for a posed model and its roles.
"""

from kneegui.smoothing.free_nodes import (
    MOVABLE_SOLID_TYPES,
    degraded_elements,
    smoothing_free_nodes,
    smoothing_sliding_nodes,
)
from kneegui.smoothing.pipeline import smooth_posed_model
from kneegui.smoothing.smoother import (
    SMOOTHED_TYPES,
    SmoothingReport,
    corner_quality,
    smooth_mesh,
)

__all__ = [
    "MOVABLE_SOLID_TYPES",
    "SMOOTHED_TYPES",
    "SmoothingReport",
    "corner_quality",
    "degraded_elements",
    "smooth_mesh",
    "smooth_posed_model",
    "smoothing_free_nodes",
    "smoothing_sliding_nodes",
]
