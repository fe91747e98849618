"""Relaxing and smoothing the current pose through the engine (runs in the worker thread)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import SetupError
from kneegui.model import Model
from kneegui.reposition.relax import RelaxReport
from kneegui.setup import JointSetup

SOFT_ROLES = ("flesh", "ligament", "meniscus", "tendon", "capsule")
FIXED_ROLES = ("femur", "tibia", "fibula", "patella", "fixed")


@dataclass(frozen=True)
class SmoothingOutcome:
    """New coordinates and a one-line summary."""

    coords: NDArray[np.float64]
    report: object
    message: str


def smooth_current(
    model: Model,
    coords: NDArray[np.float64],
    setup: JointSetup | None,
    progress: Callable[[float, str], None],
    cancelled: Callable[[], bool],
    relax: Callable[..., tuple[NDArray[np.float64], RelaxReport]] | None = None,
    bone_guard: Callable[[NDArray[np.float64]], Callable[..., NDArray[np.bool_]]] | None = None,
) -> SmoothingOutcome:
    """Relax (``relax(coords, progress, cancelled)``, e.g. a bound
    :meth:`kneegui.reposition.Repositioner.relax`) and smooth the soft tissue of ``model`` at
    ``coords`` around its degraded elements; ``bone_guard(coords)`` (e.g.
    :meth:`kneegui.reposition.Repositioner.bone_depth_guard` at the pose's flexion) gives the
    smoother's position guard that keeps the tissue out of the bones."""
    from kneegui.meshopt.smoothing_pipeline import smooth_posed_model

    if setup is None:
        raise SetupError("smoothing needs a valid setup (roles say which parts may move)")
    relaxed = ""
    if relax is not None:

        def relax_progress(fraction: float, message: str) -> None:
            progress(0.6 * fraction, message)

        coords, relax_report = relax(coords, relax_progress, cancelled)
        stages = ""
        quality = relax_report.quality
        if quality is not None and quality.free_nodes:
            stages += (
                f", quality optimised: worst Jacobian {quality.worst_before:.3f} -> "
                f"{quality.worst_after:.3f}"
            )
        done = relax_report.polish
        if done is not None and done.moved_nodes:
            stages += (
                f", polish: worst Jacobian {done.worst_jacobian_before:.3f} -> "
                f"{done.worst_jacobian_after:.3f}"
            )
        relaxed = (
            f"relaxed {relax_report.free_nodes} nodes ({relax_report.inverted_corners_before} "
            f"inverted corners -> {relax_report.inverted_corners_after}{stages}, "
            f"{relax_report.seconds:.1f} s); "
        )

    def smooth_progress(fraction: float, message: str) -> None:
        progress(0.6 + 0.4 * fraction if relax is not None else fraction, message)

    posed = model.with_coords(coords)
    smoothed, report = smooth_posed_model(
        posed,
        setup.parts_of(*SOFT_ROLES),
        setup.parts_of(*FIXED_ROLES),
        initial=model,
        progress=smooth_progress,
        cancel=cancelled,
        position_guard=None if bone_guard is None else bone_guard(coords),
    )
    message = relaxed + (
        f"smoothed: {report.moved_nodes} nodes moved, worst Jacobian "
        f"{report.worst_jacobian_before:.3f} -> {report.worst_jacobian_after:.3f}, inverted "
        f"{report.inverted_before} -> {report.inverted_after} ({report.seconds:.1f} s)"
    )
    return SmoothingOutcome(np.array(smoothed.coords), report, message)
