"""The export: pose, relax, measure, smooth, gate and report.

:func:`pose_model` is the one posing path that writes a pose: ``kneegui pose``, the GUI's
Relax + smooth, the benchmarks and the scripts all call it, so they choose the fixed parts,
solve the bones and word the warnings the same way.
"""

from __future__ import annotations

from kneegui.reproducible import dispatch_state

import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import raise_if_cancelled
from kneegui.geometry.axes import measure_flexion
from kneegui.io.lsdyna import write_deck
from kneegui.meshopt.chain import StageCallback
from kneegui.model import ElementBlock, Model
from kneegui.quality import (
    compute_quality,
    jsonable,
    quality_gate,
    summarize_quality,
    volume_change_pct,
)
from kneegui.quality.metrics import METRICS, ElementQuality, QualityResult
from kneegui.quality.summary import GATE_NAMES
from kneegui.reposition.bone_overlap import BONE_OVERLAP_TOLERANCE, BoneOverlap
from kneegui.reposition.preflight import Preflight, preflight_of
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


def requalify(
    previous: QualityResult,
    previous_coords: NDArray[np.float64],
    coords: NDArray[np.float64],
    blocks: Mapping[str, ElementBlock],
) -> QualityResult:
    """The quality at ``coords`` from the quality at ``previous_coords``: only the elements
    with a node that moved are measured again (the smoothing moves a few thousand nodes of a
    model that may have millions), the others keep their values. Same values as measuring
    every element.

    Parameters
    ----------
    previous : QualityResult
        Quality at ``previous_coords`` (full blocks or rows, as measured).
    previous_coords, coords : (N, 3) ndarray
        Coordinates before and after.
    blocks : mapping of str to ElementBlock
    """
    moved = np.any(previous_coords != coords, axis=1)
    rows = {}
    for etype, q in previous.by_type.items():
        changed = moved[blocks[etype].conn[q.rows]].any(axis=1)
        rows[etype] = np.flatnonzero(changed)
    fresh = compute_quality(
        coords, blocks, rows={e: previous[e].rows[r] for e, r in rows.items() if len(r)}
    )
    out = {}
    for etype, q in previous.by_type.items():
        r = rows[etype]
        if len(r) == 0:
            out[etype] = q
            continue
        values = {name: getattr(q, name).copy() for name in (*METRICS, "inverted")}
        for name in values:
            values[name][r] = getattr(fresh[etype], name)
        out[etype] = ElementQuality(etype=etype, rows=q.rows, **values)
    return QualityResult(out)


def pose_warnings(
    overlaps: list[BoneOverlap], in_bones: dict[str, Any], length_scale: float = 1.0
) -> list[str]:
    """The pose's warnings, one line each (the report's, the CLI's and the GUI's status line):
    a bone reaching into another deeper than it did at rest by more than
    :data:`BONE_OVERLAP_TOLERANCE` times ``length_scale`` (the kinematics do not suit these
    bones: axes, landmarks or tables, and tissue between them is crushed), then each bone with
    soft tissue inside it."""
    tolerance = BONE_OVERLAP_TOLERANCE * length_scale
    warnings = [o.describe() for o in overlaps if o.added_depth > tolerance]
    return warnings + tissue_in_bones_warnings(in_bones)


#: Element ids a gate reason or warning names before "and N more" (the report lists them all).
NAMED_IDS = 12


def _id_list(ids: list[int]) -> str:
    shown = ", ".join(str(i) for i in ids[:NAMED_IDS])
    return shown + (f" and {len(ids) - NAMED_IDS} more" if len(ids) > NAMED_IDS else "")


def split_gate_reasons(reasons: list[str], inverted: dict[str, Any]) -> list[str]:
    """The gate's reasons with its inverted-element count split into movable elements (the
    repositioner's to fix) and locked ones (tied to bones the kinematics move apart), each
    named by id (:meth:`Preflight.split_inverted`)."""
    if not inverted["total"]:
        return reasons
    split = [
        f"{inverted[key]} {label} ({_id_list(inverted[f'{key}_ids'])})"
        for key, label in (
            ("movable", "movable"),
            ("locked", "locked between segments"),
            ("other", "rigid with one segment"),
        )
        if inverted[key]
    ]
    head = f"{inverted['total']} inverted element(s)"
    return [f"{head}: {', '.join(split)}" if r == head else r for r in reasons]


