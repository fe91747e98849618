"""Relax + smooth: the export's posing path for the pose on screen (runs in the worker thread)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kneegui.meshopt.chain import StageCallback
from kneegui.reposition import Repositioner
from kneegui.reposition.pipeline import PosedModel, pose_model


@dataclass(frozen=True)
class SmoothingOutcome:
    """New coordinates, the export's report and a one-line summary; ``posed`` is what an
    export writes."""

    coords: NDArray[np.float64]
    report: dict[str, Any]
    message: str
    posed: PosedModel


def smooth_current(
    repositioner: Repositioner,
    flexion_deg: float,
    progress: Callable[[float, str], None],
    cancelled: Callable[[], bool],
    stage_done: StageCallback | None = None,
) -> SmoothingOutcome:
    """Pose, relax and smooth the model at ``flexion_deg`` exactly as ``kneegui pose`` does
    (:func:`kneegui.reposition.pipeline.pose_model`), with a status line built from its report;
    ``stage_done(stage, coords)`` gets the pose each stage of the mesh improvement ends on."""
    from app.heatmaps import jacobian_says_something

    posed = pose_model(
        repositioner, flexion_deg, progress=progress, cancel=cancelled, stage_done=stage_done
    )
    message = status_line(posed.report, jacobian_says_something(posed.model))
    return SmoothingOutcome(np.array(posed.model.coords), posed.report, message, posed)


def status_line(report: Mapping[str, Any], jacobian: bool = True) -> str:
    """One line from a :func:`~kneegui.reposition.pipeline.pose_model` report: its warnings
    first (the status bar cuts a long line at the window's edge), then what the relaxation, its
    quality optimisation and the smoother did. The quality optimisation's worst tet collapse
    is quoted when it measured tets, its worst Jacobian when ``jacobian`` (the model has
    elements whose Jacobian is more than its sign) or when there were no tets."""
    parts = []
    relax = report.get("relaxation")
    if relax is not None:
        stages = ""
        quality = relax.get("quality")
        if quality is not None and quality["free_nodes"]:
            figures = []
            before, after = (
                quality.get("collapse_worst_before"),
                quality.get("collapse_worst_after"),
            )
            tets = before is not None and after is not None and np.isfinite([before, after]).all()
            if tets:
                figures.append(f"worst tet collapse {before:.3f} -> {after:.3f}")
            if jacobian or not tets:
                figures.append(
                    f"worst Jacobian {quality['worst_before']:.3f} -> {quality['worst_after']:.3f}"
                )
            beyond = quality.get("beyond_region_nodes", 0)
            if beyond:  # the pass that mends what the mapping degraded far from the joint
                figures.append(f"{beyond} nodes beyond the relaxed region")
            settled = quality.get("bone_settled_nodes", 0)
            if settled:  # tissue the optimisation left in a bone, settled on its own
                figures.append(f"{settled} nodes settled out of a bone")
            held = quality.get("held_nodes", 0)
            if held:  # the untangling left elements inverted: the stage ran around them
                figures.append(f"{held} nodes of inverted elements held")
            stages += ", quality optimised: " + ", ".join(figures)
        parts.append(
            f"relaxed {relax['free_nodes']} nodes ({relax['inverted_corners_before']} "
            f"inverted corners -> {relax['inverted_corners_after']}{stages}, "
            f"{relax['seconds']:.1f} s)"
        )
    smooth = report.get("smoothing")
    if smooth is not None and not smooth["moved_nodes"]:
        parts.append("smoothed: nothing to move")  # no Jacobian before / after to quote
    elif smooth is not None:
        parts.append(
            f"smoothed: {smooth['moved_nodes']} nodes moved, worst Jacobian "
            f"{smooth['worst_jacobian_before']:.3f} -> {smooth['worst_jacobian_after']:.3f}, "
            f"inverted {smooth['inverted_before']} -> {smooth['inverted_after']} "
            f"({smooth['seconds']:.1f} s)"
        )
    message = "; ".join(parts)
    warnings = report.get("warnings") or []
    return f"warning: {'; '.join(warnings)}; {message}" if warnings else message
