"""The pre-flight panel: what limits the pose, before posing (:mod:`kneegui.reposition.preflight`).

When a poser is ready the check runs in its own background thread (about a second: the bones'
motions over the supported flexion range) and the panel shows its summary (locked elements,
coincident node pairs, the movable region) and lists the locked elements with the flexion range
over which each stays valid; double-click zooms to one, as the quality panel's worst elements do.
:class:`LockedOverlay` draws the locked elements in their own colour over the model and moves
them with every pose.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from PySide6.QtCore import QObject, QRunnable, Qt, QThreadPool, Signal
from PySide6.QtWidgets import (
    QCheckBox,
    QLabel,
    QListWidget,
    QListWidgetItem,
    QVBoxLayout,
    QWidget,
)
from vtk.util.numpy_support import vtk_to_numpy

from app.workspace import Workspace
from kneegui.reposition.preflight import Preflight, preflight_of
from kneegui.topology import block_offsets

#: The locked elements' colour in the 3-D view (no role colour is orange).
LOCKED_COLOUR = "#ff7f0e"


class _Relay(QObject):
    done = Signal(object)


class PreflightPanel(QWidget):
    """Summary and locked-element list of the current poser's pre-flight check.

    Signals
    -------
    zoom_requested(int) : a locked element (global cell index) was double-clicked
    preflight_changed : a new check result (or none) is shown
    """

    zoom_requested = Signal(int)
    preflight_changed = Signal()

    def __init__(self, ws: Workspace, parent: QWidget | None = None):
        super().__init__(parent)
        self.ws = ws
        self.preflight: Preflight | None = None
        self.cells: NDArray[np.int64] = np.zeros(0, dtype=np.int64)
        layout = QVBoxLayout(self)
        self.summary = QLabel("Pre-flight check: waiting for the repositioner")
        self.summary.setWordWrap(True)
        self.summary.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        layout.addWidget(self.summary)
        self.show_locked = QCheckBox("Show locked elements in the view")
        self.show_locked.setChecked(True)
        layout.addWidget(self.show_locked)
        layout.addWidget(QLabel("Locked elements (double-click to zoom)"))
        self.locked_list = QListWidget()
        layout.addWidget(self.locked_list, 1)
        self.locked_list.itemDoubleClicked.connect(
            lambda item: self.zoom_requested.emit(int(item.data(Qt.ItemDataRole.UserRole)))
        )
        self._pool = QThreadPool(self)
        self._pool.setMaxThreadCount(1)
        self._relay = _Relay(self)
        self._relay.done.connect(self._on_done)
        ws.model_changed.connect(self._clear)
        ws.poser_changed.connect(self.run_check)

    # ------------------------------------------------------------------ the check
    def run_check(self) -> None:
        """Run the check for the current poser in the background (cached per poser)."""
        poser = self.ws.poser
        if poser is None:
            return
        self.summary.setText("Pre-flight check: running…")
        relay = self._relay

        class Job(QRunnable):
            def run(self) -> None:
                try:
                    result = preflight_of(poser)
                except Exception as exc:  # shown by the workspace's error boundary
                    result = exc
                relay.done.emit((poser, result))

        job = Job()
        job.setAutoDelete(True)
        self._pool.start(job)

    def busy(self) -> bool:
        """True while a check runs."""
        return self._pool.activeThreadCount() > 0

    def shutdown(self, msecs: int = 10000) -> None:
        """Wait for a running check (the window is closing)."""
        self._pool.waitForDone(msecs)

    def _on_done(self, payload) -> None:
        poser, result = payload
        if poser is not self.ws.poser:
            return  # a newer poser's check follows
        if isinstance(result, Exception):
            self.summary.setText(f"Pre-flight check failed: {result}")
            self.ws.error.emit(result)
            return
        self._show(result)

    def _clear(self) -> None:
        self.preflight = None
        self.cells = np.zeros(0, dtype=np.int64)
        self.locked_list.clear()
        self.summary.setText("Pre-flight check: waiting for the repositioner")
        self.preflight_changed.emit()

    # ------------------------------------------------------------------ display
    def _show(self, pre: Preflight) -> None:
        model = self.ws.model
        if model is None:
            return
        self.preflight = pre
        offsets = block_offsets(model.blocks)
        locked = pre.locked
        self.cells = np.array(
            [offsets[str(t)] + int(r) for t, r in zip(locked.etype, locked.rows, strict=True)],
            dtype=np.int64,
        )
        lo, hi = pre.valid_range_deg()
        lines = [
            f"Locked elements: {len(locked)}"
            + (f", all valid from {lo:.1f} to {hi:.1f}°" if len(locked) else ""),
            f"Coincident node pairs (sliding interfaces): {len(pre.coincident_pairs)}",
        ]
        for (a, b), (n, _pa, _pb) in pre.coincident_by_segment().items():
            lines.append(f"    {n} {a} | {b}")
        lines.append(
            f"Movable region: {pre.movable_nodes} nodes, {pre.movable_elements} elements "
            f"with a movable node"
        )
        lines.append(
            f"Checked {pre.flexion_range_deg[0]:g} to {pre.flexion_range_deg[1]:g}° from the "
            f"initial {pre.initial_flexion_deg:.1f}°"
        )
        self.summary.setText("\n".join(lines))
        self.locked_list.clear()
        order = np.argsort(
            np.where(np.isfinite(locked.inverts_above_deg), locked.inverts_above_deg, np.inf),
            kind="stable",
        )
        for k in order.tolist():
            pid = int(locked.part_ids[k])
            title = pre.part_titles.get(pid, "")
            item = QListWidgetItem(
                f"{int(locked.ids[k]):>8}  {'+'.join(locked.segments[k])}  "
                f"{pre.locked_limits(k)}  {pid} {title}".rstrip()
            )
            item.setData(Qt.ItemDataRole.UserRole, int(self.cells[k]))
            self.locked_list.addItem(item)
        self.preflight_changed.emit()


class LockedOverlay:
    """The locked elements drawn in :data:`LOCKED_COLOUR` over the model, moving with the pose.

    Parameters
    ----------
    viewport : app.viewport.Viewport
    panel : PreflightPanel
        Whose check result and check box it follows.
    """

    NAME = "preflight-locked"

    def __init__(self, viewport, panel: PreflightPanel):
        self.viewport = viewport
        self.panel = panel
        self.ws = panel.ws
        self._mesh = None
        self._index: NDArray[np.int64] = np.zeros(0, dtype=np.int64)
        panel.preflight_changed.connect(self.rebuild)
        panel.show_locked.toggled.connect(lambda _on: self.rebuild())
        self.ws.model_changed.connect(self._forget)
        self.ws.coords_changed.connect(self.move)

    @property
    def shown_cells(self) -> NDArray[np.int64]:
        """Global cells drawn (empty when hidden or none is locked)."""
        if self._mesh is None:
            return np.zeros(0, dtype=np.int64)
        return np.asarray(self._mesh.cell_data["vtkOriginalCellIds"], dtype=np.int64)

    def _forget(self) -> None:
        # the viewport clears every actor when a model is loaded
        self._mesh = None
        self._index = np.zeros(0, dtype=np.int64)

    def rebuild(self) -> None:
        """Draw the panel's locked elements (or remove them)."""
        plotter = self.viewport.plotter
        cells = self.panel.cells
        grid = self.viewport.grid
        if grid is None or not len(cells) or not self.panel.show_locked.isChecked():
            self._forget()
            plotter.remove_actor(self.NAME, render=False)
            self.viewport.render()
            return
        sub = grid.extract_cells(cells)
        self._index = np.asarray(sub.point_data["vtkOriginalPointIds"], dtype=np.int64)
        self._mesh = sub
        self.move()
        plotter.add_mesh(
            sub,
            color=LOCKED_COLOUR,
            show_edges=True,
            edge_color="black",
            name=self.NAME,
            reset_camera=False,
            render=False,
        )
        self.viewport.render()

    def move(self) -> None:
        """Follow the current pose (a few elements: cheap on every slider step)."""
        if self._mesh is None or self.ws.model is None:
            return
        points = self._mesh.GetPoints()
        vtk_to_numpy(points.GetData())[:] = self.ws.coords[self._index]
        points.Modified()
