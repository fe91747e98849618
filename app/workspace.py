"""The one state object of the window: model, setup, poser, current pose, quality and view state.

Widgets call :class:`Workspace` methods and listen to its signals; they never call each other.
Long work (reading a deck, precomputing the repositioner, smoothing, export, ligament curves)
runs through :attr:`Workspace.tasks` in a worker thread. Engine errors propagate out of the
methods called from the GUI (they are shown at one boundary, see ``MainWindow.guard``); errors of
background tasks are emitted through :attr:`Workspace.error`.

Every setup edit of a deck read from disk is autosaved (debounced, atomic) to
:func:`app.autosave.autosave_path`; a clean save or a normal close removes the file, and opening a
deck that has one emits :attr:`Workspace.autosave_found` so the window can offer it back.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from PySide6.QtCore import QObject, QTimer, Signal

from app.autosave import AUTOSAVE_DELAY_MS, autosave_path
from app.heatmaps import HEATMAP_METRICS, heatmap_metrics
from app.poser import Poser, make_poser, with_volume_step
from app.preview import STAGE_NAMES, ExportedPose, ExportPreview, PoseFigures, pose_figures
from kneegui.errors import GeometryError, KneeguiError, SetupError
from kneegui.geometry import JointAxes, compute_joint_axes
from kneegui.io.atomic import atomic_write_text
from kneegui.ligaments import Ligament, length_curve, ligament_fibres
from kneegui.model import Model
from kneegui.quality import QualityEvaluator, QualityResult, volume_change_pct
from kneegui.quality.metrics import ONLY_METRICS
from kneegui.setup import ROLES, JointSetup, load_setup
from kneegui.setup.kinematic_tables import VALIDATED_FLEXION_DEG
from kneegui.topology import SOLID_TYPES

#: Slider range (degrees): the engine's validated flexion range (see its definition for why
#: it is narrower than the supported one).
FLEXION_RANGE = VALIDATED_FLEXION_DEG


def _quality_metric(metric: str) -> str:
    """The :class:`~kneegui.quality.QualityResult` metric the heat-map ``metric`` is made of
    (a volume or area change, of the volume)."""
    return {"volume_change": "volume", "area_change": "volume"}.get(
        metric, HEATMAP_METRICS[metric][1]
    )


def _measured(quality: QualityResult, metric: str) -> bool:
    """Whether every type of ``quality`` was measured for the heat-map ``metric``."""
    key = _quality_metric(metric)
    return all(q.measured is None or key in q.measured for q in quality.by_type.values())


#: Default threshold per metric (from resources/quality_thresholds.csv "warn" where it exists).
CONDYLE_KEYS = ("lateral_condyle", "medial_condyle")
AXIS_KEYS = ("lr_axis", "femur_axis", "tibia_axis")


class ExportBlocked(KneeguiError):
    """Export refused because the posed mesh has inverted elements (pass force=True)."""


class Workspace(QObject):
    """State of one window. See the module docstring.

    Signals
    -------
    model_changed : a new model (and setup) was loaded
    setup_changed : the setup dictionary changed (roles, landmarks); ``setup``/``axes`` updated
    poser_changed : a new poser is ready (initial flexion may differ)
    coords_changed : the current coordinates changed (slider, smoothing)
    display_changed(str) : a view setting changed (colour, metric, threshold, visibility, clip)
    pick_target_changed(str) : the landmark being picked ('' when not picking)
    ligaments_changed : ligament length curves were (re)computed
    error(object) : a background task failed (the exception)
    status(str) : a one-line message for the status bar
    live_idle : the last requested slider pose is shown
    dirty_changed(bool) : the setup has (True) or no longer has (False) unsaved edits
    autosave_found(object) : the deck just opened has an autosaved setup (its path) differing
        from the one loaded; :meth:`restore_autosave` loads it, :meth:`discard_autosave` drops it
    """

    model_changed = Signal()
    setup_changed = Signal()
    poser_changed = Signal()
    coords_changed = Signal()
    display_changed = Signal(str)
    pick_target_changed = Signal(str)
    ligaments_changed = Signal()
    error = Signal(object)
    status = Signal(str)
    live_idle = Signal()
    autosave_found = Signal(object)
    dirty_changed = Signal(bool)

    def __init__(self, parent: QObject | None = None):
        super().__init__(parent)
        from app.tasks import TaskRunner

        self.tasks = TaskRunner(self)
        self.model: Model | None = None
        self.deck_path: Path | None = None
        #: the deck being read (None when no open is running)
        self.pending_deck: Path | None = None
        self.setup_path: Path | None = None
        self.setup_dict: dict[str, Any] = {}
        self.setup: JointSetup | None = None
        self.setup_problem: str | None = None
        self.axes: JointAxes | None = None
        self.poser: Poser | None = None
        #: the export restores the soft tissue's volume before relaxing (Mesh menu; the CLI's
        #: ``--restore-volume``)
        self.restore_volume = False
        self.flexion: float = 0.0
        self.coords: NDArray[np.float64] = np.zeros((0, 3))
        #: the angle last asked for (the live pose or the export may still be on their way)
        self.target_flexion: float = 0.0
        #: bumped by every pose request; exports answer one generation (app.preview)
        self.pose_generation = 0
        #: the export path's result while the view shows it (None: the live mapping)
        self.exported: ExportedPose | None = None
        #: while the export runs: the stage whose pose the view shows and the generation it
        #: answers (``show_stage``; None: no stage shown)
        self.stage: str | None = None
        self._stage_generation = -1
        self._custom_coords = False  # coordinates given by set_coords, not a pose
        self._figures: tuple[NDArray[np.float64], PoseFigures] | None = None
        #: the setup has edits not saved to a file
        self.setup_dirty = False
        self._evaluator: QualityEvaluator | None = None
        self._quality: QualityResult | None = None
        self._pose_quality: tuple[NDArray[np.int64], QualityResult] | None = None
        self._live_cells: NDArray[np.int64] | None = None
        self._live_rows: dict[str, NDArray[np.int64]] | None = None
        self._initial_quality: QualityResult | None = None
        self.ligaments: tuple[Ligament, ...] = ()
        self.ligament_curve: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        # view state
        self.colour_mode = "part"  # part | quality | stretch
        self.metric = "jacobian"
        self.threshold: float | None = None
        self.hidden_parts: set[int] = set()
        self.clip_enabled = False
        self.clip_normal = "lateral"
        self.clip_offset = 0.0
        self.pick_target = ""
        self._undo: list[dict[str, Any]] = []
        self._redo: list[dict[str, Any]] = []
        self._poser_stale = False
        self.tasks.finished.connect(lambda _name: QTimer.singleShot(0, self.on_task_finished))
        self._live = LivePoser(self)
        self.preview = ExportPreview(self)
        #: False: no autosave is written, offered or removed (``--screenshot`` runs)
        self.autosave_enabled = True
        self._autosave_held = False  # an offered autosave is not overwritten until answered
        self._autosave_timer = QTimer(self)
        self._autosave_timer.setSingleShot(True)
        self._autosave_timer.setInterval(AUTOSAVE_DELAY_MS)
        self._autosave_timer.timeout.connect(self.write_autosave)

    # ------------------------------------------------------------------ loading
    def load(
        self,
        model: Model,
        setup: Mapping[str, Any] | str | Path | None = None,
        deck_path: str | Path | None = None,
        setup_path: str | Path | None = None,
    ) -> None:
        """Make ``model`` (and its setup) current. Setup problems are kept, not raised.

        A setup given as a path is read as JSON (a bad file raises :class:`SetupError`, and the
        previous model stays).
        """
        if isinstance(setup, str | Path):
            setup_path = Path(setup)
            setup = read_setup_json(setup_path)
        self._leave_deck(deck_path)
        # the user's heat-map choice is kept for the next deck; the default follows the model
        chose_default = self.model is None or self.metric == heatmap_metrics(self.model)[0]
        self.model = model
        self.deck_path = None if deck_path is None else Path(deck_path)
        self.setup_path = None if setup_path is None else Path(setup_path)
        self.setup_dict = dict(setup) if setup is not None else default_setup_dict(model)
        self.coords = np.array(model.coords, dtype=np.float64)
        self.exported = None
        self.stage = None
        self._custom_coords = False
        self._bump(schedule=False)
        self.preview.reset()
        self._set_dirty(False)
        self._evaluator = QualityEvaluator(model.blocks)
        self._initial_quality = self._evaluator.evaluate(model.coords)
        offered = heatmap_metrics(model)
        if offered and (self.metric not in offered or chose_default):
            self.metric, self.threshold = offered[0], None  # a tet model opens on tet collapse
        self._quality = self._initial_quality
        self._pose_quality = None
        self._live_cells = self._live_rows = None
        self.poser = None
        self.ligaments = ()
        self.ligament_curve = None
        self.hidden_parts = set()
        self._undo.clear()
        self._redo.clear()
        self.flexion = 0.0
        self.target_flexion = 0.0
        self.setup = None
        self.axes = None
        self._validate_setup()
        if self.setup is not None:
            self.hidden_parts = set(self.setup.parts_of("skin", "flesh"))
        self.model_changed.emit()
        self.setup_changed.emit()
        self.coords_changed.emit()
        self.rebuild_poser()
        self._check_autosave()

    def open_deck(self, path: str | Path, setup_path: str | Path | None = None) -> None:
        """Read a deck (and setup) in the worker thread; on success it becomes current."""
        from kneegui.errors import Cancelled
        from kneegui.io.lsdyna import read_deck

        path = Path(path)
        setup_data = read_setup_json(setup_path) if setup_path is not None else None

        def work(progress, cancelled):
            progress(0.05, f"reading {path.name}")
            model = read_deck(path)
            if cancelled():
                raise Cancelled(f"opening {path.name} cancelled")
            progress(1.0, f"read {model.n_nodes} nodes, {model.n_elements} elements")
            return model

        def done(model):
            self.pending_deck = None
            self.load(model, setup_data, deck_path=path, setup_path=setup_path)
            self.status.emit(f"opened {path}")

        def failed(exc):
            self.pending_deck = None
            self.error.emit(exc)

        self.pending_deck = path
        if not self.tasks.start("Opening deck", work, done, failed):
            self.pending_deck = None
            self.status.emit(f"busy with {self.tasks.current_name}; try again when it ends")

    def open_setup(self, path: str | Path) -> None:
        """Read a setup file for the current model (a bad file raises; nothing changes then)."""
        if self.model is None:
            raise SetupError("open a deck first")
        path = Path(path)
        checked = self._read_checked_setup(path)
        self._push_undo()
        self.setup_path = path
        self.setup_dict = checked
        self._after_setup_edit()
        self._set_dirty(False)  # what is shown is that file

    def _read_checked_setup(self, path: Path) -> dict[str, Any]:
        assert self.model is not None
        data = read_setup_json(path)
        try:
            checked = load_setup(data, self.model)
        except SetupError as exc:  # name the file as well as the key
            raise SetupError(exc.message, key=exc.key, path=path) from None
        return checked.to_dict()

    def save_setup(self, path: str | Path) -> Path:
        """Write the current setup dictionary (atomically); the autosave is then dropped."""
        from kneegui.setup import save_setup

        out = save_setup(self.setup_dict, path)
        self.setup_path = Path(out)
        self.discard_autosave()
        self._set_dirty(False)
        return Path(out)

    # ------------------------------------------------------------------ autosave
    @property
    def autosave_file(self) -> Path | None:
        """The autosave file of the current deck (None for a model not read from a deck)."""
        if self.deck_path is None or not self.autosave_enabled:
            return None
        return autosave_path(self.deck_path)

    def write_autosave(self) -> Path | None:
        """Write the setup being edited to :attr:`autosave_file` now (atomically).

        Called by a 1 s single-shot timer restarted by every setup edit. A failed write is
        reported in the status bar and never interrupts editing. While the autosave found at
        opening is still being offered it is left as it is (and the write retried later).
        """
        self._autosave_timer.stop()
        target = self.autosave_file
        if target is None:
            return None
        if self._autosave_held:
            self._autosave_timer.start()
            return None
        try:
            atomic_write_text(target, json.dumps(self.setup_dict, indent=1) + "\n")
        except (OSError, TypeError, ValueError) as exc:
            self.status.emit(f"autosave failed: {exc}")
            return None
        return target

    def discard_autosave(self) -> None:
        """Forget the autosave of the current deck (clean save, normal close, declined offer)."""
        self._autosave_timer.stop()
        self._autosave_held = False
        target = self.autosave_file
        if target is not None:
            try:
                target.unlink(missing_ok=True)
            except OSError as exc:
                self.status.emit(f"could not remove the autosave: {exc}")

    def restore_autosave(self) -> None:
        """Load the autosaved setup of the current deck, as :meth:`open_setup` loads a file.

        A bad or invalid autosave raises :class:`SetupError` naming the file; nothing changes
        then and the file stays until the next edit overwrites it. The restore is one undo step.
        """
        target = self.autosave_file
        self._autosave_held = False
        if self.model is None or target is None or not target.is_file():
            raise SetupError("there is no autosaved setup for this deck")
        checked = self._read_checked_setup(target)
        self._push_undo()
        self.setup_dict = checked
        self._after_setup_edit()
        self.status.emit(f"restored the autosaved setup ({target})")

    def decline_autosave(self) -> None:
        """Drop the autosave offered at opening; edits made since are autosaved again."""
        edited = self.can_undo
        self.discard_autosave()
        if edited and self.autosave_file is not None:
            self._autosave_timer.start()

    def close_deck(self) -> None:
        """A normal close of the deck (window closed, another deck opened): its autosave goes,
        unless it is the one found at opening and still unanswered."""
        if self._autosave_held:
            self._autosave_timer.stop()
            self._autosave_held = False
        else:
            self.discard_autosave()

    def _leave_deck(self, new_deck: str | Path | None) -> None:
        """Before another model becomes current: :meth:`close_deck`, unless the same deck is
        opened again (then its pending autosave is written, and offered)."""
        if self.deck_path is None:
            return
        same = new_deck is not None and Path(new_deck).resolve() == self.deck_path.resolve()
        if not same:
            self.close_deck()
        elif self._autosave_timer.isActive():
            self.write_autosave()

    def _check_autosave(self) -> None:
        target = self.autosave_file
        if target is None or not target.is_file():
            return
        try:
            same = json.loads(target.read_text(encoding="utf-8")) == self.setup_dict
        except (OSError, ValueError):
            same = False  # offered all the same: restoring names the problem
        if same:
            self.discard_autosave()
        else:
            self._autosave_held = True
            self.autosave_found.emit(target)

    # ------------------------------------------------------------------ setup and poser
    def _validate_setup(self) -> None:
        assert self.model is not None
        try:
            setup = load_setup(self.setup_dict, self.model)
            axes = compute_joint_axes(self.model.coords, setup)
        except (SetupError, GeometryError) as exc:
            # keep the last valid setup and axes: the poser built from them still works
            self.setup_problem = str(exc)
            return
        self.setup = setup
        self.axes = axes
        self.setup_problem = None

    def rebuild_poser(self) -> None:
        """Precompute the poser for the current valid setup in the worker thread."""
        if self.model is None or self.setup is None or self.setup_problem is not None:
            return
        if self.tasks.busy:
            self._poser_stale = True
            return
        model, setup, restore_volume = self.model, self.setup, self.restore_volume
        self._poser_stale = False

        def work(progress, cancelled):
            poser = make_poser(model, setup, progress, cancelled, restore_volume)
            ligaments = ligament_fibres(model, setup.roles.get("ligament", ()))
            return poser, ligaments

        def done(result):
            if self.model is not model:
                return
            self.poser, self.ligaments = result
            if restore_volume != self.restore_volume:  # switched while it was built
                self.poser = with_volume_step(self.poser, self.restore_volume)
            self.ligament_curve = None
            self.preview.reset()
            self.preview.start_curve()
            self.poser_changed.emit()
            self.set_flexion(
                self.flexion if self.flexion else self.poser.initial_flexion, force=True
            )
            self.status.emit(f"poser ready; initial flexion {self.poser.initial_flexion:.1f}°")

        self._start("Preparing the repositioner", work, done)

    def set_restore_volume(self, enabled: bool) -> None:
        """Switch the export's volume step on or off (``kneegui pose --restore-volume``): the
        poser shares its precompute with the new setting, the exports kept for the old one
        are dropped and the export of the current angle runs again."""
        enabled = bool(enabled)
        if enabled == self.restore_volume:
            return
        self.restore_volume = enabled
        if self.poser is None:
            return  # the poser being built reads the setting when it is done
        self.poser = with_volume_step(self.poser, enabled)
        self.preview.forget_exports()  # the mapping is the same: no poser_changed
        self.status.emit(
            "the export restores the soft tissue's volume before relaxing"
            if enabled
            else "the export relaxes the mapping as it is (no volume step)"
        )
        self.set_flexion(self.target_flexion, force=True)

    def _set_dirty(self, dirty: bool) -> None:
        if dirty != self.setup_dirty:
            self.setup_dirty = dirty
            self.dirty_changed.emit(dirty)

    def _after_setup_edit(self) -> None:
        self._set_dirty(True)
        if self.autosave_file is not None:
            self._autosave_timer.start()
        self._validate_setup()
        self.setup_changed.emit()
        self._emit_undo()
        if self.setup_problem is None:
            self.rebuild_poser()

    # ------------------------------------------------------------------ roles
    def part_role(self, pid: int) -> str | None:
        """Role of a part in the setup dictionary (None if unassigned)."""
        for role, pids in self.setup_dict.get("roles", {}).items():
            if int(pid) in [int(p) for p in pids]:
                return role
        return None

    def set_part_role(self, pid: int, role: str | None) -> None:
        """Move a part to ``role`` (None: no role)."""
        if role is not None and role not in ROLES:
            raise SetupError(f"unknown role {role!r}", key="roles")
        if self.part_role(pid) == role:
            return
        self._push_undo()
        roles = {
            r: [int(p) for p in v if int(p) != int(pid)]
            for r, v in self.setup_dict.get("roles", {}).items()
        }
        if role is not None:
            roles.setdefault(role, []).append(int(pid))
            roles[role].sort()
        self.setup_dict["roles"] = roles
        self._after_setup_edit()

    # ------------------------------------------------------------------ landmarks
    def condyle_ids(self, key: str) -> list[int]:
        """Node ids of a condyle set as in the setup dictionary."""
        return [int(n) for n in self.setup_dict.get("landmarks", {}).get(key, [])]

    def set_condyle_ids(self, key: str, ids: Iterable[int]) -> None:
        """Replace a condyle set (one undo step)."""
        if key not in CONDYLE_KEYS:
            raise KeyError(key)
        new = sorted({int(i) for i in ids})
        if new == self.condyle_ids(key):
            return
        self._push_undo()
        self.setup_dict.setdefault("landmarks", {})[key] = new
        self._after_setup_edit()

    def add_condyle_ids(self, key: str, ids: Iterable[int]) -> None:
        """Add nodes to a condyle set (one undo step)."""
        self.set_condyle_ids(key, [*self.condyle_ids(key), *ids])

    def remove_condyle_ids(self, key: str, ids: Iterable[int]) -> None:
        """Remove nodes from a condyle set (one undo step)."""
        drop = {int(i) for i in ids}
        self.set_condyle_ids(key, [i for i in self.condyle_ids(key) if i not in drop])

    def set_axis_point(self, key: str, which: int, node_id: int) -> None:
        """Set the proximal (0) or distal (1) point of an axis to a node (one undo step)."""
        if key not in AXIS_KEYS or which not in (0, 1):
            raise KeyError(f"{key}[{which}]")
        points = list(self.setup_dict.setdefault("landmarks", {}).get(key, [None, None]))
        while len(points) < 2:
            points.append(None)
        if points[which] == int(node_id):
            return
        self._push_undo()
        points[which] = int(node_id)
        self.setup_dict["landmarks"][key] = points
        self._after_setup_edit()

    def suggest_condyles(self) -> None:
        """Fill both condyle sets with the engine's suggestion (one undo step)."""
        from kneegui.setup import suggest_condyle_nodes

        if self.model is None:
            return
        roles = self.setup_dict.get("roles", {})
        lat, med = suggest_condyle_nodes(
            self.model,
            roles.get("femur", []),
            self.setup_dict.get("side", "right"),
            tibia_part_ids=roles.get("tibia", []) or None,
            patella_part_ids=roles.get("patella", []) or None,
        )
        self._push_undo()
        lm = self.setup_dict.setdefault("landmarks", {})
        lm["lateral_condyle"] = [int(i) for i in lat]
        lm["medial_condyle"] = [int(i) for i in med]
        self._after_setup_edit()

    def set_pick_target(self, target: str) -> None:
        """``lateral_condyle``, ``medial_condyle``, ``lr_axis:0`` ... or '' to stop picking."""
        if target == self.pick_target:
            return
        self.pick_target = target
        self.pick_target_changed.emit(target)

    def pick_nodes(self, ids: Iterable[int], remove: bool = False) -> None:
        """Apply picked node ids to the current pick target (called by the viewport)."""
        ids = [int(i) for i in ids]
        if not ids or not self.pick_target:
            return
        target = self.pick_target
        if target in CONDYLE_KEYS:
            if remove:
                self.remove_condyle_ids(target, ids)
            else:
                self.add_condyle_ids(target, ids)
        else:
            key, which = target.split(":")
            self.set_axis_point(key, int(which), ids[0])

    # ------------------------------------------------------------------ undo
    @property
    def can_undo(self) -> bool:
        return bool(self._undo)

    @property
    def can_redo(self) -> bool:
        return bool(self._redo)

    def _push_undo(self) -> None:
        self._undo.append(copy.deepcopy(self.setup_dict))
        self._redo.clear()

    def _emit_undo(self) -> None:
        self.display_changed.emit("undo")

    def undo(self) -> None:
        """Undo the last role or landmark edit."""
        if not self._undo:
            return
        self._redo.append(copy.deepcopy(self.setup_dict))
        self.setup_dict = self._undo.pop()
        self._after_setup_edit()

    def redo(self) -> None:
        """Redo the last undone edit."""
        if not self._redo:
            return
        self._undo.append(copy.deepcopy(self.setup_dict))
        self.setup_dict = self._redo.pop()
        self._after_setup_edit()

    # ------------------------------------------------------------------ pose
    def set_flexion(self, degrees: float, force: bool = False) -> None:
        """Re-pose the model at ``degrees`` now (synchronously) through the precomputed poser."""
        deg = float(np.clip(degrees, *FLEXION_RANGE))
        self._live.discard()
        if self.poser is None:
            self.flexion = self.target_flexion = deg
            return
        if deg == self.flexion and not force and not self._custom_coords:
            return
        self.target_flexion = deg
        self._bump(schedule=True)
        self._apply_pose(deg, self.poser.pose(deg))

    def _bump(self, schedule: bool) -> None:
        """A new pose is asked for: what runs for the previous one is stale from now on."""
        self.pose_generation += 1
        self.preview.pose_requested(schedule)

    def settle_flexion(self) -> None:
        """The slider was released: the export of its angle runs now."""
        self.preview.settle()

    def set_live_cells(self, cells: NDArray[np.int64] | None) -> None:
        """Elements whose quality the view shows (measured with each slider pose), or None."""
        self._live_cells = cells
        self._live_rows = None if cells is None else self._block_rows(cells)

    def _block_rows(self, cells: NDArray[np.int64]) -> dict[str, NDArray[np.int64]]:
        """Global cells as rows of each block (types without any left out)."""
        from kneegui.topology import block_offsets

        assert self.model is not None
        offsets = block_offsets(self.model.blocks)
        rows = {}
        for etype, block in self.model.blocks.items():
            start = offsets[etype]
            sel = cells[(cells >= start) & (cells < start + len(block))] - start
            if len(sel):
                rows[etype] = sel
        return rows

    def _live_quality_job(self):
        """A function measuring the shown elements at given coordinates, for the pose thread."""
        cells, rows, evaluator = self._live_cells, self._live_rows, self._evaluator
        if cells is None or rows is None or evaluator is None or self.model is None:
            return None
        # a heat-map needs its measure alone (bit-identical, a sixth to two thirds of the cost)
        only = None
        if self.colour_mode == "quality" and _quality_metric(self.metric) in ONLY_METRICS:
            only = _quality_metric(self.metric)
        return lambda coords: (cells, evaluator.evaluate(coords, rows, only=only))

    def request_flexion(self, degrees: float) -> None:
        """Re-pose at ``degrees`` as soon as possible (slider drags).

        The pose is computed in a pose thread while the GUI thread draws the previous one;
        requests that arrive meanwhile collapse into the latest, so a fast drag never queues up.
        """
        deg = float(np.clip(degrees, *FLEXION_RANGE))
        if self.poser is None:
            self.flexion = self.target_flexion = deg
            return
        if deg == self.target_flexion and not self._custom_coords:
            return
        self.target_flexion = deg
        self.pose_generation += 1  # (as _bump, with the pose pending before anyone is told)
        self._live.request(self.poser, deg, self._live_quality_job(), self.pose_generation)
        self.preview.pose_requested(schedule=True)

    @property
    def pose_pending(self) -> bool:
        """Whether a requested pose is still being computed."""
        return self._live.busy

    @property
    def preview_pending(self) -> bool:
        """Whether the export of the current angle is running or waiting to run."""
        return self.preview.busy

    @property
    def smoothed(self) -> bool:
        """Whether the view shows the export path's result (relaxed and smoothed)."""
        return self.exported is not None

    @property
    def view_kind(self) -> str:
        """``"as exported"``, ``"relaxing"`` (a stage of the running export) or ``"live
        mapping"``: what the view shows."""
        from app.preview import EXPORTED, LIVE, RELAXING

        if self.exported is not None:
            return EXPORTED
        return RELAXING if self.stage is not None else LIVE

    def _apply_pose(
        self,
        deg: float,
        coords: NDArray[np.float64],
        pose_quality=None,
        generation: int | None = None,
    ) -> None:
        if (
            generation is not None
            and self.exported is not None
            and self.exported.generation >= generation
        ):
            return  # the export of this (or a later) request is already shown
        if self.stage is not None and generation is not None:
            if self._stage_generation >= generation:
                return  # a stage of its export is already shown
        self._show(deg, coords, pose_quality=pose_quality)

    def _show(
        self,
        flexion: float,
        coords: NDArray[np.float64],
        *,
        exported: ExportedPose | None = None,
        stage: str | None = None,
        custom: bool = False,
        pose_quality=None,
    ) -> None:
        """Make ``coords`` the view: what they are (a live pose, an export, a stage of one,
        custom coordinates), the measures of the previous view forgotten."""
        self.flexion = flexion
        self.coords = coords
        self.exported = exported
        self.stage = stage
        self._custom_coords = custom
        self._quality = None
        self._pose_quality = pose_quality
        self.coords_changed.emit()

    def show_exported(self, exported: ExportedPose) -> bool:
        """Show the export path's result unless a newer pose was asked for meanwhile."""
        if exported.generation != self.pose_generation or self.model is None:
            return False
        self._show(exported.flexion, np.array(exported.coords, dtype=np.float64), exported=exported)
        self.status.emit(exported.message)
        return True

    def show_stage(
        self, generation: int, flexion: float, stage: str, coords: NDArray[np.float64]
    ) -> bool:
        """Show the pose a stage of the running export ended on (``"untangle"``: the
        untangled pose while the quality stage runs), unless a newer pose was asked for or
        the export is already shown; whether it was shown. It is not what the export writes:
        :meth:`export` refuses it."""
        if generation != self.pose_generation or self.model is None or self.exported is not None:
            return False
        self._stage_generation = generation
        self._show(flexion, coords, stage=stage)
        return True

    def drop_stage(self) -> None:
        """Back to the live mapping at the angle shown when the view shows a stage of an
        export that ended without its result (failed or cancelled): a stage is never left as
        if it were a pose of its own. Asks for no export."""
        if self.stage is None or self.exported is not None or self.poser is None:
            return
        self._apply_pose(self.flexion, self.poser.pose(self.flexion))

    def set_coords(self, coords: NDArray[np.float64]) -> None:
        """Replace the current coordinates with arbitrary ones (not a pose, not exported)."""
        self._live.discard()
        self._bump(schedule=False)
        self._show(self.flexion, np.array(coords, dtype=np.float64), custom=True)

    def view_figures(self) -> PoseFigures | None:
        """Inverted elements, worst Jacobian and largest volume change of what is shown (the
        export's report figures when it is shown; measured on demand otherwise)."""
        if self.model is None or self._initial_quality is None:
            return None
        if self.exported is not None:
            return self.exported.figures
        if self._figures is None or self._figures[0] is not self.coords:
            figures = pose_figures(self.model, self.quality(), self._initial_quality)
            self._figures = (self.coords, figures)
        return self._figures[1]

    @property
    def evaluator(self) -> QualityEvaluator | None:
        """The quality evaluator of the current model's blocks."""
        return self._evaluator

    @property
    def initial_quality(self) -> QualityResult | None:
        """Quality of the model as read (the reference of volume changes)."""
        return self._initial_quality

    def posed_model(self) -> Model:
        """The model at the current coordinates."""
        assert self.model is not None
        return self.model.with_coords(self.coords)

    # ------------------------------------------------------------------ quality
    def quality(self) -> QualityResult:
        """Quality of the current pose (computed on demand, cached until the pose changes)."""
        if self._quality is None:
            assert self._evaluator is not None
            self._quality = self._evaluator.evaluate(self.coords)
        return self._quality

    def element_values(
        self, metric: str, cells: NDArray[np.int64] | None = None
    ) -> NDArray[np.float64]:
        """One value per global cell (``model.blocks`` order); NaN for unmeasured types.

        Parameters
        ----------
        metric : str
            A key of :data:`HEATMAP_METRICS`. ``volume_change`` is measured on solids only and
            ``area_change`` on shells only (percent against the initial pose); a tet measure
            is NaN on other element types.
        cells : (k,) ndarray of int, optional
            Measure only these global cells (the others are NaN): what the view shows.
        """
        assert self.model is not None and self._evaluator is not None
        from kneegui.topology import block_offsets

        if cells is None:
            q = self.quality()
            rows = {e: np.arange(len(b)) for e, b in self.model.blocks.items()}
        else:
            # the shown cells' rows are worked out once, when the view sets them
            live = cells is self._live_cells and self._live_rows is not None
            rows = self._live_rows if live else self._block_rows(cells)
            if self._quality is not None:
                q = self._quality
            elif (
                self._pose_quality is not None
                and self._pose_quality[0] is cells
                and _measured(self._pose_quality[1], metric)
            ):
                q = self._pose_quality[1]  # measured in the pose thread with this pose
            else:
                q = self._evaluator.evaluate(self.coords, rows)
        out = np.full(self.model.n_elements, np.nan)
        offsets = block_offsets(self.model.blocks)
        for etype, sel in rows.items():
            if etype not in q:
                continue
            part = q[etype]
            solid = etype in SOLID_TYPES
            if (metric == "volume_change" and not solid) or (metric == "area_change" and solid):
                continue  # a solid's volume and a shell's area are different measures
            if metric not in ("volume_change", "area_change") and not part.has(
                HEATMAP_METRICS[metric][1]
            ):
                continue  # a tet measure on another element type
            if cells is not None and self._quality is not None:
                values_rows = sel
            else:
                values_rows = np.arange(len(part)) if cells is not None else sel
            if metric in ("volume_change", "area_change"):
                v0 = self._initial_quality[etype].volume[sel]
                v = part.volume[values_rows]
                vals = volume_change_pct(v, v0)
                vals[~np.isfinite(vals)] = np.nan  # a flat initial element: no colour
            else:
                vals = np.asarray(part.metric(HEATMAP_METRICS[metric][1]), float)[values_rows]
            out[offsets[etype] + sel] = vals
        return out

    def worst_elements(self, metric: str, count: int = 20) -> list[tuple[int, int, str, float]]:
        """The ``count`` worst elements: ``(global cell, element id, part title, value)``."""
        assert self.model is not None
        values = self.element_values(metric)
        low_bad = HEATMAP_METRICS[metric][2]
        finite = np.flatnonzero(np.isfinite(values))
        if not len(finite):
            return []
        key = values[finite] if low_bad else -np.abs(values[finite])
        order = finite[np.argsort(key, kind="stable")[:count]]
        ids = np.concatenate([b.ids for b in self.model.blocks.values()])
        pids = np.concatenate([b.part_ids for b in self.model.blocks.values()])
        out = []
        for c in order.tolist():
            pid = int(pids[c])
            title = self.model.parts[pid].title if pid in self.model.parts else ""
            out.append((c, int(ids[c]), f"{pid} {title}".strip(), float(values[c])))
        return out

    def ligament_stretch_values(self) -> NDArray[np.float64]:
        """Fibre stretch per global cell (NaN outside ligaments)."""
        assert self.model is not None
        from kneegui.topology import block_offsets

        out = np.full(self.model.n_elements, np.nan)
        offsets = block_offsets(self.model.blocks)
        for lig in self.ligaments:
            s = lig.element_stretch(self.coords)
            start = 0
            for etype, rows in zip(lig.element_types, lig.rows, strict=True):
                out[offsets[etype] + rows] = s[start : start + len(rows)]
                start += len(rows)
        return out

    # ------------------------------------------------------------------ view state
    def set_colour_mode(self, mode: str) -> None:
        if mode not in ("part", "quality", "stretch"):
            raise ValueError(mode)
        if mode != self.colour_mode:
            self.colour_mode = mode
            self.display_changed.emit("colour")

    def heatmap_metrics(self) -> list[str]:
        """The heat-map metrics the current model offers (:func:`heatmap_metrics`)."""
        return heatmap_metrics(self.model)

    def set_metric(self, metric: str) -> None:
        if metric not in HEATMAP_METRICS:
            raise ValueError(metric)
        if metric != self.metric:
            self.metric = metric
            self.threshold = None
            self.display_changed.emit("colour")

    def set_threshold(self, value: float | None) -> None:
        self.threshold = value
        self.display_changed.emit("threshold")

    def set_part_visible(self, pid: int, visible: bool) -> None:
        before = pid in self.hidden_parts
        (self.hidden_parts.discard if visible else self.hidden_parts.add)(int(pid))
        if before == visible:
            self.display_changed.emit("visibility")

    def set_clip(self, enabled: bool, normal: str | None = None, offset: float | None = None):
        self.clip_enabled = bool(enabled)
        if normal is not None:
            self.clip_normal = normal
        if offset is not None:
            self.clip_offset = float(offset)
        self.display_changed.emit("clip")

    def knee_frame(self) -> dict[str, NDArray[np.float64]]:
        """Knee centre and anatomical directions (from the axes, else the model's box)."""
        if self.axes is not None:
            a = self.axes
            lateral = -a.sagittal_normal
            return {
                "center": np.asarray(a.knee_center),
                "anterior": np.asarray(a.anterior),
                "superior": np.asarray(a.superior),
                "lateral": np.asarray(lateral),
            }
        box = self.model.bounding_box() if self.model is not None else np.zeros((2, 3))
        return {
            "center": box.mean(axis=0),
            "anterior": np.array([1.0, 0, 0]),
            "superior": np.array([0, 0, 1.0]),
            "lateral": np.array([0, -1.0, 0]),
        }

    # ------------------------------------------------------------------ long tasks
    def _start(self, name, work, done) -> bool:
        def on_error(exc):
            self.error.emit(exc)

        def finished(result):
            done(result)

        started = self.tasks.start(name, work, finished, on_error)
        if not started:
            self.status.emit(f"busy with {self.tasks.current_name}; try again when it ends")
        return started

    def shutdown(self, msecs: int = 10000) -> None:
        """Cancel background work and wait for the worker threads (window closing, tests)."""
        self.tasks.cancel()
        self.preview.reset()
        self._live.discard()
        self.tasks.wait(msecs)
        self.preview.tasks.wait(msecs)
        self._live.wait(msecs)

    def on_task_finished(self) -> None:
        """Run a poser rebuild that was deferred while another task ran."""
        if self._poser_stale:
            self.rebuild_poser()

    def compute_ligament_curve(self, step: float = 5.0) -> bool:
        """Each ligament's length from -5° to 140° (worker thread)."""
        if self.poser is None or not self.ligaments:
            return False
        poser, ligaments = self.poser, self.ligaments
        angles = np.arange(FLEXION_RANGE[0], FLEXION_RANGE[1] + 1e-9, step)

        def work(progress, cancelled):
            return angles, length_curve(ligaments, poser.pose, angles, cancelled, progress)

        def done(result):
            self.ligament_curve = result
            self.ligaments_changed.emit()

        return self._start("Ligament lengths", work, done)

    def smooth(self) -> bool:
        """Show the export of the current angle now (Relax + smooth): the export path
        (:func:`kneegui.reposition.pipeline.pose_model`) runs in the preview worker, its result
        becomes the view and the status line gives the report's warnings and what was done. A
        failure is shown in a dialog.

        Returns False (and says why) while no poser is ready or when the export is shown.
        """
        if self.model is None:
            return False
        if self.poser is None:
            self.status.emit("Relax + smooth waits for the poser (precomputing)")
            return False
        if self.exported is not None and self.exported.generation == self.pose_generation:
            self.status.emit("the view already shows the export of this angle")
            return False
        if self._custom_coords:
            self.set_flexion(self.target_flexion, force=True)
        self.preview.start(explicit=True)
        return True

    def export(self, path: str | Path, force: bool = False, flatten: bool = False) -> bool:
        """Write the posed deck (worker thread, atomic).

        Raises
        ------
        ExportBlocked
            If the current pose has inverted elements and ``force`` is false.
        """
        if self.model is None:
            raise KneeguiError("nothing to export")
        exported = self.exported
        if exported is not None:
            # what is shown is the export path's result: written as it is, not solved again
            n_inv = exported.figures.inverted
            if not exported.posed.passes_gate and not force:
                raise ExportBlocked(
                    f"the export at {exported.flexion:g}° fails the quality gate: "
                    f"{'; '.join(exported.posed.gate_reasons)}; force the export to write it"
                )
            posed = exported.posed.model
        elif self.stage is not None:
            # a stage's pose is not a product: the export writes the chain's end, once shown
            raise KneeguiError(
                f"the view shows the {STAGE_NAMES.get(self.stage, self.stage)} pose of the "
                f"export at {self.flexion:g}°, not what the export writes: export once the "
                "view says 'as exported'"
            )
        else:
            n_inv = self.quality().n_inverted
            if n_inv and not force:
                waiting = (
                    " (the export of this angle is still running: wait for 'as exported')"
                    if self.preview_pending
                    else ""
                )
                raise ExportBlocked(
                    f"{n_inv} inverted element(s) in the live mapping at {self.flexion:.1f}°"
                    f"{waiting}: relax and smooth first, or force the export"
                )
            posed = self.posed_model()
        target = Path(path)

        def work(progress, cancelled):
            from kneegui.io.lsdyna import write_deck, write_model

            progress(0.2, f"writing {target.name}")
            if posed.source is not None:
                write_deck(posed, target, flatten=flatten)
            else:
                write_model(posed, target, title=f"kneegui posed at {self.flexion:.1f} deg")
            progress(1.0, "written")
            return target

        kind = self.view_kind

        def done(result):
            self.status.emit(f"exported {result} ({kind}, {n_inv} inverted)")

        return self._start("Exporting", work, done)


