"""The pre-flight panel in the real window: summary, locked-element list, zoom, overlay."""

from __future__ import annotations

import json

import numpy as np
import pytest
from vtk.util.numpy_support import vtk_to_numpy

from kneegui.io.lsdyna import write_model
from kneegui.reposition.preflight import preflight_of

from .conftest import wait_idle

pytestmark = pytest.mark.gui


def wait_preflight(window, qtbot):
    panel = window.preflight_panel
    qtbot.waitUntil(lambda: window.ws.poser is not None, timeout=60000)
    qtbot.waitUntil(
        lambda: panel.preflight is not None and panel.preflight is preflight_of(window.ws.poser),
        timeout=60000,
    )
    return panel


@pytest.fixture
def welded_window(window, qtbot, welded_leg, tmp_path):
    model, setup = welded_leg
    deck = write_model(model, tmp_path / "welded.k")
    setup_path = tmp_path / "welded.setup.json"
    setup_path.write_text(json.dumps(setup), encoding="utf-8")
    window.open_deck(deck, setup_path)
    wait_idle(qtbot, window.ws)
    wait_preflight(window, qtbot)
    assert window.last_error is None, window.last_error
    window.viewport.flush()
    return window


def test_locked_elements_are_listed_drawn_and_zoomed_to(welded_window, qtbot):
    win = welded_window
    ws, vp, panel = win.ws, win.viewport, win.preflight_panel
    pre = panel.preflight
    assert len(pre.locked) >= 5
    assert panel.locked_list.count() == len(pre.locked)
    texts = [panel.locked_list.item(k).text() for k in range(panel.locked_list.count())]
    ids = {int(t.split()[0]) for t in texts}
    assert ids == set(pre.locked.ids.tolist())
    # each row gives the flexion at which the element inverts
    first = texts[0]
    k = int(np.flatnonzero(pre.locked.ids == int(first.split()[0]))[0])
    assert f"inverts at {pre.locked.inverts_above_deg[k]:.1f} deg" in first
    assert f"Locked elements: {len(pre.locked)}" in panel.summary.text()
    assert "Movable region:" in panel.summary.text()
    # drawn in their own colour: exactly the locked cells
    overlay = win.locked_overlay
    assert sorted(overlay.shown_cells.tolist()) == sorted(panel.cells.tolist())
    assert overlay.NAME in vp.plotter.actors
    blocks = ws.model.blocks
    starts = dict(zip(blocks, np.cumsum([0, *[len(b) for b in blocks.values()]]), strict=False))
    for cell, etype, row in zip(panel.cells, pre.locked.etype, pre.locked.rows, strict=True):
        assert cell == starts[etype] + row
    # double-click zooms to the element
    item = panel.locked_list.item(0)
    panel.locked_list.itemDoubleClicked.emit(item)
    focus, _ = vp._focus
    assert focus.cell_data["vtkOriginalCellIds"].tolist() == [item.data(256)]
    # the overlay follows the pose
    win.flexion_panel.slider.setValue(900)
    wait_idle(qtbot, ws)
    vp.flush()
    points = vtk_to_numpy(overlay._mesh.GetPoints().GetData())
    assert np.array_equal(points, ws.coords[overlay._index])
    assert not np.allclose(points, ws.model.coords[overlay._index])
    # hidden on request
    panel.show_locked.setChecked(False)
    assert len(overlay.shown_cells) == 0 and overlay.NAME not in vp.plotter.actors


def test_the_sliding_demo_has_nothing_locked(demo_window, qtbot):
    panel = wait_preflight(demo_window, qtbot)
    assert panel.locked_list.count() == 0
    text = panel.summary.text()
    assert "Locked elements: 0" in text
    pairs = int(text.split("Coincident node pairs (sliding interfaces): ")[1].split()[0])
    assert pairs == len(panel.preflight.coincident_pairs) > 100
    assert len(demo_window.locked_overlay.shown_cells) == 0


def test_an_export_that_fails_the_gate_says_so_in_the_banner(welded_window, qtbot, tmp_path):
    """The welded joint at 90 deg: the export leaves locked and movable elements inverted
    (21 and 13; at 60 deg only locked ones since the skin may bulge outwards, at 70 deg 16 and
    4, 7 December).
    The banner says the export fails the gate, splits the inverted elements as the report does,
    names the reasons in its tooltip, and File > Export refuses it unless forced."""
    from app.panels import INDICATOR_STYLES
    from app.workspace import ExportBlocked

    win = welded_window
    ws, indicator = win.ws, win.indicator
    win.set_rest_export(True)
    win.flexion_panel.slider.setValue(900)
    qtbot.waitUntil(lambda: ws.view_kind == "as exported" and ws.flexion == 90.0, timeout=120000)
    wait_idle(qtbot, ws)
    report = ws.exported.posed.report
    inverted = report["inverted"]
    assert not report["gate"]["passed"] and inverted["locked"] > 0 and inverted["movable"] > 0
    text = indicator.text()
    expected = (
        f"AS EXPORTED · FAILS THE GATE · 90.0° · inverted {inverted['total']} "
        f"({inverted['locked']} locked, {inverted['movable']} movable)"
    )
    assert text.startswith(expected), text
    assert INDICATOR_STYLES["fails the gate"][0] in indicator.styleSheet()
    for reason in report["gate"]["reasons"]:
        assert reason in indicator.toolTip()
    # movable elements inverted without the volume step: the tooltip points at it
    assert "Mesh > Restore the soft tissue's volume before relaxing" in indicator.toolTip()
    ws.restore_volume = True  # (the switch itself is tested in test_gui_preview.py)
    indicator.refresh()
    assert "Restore the soft tissue's volume" not in indicator.toolTip()
    ws.restore_volume = False
    indicator.refresh()
    # the quality panel splits them too and marks the locked ones among the worst elements
    panel = win.quality_panel
    panel.refresh()
    assert f"inverted {inverted['total']} ({inverted['locked']} locked," in panel.stats.text()
    rows = [panel.worst.item(k).text() for k in range(panel.worst.count())]
    marked = {int(r.split()[0]) for r in rows if r.endswith("locked")}
    listed = {int(r.split()[0]) for r in rows}
    assert marked and marked == listed & set(inverted["locked_ids"])
    # the quality-against-flexion plot draws the failing export in its own mark, on the plot
    # even where its worst Jacobian is below the plot's -1
    curve = win.quality_curve_panel
    worst = ws.exported.figures.worst_jacobian
    marks = {angle: rest for angle, *rest in curve.exported_marks("worst_jacobian")}
    y, failed, off = marks[90.0]
    assert failed and off == (worst < -1.0) and y == max(worst, -1.0)
    assert not any(m[1] for a, m in marks.items() if a != 90.0)  # the others pass
    with pytest.raises(ExportBlocked, match="fails the quality gate"):
        ws.export(tmp_path / "posed.k")
    assert not (tmp_path / "posed.k").exists()
    # a live pose again: the banner is the live mapping's, without the gate's reasons
    win.set_rest_export(False)
    win.flexion_panel.slider.setValue(300)
    wait_idle(qtbot, ws)
    qtbot.waitUntil(lambda: indicator.text().startswith("LIVE MAPPING · 30.0°"), timeout=10000)
    assert INDICATOR_STYLES["live mapping"][0] in indicator.styleSheet()
    assert indicator.toolTip() == ""
