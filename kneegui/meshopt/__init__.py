"""Mesh improvement: every stage that moves free nodes to make a posed mesh solver-ready.

The chain, written once in :mod:`~kneegui.meshopt.chain` (:func:`improve_region`, options
:class:`ImprovementOptions`, one dataclass per stage), in the order an export runs it
(ALGORITHM.md §5):

- :mod:`~kneegui.meshopt.foldover` (+ its kernel :mod:`~kneegui.meshopt.foldover_kernel` and
  :mod:`~kneegui.meshopt.lbfgs`): the foldover-free energy and the deterministic L-BFGS that
  untangle inverted elements (:class:`RelaxOptions`);
- :mod:`~kneegui.meshopt.quality_optimiser`: all free nodes moved together until every element
  meets its quality aims (:class:`QualityOptions`);
- :mod:`~kneegui.meshopt.smoother`: connectivity-preserving smoothing of what is still degraded
  (:class:`SmoothOptions`).

The caller (``kneegui.reposition``) gives the region: which nodes are free and what constrains
them. Numba is a dependency: every compiled kernel has a NumPy reference beside it that the
tests compare it with.

Smoothing helpers:

- :func:`smoothing_free_nodes` / :func:`smoothing_sliding_nodes`: which nodes may move.
- :func:`degraded_elements`: the elements to work on (inverted, or below the warn level and
  worse than in the initial model).
- :func:`smooth_mesh`: stage 1 guarded Laplacian moves + stage 2 Nelder-Mead per node.
- :func:`smooth_posed_model`: all of the above for a posed model and its roles.
"""

from kneegui.meshopt.chain import (
    ImprovementOptions,
    ImprovementRegion,
    ImprovementReport,
    improve_region,
)
from kneegui.meshopt.foldover import RelaxOptions, RelaxReport
from kneegui.meshopt.free_nodes import (
    MOVABLE_SOLID_TYPES,
    degraded_elements,
    smoothing_free_nodes,
    smoothing_sliding_nodes,
)
from kneegui.meshopt.quality_optimiser import QualityOptions
from kneegui.meshopt.smoother import (
    SMOOTHED_TYPES,
    SmoothingReport,
    SmoothOptions,
    corner_quality,
    smooth_mesh,
)
from kneegui.meshopt.smoothing_pipeline import smooth_posed_model

__all__ = [
    "MOVABLE_SOLID_TYPES",
    "SMOOTHED_TYPES",
    "ImprovementOptions",
    "ImprovementRegion",
    "ImprovementReport",
    "QualityOptions",
    "RelaxOptions",
    "RelaxReport",
    "SmoothOptions",
    "SmoothingReport",
    "corner_quality",
    "degraded_elements",
    "improve_region",
    "smooth_mesh",
    "smooth_posed_model",
    "smoothing_free_nodes",
    "smoothing_sliding_nodes",
]