class _LiveRelay(QObject):
    done = Signal(object)


class LivePoser(QObject):
    """Computes slider poses in one background thread, keeping only the latest request."""

    def __init__(self, workspace: Workspace):
        super().__init__(workspace)
        from PySide6.QtCore import QThreadPool

        self._ws = workspace
        self._pool = QThreadPool(self)
        self._pool.setMaxThreadCount(1)
        self._relay = _LiveRelay(self)
        self._relay.done.connect(self._on_done)
        self._running = False
        self._next: tuple | None = None
        self._generation = 0

    @property
    def busy(self) -> bool:
        return self._running or self._next is not None

    def request(self, poser: Poser, degrees: float, measure=None, tag: int | None = None) -> None:
        """Pose at ``degrees`` (``tag``: the workspace's pose generation of the request)."""
        self._next = (poser, degrees, measure, tag)
        if not self._running:
            self._start()

    def discard(self) -> None:
        """Forget pending and running requests (a synchronous pose supersedes them)."""
        self._next = None
        self._generation += 1

    def wait(self, msecs: int = -1) -> bool:
        return self._pool.waitForDone(msecs)

    def _start(self) -> None:
        from PySide6.QtCore import QRunnable

        poser, degrees, measure, tag = self._next
        self._next = None
        self._running = True
        generation, relay = self._generation, self._relay

        class Job(QRunnable):
            def run(self) -> None:
                quality = None
                try:
                    result = poser.pose(degrees)
                    if measure is not None:
                        quality = measure(result)
                except Exception as exc:  # shown by the workspace's error boundary
                    result = exc
                relay.done.emit((generation, poser, degrees, result, quality, tag))

        job = Job()
        job.setAutoDelete(True)
        self._pool.start(job)

    def _on_done(self, payload) -> None:
        generation, poser, degrees, result, quality, tag = payload
        self._running = False
        ws = self._ws
        if generation == self._generation and poser is ws.poser:
            if isinstance(result, Exception):
                ws.error.emit(result)
            else:
                ws._apply_pose(degrees, result, quality, tag)
        if self._next is not None:
            self._start()
        elif not self._running:
            ws.live_idle.emit()


def read_setup_json(path: str | Path) -> dict[str, Any]:
    """The setup file as a dictionary (SetupError with the file and line on bad JSON)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise SetupError(f"cannot read: {exc.strerror or exc}", path=p) from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SetupError(f"line {exc.lineno}: invalid JSON ({exc.msg})", path=p) from None
    if not isinstance(data, dict):
        raise SetupError("the file must hold a JSON object", path=p)
    return data


def default_setup_dict(model: Model, side: str = "right") -> dict[str, Any]:
    """A starting setup for a deck without one: the engine's suggestion, else roles only."""
    from kneegui.setup import suggest_roles, suggest_setup

    try:
        return suggest_setup(model, side)
    except KneeguiError:
        pass
    roles = suggest_roles(model, side=side)
    return {
        "format": "kneegui-setup",
        "version": 1,
        "side": side,
        "roles": {r: list(v) for r, v in roles.items()},
        "landmarks": {
            "lateral_condyle": [],
            "medial_condyle": [],
            "lr_axis": [None, None],
            "femur_axis": [None, None],
            "tibia_axis": [None, None],
        },
    }