def name_worst_elements(
    reasons: list[str],
    summary: Mapping[str, Any],
    model: Model,
    quality: QualityResult,
    preflight: Preflight,
) -> list[str]:
    """The gate's reasons with each worst measure's element named, and whether the
    repositioner may move it (:meth:`Preflight.kind_of`): ``worst Jacobian 0.225 is below the
    initial model's 0.330 (element 5156, locked between segments)``. A locked element's
    shape is the kinematics', not the repositioner's doing."""
    directions = summary.get("thresholds", {}).get("*", {})
    labels = {"jacobian": "Jacobian", **GATE_NAMES}
    out = []
    for reason in reasons:
        name = next(
            (m for m, label in labels.items() if reason.startswith(f"worst {label} ")), None
        )
        low_bad = name == "jacobian" or directions.get(name, {}).get("direction") == "min"
        best = None
        for etype in quality if name is not None else ():
            q = quality[etype]
            if not len(q) or not q.has(name):
                continue
            values = q.metric(name)
            if np.isnan(values).all():
                continue
            k = int(np.nanargmin(values) if low_bad else np.nanargmax(values))
            value = float(values[k]) if low_bad else -float(values[k])
            if best is None or value < best[0]:
                best = (value, etype, int(q.rows[k]))
        if best is None:
            out.append(reason)
            continue
        _, etype, row = best
        element = int(model.blocks[etype].ids[row])
        out.append(f"{reason} (element {element}, {preflight.kind_of(etype, row)})")
    return out


def locked_inverted_warning(
    inverted: dict[str, Any], preflight: Preflight, locked_corners: int = 0
) -> list[str]:
    """The warning for locked elements a pose inverts: not the repositioner's failure (no stage
    may move their nodes), named with the flexion range the pre-flight check found valid, and
    the corners of such elements the relaxation left out of its energy (``locked_corners``,
    :class:`~kneegui.reposition.relax.LockedCorners`)."""
    if not inverted["locked"]:
        return []
    lo, hi = preflight.valid_range_deg()
    left_out = (
        f"; the relaxation left {locked_corners} corner(s) of those with free nodes out of its "
        "energy (their free nodes cannot save them at this pose)"
        if locked_corners
        else ""
    )
    return [
        f"{inverted['locked']} locked element(s) inverted (nodes tied to bones the kinematics "
        f"move apart, and no free node that could save them; ids "
        f"{_id_list(inverted['locked_ids'])}); the pre-flight check finds every locked "
        f"element valid only from {lo:.1f} to {hi:.1f} deg{left_out}"
    ]


