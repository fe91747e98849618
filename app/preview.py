"""What the window shows: the live mapping while the slider moves, the export once it rests.

While the flexion slider is dragged the view follows the repositioner's cheap mapping
(:meth:`kneegui.reposition.Repositioner.pose`). When it rests (:data:`REST_DELAY_MS` after the
last move, or at once on release) :class:`ExportPreview` runs the export path,
:func:`kneegui.reposition.pipeline.pose_model` with relaxation and smoothing, on the resting
angle in a worker thread; its result (an :class:`ExportedPose`) becomes the view and is what
File > Export writes, without solving again. While it runs, the poses of its stages are shown
as they come (:data:`RELAXING`: the first untangling round that leaves nothing inverted, 0.3 of
the export's time on the paper-scale demo at 90°, the untangling's end, then the
quality-optimised pose), marked as such: they are not what the export writes, and File > Export
refuses them.

The export of an angle depends on the poser and the angle alone (the engine's rule: the same
bits whatever was posed before), so each result is kept for the poser it came from: back at an
angle already exported, the view shows its export at once instead of solving again (at most
:data:`KEPT_EXPORTS` of them and :data:`KEPT_EXPORT_NODES` node positions in all, the most
recently shown kept).

Every pose request bumps the workspace's *pose generation*; a job carries the generation it
was started for, stops (raises :class:`kneegui.errors.Cancelled` at the engine's next check) as
soon as the generation moves on, and a result whose generation is no longer current is dropped,
so a stale export is never shown.

:class:`PoseFigures` are the three figures the indicator, the quality-against-flexion plot and
the CLI report (``kneegui pose --report``) share: inverted elements, worst corner Jacobian,
largest element volume change of the solids.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from PySide6.QtCore import QObject, QTimer, Signal

from app.heatmaps import jacobian_says_something
from app.tasks import TaskRunner
from kneegui.errors import Cancelled
from kneegui.model import Model
from kneegui.quality import QualityEvaluator, QualityResult, volume_change_pct
from kneegui.reposition.pipeline import PosedModel
from kneegui.topology import SOLID_TYPES

if TYPE_CHECKING:
    from app.workspace import Workspace

#: How long the slider must rest before the export path runs on its angle (ms).
REST_DELAY_MS = 300
#: Spacing of the live mapping's quality-against-flexion samples (degrees).
CURVE_STEP_DEG = 5.0
#: Most exports kept for a return to their angle.
KEPT_EXPORTS = 16
#: Most node positions kept in all (24 bytes each): 8 exports of a 1M-node model.
KEPT_EXPORT_NODES = 8_000_000
LIVE = "live mapping"
EXPORTED = "as exported"
#: What the view is while it shows a stage of the running export
RELAXING = "relaxing"
#: How the indicator names the pose each stage of the mesh improvement ends on
#: (:data:`kneegui.meshopt.chain.StageCallback`)
STAGE_NAMES = {"untangle": "untangled", "quality": "quality-optimised"}


@dataclass(frozen=True)
class PoseFigures:
    """The quality of one pose in three figures (the CLI report's names in brackets).

    Attributes
    ----------
    inverted : int
        Elements with a non-positive corner Jacobian (``quality.<final>.inverted``).
    worst_jacobian : float
        Smallest corner Jacobian ratio (``quality.<final>.jacobian.worst``); NaN without
        measured elements.
    max_volume_change_pct : float
        Signed volume change of the solid whose change is largest in magnitude, percent
        (``volume_change.max_element_pct``); NaN without solids.
    worst_tet_collapse : float
        Smallest tet collapse (``quality.<final>.tet_collapse.worst``); NaN without tets.
    jacobian_says_something : bool
        Whether the model has elements whose corner Jacobian is more than its sign (hexes,
        wedges, pyramids, quad shells); on tets and triangles alone it is 1 by definition and
        the figures leave it out.
    split : tuple of int, optional
        ``inverted`` split by the pre-flight check (``inverted.locked / movable / other``):
        locked between segments, with a node the repositioner may move, tied to one segment;
        known for an export's report, ``None`` for a live pose.
    passes_gate : bool, optional
        Whether the export passes the quality gate (``gate.passed``); ``None`` for a live pose.
    """

    inverted: int
    worst_jacobian: float
    max_volume_change_pct: float
    worst_tet_collapse: float = float("nan")
    jacobian_says_something: bool = True
    split: tuple[int, int, int] | None = None
    passes_gate: bool | None = None

    @classmethod
    def from_report(cls, report: Mapping[str, Any], model: Model) -> PoseFigures:
        """The figures of a :func:`~kneegui.reposition.pipeline.pose_model` report (the pose
        it writes: smoothed when it was smoothed) of ``model``."""
        quality = report["quality"]
        final = quality.get("smoothed", quality["posed"])
        worst = final["jacobian"]["worst"]
        change = report["volume_change"]["max_element_pct"]
        collapse = (final.get("tet_collapse") or {}).get("worst")
        inverted = report.get("inverted") or {}
        split = None
        if all(key in inverted for key in ("locked", "movable", "other")):
            split = (int(inverted["locked"]), int(inverted["movable"]), int(inverted["other"]))
        return cls(
            int(final["inverted"]),
            float("nan") if worst is None else float(worst),
            float("nan") if change is None else float(change),
            float("nan") if collapse is None else float(collapse),
            jacobian_says_something(model),
            split,
            bool(report["gate"]["passed"]) if "gate" in report else None,
        )

    def text(self) -> str:
        """``inverted 3 · worst Jacobian 0.213 · largest volume change +12.1 %``, with the worst
        tet collapse before the Jacobian on a model with tets (and without the Jacobian when
        it says nothing there). An export's inverted elements are split as its report splits
        them: ``inverted 16 (8 locked, 8 movable)``."""
        parts = [self.inverted_text()]
        if np.isfinite(self.worst_tet_collapse):
            parts.append(f"worst tet collapse {self.worst_tet_collapse:.3f}")
        if self.jacobian_says_something or not np.isfinite(self.worst_tet_collapse):
            parts.append(f"worst Jacobian {self.worst_jacobian:.3f}")
        parts.append(f"largest volume change {self.max_volume_change_pct:+.1f} %")
        return " · ".join(parts)

    def inverted_text(self) -> str:
        """``inverted 16``, split where the export's report split it: ``inverted 16 (8 locked,
        8 movable)`` (and ``N tied to one bone`` when there are such)."""
        text = f"inverted {self.inverted}"
        if self.split is None or not self.inverted:
            return text
        locked, movable, other = self.split
        named = [f"{locked} locked", f"{movable} movable"]
        if other:
            named.append(f"{other} tied to one bone")
        return f"{text} ({', '.join(named)})"


def pose_figures(model: Model, quality: QualityResult, initial: QualityResult) -> PoseFigures:
    """The figures of a measured pose, by the rules of the export's report.

    Parameters
    ----------
    model : Model
        The model (its blocks order the results).
    quality, initial : QualityResult
        Every element measured now and in the initial pose.
    """
    largest = 0.0
    found = False
    for etype in SOLID_TYPES:
        if etype not in quality or etype not in initial or not len(quality[etype]):
            continue
        pct = volume_change_pct(quality[etype].volume, initial[etype].volume)
        k = int(np.argmax(np.abs(pct)))
        if not found or abs(pct[k]) > abs(largest):
            largest, found = float(pct[k]), True
    collapses = [
        quality[t].tet_collapse for t in ("tet4", "tet10") if t in quality and len(quality[t])
    ]
    return PoseFigures(
        quality.n_inverted,
        quality.worst_jacobian(),
        largest if found else float("nan"),
        float(min(c.min() for c in collapses)) if collapses else float("nan"),
        jacobian_says_something(model),
    )


@dataclass(frozen=True)
class ExportedPose:
    """The export path's result for one angle, tagged with the pose generation it answers."""

    flexion: float
    generation: int
    posed: PosedModel
    message: str
    figures: PoseFigures

    @property
    def coords(self) -> NDArray[np.float64]:
        """The exported node coordinates (N, 3)."""
        return self.posed.model.coords


