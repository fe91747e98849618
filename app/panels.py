"""Dock panels. Each one calls the workspace and listens to it; none talks to another.

- :class:`ModelPanel`: parts grouped by role, colour swatches, visibility, role editing, counts.
- :class:`LandmarkPanel`: pick targets, condyle sets, axis points, fits (radius, RMS, axis
  spread), undo/redo.
- :class:`FlexionPanel`: the flexion slider and spin box.
- :class:`QualityPanel`: heat-map metric, threshold, worst elements with zoom, cut-away.
- :class:`LigamentPanel`: stretch colouring and the length-vs-flexion plot.
- :class:`ViewIndicator`: the banner over the 3-D view saying what it shows (live mapping / as
  exported) with its quality figures.
- :class:`QualityCurvePanel`: worst Jacobian, inverted elements and largest volume change
  against flexion, for the live mapping and the exported angles.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QColor, QIcon, QPixmap
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QListWidget,
    QListWidgetItem,
    QPushButton,
    QSlider,
    QTreeWidget,
    QTreeWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.colors import ROLE_COLOURS, UNASSIGNED_COLOUR
from app.heatmaps import HEATMAP_METRICS, has_tets, jacobian_says_something
from app.workspace import FLEXION_RANGE, Workspace
from kneegui.setup import ROLES

SLIDER_STEPS_PER_DEGREE = 10


@contextmanager
def _blocked(*widgets):
    """Block the widgets' signals while syncing them from the workspace.

    (Not ``QSignalBlocker``: as a context manager in PySide6 6.12 it drops a reference to
    ``None`` on every exit, which eventually crashes the interpreter.)
    """
    previous = [w.blockSignals(True) for w in widgets]
    try:
        yield
    finally:
        for w, was in zip(widgets, previous, strict=True):
            w.blockSignals(was)


def _swatch(colour: str) -> QIcon:
    pix = QPixmap(14, 14)
    pix.fill(QColor(colour))
    return QIcon(pix)


# ---------------------------------------------------------------------------- model
class ModelPanel(QWidget):
    """Part tree grouped by role: swatch, visibility check box, role (editable), elements."""

    def __init__(self, ws: Workspace, parent: QWidget | None = None):
        super().__init__(parent)
        self.ws = ws
        layout = QVBoxLayout(self)
        self.summary = QLabel("no model")
        self.summary.setWordWrap(True)
        layout.addWidget(self.summary)
        self.tree = QTreeWidget()
        self.tree.setColumnCount(3)
        self.tree.setHeaderLabels(["Part", "Role", "Elements"])
        self.tree.setRootIsDecorated(True)
        header = self.tree.header()
        header.setStretchLastSection(False)
        header.setSectionResizeMode(0, QHeaderView.ResizeMode.Stretch)
        header.setSectionResizeMode(1, QHeaderView.ResizeMode.Fixed)
        header.setSectionResizeMode(2, QHeaderView.ResizeMode.ResizeToContents)
        header.resizeSection(1, 100)
        self.setMinimumWidth(430)
        layout.addWidget(self.tree)
        self.tree.itemChanged.connect(self._on_item_changed)
        ws.model_changed.connect(self.refresh)
        ws.setup_changed.connect(self.refresh)
        ws.display_changed.connect(lambda what: what == "visibility" and self.refresh())
        self.role_boxes: dict[int, QComboBox] = {}

    def refresh(self) -> None:
        ws = self.ws
        model = ws.model
        with _blocked(self.tree):
            self.tree.clear()
            self.role_boxes.clear()
            if model is None:
                return
            self.summary.setText(
                f"{ws.deck_path.name if ws.deck_path else 'demo'}: {model.n_nodes} nodes, "
                f"{model.n_elements} elements, {len(model.part_ids())} parts"
            )
            counts = model.element_counts()
            groups: dict[str | None, list[int]] = {}
            for pid in model.part_ids().tolist():
                groups.setdefault(ws.part_role(pid), []).append(pid)
            for role in [*ROLES, None]:
                pids = groups.get(role)
                if not pids:
                    continue
                colour = ROLE_COLOURS.get(role, UNASSIGNED_COLOUR)
                n = sum(sum(counts.get(p, {}).values()) for p in pids)
                top = QTreeWidgetItem([role or "unassigned", "", str(n)])
                top.setIcon(0, _swatch(colour))
                top.setFlags(top.flags() | Qt.ItemFlag.ItemIsUserCheckable)
                hidden = all(p in ws.hidden_parts for p in pids)
                top.setCheckState(0, Qt.CheckState.Unchecked if hidden else Qt.CheckState.Checked)
                top.setData(0, Qt.ItemDataRole.UserRole, ("role", role))
                self.tree.addTopLevelItem(top)
                for pid in pids:
                    part = model.parts.get(pid)
                    title = part.title if part else ""
                    item = QTreeWidgetItem(
                        [f"{pid} {title}".strip(), "", str(sum(counts.get(pid, {}).values()))]
                    )
                    item.setIcon(0, _swatch(colour))
                    item.setFlags(item.flags() | Qt.ItemFlag.ItemIsUserCheckable)
                    item.setCheckState(
                        0,
                        Qt.CheckState.Unchecked
                        if pid in ws.hidden_parts
                        else Qt.CheckState.Checked,
                    )
                    item.setData(0, Qt.ItemDataRole.UserRole, ("part", pid))
                    top.addChild(item)
                    box = QComboBox()
                    box.addItems(["(none)", *ROLES])
                    box.setCurrentText(role or "(none)")
                    box.currentTextChanged.connect(
                        lambda text, p=pid: self.ws.set_part_role(
                            p, None if text == "(none)" else text
                        )
                    )
                    self.tree.setItemWidget(item, 1, box)
                    self.role_boxes[pid] = box
                top.setExpanded(role not in ("skin", "flesh", "fixed", None))

    def _on_item_changed(self, item: QTreeWidgetItem, column: int) -> None:
        if column != 0:
            return
        kind, value = item.data(0, Qt.ItemDataRole.UserRole)
        visible = item.checkState(0) == Qt.CheckState.Checked
        if kind == "part":
            self.ws.set_part_visible(value, visible)
        else:
            for i in range(item.childCount()):
                _, pid = item.child(i).data(0, Qt.ItemDataRole.UserRole)
                self.ws.set_part_visible(pid, visible)


# ---------------------------------------------------------------------------- landmarks
PICK_TARGETS = (
    ("lateral_condyle", "Lateral condyle nodes"),
    ("medial_condyle", "Medial condyle nodes"),
    ("lr_axis:0", "L-R axis: proximal (medial plateau)"),
    ("lr_axis:1", "L-R axis: distal (ankle centre)"),
    ("femur_axis:0", "Femoral axis: proximal"),
    ("femur_axis:1", "Femoral axis: distal"),
    ("tibia_axis:0", "Tibial axis: proximal"),
    ("tibia_axis:1", "Tibial axis: distal"),
)


class LandmarkPanel(QWidget):
    """Pick condyle sets and axis points; shows the circle fits and axes live."""

    def __init__(self, ws: Workspace, parent: QWidget | None = None):
        super().__init__(parent)
        self.ws = ws
        layout = QVBoxLayout(self)
        self.pick_box = QCheckBox("Pick in the view")
        self.pick_box.setToolTip("Left click: nearest node; left drag: box; Ctrl: remove")
        layout.addWidget(self.pick_box)
        self.target = QComboBox()
        for key, label in PICK_TARGETS:
            self.target.addItem(label, key)
        layout.addWidget(self.target)
        row = QHBoxLayout()
        self.clear_button = QPushButton("Clear set")
        self.suggest_button = QPushButton("Suggest condyles")
        row.addWidget(self.clear_button)
        row.addWidget(self.suggest_button)
        layout.addLayout(row)
        row = QHBoxLayout()
        self.undo_button = QPushButton("Undo")
        self.redo_button = QPushButton("Redo")
        row.addWidget(self.undo_button)
        row.addWidget(self.redo_button)
        layout.addLayout(row)
        box = QGroupBox("Landmarks and fit")
        form = QFormLayout(box)
        self.labels: dict[str, QLabel] = {}
        for key, label in (
            ("lateral_condyle", "Lateral nodes"),
            ("medial_condyle", "Medial nodes"),
            ("lateral_fit", "Lateral circle"),
            ("medial_fit", "Medial circle"),
            ("fe_spread", "F-E axis spread"),
            ("lr_axis", "L-R axis"),
            ("femur_axis", "Femoral axis"),
            ("tibia_axis", "Tibial axis"),
            ("flexion", "Initial flexion"),
        ):
            self.labels[key] = QLabel("–")
            self.labels[key].setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
            form.addRow(label, self.labels[key])
        self.labels["fe_spread"].setToolTip(
            "How much the F-E axis depends on the picked condyle nodes: 95th percentile of the "
            "change of the axis direction, of the circle centres (lateral / medial) and of the "
            "radii (± in the circle rows) over 200 fits, each leaving out a random fifth of "
            "each condyle's nodes. Real condyles are not circles; a large spread means the "
            "axis follows the picking."
        )
        layout.addWidget(box)
        self.problem = QLabel("")
        self.problem.setWordWrap(True)
        self.problem.setStyleSheet("color: #d04040")
        layout.addWidget(self.problem)
        layout.addStretch(1)
        self.pick_box.toggled.connect(self._on_pick_changed)
        self.target.currentIndexChanged.connect(self._on_pick_changed)
        self.clear_button.clicked.connect(self._clear)
        self.suggest_button.clicked.connect(ws.suggest_condyles)
        self.undo_button.clicked.connect(ws.undo)
        self.redo_button.clicked.connect(ws.redo)
        ws.setup_changed.connect(self.refresh)
        ws.model_changed.connect(self.refresh)
        ws.display_changed.connect(lambda what: what == "undo" and self.refresh())
        ws.pick_target_changed.connect(self._sync_pick)

    def _on_pick_changed(self, *_args) -> None:
        key = self.target.currentData() if self.pick_box.isChecked() else ""
        self.ws.set_pick_target(key)

    def _sync_pick(self, target: str) -> None:
        with _blocked(self.pick_box), _blocked(self.target):
            self.pick_box.setChecked(bool(target))
            if target:
                self.target.setCurrentIndex(self.target.findData(target))

    def _clear(self) -> None:
        key = self.target.currentData()
        if key in ("lateral_condyle", "medial_condyle"):
            self.ws.set_condyle_ids(key, [])

    def _point_text(self, point: object) -> str:
        """An axis landmark as numbers: a node by its id and rest position, a point by its
        coordinates (model units)."""
        if point is None:
            return "–"
        if isinstance(point, int):
            try:
                xyz = self.ws.model.coords[int(self.ws.model.node_index(point))]
            except Exception:  # an id the model lacks: the setup check reports it
                return f"node {point} (not in the model)"
            return f"node {point} ({xyz[0]:.1f}, {xyz[1]:.1f}, {xyz[2]:.1f})"
        x, y, z = (float(v) for v in point)
        return f"({x:.1f}, {y:.1f}, {z:.1f})"

    def refresh(self) -> None:
        ws = self.ws
        self.undo_button.setEnabled(ws.can_undo)
        self.redo_button.setEnabled(ws.can_redo)
        lm = ws.setup_dict.get("landmarks", {})
        for key in ("lateral_condyle", "medial_condyle"):
            self.labels[key].setText(f"{len(lm.get(key, []) or [])} nodes")
        for key in ("lr_axis", "femur_axis", "tibia_axis"):
            pts = lm.get(key, []) or []
            self.labels[key].setText(" → ".join(self._point_text(p) for p in pts) or "–")
        axes = ws.axes if ws.setup_problem is None else None
        if axes is not None:
            spread = axes.sensitivity
            radius_spread = (
                (None, None)
                if spread is None
                else (spread.lateral_radius_spread_mm, spread.medial_radius_spread_mm)
            )
            for side, fit, dr in (
                ("lateral", axes.lateral_fit, radius_spread[0]),
                ("medial", axes.medial_fit, radius_spread[1]),
            ):
                pm = "" if dr is None else f" ± {dr:.2f}"
                self.labels[f"{side}_fit"].setText(
                    f"R = {fit.radius:.2f}{pm} mm, RMS = {fit.rms:.3f} mm, "
                    f"arc {fit.arc_span_deg:.0f}°"
                )
            if spread is None:
                text = "– (too few nodes)"
            elif not np.isfinite(spread.direction_spread_deg):
                text = f"unstable: {spread.n_failed} of {spread.settings.n_subsets} fits failed"
            else:
                text = (
                    f"{spread.direction_spread_deg:.2f}°, centres "
                    f"{spread.lateral_center_spread_mm:.2f} / "
                    f"{spread.medial_center_spread_mm:.2f} mm"
                )
            self.labels["fe_spread"].setText(text)
            self.labels["flexion"].setText(f"{axes.initial_flexion_deg:.1f}°")
        else:
            for key in ("lateral_fit", "medial_fit", "fe_spread", "flexion"):
                self.labels[key].setText("–")
        problem = ws.setup_problem or ""
        warnings = list(axes.warnings) if axes is not None else []
        self.problem.setText("\n".join(([f"Setup: {problem}"] if problem else []) + warnings))


# ---------------------------------------------------------------------------- flexion
class FlexionPanel(QWidget):
    """Slider and spin box over ``FLEXION_RANGE``, driving ``Workspace.set_flexion``."""

    def __init__(self, ws: Workspace, parent: QWidget | None = None):
        super().__init__(parent)
        self.ws = ws
        layout = QHBoxLayout(self)
        layout.addWidget(QLabel("Flexion"))
        self.slider = QSlider(Qt.Orientation.Horizontal)
        lo, hi = FLEXION_RANGE
        self.slider.setRange(int(lo * SLIDER_STEPS_PER_DEGREE), int(hi * SLIDER_STEPS_PER_DEGREE))
        self.slider.setMinimumWidth(300)
        layout.addWidget(self.slider, 1)
        self.spin = QDoubleSpinBox()
        self.spin.setRange(lo, hi)
        self.spin.setDecimals(1)
        self.spin.setSuffix("°")
        self.spin.setKeyboardTracking(False)
        layout.addWidget(self.spin)
        self.info = QLabel("")
        layout.addWidget(self.info)
        self.slider.valueChanged.connect(
            lambda v: self.ws.request_flexion(v / SLIDER_STEPS_PER_DEGREE)
        )
        self.slider.sliderReleased.connect(ws.settle_flexion)
        self.spin.valueChanged.connect(self.ws.set_flexion)
        ws.coords_changed.connect(self.sync)
        ws.poser_changed.connect(self.sync)
        ws.model_changed.connect(self.sync)
        self.sync()

    def sync(self) -> None:
        ws = self.ws
        enabled = ws.poser is not None
        self.slider.setEnabled(enabled)
        self.spin.setEnabled(enabled)
        with _blocked(self.slider), _blocked(self.spin):
            # while a drag is being followed, the slider is ahead of the pose: leave it
            if not (ws.pose_pending or self.slider.isSliderDown()):
                self.slider.setValue(round(ws.flexion * SLIDER_STEPS_PER_DEGREE))
            self.spin.setValue(ws.flexion)
        if ws.poser is None:
            self.info.setText("preparing…" if ws.model is not None else "")
        else:
            self.info.setText(f"initial {ws.poser.initial_flexion:.1f}°")


# ---------------------------------------------------------------------------- quality
class QualityPanel(QWidget):
    """Colour mode, heat-map metric, threshold highlight, worst elements, cut-away."""

    zoom_requested = Signal(int)

    def __init__(self, ws: Workspace, parent: QWidget | None = None):
        super().__init__(parent)
        self.ws = ws
        layout = QVBoxLayout(self)
        form = QFormLayout()
        self.mode = QComboBox()
        self.mode.addItem("Part colours", "part")
        self.mode.addItem("Quality heat-map", "quality")
        self.mode.addItem("Ligament stretch", "stretch")
        form.addRow("Colour by", self.mode)
        self.metric = QComboBox()
        self._fill_metrics()
        form.addRow("Metric", self.metric)
        row = QHBoxLayout()
        self.threshold_on = QCheckBox()
        self.threshold = QDoubleSpinBox()
        self.threshold.setRange(-1000, 1000)
        self.threshold.setDecimals(3)
        self.threshold.setValue(0.3)
        row.addWidget(self.threshold_on)
        row.addWidget(self.threshold, 1)
        form.addRow("Highlight beyond", row)
        layout.addLayout(form)
        self.stats = QLabel("")
        self.stats.setWordWrap(True)
        layout.addWidget(self.stats)
        layout.addWidget(QLabel("Worst elements (double-click to zoom)"))
        self.worst = QListWidget()
        layout.addWidget(self.worst, 1)
        clip = QGroupBox("Cut-away")
        clip_form = QFormLayout(clip)
        self.clip_on = QCheckBox("Cut away the")
        self.clip_side = QComboBox()
        self.clip_side.addItems(["lateral", "medial", "anterior", "posterior"])
        row = QHBoxLayout()
        row.addWidget(self.clip_on)
        row.addWidget(self.clip_side)
        clip_form.addRow(row)
        self.clip_offset = QDoubleSpinBox()
        self.clip_offset.setRange(-200, 200)
        self.clip_offset.setSuffix(" mm")
        clip_form.addRow("Plane offset", self.clip_offset)
        layout.addWidget(clip)
        self.mode.currentIndexChanged.connect(
            lambda: self.ws.set_colour_mode(self.mode.currentData())
        )
        self.metric.currentIndexChanged.connect(
            lambda: self.ws.set_metric(self.metric.currentData())
        )
        self.threshold_on.toggled.connect(self._on_threshold)
        self.threshold.valueChanged.connect(self._on_threshold)
        self.worst.itemDoubleClicked.connect(
            lambda item: self.zoom_requested.emit(int(item.data(Qt.ItemDataRole.UserRole)))
        )
        for w in (self.clip_on,):
            w.toggled.connect(self._on_clip)
        self.clip_side.currentIndexChanged.connect(self._on_clip)
        self.clip_offset.valueChanged.connect(self._on_clip)
        ws.display_changed.connect(self._on_display)
        ws.coords_changed.connect(self._schedule)
        ws.model_changed.connect(self._fill_metrics)
        ws.model_changed.connect(self._schedule)
        from PySide6.QtCore import QTimer

        self._timer = QTimer(self)
        self._timer.setSingleShot(True)
        self._timer.setInterval(150)
        self._timer.timeout.connect(self.refresh)

    def _fill_metrics(self) -> None:
        """The metrics the model offers (tet measures with tets, the Jacobian with hexes)."""
        with _blocked(self.metric):
            self.metric.clear()
            for key in self.ws.heatmap_metrics():
                self.metric.addItem(HEATMAP_METRICS[key][0], key)
            self.metric.setCurrentIndex(self.metric.findData(self.ws.metric))

    def _on_threshold(self, *_args) -> None:
        self.ws.set_threshold(self.threshold.value() if self.threshold_on.isChecked() else None)

    def _on_clip(self, *_args) -> None:
        self.ws.set_clip(
            self.clip_on.isChecked(), self.clip_side.currentText(), self.clip_offset.value()
        )

    def _on_display(self, what: str) -> None:
        ws = self.ws
        with (
            _blocked(self.mode),
            _blocked(self.metric),
            _blocked(self.threshold_on),
            _blocked(self.threshold),
        ):
            self.mode.setCurrentIndex(self.mode.findData(ws.colour_mode))
            self.metric.setCurrentIndex(self.metric.findData(ws.metric))
            self.threshold_on.setChecked(ws.threshold is not None)
            if ws.threshold is not None:
                self.threshold.setValue(ws.threshold)
        if what == "colour":
            self._schedule()

    def _schedule(self) -> None:
        if self.isVisible():
            self._timer.start()

    def showEvent(self, event) -> None:
        super().showEvent(event)
        self._schedule()

    def refresh(self) -> None:
        ws = self.ws
        if ws.model is None:
            return
        q = ws.quality()
        values = ws.element_values(ws.metric)
        finite = values[np.isfinite(values)]
        label = HEATMAP_METRICS[ws.metric][0]
        if len(finite):
            offered = ws.heatmap_metrics()
            worst = []
            if "tet_collapse" in offered:
                worst.append(f"worst tet collapse {np.nanmin(q.concatenated('tet_collapse')):.3f}")
            if "jacobian" in offered:
                worst.append(f"worst Jacobian {q.worst_jacobian():.3f}")
            # an exported pose's count split as its report splits it
            exported = ws.exported
            inverted = (
                exported.figures.inverted_text()
                if exported is not None
                else f"inverted {q.n_inverted}"
            )
            self.stats.setText(
                f"{q.n_elements} measured · {inverted} · {' · '.join(worst)}\n"
                f"{label}: min {finite.min():.3g}, mean {finite.mean():.3g}, "
                f"max {finite.max():.3g}"
            )
        # an exported pose's locked elements (no repositioner can save them) are marked
        locked: set[int] = set()
        if ws.exported is not None:
            locked = set(ws.exported.posed.report.get("inverted", {}).get("locked_ids", ()))
        self.worst.clear()
        for cell, eid, part, value in ws.worst_elements(ws.metric, 25):
            mark = "  locked" if eid in locked else ""
            item = QListWidgetItem(f"{eid:>8}  {value:9.3f}  {part}{mark}")
            item.setData(Qt.ItemDataRole.UserRole, cell)
            self.worst.addItem(item)


# ---------------------------------------------------------------------------- ligaments
class LigamentPanel(QWidget):
    """Ligament stretch colouring and each ligament's length vs. flexion."""

    def __init__(self, ws: Workspace, parent: QWidget | None = None):
        super().__init__(parent)
        self.ws = ws
        layout = QVBoxLayout(self)
        self.show_stretch = QPushButton("Colour ligaments by stretch")
        self.compute = QPushButton("Compute length vs. flexion")
        layout.addWidget(self.show_stretch)
        layout.addWidget(self.compute)
        self.table = QLabel("")
        self.table.setWordWrap(True)
        layout.addWidget(self.table)
        from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
        from matplotlib.figure import Figure

        self.figure = Figure(figsize=(3.2, 2.4), dpi=90, layout="constrained")
        self.canvas = FigureCanvasQTAgg(self.figure)
        self.canvas.setMinimumHeight(200)
        layout.addWidget(self.canvas, 1)
        self.show_stretch.clicked.connect(lambda: ws.set_colour_mode("stretch"))
        self.compute.clicked.connect(lambda: ws.compute_ligament_curve())
        ws.ligaments_changed.connect(self.redraw)
        ws.poser_changed.connect(self.redraw)
        ws.coords_changed.connect(self._update_table)
        self.redraw()

    def _update_table(self) -> None:
        ws = self.ws
        if not ws.ligaments or not self.isVisible():
            return
        rows = []
        for lig in ws.ligaments:
            s = lig.element_stretch(ws.coords)
            rows.append(
                f"{lig.name}: length {lig.length(ws.coords):.1f} mm "
                f"({100 * (lig.length(ws.coords) / lig.initial_length - 1):+.1f} %), "
                f"fibre stretch {s.min():.3f}…{s.max():.3f}"
            )
        self.table.setText("\n".join(rows))
        if ws.ligament_curve is not None:
            self._marker()

    def redraw(self) -> None:
        ws = self.ws
        self.figure.clear()
        ax = self.figure.add_subplot(111)
        ax.set_xlabel("flexion (°)")
        ax.set_ylabel("length / initial")
        self._ax = ax
        self._line = None
        if ws.ligament_curve is not None and ws.ligaments:
            angles, lengths = ws.ligament_curve
            for j, lig in enumerate(ws.ligaments):
                ax.plot(angles, lengths[:, j] / lig.initial_length, label=lig.name)
            ax.legend(fontsize=7)
            ax.grid(alpha=0.3)
            self._marker()
        else:
            ax.text(
                0.5,
                0.5,
                "press 'Compute'" if ws.ligaments else "no ligament parts",
                ha="center",
                va="center",
                transform=ax.transAxes,
            )
        self.canvas.draw_idle()
        self._update_table()

    def _marker(self) -> None:
        if self._line is not None:
            self._line.remove()
        self._line = self._ax.axvline(self.ws.flexion, color="k", lw=0.8, ls="--")
        self.canvas.draw_idle()

    def showEvent(self, event) -> None:
        super().showEvent(event)
        self._update_table()


