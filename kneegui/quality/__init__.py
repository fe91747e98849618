"""Mesh quality: per-element metrics (QUALITY.md), statistics, thresholds and the quality table.

- :func:`compute_quality` / :class:`QualityEvaluator`: per-element Jacobians (corner and Gauss),
  aspect ratio, warpage, skew, signed volume and inverted masks; on tetrahedra also the tet
  collapse, dihedral angles, volumetric skew and tet aspect ratio (10-node tets: mid-side
  offsets), docs/quality.md.
- :func:`summarize_quality`: worst / mean / std / warn / fail per model, part and role, and the
  change against the initial pose; :func:`format_quality_table` prints it like the paper's Table I.
- :func:`load_thresholds`: the warn / fail table in ``resources/quality_thresholds.csv``.
- :func:`volume_change_pct` / :func:`volume_change`: element volume change against the initial
  pose, with the one rule for a zero initial volume.
- :mod:`kneegui.quality.kernels`: the per-type kernels and the one corner-determinant code.
"""

from kneegui.quality.metrics import (
    MEASURED_TYPES,
    METRICS,
    TET_ONLY_METRICS,
    ElementQuality,
    QualityEvaluator,
    QualityResult,
    compute_quality,
    element_quality,
)
from kneegui.quality.summary import (
    format_quality_table,
    jsonable,
    quality_gate,
    summarize_quality,
    summary_metrics,
)
from kneegui.quality.thresholds import (
    TET_THRESHOLD_METRICS,
    THRESHOLD_METRICS,
    MetricThreshold,
    Thresholds,
    ThresholdsError,
    load_thresholds,
)
from kneegui.quality.volume import volume_change, volume_change_pct

__all__ = [
    "MEASURED_TYPES",
    "METRICS",
    "TET_ONLY_METRICS",
    "TET_THRESHOLD_METRICS",
    "THRESHOLD_METRICS",
    "ElementQuality",
    "MetricThreshold",
    "QualityEvaluator",
    "QualityResult",
    "Thresholds",
    "ThresholdsError",
    "compute_quality",
    "element_quality",
    "format_quality_table",
    "jsonable",
    "load_thresholds",
    "quality_gate",
    "summarize_quality",
    "summary_metrics",
    "volume_change",
    "volume_change_pct",
]