@dataclass(frozen=True)
class QualityCurve:
    """Pose figures against flexion (one row per angle)."""

    angles: NDArray[np.float64]
    inverted: NDArray[np.int64]
    worst_jacobian: NDArray[np.float64]
    max_volume_change_pct: NDArray[np.float64]
    worst_tet_collapse: NDArray[np.float64]


def live_quality_curve(
    pose: Callable[[float], NDArray[np.float64]],
    model: Model,
    evaluator: QualityEvaluator,
    initial: QualityResult,
    angles: NDArray[np.float64],
    progress: Callable[[float, str], None],
    cancelled: Callable[[], bool],
) -> QualityCurve:
    """The live mapping's figures at each of ``angles`` (run in a worker thread)."""
    rows = []
    for i, angle in enumerate(angles):
        if cancelled():
            raise Cancelled("quality curve cancelled")
        rows.append(pose_figures(model, evaluator.evaluate(pose(float(angle))), initial))
        progress((i + 1) / len(angles), f"live mapping quality at {angle:g}°")
    return QualityCurve(
        np.asarray(angles, dtype=np.float64),
        np.array([r.inverted for r in rows], dtype=np.int64),
        np.array([r.worst_jacobian for r in rows]),
        np.array([r.max_volume_change_pct for r in rows]),
        np.array([r.worst_tet_collapse for r in rows]),
    )


