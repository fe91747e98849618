"""Deck-to-deck posing: pose, measure, smooth, gate and report (what ``kneegui pose`` runs)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from kneegui.model import Model
from kneegui.quality import (
    compute_quality,
    jsonable,
    quality_gate,
    summarize_quality,
    volume_change_pct,
)
from kneegui.quality.metrics import QualityResult
from kneegui.reposition.bone_overlap import BONE_OVERLAP_TOLERANCE
from kneegui.reposition.repositioner import SOFT_ROLES, Repositioner, tissue_in_bones_warnings
from kneegui.topology import SOLID_TYPES

ProgressCallback = Callable[[float, str], None]


@dataclass(frozen=True)
class PosedModel:
    """A posed (and possibly smoothed) model with its report."""

    model: Model
    report: dict[str, Any]
    gate_reasons: list[str]

    @property
    def passes_gate(self) -> bool:
        """True when the quality gate found nothing wrong."""
        return not self.gate_reasons


def _stats(model: Model, result: QualityResult) -> dict[str, Any]:
    return summarize_quality(model, result)["model"]


#: Thresholds (percent) over which the report counts soft-tissue solids by volume change; 3.8 is
#: the largest element change the paper reports at 90 deg.
VOLUME_CHANGE_COUNTS_PCT = (3.8, 10.0, 25.0)


def _volume_change(
    model: Model, result: QualityResult, initial: QualityResult, soft_parts: set[int]
) -> dict[str, Any]:
    """Largest element volume change (all solids), how the soft-tissue solids' changes are
    distributed (median, 95th percentile, counts over :data:`VOLUME_CHANGE_COUNTS_PCT`), and
    the total change of the soft-tissue solids."""
    max_pct, max_id, soft_now, soft_before = 0.0, None, 0.0, 0.0
    soft_abs: list[np.ndarray] = []
    for etype in SOLID_TYPES:
        if etype not in result or etype not in initial:
            continue
        v, v0 = result[etype].volume, initial[etype].volume
        block = model.blocks[etype]
        pct = volume_change_pct(v, v0)
        if len(pct):
            k = int(np.argmax(np.abs(pct)))
            if abs(pct[k]) > abs(max_pct):
                max_pct, max_id = float(pct[k]), int(block.ids[result[etype].rows[k]])
        soft = np.isin(block.part_ids[result[etype].rows], list(soft_parts))
        soft_abs.append(np.abs(pct[soft]))
        soft_now += float(v[soft].sum())
        soft_before += float(v0[soft].sum())
    total = 100.0 * (soft_now - soft_before) / soft_before if soft_before else None
    changes = np.concatenate(soft_abs) if soft_abs else np.zeros(0)
    has = len(changes) > 0
    return {
        "max_element_pct": max_pct,
        "max_element_id": max_id,
        "soft_tissue_total_pct": total,
        "soft_element_median_abs_pct": float(np.median(changes)) if has else None,
        "soft_element_p95_abs_pct": float(np.percentile(changes, 95)) if has else None,
        "soft_elements_over_pct": {
            f"{t:g}": int(np.sum(changes > t)) for t in VOLUME_CHANGE_COUNTS_PCT
        },
        "soft_elements": len(changes),
    }


def pose_model(
    repositioner: Repositioner,
    flexion_deg: float,
    *,
    smooth: bool = True,
    progress: ProgressCallback | None = None,
    cancel: Callable[[], bool] | None = None,
) -> PosedModel:
    """Pose the model, check its quality, smooth what degraded, and report.

    Parameters
    ----------
    repositioner : Repositioner
        Precomputed for the model and setup.
    flexion_deg : float
        Target flexion (degrees).
    smooth : bool
        Run the connectivity-preserving smoother on degraded soft-tissue elements.
    progress, cancel : callable, optional
        ``progress(fraction, message)``; ``cancel()`` returns True to stop (raises
        :class:`kneegui.errors.Cancelled`).

    Returns
    -------
    PosedModel
        The model with new coordinates (ids and connectivity unchanged) and the report: initial /
        target / achieved flexion, quality (initial, posed — after the relaxation when the
        repositioner's options ask for it —, smoothed), what the relaxation did, volume change,
        gate, timings.
    """
    report_progress = progress or (lambda fraction, message: None)
    model, setup = repositioner.model, repositioner.setup
    timings: dict[str, float] = {}
    t = time.perf_counter()
    initial_q = compute_quality(model.coords, model.blocks)
    timings["quality_initial"] = time.perf_counter() - t
    report_progress(0.05, "posing")

    def relax_progress(fraction: float, message: str) -> None:
        report_progress(0.05 + 0.45 * fraction, message)

    result = repositioner.pose_detailed(flexion_deg, progress=relax_progress, cancel=cancel)
    timings["pose"] = result.timings_s["total"]
    posed = model.with_coords(result.coords)
    t = time.perf_counter()
    posed_q = compute_quality(posed.coords, posed.blocks)
    timings["quality_posed"] = time.perf_counter() - t
    soft_parts = set(setup.parts_of(*SOFT_ROLES))
    quality: dict[str, Any] = {"initial": _stats(model, initial_q), "posed": _stats(posed, posed_q)}
    final, final_q = posed, posed_q
    smoothing = None
    if smooth:
        from kneegui.meshopt.smoothing_pipeline import smooth_posed_model

        def smoothing_progress(fraction: float, message: str) -> None:
            report_progress(0.5 + 0.45 * fraction, message)

        t = time.perf_counter()
        fixed_parts = set(setup.parts_of("femur", "tibia", "fibula", "patella", "fixed"))
        fixed_parts |= set(setup.unassigned_parts)
        movable = soft_parts - set(setup.parts_of("skin"))
        final, smooth_report = smooth_posed_model(
            posed,
            sorted(movable),
            sorted(fixed_parts),
            initial_q,
            progress=smoothing_progress,
            cancel=cancel,
            position_guard=repositioner.bone_depth_guard(posed.coords, result.bone_pose),
        )
        timings["smoothing"] = time.perf_counter() - t
        final_q = compute_quality(final.coords, final.blocks)
        quality["smoothed"] = _stats(final, final_q)
        smoothing = smooth_report.to_dict()
    summary = summarize_quality(final, final_q, initial=initial_q)
    reasons = quality_gate(summary)
    overlaps = repositioner.bone_overlap(result.bone_pose)
    # a bone reaching into another deeper than it did at rest: the kinematics do not suit
    # these bones (axes, landmarks or tables), and tissue between them is crushed
    warnings = [o.describe() for o in overlaps if o.added_depth > BONE_OVERLAP_TOLERANCE]
    t = time.perf_counter()
    in_bones = repositioner.tissue_in_bones(final.coords, result.bone_pose)
    timings["tissue_in_bones"] = time.perf_counter() - t
    warnings += tissue_in_bones_warnings(in_bones)
    report = {
        "method": repositioner.options.method,
        "initial_flexion": repositioner.initial_flexion,
        "target_flexion": float(flexion_deg),
        "achieved_flexion": result.achieved_flexion_deg,
        "quality": quality,
        "volume_change": _volume_change(final, final_q, initial_q, soft_parts),
        "gate": {"passed": not reasons, "reasons": reasons},
        "relaxation": None if result.relaxation is None else result.relaxation.to_dict(),
        "smoothing": smoothing,
        "skin": None
        if result.skin is None
        else {
            "half_angle_deg": result.skin.half_angle_deg,
            "scale_capped_nodes": result.skin.scaled_capped,
            "penetrations_fixed": result.skin.penetrations_fixed,
        },
        "tissue_in_bones": in_bones,
        "bones": {
            "fe_rotation_deg": result.bone_pose.fe_rotation_deg,
            "tibial_rotation_deg": result.bone_pose.tibial_rotation_deg,
            "patellar_flexion_deg": result.bone_pose.patellar_flexion_deg,
            "patellar_tilt_deg": result.bone_pose.patellar_tilt_deg,
            "patellar_lift": result.bone_pose.patellar_lift,
            "overlap": [o.to_dict() for o in overlaps if o.depth > 0 or o.rest_depth > 0],
        },
        "warnings": warnings,
        "timings_s": {**{f"pose_{k}": v for k, v in result.timings_s.items()}, **timings},
    }
    report_progress(1.0, "done")
    return PosedModel(final, jsonable(report), reasons)