# ---------------------------------------------------------------------------- what is shown
#: Banner colours: (background, text) for the live mapping and the exported pose.
INDICATOR_STYLES = {
    "live mapping": ("#e0a030", "#1a1a1a"),
    "as exported": ("#3a9a50", "#ffffff"),
    "relaxing": ("#3a6ea5", "#ffffff"),
    # an export that fails the quality gate: shown as it is, never dressed as a success
    "fails the gate": ("#b03a2e", "#ffffff"),
}


class ViewIndicator(QLabel):
    """One line over the 3-D view: what it shows and that pose's quality figures.

    While the slider moves the text stays the same (no repaint per frame); at rest it gives the
    angle, the figures (:class:`app.preview.PoseFigures`) and the export's progress.
    """

    def __init__(self, ws: Workspace, parent: QWidget | None = None):
        super().__init__(parent)
        self.ws = ws
        self.kind = ""
        self._style = ""
        self.setObjectName("view-indicator")
        self.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.setContentsMargins(8, 3, 8, 3)
        from PySide6.QtCore import QTimer

        self._timer = QTimer(self)
        self._timer.setSingleShot(True)
        self._timer.setInterval(150)
        self._timer.timeout.connect(self.refresh)
        ws.coords_changed.connect(self._on_coords)
        ws.model_changed.connect(self.refresh)
        ws.poser_changed.connect(self.refresh)
        ws.preview.changed.connect(self.refresh)
        # the last live pose of a drag: its figures once no other pose follows within the
        # debounce (measuring the whole model on every slider step would halve the frame rate)
        ws.live_idle.connect(self._timer.start)
        self.refresh()

    def _on_coords(self) -> None:
        if self.ws.view_kind != self.kind:
            self.refresh()
        else:
            self._timer.start()

    def moving(self) -> bool:
        """Whether the slider is still moving (a live pose pending or the rest not reached)."""
        ws = self.ws
        return ws.pose_pending or ws.preview._timer.isActive()

    def failed_gate(self) -> list[str] | None:
        """The quality gate's reasons when the view shows an export that fails it, else None."""
        exported = self.ws.exported
        if self.ws.view_kind != "as exported" or exported is None:
            return None
        return None if exported.posed.passes_gate else list(exported.posed.gate_reasons)

    def _volume_hint(self) -> str:
        """A pointer to the volume step when the shown export left movable elements inverted
        without it (it freed the 177k demo's crease, not the welded joint's elements)."""
        exported = self.ws.exported
        inverted = (exported.posed.report.get("inverted") or {}) if exported else {}
        if self.ws.restore_volume or not inverted.get("movable"):
            return ""
        return (
            "\n\nMovable elements stay inverted: Mesh > Restore the soft tissue's volume before "
            "relaxing may free them. It does on some decks and not on others (and it takes "
            "longer), so compare the figures both ways."
        )

    def refresh(self) -> None:
        ws = self.ws
        kind = ws.view_kind
        reasons = self.failed_gate()
        style = "fails the gate" if reasons else kind
        if style != self._style:
            background, colour = INDICATOR_STYLES[style]
            self.setStyleSheet(
                f"QLabel#view-indicator {{ background: {background}; color: {colour}; "
                "font-weight: bold; }"
            )
            self._style = style
        self.kind = kind
        self.setToolTip(
            "The export fails the quality gate (File > Export writes it only when forced):\n"
            + "\n".join(f"- {r}" for r in reasons)
            + self._volume_hint()
            if reasons
            else ""
        )
        if ws.model is None:
            self.setText("")
            return
        if ws.poser is None:
            self.setText(f"{kind.upper()} · preparing the repositioner…")
            return
        if kind == "live mapping" and self.moving():
            self.setText("LIVE MAPPING · moving: the export runs when the slider rests")
            return
        figures = ws.view_figures()
        text = f"{kind.upper()} · {ws.flexion:.1f}° · {figures.text()}"
        if reasons:
            text = (
                f"{kind.upper()} · FAILS THE GATE · {ws.flexion:.1f}° · {figures.text()} · "
                f"why: hover here ({len(reasons)} reason{'s' if len(reasons) > 1 else ''}); "
                "Export writes it only when forced"
            )
        preview = ws.preview
        if kind == "as exported" and ws.exported.posed.report.get("volume_correction"):
            text += " · volume restored before relaxing"
        if kind == "relaxing":
            from app.preview import STAGE_NAMES

            text += f" · {STAGE_NAMES.get(ws.stage, ws.stage)}, not yet exported"
        if kind != "as exported":
            if preview.running_for is not None:
                text += f" · exporting: {preview.message} {100 * preview.fraction:.0f} %"
            elif preview.error:
                text += f" · the export failed: {preview.error}"
            elif not preview.enabled:
                text += " · press Relax + smooth for the export"
        self.setText(text)