def pose_model(
    repositioner: Repositioner,
    flexion_deg: float,
    *,
    smooth: bool = True,
    progress: ProgressCallback | None = None,
    cancel: Callable[[], bool] | None = None,
    stage_done: StageCallback | None = None,
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
    stage_done : callable, optional
        ``stage_done(stage, coords)`` with the whole pose after each stage of the mesh
        improvement that another follows (:meth:`Repositioner.improve`): a window shows the
        untangled pose while the quality stage runs. It cannot change the result.

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
    initial_q = repositioner.initial_quality(cancel)  # once per setup
    timings["quality_initial"] = time.perf_counter() - t
    # the first export measures the initial model (1.6 s at 1.76M nodes), then poses (1.5 s)
    raise_if_cancelled(cancel, "export cancelled before posing")
    report_progress(0.05, "posing")

    def improve_progress(fraction: float, message: str) -> None:
        report_progress(0.05 + 0.9 * fraction, message)

    result = repositioner.pose_detailed(flexion_deg, remeasure=False, relax=False)
    coords, improved = repositioner.improve(
        result.coords,
        result.bone_pose,
        relax=repositioner.options.relax,
        smooth=smooth,
        progress=improve_progress,
        cancel=cancel,
        stage_done=stage_done,
    )
    relaxation, smoothing = improved.relaxation, improved.smoothing

    def measuring(step: str) -> None:
        # the report's measures take seconds on a whole-body model (the 1M demo: 4 s)
        raise_if_cancelled(cancel, f"export cancelled while {step}")
        report_progress(0.95, "measuring the pose")

    measuring("measuring the flexion")
    achieved = measure_flexion(improved.relaxed, setup)
    # the mapping's stages (pose_bones, pose_blend, ...) and the relaxation's, as before
    if relaxation is not None:  # no key when nothing was relaxed (reports read it as absent)
        timings["pose_relax"] = relaxation.seconds
        # finding the region to relax, within pose_relax
        timings["relax_region"] = relaxation.region_seconds + (
            relaxation.quality.region_seconds if relaxation.quality is not None else 0.0
        )
    correction = improved.volume_correction
    if correction is not None:
        timings["volume_correction"] = correction.seconds
    timings["pose"] = (
        result.timings_s["total"]
        + timings.get("pose_relax", 0.0)
        + timings.get("volume_correction", 0.0)
    )
    posed = model.with_coords(improved.relaxed)
    measuring("measuring the quality")
    t = time.perf_counter()
    posed_q = repositioner.quality_of(posed.coords, cancel)  # the smoothing measured it already
    timings["quality_posed"] = time.perf_counter() - t
    soft_parts = set(setup.parts_of(*SOFT_ROLES))
    quality: dict[str, Any] = {"initial": _stats(model, initial_q), "posed": _stats(posed, posed_q)}
    final, final_q = posed, posed_q
    if smoothing is not None:
        timings["smoothing"] = smoothing.seconds
        final = model.with_coords(coords)
        t = time.perf_counter()
        final_q = requalify(posed_q, posed.coords, final.coords, final.blocks)
        timings["quality_smoothed"] = time.perf_counter() - t
        quality["smoothed"] = _stats(final, final_q)
    measuring("summarising the quality")
    summary = summarize_quality(final, final_q, initial=initial_q)
    measuring("running the pre-flight check")
    t = time.perf_counter()
    preflight = preflight_of(repositioner, cancel)  # run once per repositioner
    timings["preflight"] = time.perf_counter() - t
    inverted = preflight.split_inverted(final, final_q)
    reasons = split_gate_reasons(quality_gate(summary), inverted)
    reasons = name_worst_elements(reasons, summary, final, final_q, preflight)
    measuring("measuring the bones' overlap")
    overlaps = repositioner.bone_overlap(result.bone_pose)
    measuring("measuring the tissue in the bones")
    t = time.perf_counter()
    in_bones = repositioner.tissue_in_bones(final.coords, result.bone_pose)
    timings["tissue_in_bones"] = time.perf_counter() - t
    measuring("writing the report")
    locked_corners = 0 if relaxation is None else relaxation.locked_corners
    warnings = locked_inverted_warning(inverted, preflight, locked_corners) + pose_warnings(
        overlaps, in_bones, repositioner.length_scale
    )
    report = {
        "method": repositioner.options.method,
        "initial_flexion": repositioner.initial_flexion,
        "target_flexion": float(flexion_deg),
        "achieved_flexion": float(achieved),
        "quality": quality,
        "volume_change": _volume_change(final, final_q, initial_q, soft_parts),
        "gate": {"passed": not reasons, "reasons": reasons},
        "inverted": inverted,
        "preflight": preflight.to_dict(pair_ids=False),
        "axis_sensitivity": None
        if repositioner.axes.sensitivity is None
        else repositioner.axes.sensitivity.to_dict(),
        "volume_correction": None if correction is None else asdict(correction),
        "relaxation": None if relaxation is None else relaxation.to_dict(),
        "smoothing": None if smoothing is None else smoothing.to_dict(),
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
        "numerics": dispatch_state(),
        "timings_s": {**{f"pose_{k}": v for k, v in result.timings_s.items()}, **timings},
    }
    report_progress(1.0, "done")
    return PosedModel(final, jsonable(report), reasons)


def angle_tag(deg: float) -> str:
    """The angle as it appears in an output name (``37.5`` -> ``37p5``, ``-5`` -> ``m5``)."""
    return f"{deg:g}".replace("-", "m").replace(".", "p")


def export_pose(
    repositioner: Repositioner,
    flexion_deg: float,
    out: str | Path,
    *,
    model_path: str | Path,
    smooth: bool = True,
    force: bool = False,
    flatten: bool = False,
    overwrite: bool = False,
    context_timings: dict[str, float] | None = None,
    progress: ProgressCallback | None = None,
    cancel: Callable[[], bool] | None = None,
) -> PosedModel:
    """Pose one angle with :func:`pose_model` and write the posed deck: the export step that
    ``kneegui pose``, ``kneegui batch`` and the GUI's export share.

    Parameters
    ----------
    repositioner : Repositioner
        Precomputed for the model and setup.
    flexion_deg : float
        Target flexion (degrees).
    out : str or Path
        The posed deck; its includes are written beside it.
    model_path : str or Path
        The deck the model was read from (recorded in the report).
    smooth : bool
        Run the smoother after the relaxation.
    force : bool
        Write the deck even when the pose fails the quality gate.
    flatten : bool
        Inline every ``*INCLUDE`` into one file.
    overwrite : bool
        Replace existing files beside ``out`` that the write would otherwise refuse to touch
        (:mod:`kneegui.io.output_plan`: another deck's includes, files the user did not name).
    context_timings : dict, optional
        Timings of the caller's stages (read, setup, precompute) added to the report's.
    progress, cancel : callable, optional
        As for :func:`pose_model`; the write is the last 5 % of the progress. The write asks
        ``cancel()`` too; a cancel during it leaves nothing written.

    Returns
    -------
    PosedModel
        Its report has ``model`` (absolute path) and ``written`` (the files written, none when
        the gate failed without ``force``). The report file is the caller's to write.
    """
    report_progress = progress or (lambda fraction, message: None)

    def pose_progress(fraction: float, message: str) -> None:
        report_progress(0.95 * fraction, message)

    posed = pose_model(
        repositioner, flexion_deg, smooth=smooth, progress=pose_progress, cancel=cancel
    )
    report = posed.report
    report["timings_s"].update(context_timings or {})
    report["model"] = str(Path(model_path).resolve())
    written = []
    if posed.passes_gate or force:
        raise_if_cancelled(cancel, "export cancelled before writing the deck")  # nothing written
        report_progress(0.95, "writing the deck")
        t = time.perf_counter()
        written = write_deck(posed.model, out, flatten=flatten, overwrite=overwrite, cancel=cancel)
        report["timings_s"]["write"] = time.perf_counter() - t
    report["written"] = [str(p) for p in written]
    report_progress(1.0, "written")
    return posed
