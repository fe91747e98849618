"""The real window under Xvfb: demo, picking, slider, heat-maps, stretch, smoothing, export."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import pyvista as pv
from PySide6.QtCore import QPoint, Qt
from PySide6.QtGui import QImage
from PySide6.QtTest import QTest
from vtk.util.numpy_support import vtk_to_numpy

from app.viewport import CAMERA_PRESETS
from app.workspace import HEATMAP_METRICS, ExportBlocked
from kneegui.geometry import measure_flexion
from kneegui.io.lsdyna import read_deck
from kneegui.ligaments import ligament_short_name
from kneegui.quality import compute_quality, volume_change_pct
from kneegui.reposition.pipeline import pose_model

from .conftest import wait_idle

pytestmark = pytest.mark.gui


def widget_point(viewport, xyz) -> QPoint:
    """Where a world point appears in the interactor widget (Qt coordinates)."""
    ren = viewport.plotter.renderer
    ren.SetWorldPoint(*xyz, 1.0)
    ren.WorldToDisplay()
    x, y, _ = ren.GetDisplayPoint()
    h = viewport.plotter.ren_win.GetSize()[1]
    ratio = viewport.plotter.devicePixelRatioF()
    return QPoint(round(x / ratio), round((h - 1 - y) / ratio))


def set_slider(window, qtbot, degrees: float) -> None:
    panel = window.flexion_panel
    panel.slider.setValue(round(degrees * 10))
    wait_idle(qtbot, window.ws)
    window.viewport.flush()


def test_opens_the_demo_with_its_setup(demo_window):
    ws, vp = demo_window.ws, demo_window.viewport
    assert ws.setup is not None and ws.setup_problem is None
    counts = ws.model.element_counts()
    assert set(vp.actors) == set(counts)
    tree = demo_window.model_panel.tree
    groups = {
        tree.topLevelItem(i).text(0): int(tree.topLevelItem(i).text(2))
        for i in range(tree.topLevelItemCount())
    }
    assert sum(groups.values()) == ws.model.n_elements
    assert {"femur", "tibia", "patella", "ligament"} <= set(groups)
    assert ws.flexion == pytest.approx(ws.poser.initial_flexion)
    assert demo_window.flexion_panel.slider.isEnabled()


def test_the_view_draws_into_a_native_window_qt_composes_without_opengl(demo_window):
    from PySide6.QtGui import QGuiApplication
    from PySide6.QtOpenGLWidgets import QOpenGLWidget

    from app.native_view import NativeInteractor

    if QGuiApplication.platformName() != "xcb":
        pytest.skip("the native view is used on X11, Windows and macOS")
    vp = demo_window.viewport
    assert isinstance(vp.plotter, NativeInteractor)
    assert vp.plotter.testAttribute(Qt.WidgetAttribute.WA_NativeWindow)
    # no render-to-texture widget left: Qt paints the rest of the window with its raster engine
    assert demo_window.findChildren(QOpenGLWidget) == []
    before = vp.renders
    vp.render(now=True)
    assert vp.renders == before + 1  # one repaint renders the scene exactly once


def test_role_edit_and_visibility_from_the_part_tree(demo_window, qtbot):
    ws, panel = demo_window.ws, demo_window.model_panel
    pid = ws.setup_dict["roles"]["patella"][0]
    panel.role_boxes[pid].setCurrentText("fixed")
    assert ws.part_role(pid) == "fixed"
    assert pid in ws.setup_dict["roles"]["fixed"]
    ws.undo()
    assert ws.part_role(pid) == "patella"
    vp = demo_window.viewport
    ws.set_part_visible(pid, False)
    vp.flush()
    assert not vp.actors[pid].GetVisibility()
    ws.set_part_visible(pid, True)
    vp.flush()
    assert vp.actors[pid].GetVisibility()


def test_slider_reposes_live_points_in_place(demo_window, qtbot):
    ws, vp = demo_window.ws, demo_window.viewport
    meshes = {pid: s.mesh for pid, s in vp.surfaces.items()}
    buffers = {pid: vp._points[pid] for pid in vp.surfaces}
    renders, frames = vp.renders, vp.pose_frames
    slider = demo_window.flexion_panel.slider
    for value in (300, 600, 900):
        slider.setValue(value)
    assert ws.pose_pending  # computed in the pose thread while the GUI stays responsive
    wait_idle(qtbot, ws)
    qtbot.waitUntil(lambda: vp.renders > renders, timeout=5000)
    # three slider events: the 60° request was superseded, at most two poses were drawn
    assert 1 <= vp.pose_frames - frames <= 2
    assert ws.flexion == 90.0
    np.testing.assert_allclose(ws.coords, ws.poser.pose(90.0))
    assert measure_flexion(ws.coords, ws.setup) == pytest.approx(90.0, abs=0.2)
    hidden = set(ws.hidden_parts)
    assert hidden  # skin and flesh start hidden: their points do not follow the slider
    drawn = set(vp.drawn_parts())
    # the trabecular bones, each inside its cortical shell, are shown but not drawn
    inside = set(vp.surfaces) - hidden - drawn
    assert len(inside) == 4
    for pid, surf in vp.surfaces.items():
        assert surf.mesh is meshes[pid]
        pts = vtk_to_numpy(surf.mesh.GetPoints().GetData())
        assert np.shares_memory(pts, buffers[pid])
        if pid in drawn:
            np.testing.assert_array_equal(pts, ws.coords[surf.model_index])
    ws.set_clip(True)  # cut open, the view draws them, brought up to date
    vp.flush()
    assert inside <= set(vp.drawn_parts())
    for pid in inside:
        pts = vtk_to_numpy(vp.surfaces[pid].mesh.GetPoints().GetData())
        np.testing.assert_array_equal(pts, ws.coords[vp.surfaces[pid].model_index])
    ws.set_clip(False)
    vp.flush()
    assert not inside & set(vp.drawn_parts())
    for pid in hidden:  # shown, a part is brought up to date
        ws.set_part_visible(pid, True)
    vp.flush()
    for pid in hidden:
        pts = vtk_to_numpy(vp.surfaces[pid].mesh.GetPoints().GetData())
        np.testing.assert_array_equal(pts, ws.coords[vp.surfaces[pid].model_index])
    # everything shown: the faces between two parts (flesh on flesh, bone or under the skin)
    # are not drawn; what is drawn is each surface's own faces on its own moving points
    drawn_faces = 0
    for pid in vp.drawn_parts():
        surf, data = vp.surfaces[pid], vp.actors[pid].mapper.GetInput()
        assert data.GetPoints() is surf.mesh.GetPoints()
        rows = vp._drawn_rows.get(pid)
        if rows is not None:
            lines = surf.mesh.GetNumberOfLines()
            faces = surf.mesh.irregular_faces
            expected = [tuple(faces[r - lines]) for r in rows if r >= lines]
            assert [tuple(f) for f in pv.wrap(data).irregular_faces] == expected
            np.testing.assert_array_equal(vp.drawn_cells(pid), surf.cell_index[rows])
        drawn_faces += data.GetNumberOfPolys()
    total_faces = sum(s.mesh.GetNumberOfPolys() for s in vp.surfaces.values())
    assert drawn_faces < 0.4 * total_faces  # 6,181 of 17,938 (an exact count)
    ws.set_clip(True)
    vp.flush()
    assert sum(vp.actors[p].mapper.GetInput().GetNumberOfPolys() for p in vp.drawn_parts()) == sum(
        s.mesh.GetNumberOfPolys() for s in vp.surfaces.values()
    )
    ws.set_clip(False)
    for pid in hidden:
        ws.set_part_visible(pid, False)
    vp.flush()
    assert demo_window.flexion_panel.spin.value() == pytest.approx(90.0)
    demo_window.flexion_panel.spin.setValue(45.0)
    assert ws.flexion == 45.0 and slider.value() == 450


def test_pick_a_condyle_set_by_box_and_click(demo_window, qtbot):
    ws, vp = demo_window.ws, demo_window.viewport
    original = ws.condyle_ids("lateral_condyle")
    radius0 = ws.axes.lateral_fit.radius
    femur = ws.setup_dict["roles"]["femur"]
    for pid in vp.actors:
        ws.set_part_visible(pid, pid in femur)
    vp.flush()
    vp.camera_preset("posterior")
    panel = demo_window.landmark_panel
    panel.target.setCurrentIndex(panel.target.findData("lateral_condyle"))
    panel.pick_box.setChecked(True)
    assert ws.pick_target == "lateral_condyle"
    panel.clear_button.click()
    assert ws.condyle_ids("lateral_condyle") == []
    assert ws.setup_problem is not None  # too few nodes: reported, not raised
    # box: drag a rectangle around where the set appears on screen
    pts = [widget_point(vp, ws.coords[i]) for i in ws.model.node_index(original)]
    xs, ys = [p.x() for p in pts], [p.y() for p in pts]
    a, b = QPoint(min(xs) - 2, min(ys) - 2), QPoint(max(xs) + 2, max(ys) + 2)
    QTest.mousePress(vp.plotter, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier, a)
    QTest.mouseMove(vp.plotter, b)
    # the rectangle is drawn in the scene while dragging (a Qt rubber band could not be
    # blended over the native GL window), and gone after the release
    assert vp.selection_rect_shown()
    QTest.mouseRelease(vp.plotter, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier, b)
    assert not vp.selection_rect_shown()
    boxed = ws.condyle_ids("lateral_condyle")
    surface = vp.surfaces
    femur_surface = set(
        ws.model.node_ids[np.concatenate([surface[p].model_index for p in femur])].tolist()
    )
    assert set(boxed) <= femur_surface
    assert len(set(boxed) & set(original)) >= 0.8 * len(original)
    assert ws.setup_problem is None, ws.setup_problem
    # undo / redo every pick
    panel.undo_button.click()
    assert ws.condyle_ids("lateral_condyle") == []
    panel.redo_button.click()
    assert ws.condyle_ids("lateral_condyle") == boxed
    panel.clear_button.click()
    # clicks: one per node, from behind and below the condyle
    frame = ws.knee_frame()
    view = -frame["anterior"] - 0.7 * frame["superior"]
    centre = ws.coords[ws.model.node_index(original)].mean(axis=0)
    cam = vp.plotter.camera
    cam.focal_point = centre
    cam.position = centre + 400.0 * view / np.linalg.norm(view)
    cam.up = frame["superior"]
    vp.plotter.reset_camera_clipping_range()
    vp.render()
    for i in ws.model.node_index(original):
        QTest.mouseClick(
            vp.plotter,
            Qt.MouseButton.LeftButton,
            Qt.KeyboardModifier.NoModifier,
            widget_point(vp, ws.coords[i]),
        )
    assert ws.condyle_ids("lateral_condyle") == sorted(original)
    assert ws.setup_problem is None
    assert ws.axes.lateral_fit.radius == pytest.approx(radius0, rel=1e-9)
    assert "R =" in panel.labels["lateral_fit"].text()
    assert vp.overlay_actors.get("circles") is not None
    # Ctrl+click removes the node under the cursor; a plain click adds it back
    node = ws.model.node_index(original[len(original) // 2])
    where = widget_point(vp, ws.coords[node])
    QTest.mouseClick(
        vp.plotter, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.ControlModifier, where
    )
    assert original[len(original) // 2] not in ws.condyle_ids("lateral_condyle")
    QTest.mouseClick(vp.plotter, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier, where)
    assert ws.condyle_ids("lateral_condyle") == sorted(original)
    # an axis point by clicking
    panel.target.setCurrentIndex(panel.target.findData("femur_axis:1"))
    assert ws.pick_target == "femur_axis:1"
    QTest.mouseClick(vp.plotter, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier, where)
    assert ws.setup_dict["landmarks"]["femur_axis"][1] == original[len(original) // 2]
    panel.pick_box.setChecked(False)
    assert ws.pick_target == ""
    wait_idle(qtbot, ws)


def test_live_heatmaps_are_the_full_evaluations_values(demo_window, qtbot):
    # each heat-map is measured alone in the pose thread (the rest of the kernel is skipped);
    # what it shows must be the full evaluation's values, bit for bit
    ws, vp = demo_window.ws, demo_window.viewport
    rest_export = demo_window.rest_export_action.isChecked()
    demo_window.set_rest_export(False)
    try:
        ws.set_colour_mode("quality")
        for angle, metric, measured in (
            (75.0, "jacobian", "jacobian_corner"),
            (80.0, "aspect", "aspect"),
            (85.0, "warpage", "warpage"),
            (70.0, "skew", "skew"),
            (65.0, "volume_change", "volume"),
            (60.0, "area_change", "volume"),
        ):
            ws.set_metric(metric)
            vp.flush()
            ws.request_flexion(angle)  # a slider pose: measured in the pose thread
            wait_idle(qtbot, ws)
            assert ws.flexion == pytest.approx(angle) and ws.view_kind == "live mapping"
            cells, live = ws._pose_quality
            assert cells is vp._shown_cells and len(cells)
            for q in live.by_type.values():  # the measure alone, not every metric
                assert q.measured[0] == "jacobian_corner" and measured in q.measured
                assert len(q.measured) <= 3
            full = compute_quality(ws.coords, ws.model.blocks)
            expected = full.concatenated(measured)
            if measured == "volume":
                initial = compute_quality(ws.model.coords, ws.model.blocks)
                expected = volume_change_pct(expected, initial.concatenated("volume"))
            # the Jacobian's live measure has no aspect: that one is measured anew
            aspect = full.concatenated("aspect")
            for shown_metric, values in ((metric, expected), ("aspect", aspect)):
                shown = ws.element_values(shown_metric, cells)
                sel = cells[np.isfinite(shown[cells])]
                # solids drawn: ligaments, menisci, tendon (the trabecular bones, inside
                # their cortical shells, are not drawn, so not measured)
                assert len(sel) >= 50, shown_metric
                np.testing.assert_array_equal(shown[sel], values[sel])
    finally:
        ws.set_colour_mode("part")
        demo_window.set_rest_export(rest_export)
        wait_idle(qtbot, ws)


def test_heatmaps_threshold_worst_list_and_cutaway(demo_window, qtbot):
    ws, vp, panel = demo_window.ws, demo_window.viewport, demo_window.quality_panel
    set_slider(demo_window, qtbot, 90.0)
    panel.mode.setCurrentIndex(panel.mode.findData("quality"))
    assert ws.colour_mode == "quality"
    offered = [panel.metric.itemData(i) for i in range(panel.metric.count())]
    assert offered == ws.heatmap_metrics() and offered[0] == "jacobian"  # a hex + shell deck
    assert not set(offered) & {"tet_collapse", "dihedral_min", "dihedral_max"}
    for key in offered:
        label = HEATMAP_METRICS[key][0]
        panel.metric.setCurrentIndex(panel.metric.findData(key))
        vp.flush()
        values = ws.element_values(key)
        assert vp._scalar_title == label
        shown = vp._displayed_cells()
        ws._quality = None  # the per-frame path measures only the elements on screen
        partial = ws.element_values(key, shown)
        np.testing.assert_array_equal(partial[shown], values[shown])
        assert np.isnan(np.delete(partial, shown)).all()
        for pid, surf in vp.surfaces.items():
            np.testing.assert_array_equal(surf.mesh.cell_data["value"], values[surf.cell_index])
            has = bool(np.isfinite(values[surf.cell_index]).any())
            assert bool(vp.actors[pid].mapper.GetScalarVisibility()) == has
    # the Jacobian shown is the engine's
    q = compute_quality(ws.coords, ws.model.blocks)
    panel.metric.setCurrentIndex(panel.metric.findData("jacobian"))
    jac = ws.element_values("jacobian")
    np.testing.assert_array_equal(jac[np.isfinite(jac)], q.concatenated("jacobian_corner"))
    # threshold highlight = exactly the elements below it
    level = float(np.nanpercentile(jac, 5))
    panel.threshold.setValue(level)
    panel.threshold_on.setChecked(True)
    vp.flush()
    assert ws.threshold == pytest.approx(level, abs=1e-3)  # the spin box rounds to 3 decimals
    expected = np.flatnonzero(jac < ws.threshold)
    assert 0 < len(expected) < len(jac)
    np.testing.assert_array_equal(np.sort(vp.highlighted_cells()), expected)
    # worst list (worst first) and zoom
    panel.refresh()
    first = panel.worst.item(0)
    cell = int(first.data(Qt.ItemDataRole.UserRole))
    assert jac[cell] == np.nanmin(jac)
    panel.worst.itemDoubleClicked.emit(first)
    focal = np.asarray(vp.plotter.camera.focal_point)
    block_cells = vp.grid.extract_cells([cell])
    centre = ws.coords[np.asarray(block_cells.point_data["vtkOriginalPointIds"])].mean(axis=0)
    np.testing.assert_allclose(focal, centre, atol=1e-6)
    # cut-away: one clipping plane on every part mapper, none when off
    panel.clip_on.setChecked(True)
    vp.flush()
    assert all(
        a.GetMapper().GetClippingPlanes().GetNumberOfItems() == 1 for a in vp.actors.values()
    )
    panel.clip_on.setChecked(False)
    vp.flush()
    assert all(
        a.GetMapper().GetClippingPlanes().GetNumberOfItems() == 0 for a in vp.actors.values()
    )
    panel.threshold_on.setChecked(False)
    vp.flush()
    # a slider pose brings the quality of the shown elements, measured in the pose thread
    set_slider(demo_window, qtbot, 60.0)
    assert ws._pose_quality is not None and ws._pose_quality[0] is vp._shown_cells
    full = compute_quality(ws.coords, ws.model.blocks).concatenated("jacobian_corner")
    measured = np.full(ws.model.n_elements, np.nan)
    measured[np.isfinite(jac)] = full
    for pid in vp.drawn_parts():  # the faces drawn (a face between two parts is not)
        surf, rows = vp.surfaces[pid], vp._drawn_rows.get(pid)
        sel = slice(None) if rows is None else rows
        np.testing.assert_allclose(
            surf.mesh.cell_data["value"][sel], measured[surf.cell_index][sel]
        )
    panel.mode.setCurrentIndex(panel.mode.findData("part"))
    vp.flush()
    assert not any(a.mapper.GetScalarVisibility() for a in vp.actors.values())


def test_ligament_stretch_and_length_curve(demo_window, qtbot):
    ws, vp = demo_window.ws, demo_window.viewport
    assert ws.ligaments, "the demo has ligament parts"
    names = {lig.name for lig in ws.ligaments}
    titled = {
        ligament_short_name(ws.model.parts[p].title) for p in ws.setup_dict["roles"]["ligament"]
    }
    assert "ACL" in names and names >= titled - {None}
    set_slider(demo_window, qtbot, 90.0)
    demo_window.ligament_panel.show_stretch.click()
    assert ws.colour_mode == "stretch"
    vp.flush()
    stretch = ws.ligament_stretch_values()
    lig_parts = {lig.part_id for lig in ws.ligaments}
    for pid, surf in vp.surfaces.items():
        vals = surf.mesh.cell_data["value"]
        if pid in lig_parts:
            assert np.isfinite(vals).all()
            np.testing.assert_array_equal(vals, stretch[surf.cell_index])
            assert vp.actors[pid].mapper.GetScalarVisibility()
        else:
            assert not vp.actors[pid].mapper.GetScalarVisibility()
    assert not np.allclose(stretch[np.isfinite(stretch)], 1.0)  # the knee moved them
    demo_window.ligament_panel.compute.click()
    wait_idle(qtbot, ws)
    angles, lengths = ws.ligament_curve
    assert angles[0] == -5.0 and angles[-1] == 140.0
    assert lengths.shape == (len(angles), len(ws.ligaments))
    j = int(np.argmin(np.abs(angles - 90.0)))
    expected = [lig.length(ws.poser.pose(float(angles[j]))) for lig in ws.ligaments]
    np.testing.assert_allclose(lengths[j], expected)
    assert len(demo_window.ligament_panel._ax.lines) >= len(ws.ligaments)


def test_smooth_and_export_match_the_engine(demo_window, qtbot, tmp_path):
    ws = demo_window.ws
    set_slider(demo_window, qtbot, 90.0)
    posed = ws.poser.pose(90.0)
    out = tmp_path / "posed90.k"
    n_inverted = ws.quality().n_inverted
    if n_inverted:
        with pytest.raises(ExportBlocked):
            ws.export(out)
        assert not out.exists()
    assert ws.export(out, force=True)
    wait_idle(qtbot, ws)
    assert demo_window.last_error is None, demo_window.last_error
    back = read_deck(out)
    np.testing.assert_array_equal(back.node_ids, ws.model.node_ids)
    np.testing.assert_allclose(back.coords, posed, rtol=0, atol=1e-6)
    # relaxing + smoothing in the worker: the result becomes the current pose
    before = ws.quality()
    messages = []
    ws.status.connect(messages.append)
    demo_window.guard(ws.smooth)
    assert ws.preview_pending or ws.smoothed
    wait_idle(qtbot, ws, timeout=150)
    assert demo_window.last_error is None, demo_window.last_error
    assert ws.smoothed
    # one posing path: Relax + smooth gives exactly what `kneegui pose` writes at that angle
    assert ws.flexion == 90.0
    assert np.array_equal(ws.coords, pose_model(ws.poser, 90.0).model.coords)
    # the status line says what the relaxation, its quality optimisation and the smoother did
    assert any("relaxed" in m and "quality optimised: worst Jacobian" in m for m in messages), (
        messages
    )
    assert not any("warning" in m and "reaches" in m for m in messages), messages  # no overlap
    # tissue left inside a bone is reported, as the engine counts it
    in_bones = ws.poser.tissue_in_bones(ws.coords, ws.poser.bone_pose(90.0))["nodes"]
    assert any("inside the" in m for m in messages) == (in_bones > 0), messages
    after = ws.quality()
    assert after.n_inverted == 0 < before.n_inverted  # the relaxation untangles the pose
    assert after.worst_jacobian() > before.worst_jacobian()
    bone_nodes = np.concatenate([ws.setup.segment_nodes[s] for s in ("femur", "tibia")])
    np.testing.assert_array_equal(ws.coords[bone_nodes], posed[bone_nodes])
    out2 = tmp_path / "smoothed90.k"
    ws.export(out2, force=True)
    wait_idle(qtbot, ws)
    np.testing.assert_allclose(read_deck(out2).coords, ws.coords, rtol=0, atol=1e-6)
    # moving the slider leaves the smoothed state
    set_slider(demo_window, qtbot, 60.0)
    assert not ws.smoothed


def test_relax_and_smooth_warns_about_bones_reaching_into_each_other(demo_window, qtbot):
    """Flexed to 140 deg, beyond what the demo is built for, the back of its tibia reaches into
    the posterior femur: the status line after Relax + smooth says so (at 90 deg, above, there is
    no such warning)."""
    ws = demo_window.ws
    set_slider(demo_window, qtbot, 140.0)
    messages = []
    ws.status.connect(messages.append)
    demo_window.guard(ws.smooth)
    wait_idle(qtbot, ws, timeout=150)
    assert demo_window.last_error is None, demo_window.last_error
    # warnings lead the line, which the status bar cuts at the window's edge
    assert any(m.startswith("warning: ") and "the tibia reaches" in m for m in messages), messages
    set_slider(demo_window, qtbot, 60.0)


def test_inverted_elements_block_export_unless_forced(demo_window, qtbot, tmp_path):
    ws = demo_window.ws
    coords = ws.coords.copy()
    block = next(b for e, b in ws.model.blocks.items() if e == "hex8")
    row = block.conn[0]
    coords[row[4:]] = coords[row[:4]] - (coords[row[4:]] - coords[row[:4]])  # flip one hex
    ws.set_coords(coords)
    assert ws.quality().n_inverted >= 1
    out = tmp_path / "inverted.k"
    demo_window._export_target = str(out)
    demo_window.guard(ws.export, out)
    assert not out.exists()
    box = demo_window.error_dialog
    assert box is not None and "inverted" in box.text()
    force = next(b for b in box.buttons() if b.text() == "Export anyway")
    force.click()
    wait_idle(qtbot, ws)
    assert out.exists()
    np.testing.assert_allclose(read_deck(out).coords, coords, atol=1e-6)


def test_bad_deck_and_bad_setup_show_file_and_line(demo_window, qtbot, tmp_path):
    ws = demo_window.ws
    model, setup_dict = ws.model, dict(ws.setup_dict)
    bad = tmp_path / "bad.k"
    bad.write_text("*KEYWORD\n*NODE\n       1     abc     0.0     0.0\n*END\n")
    demo_window.open_deck(bad)
    wait_idle(qtbot, ws)
    assert demo_window.last_error is not None
    assert "bad.k" in demo_window.last_error and "line 3" in demo_window.last_error
    assert ws.model is model
    bad_setup = tmp_path / "bad.json"
    bad_setup.write_text('{"format": "kneegui-setup",\n  "version": 1,,\n}\n')
    demo_window.last_error = None
    demo_window.guard(ws.open_setup, bad_setup)
    assert "bad.json" in demo_window.last_error and "line 2" in demo_window.last_error
    assert ws.setup_dict == setup_dict
    wrong = tmp_path / "wrong.json"
    wrong.write_text('{"format": "kneegui-setup", "version": 1, "side": "middle"}\n')
    demo_window.guard(ws.open_setup, wrong)
    assert "wrong.json" in demo_window.last_error
    assert ws.setup_dict == setup_dict and ws.model is model


def test_camera_presets_and_screenshot(demo_window, tmp_path):
    vp = demo_window.viewport
    frame = demo_window.ws.knee_frame()
    expected = {
        "lateral": frame["lateral"],
        "medial": -frame["lateral"],
        "anterior": frame["anterior"],
        "posterior": -frame["anterior"],
    }
    for name in CAMERA_PRESETS:
        vp.camera_preset(name)
        cam = vp.plotter.camera
        view = np.asarray(cam.position) - np.asarray(cam.focal_point)
        np.testing.assert_allclose(view / np.linalg.norm(view), expected[name], atol=1e-9)
    out = demo_window.save_screenshot(tmp_path / "window.png")
    image = QImage(str(out))
    assert image.width() == demo_window.width() and image.height() == demo_window.height()
    centre = vp.plotter.mapTo(demo_window, vp.plotter.rect().center())
    colours = {
        image.pixel(centre.x() + dx, centre.y() + dy)
        for dx in range(-60, 61, 20)
        for dy in range(-60, 61, 20)
    }
    assert len(colours) > 3  # the 3-D view is in the picture, not a blank area


def test_layout_and_recent_files_persist(demo_window, qtbot, leg_files, isolated_settings):
    from app.main_window import MainWindow

    assert str(leg_files[0]) in demo_window.recent_files()
    demo_window.docks["Ligaments"].setFloating(False)
    demo_window.docks["Model"].hide()
    demo_window.save_layout()
    assert str(isolated_settings) in demo_window.settings.fileName()
    other = MainWindow()
    qtbot.addWidget(other)
    other.show()
    assert str(leg_files[0]) in other.recent_files()
    assert not other.docks["Model"].isVisible()
    other.docks["Model"].show()
    other.save_layout()
    other.close()


def test_cancel_a_background_task(demo_window, qtbot):
    ws = demo_window.ws
    assert ws.compute_ligament_curve(step=0.5)
    ws.tasks.cancel()
    wait_idle(qtbot, ws)
    assert ws.ligament_curve is None
    assert demo_window.last_error is None


def test_command_line_screenshot(leg_files, tmp_path):
    deck, setup = leg_files
    out = tmp_path / "cli.png"
    env = dict(
        os.environ,
        XDG_CONFIG_HOME=str(tmp_path / "config"),
        KNEEGUI_CACHE_DIR=str(tmp_path / "cache"),
        KNEEGUI_DATA_DIR=str(tmp_path / "data"),
        QT_API="pyside6",
    )
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "app.main",
            str(deck),
            "--setup",
            str(setup),
            "--flexion",
            "90",
            "--colour",
            "quality",
            "--screenshot",
            str(out),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=240,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert QImage(str(out)).width() > 800


def test_save_and_reopen_the_setup(demo_window, qtbot, tmp_path):
    ws = demo_window.ws
    lateral = ws.condyle_ids("lateral_condyle")
    ws.remove_condyle_ids("lateral_condyle", lateral[:2])
    saved = ws.save_setup(tmp_path / "edited.setup.json")
    ws.undo()
    assert ws.condyle_ids("lateral_condyle") == lateral
    demo_window.guard(ws.open_setup, saved)
    assert demo_window.last_error is None
    assert ws.condyle_ids("lateral_condyle") == lateral[2:]
    assert ws.setup_problem is None and ws.setup_path == saved
    wait_idle(qtbot, ws)
    assert ws.poser is not None
