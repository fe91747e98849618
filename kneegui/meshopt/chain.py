"""The mesh-improvement chain, written once: untangle, then meet the quality aims, then smooth.

A posed mesh is made solver-ready by three stages, each with its own options:

1. **untangle** (:class:`~kneegui.meshopt.foldover.RelaxOptions`): the foldover-free energy
   (:mod:`kneegui.meshopt.foldover`) over the degraded region, until no corner is inverted;
   when stage 2 follows it stops as soon as nothing is inverted;
2. **quality** (:class:`~kneegui.meshopt.quality_optimiser.QualityOptions`, ``None`` skips it):
   every node around an element that misses its aims moves, all together
   (:func:`~kneegui.meshopt.quality_optimiser.optimise_quality`); it runs on an untangled
   region, or (``QualityOptions.hold_inverted``) on one the untangling left with elements
   inverted, around what is past its constraints, their nodes held where they are;
3. **smooth** (:class:`~kneegui.meshopt.smoother.SmoothOptions`, ``None`` skips it): the
   quality-guarded smoother on what is still degraded (:func:`~kneegui.meshopt.smooth_mesh`).

The region (which nodes are free, which constraints hold them: bone contact, skin order, a
position guard) is the caller's: :func:`improve_region` takes it as an :class:`ImprovementRegion`,
so that ``kneegui.reposition`` only says where and how tissue may move, and this module says in
which order and with what.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from kneegui.meshopt.foldover import RelaxOptions, RelaxReport
from kneegui.meshopt.quality_optimiser import QualityOptimisationReport, QualityOptions
from kneegui.meshopt.smoother import SmoothingReport, SmoothOptions
from kneegui.meshopt.volume_correction import VolumeCorrectionReport

ProgressCallback = Callable[[float, str], None]
CancelCallback = Callable[[], bool]
#: ``stage_done(stage, coords)``: a stage ended and another follows; ``coords`` (N, 3) is the
#: whole pose after it (a copy the callee may keep). Stages: ``"untangle"``, ``"quality"``.
StageCallback = Callable[[str, NDArray[np.float64]], None]


def _export_quality() -> QualityOptions:
    """The quality stage's parameters for a posed region (docs/repositioning.md)."""
    return QualityOptions(
        rounds=15,
        iterations_per_round=150,
        constraint_stiffness=100.0,
        volume_weight=3.0,
        tolerance=0.05,
    )


@dataclass(frozen=True)
class ImprovementOptions:
    """One options dataclass per stage of the chain (``None``: the stage does not run).

    Attributes
    ----------
    relax : RelaxOptions or None
        Stage 1, the untangling energy (None skips stages 1 and 2: the mapped pose is only
        smoothed).
    quality : QualityOptions or None
        Stage 2, the quality optimisation.
    smooth : SmoothOptions or None
        Stage 3, the smoother.
    """

    relax: RelaxOptions | None = field(default_factory=RelaxOptions)
    quality: QualityOptions | None = field(default_factory=_export_quality)
    smooth: SmoothOptions | None = field(default_factory=SmoothOptions)

    def scaled(self, length: float) -> ImprovementOptions:
        """These options for a model drawn ``length`` times larger (or in other units): every
        stage's lengths scaled (:meth:`RelaxOptions.scaled`, :meth:`QualityOptions.scaled`;
        the smoother has none)."""
        return replace(
            self,
            relax=None if self.relax is None else self.relax.scaled(length),
            quality=None if self.quality is None else self.quality.scaled(length),
        )


@dataclass
class ImprovementReport:
    """What the chain did.

    Attributes
    ----------
    relaxation : RelaxReport or None
        Stages 1 and 2 (``relaxation.quality`` is stage 2's report, None when it did not run);
        None when they did not run.
    smoothing : SmoothingReport or None
        Stage 3 (None when it did not run).
    relaxed : (N, 3) ndarray
        The coordinates after stages 1 and 2, before the smoothing.
    volume_correction : VolumeCorrectionReport or None
        The caller's volume-restoring step before stage 1
        (:mod:`kneegui.meshopt.volume_correction`), when it ran.
    """

    relaxation: RelaxReport | None
    smoothing: SmoothingReport | None
    relaxed: NDArray[np.float64]
    volume_correction: VolumeCorrectionReport | None = None


