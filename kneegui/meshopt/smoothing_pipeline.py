"""Smoothing a posed model in one call: degraded elements -> free nodes -> smoother."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import raise_if_cancelled
from kneegui.meshopt.free_nodes import (
    degraded_elements,
    smoothing_free_nodes,
    smoothing_sliding_nodes,
)
from kneegui.meshopt.smoother import (
    CancelCallback,
    PositionGuard,
    ProgressCallback,
    SmoothingReport,
    SmoothOptions,
    smooth_mesh,
)
from kneegui.model import Model
from kneegui.quality.metrics import QualityResult, compute_quality
from kneegui.quality.thresholds import JACOBIAN_WARN


def smoothing_goals(
    initial: QualityResult, threshold: float = JACOBIAN_WARN, tolerance: float = 0.02
) -> dict[str, NDArray[np.float64]]:
    """Each element's quality goal for :func:`kneegui.meshopt.smooth_mesh`: ``threshold``, or
    its initial corner Jacobian less ``tolerance`` if that is lower (an element that starts
    poor is brought back to where it was, not above)."""
    return {
        etype: np.minimum(threshold, np.maximum(q.jacobian_corner - tolerance, 0.0))
        for etype, q in initial.by_type.items()
    }


def smooth_posed_model(
    posed: Model,
    soft_tissue_part_ids: Iterable[int],
    fixed_part_ids: Iterable[int] = (),
    initial: Model | QualityResult | None = None,
    *,
    threshold: float = JACOBIAN_WARN,
    tolerance: float = 0.02,
    skin_part_ids: Iterable[int] = (),
    options: SmoothOptions | None = None,
    position_guard: PositionGuard | None = None,
    progress: ProgressCallback | None = None,
    cancel: CancelCallback | None = None,
    quality: QualityResult | None = None,
) -> tuple[Model, SmoothingReport]:
    """Smooth the soft tissue of a posed model around its degraded elements.

    Parameters
    ----------
    posed : Model
        The posed model (not modified).
    soft_tissue_part_ids : iterable of int
        Parts that may be smoothed (flesh, ligament, meniscus, tendon, capsule).
    fixed_part_ids : iterable of int
        Parts whose nodes never move (bones, fixed parts).
    initial : Model or QualityResult, optional
        The initial model (or its quality): an element counts as degraded only if it got worse.
    threshold : float
        Corner-Jacobian level below which an element counts as degraded. The smoother's goal
        for each element is this level, or the element's initial Jacobian if that was lower
        (an element that starts invalid aims at being valid).
    tolerance : float
        Loss of corner Jacobian against the initial model that is ignored (both for finding
        the degraded elements and for the goals).
    skin_part_ids : iterable of int
        Skin parts (shells sharing the flesh's surface nodes), used with
        ``options.slide_skin``.
    options : SmoothOptions, optional
        The smoother's parameters and the region's (``rings``, ``slide_skin``,
        ``soft_interfaces``).
    position_guard, progress, cancel : callable, optional
        See :func:`kneegui.meshopt.smooth_mesh`.
    quality : QualityResult, optional
        The quality of ``posed`` (every element) when the caller has it already.

    Returns
    -------
    model : Model
        A new model with smoothed coordinates (same ids and connectivity).
    report : SmoothingReport
    """
    opt = options or SmoothOptions()
    soft = list(soft_tissue_part_ids)
    fixed = list(fixed_part_ids)
    if quality is None:
        quality = compute_quality(posed.coords, posed.blocks)
    raise_if_cancelled(cancel, "smoothing cancelled")
    initial_quality = (
        compute_quality(initial.coords, initial.blocks) if isinstance(initial, Model) else initial
    )
    degraded = degraded_elements(quality, initial_quality, threshold, tolerance)
    raise_if_cancelled(cancel, "smoothing cancelled")
    free = smoothing_free_nodes(
        posed, soft, fixed, degraded, opt.rings, opt.soft_interfaces, cancel=cancel
    )
    raise_if_cancelled(cancel, "smoothing cancelled")
    sliding = None
    if opt.slide_skin:
        sliding = smoothing_sliding_nodes(posed, soft, skin_part_ids, fixed, degraded, opt.rings)
    goals: dict[str, NDArray[np.float64]] | float = threshold
    if initial_quality is not None:
        goals = smoothing_goals(initial_quality, threshold, tolerance)
    coords, report = smooth_mesh(
        posed.coords,
        posed.blocks,
        free,
        sliding_nodes=sliding,
        target=goals,
        options=opt,
        position_guard=position_guard,
        progress=progress,
        cancel=cancel,
    )
    return posed.with_coords(coords), report