class QualityCurvePanel(QWidget):
    """Worst Jacobian, inverted elements and largest volume change against flexion.

    Lines: the live mapping, sampled over the validated range once per poser. Dots: each angle
    the export path ran on. A dashed line marks the angle shown (moved once the slider rests).
    """

    def __init__(self, ws: Workspace, parent: QWidget | None = None):
        super().__init__(parent)
        self.ws = ws
        layout = QVBoxLayout(self)
        from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
        from matplotlib.figure import Figure
        from PySide6.QtCore import QTimer

        self.figure = Figure(figsize=(3.4, 4.2), dpi=90)
        self.figure.subplots_adjust(left=0.22, right=0.97, top=0.94, bottom=0.1, hspace=0.12)
        self.canvas = FigureCanvasQTAgg(self.figure)
        self.canvas.setMinimumHeight(300)
        layout.addWidget(self.canvas, 1)
        self.axes = []
        self._markers = []
        self._timer = QTimer(self)
        self._timer.setSingleShot(True)
        self._timer.setInterval(300)
        self._timer.timeout.connect(self._move_marker)
        ws.preview.curve_changed.connect(self.redraw)
        ws.coords_changed.connect(self._schedule)
        self.redraw()

    #: (figure attribute, axis label, live colour)
    SERIES = (
        ("worst_tet_collapse", "worst tet\ncollapse", "#9467bd"),
        ("worst_jacobian", "worst Jacobian", "#1f77b4"),
        ("inverted", "inverted elements", "#d62728"),
        ("max_volume_change_pct", "largest volume\nchange (%)", "#2ca02c"),
    )
    #: Figures on the -1..1 scale of a determinant ratio (an inverted element's can reach -20)
    RATIO_SERIES = ("worst_tet_collapse", "worst_jacobian")

    def plotted(self) -> tuple[tuple[str, str, str], ...]:
        """The :data:`SERIES` that say something on the open model: the tet collapse with
        tets, the Jacobian with hexes, wedges, pyramids or quads (or with neither)."""
        model = self.ws.model
        tets = has_tets(model)
        jacobian = jacobian_says_something(model) or not tets
        keep = {"worst_tet_collapse": tets, "worst_jacobian": jacobian}
        return tuple(entry for entry in self.SERIES if keep.get(entry[0], True))

    def series(self) -> dict[str, tuple]:
        """What is plotted: per figure, (live angles, live values, exported angles, values)."""
        preview = self.ws.preview
        curve = preview.live_curve
        angles = sorted(preview.exported_points)
        out = {}
        for name, _, _ in self.plotted():
            live = (curve.angles, getattr(curve, name)) if curve is not None else ((), ())
            exported = [getattr(preview.exported_points[a], name) for a in angles]
            out[name] = (*live, angles, exported)
        return out

    def exported_marks(self, name: str) -> list[tuple[float, float, bool, bool]]:
        """The exported angles' points of figure ``name`` as drawn: (angle, y, fails the gate,
        off the scale). A ratio below the plot's -1 (an inverted element's Jacobian can reach
        -20) is drawn at -1 with a downward triangle, not left off the plot."""
        points = self.ws.preview.exported_points
        marks = []
        for angle in sorted(points):
            figures = points[angle]
            value = float(getattr(figures, name))
            off = name in self.RATIO_SERIES and value < RATIO_FLOOR
            marks.append(
                (float(angle), RATIO_FLOOR if off else value, figures.passes_gate is False, off)
            )
        return marks

    def redraw(self) -> None:
        self.figure.clear()
        data = self.series()
        plotted = self.plotted()
        self.axes = list(self.figure.subplots(len(plotted), 1, sharex=True))
        for ax, (name, label, colour) in zip(self.axes, plotted, strict=True):
            live_x, live_y, _, _ = data[name]
            if len(live_x):
                ax.plot(live_x, live_y, color=colour, lw=1.2, label=LIVE_LABEL)
            marks = self.exported_marks(name)
            for failed in (False, True):
                for off in (False, True):
                    group = [m for m in marks if m[2:] == (failed, off)]
                    if not group:
                        continue
                    ax.plot(
                        [m[0] for m in group],
                        [m[1] for m in group],
                        "v" if off else ("X" if failed else "o"),
                        color=FAILED_COLOUR if failed else "k",
                        ms=6 if failed or off else 4,
                        label=OFF_SCALE_LABEL
                        if off
                        else (FAILED_LABEL if failed else EXPORTED_LABEL),
                    )
            ax.set_ylabel(label, fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
            if name in self.RATIO_SERIES:
                # an inverted element's ratio can reach -20; the usable range is 0..1
                ax.axhline(0.0, color="#888888", lw=0.6)
                ax.set_ylim(RATIO_FLOOR - 0.05, 1.05)
        self.axes[-1].set_xlabel("flexion (°)", fontsize=8)
        if self.ws.preview.live_curve is None:
            self.axes[0].set_title("live mapping: computing…", fontsize=8)
        else:
            handles, labels = self.axes[0].get_legend_handles_labels()
            unique = dict(zip(labels, handles, strict=True))  # one entry per kind of point
            self.axes[0].legend(unique.values(), unique.keys(), fontsize=7, loc="lower left")
        self._markers = []
        self._move_marker()

    def _schedule(self) -> None:
        if self.isVisible():
            self._timer.start()

    def _move_marker(self) -> None:
        for line in self._markers:
            line.remove()
        self._markers = [
            ax.axvline(self.ws.flexion, color="#555555", lw=0.8, ls="--") for ax in self.axes
        ]
        if self.isVisible():  # a hidden (tabbed) canvas is drawn when it is shown
            self.canvas.draw_idle()

    def showEvent(self, event) -> None:
        super().showEvent(event)
        self._move_marker()


LIVE_LABEL = "live mapping"
EXPORTED_LABEL = "as exported"
FAILED_LABEL = "as exported, fails the gate"
FAILED_COLOUR = "#b03a2e"
OFF_SCALE_LABEL = "below -1, drawn at -1"
#: Where the plot of a ratio (worst Jacobian, worst tet collapse) stops below zero
RATIO_FLOOR = -1.0