class ImprovementRegion(Protocol):
    """Where and how the chain may move nodes: the caller's region with its constraints."""

    def untangle(
        self,
        coords: NDArray[np.float64],
        options: RelaxOptions,
        stop_when_untangled: bool,
        progress: ProgressCallback,
        cancel: CancelCallback,
        untangled: Callable[[NDArray[np.float64]], None] | None = None,
    ) -> tuple[NDArray[np.float64], RelaxReport, bool]:
        """Stage 1: the new coordinates, its report, and whether stage 2 may follow (the
        region is untangled, and there is a region). ``untangled(coords)``, when given, is
        called at most once with a copy of the whole pose as soon as nothing is inverted, if
        that is before the stage ends."""
        ...

    def optimise(
        self,
        coords: NDArray[np.float64],
        options: QualityOptions,
        progress: ProgressCallback,
        cancel: CancelCallback,
    ) -> tuple[NDArray[np.float64], QualityOptimisationReport | None]:
        """Stage 2 (None: nothing to optimise)."""
        ...

    def smooth(
        self,
        coords: NDArray[np.float64],
        options: SmoothOptions,
        progress: ProgressCallback,
        cancel: CancelCallback,
    ) -> tuple[NDArray[np.float64], SmoothingReport]:
        """Stage 3."""
        ...


def progress_span(progress: ProgressCallback, lo: float, hi: float) -> ProgressCallback:
    """``progress`` for a part of a stage: its fractions 0 to 1 reported as ``lo`` to ``hi``."""
    return lambda fraction, message: progress(lo + (hi - lo) * fraction, message)


#: Share of the progress bar of each stage (the smoothing's only when it runs).
_SPANS = {"untangle": (0.0, 0.8), "quality": (0.8, 0.9), "smooth": (0.5, 1.0)}


def improve_region(
    coords: NDArray[np.float64],
    region: ImprovementRegion,
    options: ImprovementOptions,
    progress: ProgressCallback | None = None,
    cancel: CancelCallback | None = None,
    stage_done: StageCallback | None = None,
) -> tuple[NDArray[np.float64], ImprovementReport]:
    """Run the chain (module docstring) on ``region``.

    Parameters
    ----------
    coords : (N, 3) ndarray
        The pose to improve (not modified).
    region : ImprovementRegion
        The free nodes and their constraints, per stage.
    options : ImprovementOptions
    progress, cancel : callable, optional
        ``progress(fraction, message)``; ``cancel()`` returns True to stop (the stages raise
        :class:`kneegui.errors.Cancelled`).
    stage_done : callable, optional
        :data:`StageCallback`, after each stage another follows (a window shows the untangled
        pose while the quality stage runs), and once before that with ``"untangle"`` and the
        pose of the untangling's first round that leaves nothing inverted (before its rounds
        at full stiffness); it cannot change the result.

    Returns
    -------
    coords : (N, 3) ndarray
        A new array; only the region's free nodes moved.
    report : ImprovementReport
    """
    report_progress = progress or (lambda fraction, message: None)
    should_cancel = cancel or (lambda: False)
    smoothing = options.smooth is not None
    squeeze = 0.5 if smoothing else 1.0  # the relaxation's share when the smoothing follows

    def span(stage: str) -> ProgressCallback:
        lo, hi = _SPANS[stage]
        if stage != "smooth":
            lo, hi = lo * squeeze, hi * squeeze
        return progress_span(report_progress, lo, hi)

    x, relaxation = np.array(coords, dtype=np.float64, copy=True), None

    def done(stage: str, follows: bool) -> None:
        if stage_done is not None and follows:
            stage_done(stage, x.copy())

    if options.relax is not None:
        t0 = time.perf_counter()
        optimise_next = options.quality is not None
        first_untangled: Callable[[NDArray[np.float64]], None] | None = None
        if stage_done is not None and (optimise_next or smoothing):
            # the first untangled pose, before the stage's last rounds at full stiffness (on
            # the paper-scale demo a quarter of the stage): a window shows it that much sooner
            def first_untangled(pose: NDArray[np.float64]) -> None:
                stage_done("untangle", pose)

        x, relaxation, untangled = region.untangle(
            coords, options.relax, optimise_next, span("untangle"), should_cancel, first_untangled
        )
        # a region left with corners inverted still gets the stage, around them (their nodes
        # held): its settling is what brings the tissue out of the bones
        stuck = (
            optimise_next
            and relaxation.inverted_corners_after > 0
            and options.quality.hold_inverted
        )
        optimising = optimise_next and (untangled or stuck)
        done("untangle", optimising or smoothing)
        if optimising:
            x, relaxation.quality = region.optimise(x, options.quality, span("quality"), cancel)
            done("quality", smoothing)
        relaxation.seconds = time.perf_counter() - t0
    relaxed = x
    smoothed = None
    if smoothing:
        x, smoothed = region.smooth(relaxed, options.smooth, span("smooth"), should_cancel)
    report_progress(1.0, "mesh improved")
    return x, ImprovementReport(relaxation, smoothed, relaxed)
