"""The main window: viewport in the centre, panels in docks, menus, status bar with progress.

Errors from any action are caught at one boundary (:meth:`MainWindow.guard` and the workspace's
``error`` signal) and shown in a non-blocking dialog naming the file and line; a failed open
keeps the previous model. A deck with an autosaved setup (left by a crash) is offered back in a
question (:meth:`MainWindow.offer_restore`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from PySide6.QtCore import QBuffer, QByteArray, QIODevice, QPoint, QSettings, Qt
from PySide6.QtGui import QAction, QImage, QKeySequence, QPainter
from PySide6.QtWidgets import (
    QDockWidget,
    QFileDialog,
    QLabel,
    QMainWindow,
    QMessageBox,
    QProgressBar,
    QProgressDialog,
    QPushButton,
    QToolBar,
    QVBoxLayout,
    QWidget,
)

from app.panels import (
    FlexionPanel,
    LandmarkPanel,
    LigamentPanel,
    ModelPanel,
    QualityCurvePanel,
    QualityPanel,
    ViewIndicator,
)
from app.preflight_panel import LockedOverlay, PreflightPanel
from app.qt_compat import protect_singletons
from app.viewport import CAMERA_PRESETS, Viewport
from app.workspace import ExportBlocked, Workspace
from kneegui.errors import DeckError, SetupError
from kneegui.io.atomic import atomic_write_bytes

ORGANIZATION = "kneegui"
APPLICATION = "kneegui-gui"
MAX_RECENT = 8
DECK_FILTER = "LS-DYNA decks (*.k *.key *.dyn);;All files (*)"
#: The tasks of opening a deck, followed in the open-progress dialog (the second one only
#: right after the first: it also runs after every setup edit, without a dialog).
OPEN_TASKS = ("Opening deck", "Preparing the repositioner")


def app_settings() -> QSettings:
    """The application's settings (INI format; tests redirect its folder with QSettings.setPath)."""
    return QSettings(
        QSettings.Format.IniFormat, QSettings.Scope.UserScope, ORGANIZATION, APPLICATION
    )


def describe_error(exc: BaseException) -> str:
    """One message naming the file and line when the error knows them."""
    if isinstance(exc, DeckError):
        where = str(exc.path) if exc.path else ""
        if exc.line is not None:
            where += f", line {exc.line}"
        return f"{exc.message}\n\nFile: {where}" if where else exc.message
    if isinstance(exc, SetupError):
        parts = [exc.message]
        if exc.key:
            parts.append(f"Key: {exc.key}")
        if exc.path:
            parts.append(f"File: {exc.path}")
        return "\n\n".join(parts)
    return f"{type(exc).__name__}: {exc}"