class ExportPreview(QObject):
    """Runs the export path on the resting angle and the live quality curve, in one worker.

    Signals
    -------
    changed : the state shown by the indicator changed (running, progress, failed, shown)
    curve_changed : the live curve or the exported points changed
    stage_ready(int, float, str, object) : from the worker thread, queued to the GUI thread:
        the generation, angle, stage and (N, 3) pose of a stage of the running export
    """

    changed = Signal()
    curve_changed = Signal()
    stage_ready = Signal(int, float, str, object)

    def __init__(self, workspace: Workspace):
        super().__init__(workspace)
        self._ws = workspace
        self.tasks = TaskRunner(self)
        #: False: the view stays on the live mapping until Relax + smooth is pressed
        self.enabled = True
        self.live_curve: QualityCurve | None = None
        #: exported angle -> its figures (every export shown since the poser was built)
        self.exported_points: dict[float, PoseFigures] = {}
        #: exported angle -> its export, the most recently shown last (for the current poser)
        self.kept: OrderedDict[float, ExportedPose] = OrderedDict()
        #: the angle the running export is for (None when none runs)
        self.running_for: float | None = None
        self.fraction = 0.0
        self.message = ""
        #: why the last export of the current pose failed ('' when it did not)
        self.error = ""
        self._pending = False
        self._curve_pending = False
        self._explicit = False
        self._running_generation = -1
        self._timer = QTimer(self)
        self._timer.setSingleShot(True)
        self._timer.setInterval(REST_DELAY_MS)
        self._timer.timeout.connect(lambda: self.start())
        self.tasks.progress.connect(self._on_progress)
        self.tasks.finished.connect(self._on_finished)
        self.stage_ready.connect(self._on_stage)

    @property
    def busy(self) -> bool:
        """Whether an export or the curve is running, waiting to start or waiting for rest."""
        return self.tasks.busy or self._pending or self._curve_pending or self._timer.isActive()

    # ------------------------------------------------------------------ scheduling
    def pose_requested(self, schedule: bool) -> None:
        """A new pose was asked for: a running export is now stale (its cancel check sees the
        generation move); with ``schedule`` the export runs once the slider rests."""
        self.error = ""
        self._pending = False
        if schedule and self.enabled:
            self._timer.start()
        else:
            self._timer.stop()
        self.changed.emit()

    def settle(self) -> None:
        """The slider was released: run the export now instead of after the rest delay."""
        if self._timer.isActive():
            self._timer.stop()
            self.start()

    def reset(self) -> None:
        """A new model or poser: forget the curve and the exported points."""
        self._curve_pending = False
        self.live_curve = None
        self.forget_exports()

    def forget_exports(self) -> None:
        """The poser's export options changed (not its mapping): the running export and the
        kept ones are of the old options, so they go; the live curve stays."""
        self._timer.stop()
        self._pending = False
        self.tasks.cancel()
        self.exported_points.clear()
        self.kept.clear()
        self.running_for = None
        self.error = ""
        self.curve_changed.emit()
        self.changed.emit()

    def start(self, explicit: bool = False) -> bool:
        """Run the export path on the current angle unless its result is already shown.

        Waits (returns False) while the worker is busy; it starts when the worker is free.
        ``explicit``: asked for by the user (Relax + smooth): a failure is shown in a dialog.
        """
        ws = self._ws
        self._timer.stop()
        self._explicit = self._explicit or explicit
        if ws.poser is None or ws.model is None:
            return False
        if ws.exported is not None and ws.exported.generation == ws.pose_generation:
            return False
        if self.show_kept():
            return False
        if self.tasks.busy:
            self._pending = True
            return False
        self._pending = False
        from app import smoothing

        poser, degrees, generation = ws.poser, ws.target_flexion, ws.pose_generation
        explicit_run, self._explicit = self._explicit, False

        def work(progress, cancelled):
            def stale() -> bool:
                return cancelled() or ws.pose_generation != generation

            def stage_done(stage: str, coords: NDArray[np.float64]) -> None:
                if not stale():
                    self.stage_ready.emit(generation, degrees, stage, coords)

            return smoothing.smooth_current(poser, degrees, progress, stale, stage_done)

        def done(outcome: smoothing.SmoothingOutcome) -> None:
            self.running_for = None
            exported = ExportedPose(
                degrees,
                generation,
                outcome.posed,
                outcome.message,
                PoseFigures.from_report(outcome.report, outcome.posed.model),
            )
            if poser is ws.poser:
                self.exported_points[degrees] = exported.figures
                self._keep(exported)
                self.curve_changed.emit()
            ws.show_exported(exported)  # dropped there when stale
            self.changed.emit()

        def failed(exc: BaseException) -> None:
            self.running_for = None
            if ws.pose_generation == generation:
                ws.drop_stage()
                self.error = f"{type(exc).__name__}: {exc}"
                ws.status.emit(f"the export at {degrees:g}° failed: {exc}")
                if explicit_run:
                    ws.error.emit(exc)
            self.changed.emit()

        self.running_for = degrees
        self._running_generation = generation
        self.fraction, self.message = 0.0, "posing"
        self.tasks.start(f"Export at {degrees:g}°", work, done, failed)
        self.changed.emit()
        return True

    def show_kept(self) -> bool:
        """Show the kept export of the current angle, if there is one (no solve); whether it
        was shown."""
        ws = self._ws
        kept = self.kept.get(ws.target_flexion)
        if kept is None or ws.poser is None:
            return False
        self.kept.move_to_end(kept.flexion)
        self._explicit = False
        shown = ws.show_exported(replace(kept, generation=ws.pose_generation))
        if shown:
            ws.status.emit(f"{kept.message} (kept from its export at {kept.flexion:g}°)")
        self.changed.emit()
        return shown

    def _keep(self, exported: ExportedPose) -> None:
        """Keep ``exported`` for a return to its angle, within :data:`KEPT_EXPORTS` and
        :data:`KEPT_EXPORT_NODES`, dropping the least recently shown."""
        self.kept[exported.flexion] = exported
        self.kept.move_to_end(exported.flexion)
        nodes = len(exported.coords)
        while len(self.kept) > 1 and (
            len(self.kept) > KEPT_EXPORTS or len(self.kept) * nodes > KEPT_EXPORT_NODES
        ):
            self.kept.popitem(last=False)

    def start_curve(self) -> bool:
        """Sample the live mapping's figures over the validated range (worker thread; after the
        running task when one runs)."""
        from app.workspace import FLEXION_RANGE

        ws = self._ws
        if ws.poser is None or ws.model is None or ws.evaluator is None:
            return False
        if self.tasks.busy:
            self._curve_pending = True
            return False
        self._curve_pending = False
        poser, model, evaluator = ws.poser, ws.model, ws.evaluator
        initial = ws.initial_quality
        lo, hi = FLEXION_RANGE
        angles = np.arange(lo, hi + 1e-9, CURVE_STEP_DEG)

        def work(progress, cancelled):
            return live_quality_curve(
                poser.pose, model, evaluator, initial, angles, progress, cancelled
            )

        def done(curve: QualityCurve) -> None:
            if poser is ws.poser:
                self.live_curve = curve
                self.curve_changed.emit()

        return self.tasks.start("Live quality curve", work, done, lambda exc: ws.error.emit(exc))

    def _on_stage(self, generation: int, degrees: float, stage: str, coords: object) -> None:
        if self.running_for == degrees:
            self._ws.show_stage(generation, degrees, stage, coords)
            self.changed.emit()

    def _on_progress(self, fraction: float, message: str) -> None:
        if self.running_for is not None:
            self.fraction, self.message = fraction, message
            self.changed.emit()

    def _on_finished(self, _name: str) -> None:
        if self.running_for is not None:  # cancelled: neither done nor failed ran
            self.running_for = None
            if self._ws.pose_generation == self._running_generation:
                self._ws.drop_stage()  # cancelled for itself, not for a newer pose
            self.changed.emit()
        QTimer.singleShot(0, self._after_task)

    def _after_task(self) -> None:
        if self._curve_pending and not self.tasks.busy:
            self.start_curve()
        elif self._pending and not self.tasks.busy:
            self.start()
