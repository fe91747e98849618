"""Smoothing the current pose through the engine (runs in the worker thread)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import SetupError
from kneegui.model import Model
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
) -> SmoothingOutcome:
    """Smooth the soft tissue of ``model`` at ``coords`` around its degraded elements."""
    from kneegui.smoothing.pipeline import smooth_posed_model

    if setup is None:
        raise SetupError("smoothing needs a valid setup (roles say which parts may move)")
    posed = model.with_coords(coords)
    smoothed, report = smooth_posed_model(
        posed,
        setup.parts_of(*SOFT_ROLES),
        setup.parts_of(*FIXED_ROLES),
        initial=model,
        progress=progress,
        cancel=cancelled,
    )
    message = (
        f"smoothed: {report.moved_nodes} nodes moved, worst Jacobian "
        f"{report.worst_jacobian_before:.3f} -> {report.worst_jacobian_after:.3f}, inverted "
        f"{report.inverted_before} -> {report.inverted_after} ({report.seconds:.1f} s)"
    )
    return SmoothingOutcome(np.array(smoothed.coords), report, message)