class MainWindow(QMainWindow):
    """kneegui's window. ``workspace`` holds all state; this class wires widgets to it."""

    def __init__(self, workspace: Workspace | None = None):
        protect_singletons()
        super().__init__()
        self.setWindowTitle("kneegui — knee repositioning[*]")
        self.setObjectName("kneegui-main")
        self.ws = workspace or Workspace(self)
        self.settings = app_settings()
        self.last_error: str | None = None
        self.error_dialog: QMessageBox | None = None
        #: Answers the "restore the autosaved setup?" question instead of a dialog when set:
        #: ``fn(deck path, autosave path) -> bool`` (tests).
        self.restore_answer: Callable[[Path, Path], bool] | None = None
        self.restore_dialog: QMessageBox | None = None
        self.viewport = Viewport(self.ws, self)
        self.indicator = ViewIndicator(self.ws)
        central = QWidget(self)
        column = QVBoxLayout(central)
        column.setContentsMargins(0, 0, 0, 0)
        column.setSpacing(0)
        column.addWidget(self.indicator)
        column.addWidget(self.viewport, 1)
        self.setCentralWidget(central)
        self.model_panel = ModelPanel(self.ws)
        self.landmark_panel = LandmarkPanel(self.ws)
        self.quality_panel = QualityPanel(self.ws)
        self.ligament_panel = LigamentPanel(self.ws)
        self.flexion_panel = FlexionPanel(self.ws)
        self.preflight_panel = PreflightPanel(self.ws)
        self.locked_overlay = LockedOverlay(self.viewport, self.preflight_panel)
        self.quality_curve_panel = QualityCurvePanel(self.ws)
        self.docks: dict[str, QDockWidget] = {}
        self._dock("Model", self.model_panel, Qt.DockWidgetArea.LeftDockWidgetArea)
        self._dock("Landmarks", self.landmark_panel, Qt.DockWidgetArea.RightDockWidgetArea)
        self._dock("Quality", self.quality_panel, Qt.DockWidgetArea.RightDockWidgetArea)
        self._dock("Ligaments", self.ligament_panel, Qt.DockWidgetArea.RightDockWidgetArea)
        self._dock("Pre-flight", self.preflight_panel, Qt.DockWidgetArea.RightDockWidgetArea)
        self._dock("Flexion", self.flexion_panel, Qt.DockWidgetArea.BottomDockWidgetArea)
        self._dock(
            "Quality vs flexion", self.quality_curve_panel, Qt.DockWidgetArea.RightDockWidgetArea
        )
        self.tabifyDockWidget(self.docks["Landmarks"], self.docks["Quality"])
        self.tabifyDockWidget(self.docks["Quality"], self.docks["Ligaments"])
        self.tabifyDockWidget(self.docks["Ligaments"], self.docks["Quality vs flexion"])
        self.tabifyDockWidget(self.docks["Quality vs flexion"], self.docks["Pre-flight"])
        self.docks["Landmarks"].raise_()
        self._build_status()
        self._build_actions()
        self.quality_panel.zoom_requested.connect(self.viewport.zoom_to_element)
        self.preflight_panel.zoom_requested.connect(self.viewport.zoom_to_element)
        self.ws.error.connect(self.show_error)
        self.ws.autosave_found.connect(self.offer_restore)
        self.ws.status.connect(lambda text: self.statusBar().showMessage(text, 8000))
        self.ws.tasks.started.connect(self._task_started)
        self.ws.tasks.progress.connect(self._task_progress)
        self.ws.tasks.finished.connect(self._task_finished)
        self.ws.model_changed.connect(self._on_model_opened)
        self.ws.dirty_changed.connect(self.setWindowModified)
        self.open_progress: QProgressDialog | None = None
        self._opening = False
        self.resize(1500, 920)
        self._restore_layout()

    # ------------------------------------------------------------------ construction
    def _dock(self, title: str, widget: QWidget, area) -> None:
        dock = QDockWidget(title, self)
        dock.setObjectName(f"dock-{title.lower().replace(' ', '-')}")
        dock.setWidget(widget)
        self.addDockWidget(area, dock)
        self.docks[title] = dock

    def _build_status(self) -> None:
        bar = self.statusBar()
        self.task_label = QLabel("")
        self.progress = QProgressBar()
        self.progress.setRange(0, 1000)
        self.progress.setMaximumWidth(220)
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.clicked.connect(self.ws.tasks.cancel)
        for w in (self.task_label, self.progress, self.cancel_button):
            bar.addPermanentWidget(w)
            w.setVisible(False)

    def _action(self, menu, text: str, slot: Callable, shortcut=None) -> QAction:
        action = QAction(text, self)
        if shortcut is not None:
            action.setShortcut(QKeySequence(shortcut))
        action.triggered.connect(lambda _checked=False: self.guard(slot))
        menu.addAction(action)
        return action

    def _build_actions(self) -> None:
        mb = self.menuBar()
        file_menu = mb.addMenu("&File")
        self._action(file_menu, "Open deck…", self.open_deck_dialog, QKeySequence.StandardKey.Open)
        self._action(file_menu, "Open demo leg", self.open_demo)
        self.recent_menu = file_menu.addMenu("Recent decks")
        file_menu.addSeparator()
        self._action(file_menu, "Open setup…", self.open_setup_dialog)
        self._action(
            file_menu, "Save setup…", self.save_setup_dialog, QKeySequence.StandardKey.Save
        )
        file_menu.addSeparator()
        self._action(file_menu, "Export posed deck…", self.export_dialog, "Ctrl+E")
        self._action(file_menu, "Screenshot…", self.screenshot_dialog, "Ctrl+P")
        file_menu.addSeparator()
        self._action(file_menu, "Quit", self.close, QKeySequence.StandardKey.Quit)
        edit = mb.addMenu("&Edit")
        self._action(edit, "Undo landmark/role edit", self.ws.undo, QKeySequence.StandardKey.Undo)
        self._action(edit, "Redo", self.ws.redo, QKeySequence.StandardKey.Redo)
        tools = mb.addMenu("&Mesh")
        tools.setToolTipsVisible(True)
        self._action(tools, "Relax and smooth current pose", self.ws.smooth)
        self.rest_export_action = QAction("Show the export when the slider rests", self)
        self.rest_export_action.setCheckable(True)
        self.rest_export_action.setChecked(self.ws.preview.enabled)
        self.rest_export_action.toggled.connect(self.set_rest_export)
        tools.addAction(self.rest_export_action)
        self.restore_volume_action = QAction(
            "Restore the soft tissue's volume before relaxing (slower)", self
        )
        self.restore_volume_action.setCheckable(True)
        self.restore_volume_action.setChecked(self.ws.restore_volume)
        self.restore_volume_action.setToolTip(
            "The export's volume step (kneegui pose --restore-volume): gives the soft solids "
            "back their rest volumes before the relaxation. See docs/user-guide.md."
        )
        self.restore_volume_action.toggled.connect(
            lambda on: self.guard(self.ws.set_restore_volume, on)
        )
        tools.addAction(self.restore_volume_action)
        self._action(tools, "Ligament lengths vs. flexion", self.ws.compute_ligament_curve)
        view = mb.addMenu("&View")
        toolbar = QToolBar("View", self)
        toolbar.setObjectName("toolbar-view")
        self.addToolBar(toolbar)
        for name in CAMERA_PRESETS:
            act = self._action(
                view, name.capitalize(), lambda n=name: self.viewport.camera_preset(n)
            )
            toolbar.addAction(act)
        toolbar.addSeparator()
        for text, slot in (
            ("Relax + smooth", self.ws.smooth),
            ("Export…", self.export_dialog),
            ("Screenshot…", self.screenshot_dialog),
        ):
            act = QAction(text, self)
            act.triggered.connect(lambda _c=False, s=slot: self.guard(s))
            toolbar.addAction(act)
        view.addSeparator()
        for dock in self.docks.values():
            view.addAction(dock.toggleViewAction())
        self._refresh_recent()

    # ------------------------------------------------------------------ error boundary
    def guard(self, fn: Callable, *args, **kwargs):
        """Run ``fn``; any exception becomes an error dialog (the app never crashes)."""
        try:
            return fn(*args, **kwargs)
        except ExportBlocked as exc:
            self._confirm_forced_export(exc)
        except Exception as exc:
            self.show_error(exc)
        return None

    def show_error(self, exc: BaseException) -> None:
        """Show ``exc`` in a non-blocking dialog (file and line when known)."""
        text = describe_error(exc)
        self.last_error = text
        self.statusBar().showMessage(text.splitlines()[0], 10000)
        box = QMessageBox(
            QMessageBox.Icon.Critical, "kneegui", text, QMessageBox.StandardButton.Ok, self
        )
        box.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose)
        self.error_dialog = box
        box.open()

    def offer_restore(self, autosave: Path) -> None:
        """Ask whether to restore the autosaved setup of the deck just opened (non-blocking).

        Yes loads it like Open setup… (a bad file shows the usual error dialog); No drops it.
        """
        deck = self.ws.deck_path
        if deck is None:
            return

        def answer(restore: bool) -> None:
            if self.ws.deck_path != deck:
                return  # another deck was opened meanwhile
            if restore:
                self.guard(self.ws.restore_autosave)
            else:
                self.ws.decline_autosave()

        if self.restore_answer is not None:
            answer(bool(self.restore_answer(deck, Path(autosave))))
            return
        box = QMessageBox(
            QMessageBox.Icon.Question,
            "Restore autosaved setup",
            f"The setup of {deck.name} was being edited when kneegui last stopped without saving "
            f"it.\n\nRestore those edits? (No discards them.)\n\nAutosave: {autosave}",
            QMessageBox.StandardButton.Yes | QMessageBox.StandardButton.No,
            self,
        )
        box.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose)
        yes = box.button(QMessageBox.StandardButton.Yes)
        box.finished.connect(lambda _result: answer(box.clickedButton() is yes))  # Esc: No
        self.restore_dialog = box
        box.open()

    # ------------------------------------------------------------------ file actions
    def open_demo(
        self, elements: int | None = None, element_type: str = "hex", joint: str = "sliding"
    ) -> None:
        """Open the built-in demo leg (generated on first use; ``element_type`` and ``joint``
        choose a variant, as ``kneegui demo``)."""
        from app.demo import DEFAULT_DEMO_ELEMENTS, demo_files

        deck, setup = demo_files(
            elements or DEFAULT_DEMO_ELEMENTS, element_type=element_type, joint=joint
        )
        self.ws.open_deck(deck, setup)

    def open_deck(self, path: str | Path, setup: str | Path | None = None) -> None:
        """Read ``path`` (and its setup: given, else ``<deck>.setup.json`` beside it) in the
        worker, with a progress dialog; it joins the recent decks once it is open."""
        path = Path(path)
        if setup is None:
            guess = path.with_suffix(".setup.json")
            setup = guess if guess.is_file() else None
        self.ws.open_deck(path, setup)

    def set_rest_export(self, enabled: bool) -> None:
        """Whether the export runs on the slider's angle when it rests."""
        if self.rest_export_action.isChecked() != bool(enabled):
            self.rest_export_action.setChecked(bool(enabled))  # toggled: calls this again
            return
        self.ws.preview.enabled = bool(enabled)
        if enabled:
            self.ws.preview.start()

    def open_deck_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Open deck", self._last_dir(), DECK_FILTER)
        if path:
            self.open_deck(path)

    def open_setup_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(
            self, "Open setup", self._last_dir(), "Setup (*.json);;All files (*)"
        )
        if path:
            self.ws.open_setup(path)

    def save_setup_dialog(self) -> None:
        path, _ = QFileDialog.getSaveFileName(
            self, "Save setup", self._last_dir(), "Setup (*.json)"
        )
        if path:
            self.ws.save_setup(path)

    def export_dialog(self) -> None:
        path, _ = QFileDialog.getSaveFileName(
            self, "Export posed deck", self._last_dir(), "LS-DYNA deck (*.k)"
        )
        if path:
            self._export_target = path
            self.ws.export(path)

    def _confirm_forced_export(self, exc: ExportBlocked) -> None:
        box = QMessageBox(
            QMessageBox.Icon.Warning,
            "Inverted elements",
            str(exc),
            QMessageBox.StandardButton.Cancel,
            self,
        )
        force = box.addButton("Export anyway", QMessageBox.ButtonRole.DestructiveRole)
        box.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose)
        target = getattr(self, "_export_target", None)

        def answered(_result):
            if box.clickedButton() is force and target:
                self.guard(self.ws.export, target, True)

        box.finished.connect(answered)
        self.error_dialog = box
        box.open()

    def screenshot_dialog(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Screenshot", self._last_dir(), "PNG (*.png)")
        if path:
            self.save_screenshot(path)

    def save_screenshot(self, path: str | Path) -> Path:
        """Save the whole window as a PNG, 3-D view included."""
        self.viewport.flush_all()
        image = self.grab().toImage()
        view = self.viewport.plotter
        frame = self.viewport.plotter.screenshot(None, return_img=True)
        if frame is not None and frame.size:
            h, w = frame.shape[:2]
            rgb = np.ascontiguousarray(frame[:, :, :3])
            qimg = QImage(rgb.data, w, h, 3 * w, QImage.Format.Format_RGB888).copy()
            painter = QPainter(image)
            ratio = image.devicePixelRatio() or 1.0
            origin = view.mapTo(self, QPoint(0, 0))
            target = qimg.scaled(int(view.width() * ratio), int(view.height() * ratio))
            target.setDevicePixelRatio(ratio)
            painter.drawImage(origin, target)
            painter.end()
        out = Path(path)
        buffer = QBuffer()
        buffer.open(QIODevice.OpenModeFlag.WriteOnly)
        if not image.save(buffer, "PNG"):
            raise OSError(f"could not encode the screenshot for {out}")
        return atomic_write_bytes(out, bytes(buffer.data()))

    # ------------------------------------------------------------------ recent / layout
    def _last_dir(self) -> str:
        return str(self.settings.value("last_dir", str(Path.home())))

    def recent_files(self) -> list[str]:
        value = self.settings.value("recent_decks", [])
        if isinstance(value, str):
            value = [value]
        return [str(v) for v in (value or [])]

    def _add_recent(self, path: Path) -> None:
        items = [str(path)] + [p for p in self.recent_files() if p != str(path)]
        self.settings.setValue("recent_decks", items[:MAX_RECENT])
        self.settings.setValue("last_dir", str(path.parent))
        self._refresh_recent()

    def _refresh_recent(self) -> None:
        self.recent_menu.clear()
        for p in self.recent_files():
            act = self.recent_menu.addAction(p)
            act.triggered.connect(lambda _c=False, q=p: self.guard(self.open_deck, q))
        self.recent_menu.setEnabled(bool(self.recent_files()))

    def _restore_layout(self) -> None:
        geometry = self.settings.value("window/geometry")
        state = self.settings.value("window/state")
        if isinstance(geometry, QByteArray):
            self.restoreGeometry(geometry)
        if isinstance(state, QByteArray):
            self.restoreState(state)

    def save_layout(self) -> None:
        self.settings.setValue("window/geometry", self.saveGeometry())
        self.settings.setValue("window/state", self.saveState())
        self.settings.sync()

    def closeEvent(self, event) -> None:
        self.save_layout()
        self.ws.close_deck()  # a normal close: only a crash leaves the autosave behind
        self.ws.shutdown(5000)
        self.preflight_panel.shutdown(5000)
        self.viewport.plotter.close()
        super().closeEvent(event)

    # ------------------------------------------------------------------ tasks
    def _task_started(self, name: str) -> None:
        if name == OPEN_TASKS[0] or (name in OPEN_TASKS and self._opening):
            self._opening = True
            self._show_open_progress(name)
        self.task_label.setText(name)
        self.progress.setValue(0)
        for w in (self.task_label, self.progress, self.cancel_button):
            w.setVisible(True)

    def _task_progress(self, fraction: float, message: str) -> None:
        self.progress.setValue(int(1000 * max(0.0, min(1.0, fraction))))
        if message:
            self.task_label.setText(message)
        dialog = self.open_progress
        if dialog is not None and dialog.isVisible():
            dialog.setValue(int(1000 * max(0.0, min(1.0, fraction))))
            if message:
                dialog.setLabelText(f"{self._open_title}\n{message}")

    def _task_finished(self, _name: str) -> None:
        if self.ws.tasks.busy:  # the next task started from the last one's result
            return
        for w in (self.task_label, self.progress, self.cancel_button):
            w.setVisible(False)
        self._opening = False
        if self.open_progress is not None:
            self.open_progress.hide()

    def _show_open_progress(self, name: str) -> None:
        """The open-progress dialog (window-modal; Cancel stops the reading or precompute)."""
        if self.open_progress is None:
            dialog = QProgressDialog(self)
            dialog.setWindowTitle("Opening")
            dialog.setWindowModality(Qt.WindowModality.WindowModal)
            dialog.setRange(0, 1000)
            dialog.setAutoClose(False)
            dialog.setAutoReset(False)
            dialog.setMinimumDuration(0)
            dialog.canceled.connect(self.ws.tasks.cancel)
            self.open_progress = dialog
        deck = self.ws.pending_deck or self.ws.deck_path
        self._open_title = f"{name}: {deck.name if deck else ''}"
        self.open_progress.setLabelText(self._open_title)
        self.open_progress.setValue(0)
        self.open_progress.show()

    def _on_model_opened(self) -> None:
        if self.ws.deck_path is not None:
            self._add_recent(self.ws.deck_path)
        self._update_title()

    def _update_title(self) -> None:
        """``<deck>[*] — kneegui``: Qt shows the ``*`` while the setup has unsaved edits."""
        name = self.ws.deck_path.name if self.ws.deck_path else "demo"
        self.setWindowTitle(f"{name}[*] — kneegui")
        self.setWindowModified(self.ws.setup_dirty)
