"""Mesh quality: per-element metrics (QUALITY.md), statistics, thresholds and the quality table."""

from kneegui.quality.metrics import (
    MEASURED_TYPES,
    METRICS,
    ElementQuality,
    QualityEvaluator,
    QualityResult,
    compute_quality,
    element_quality,
)

__all__ = [
    "MEASURED_TYPES",
    "METRICS",
    "ElementQuality",
    "QualityEvaluator",
    "QualityResult",
    "compute_quality",
    "element_quality",
]
