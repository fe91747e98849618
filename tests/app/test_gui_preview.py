"""What the window shows is what it exports: the export at rest, its indicator, cancelling by
dragging, Export without a second solve, quality against flexion, panels equal to the CLI."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest

import app.smoothing
from kneegui.errors import Cancelled, KneeguiError
from kneegui.io.lsdyna import read_deck
from kneegui.quality import compute_quality, summarize_quality

from .conftest import wait_idle

pytestmark = pytest.mark.gui


@pytest.fixture
def counted_exports(monkeypatch):
    """Every run of the export path from the window: (angle, 'done' | 'cancelled')."""
    runs: list[tuple[float, str]] = []
    real = app.smoothing.pose_model

    def counting(repositioner, flexion_deg, **kwargs):
        try:
            posed = real(repositioner, flexion_deg, **kwargs)
        except Cancelled:
            runs.append((flexion_deg, "cancelled"))
            raise
        runs.append((flexion_deg, "done"))
        return posed

    monkeypatch.setattr(app.smoothing, "pose_model", counting)
    return runs


@pytest.fixture(scope="module")
def cli_pose_90(leg_files, tmp_path_factory):
    """``kneegui pose DECK --setup S --flexion 90 --report R --force``: (coords, report)."""
    from kneegui.cli import main as cli

    deck, setup = leg_files
    folder = tmp_path_factory.mktemp("cli90")
    code = cli(
        [
            "pose",
            str(deck),
            "--setup",
            str(setup),
            "--flexion",
            "90",
            "--out",
            str(folder / "cli.k"),
            "--report",
            str(folder / "report.json"),
            "--force",
        ]
    )
    assert code in (0, 3)
    report = json.loads((folder / "report.json").read_text())
    return read_deck(folder / "cli.k").coords, report


def test_rest_shows_the_export_as_the_cli_writes_it_and_export_does_not_solve_again(
    demo_window, qtbot, tmp_path, counted_exports, cli_pose_90
):
    cli_coords, report = cli_pose_90
    ws, indicator = demo_window.ws, demo_window.indicator
    # the live mapping at 90 deg (export at rest off): its figures are the engine's summary
    demo_window.flexion_panel.slider.setValue(900)
    wait_idle(qtbot, ws)
    assert ws.view_kind == "live mapping" and counted_exports == []
    live = ws.view_figures()
    summary = summarize_quality(
        ws.model,
        compute_quality(ws.coords, ws.model.blocks),
        initial=compute_quality(ws.model.coords, ws.model.blocks),
    )["model"]
    assert live.inverted == summary["inverted"] > 0
    assert live.worst_jacobian == summary["jacobian"]["worst"]
    assert live.max_volume_change_pct == summary["volume_change"]["max_element_pct"]
    expected = f"LIVE MAPPING · 90.0° · inverted {live.inverted} ·"
    qtbot.waitUntil(lambda: indicator.text().startswith(expected), timeout=5000)
    # back to the initial angle, then the export at rest on, and a move to 90 deg
    demo_window.flexion_panel.spin.setValue(ws.poser.initial_flexion)
    demo_window.set_rest_export(True)
    wait_idle(qtbot, ws)
    counted_exports.clear()
    shown, banners, staged = [], [], []

    def on_coords():
        shown.append((ws.flexion, ws.view_kind))
        if ws.view_kind == "relaxing":
            staged.append(ws.coords.copy())

    def on_preview():  # after the indicator's own refresh on the same signal
        if ws.view_kind == "relaxing" and len(banners) < len(staged):
            banners.append(indicator.text())

    ws.coords_changed.connect(on_coords)
    ws.preview.changed.connect(on_preview)
    demo_window.flexion_panel.slider.setValue(900)
    # the banner changes with the view: to the live mapping when its first pose is drawn
    qtbot.waitUntil(lambda: indicator.text().startswith("LIVE MAPPING"), timeout=10000)
    wait_idle(qtbot, ws, timeout=300)
    assert demo_window.last_error is None, demo_window.last_error
    # the live pose first, then the poses of the export's stages (the untangling's first
    # round that leaves nothing inverted, the untangling's end, the quality stage's end), then
    # the export of the resting angle
    assert shown[0] == (90.0, "live mapping") and shown[-1] == (90.0, "as exported")
    kinds = [kind for _, kind in shown]
    first = kinds.index("relaxing")
    assert kinds[first:-1] == ["relaxing"] * 3 and "relaxing" not in kinds[:first]
    assert len(banners) == 3 and banners[0].startswith("RELAXING · 90.0° · inverted 0 ·")
    for banner in banners[:2]:
        assert "untangled, not yet exported · exporting:" in banner, banner
    assert "quality-optimised, not yet exported" in banners[2], banners[2]
    # stages of the same export, not copies of its end: the quality stage and the smoothing
    # still moved nodes after them
    assert np.abs(staged[0] - ws.exported.coords).max() > 1e-3
    assert counted_exports == [(90.0, "done")]
    np.testing.assert_allclose(ws.coords, cli_coords, rtol=0, atol=1e-6)
    mine = ws.exported.posed.report
    for key in ("quality", "volume_change", "achieved_flexion", "initial_flexion", "gate"):
        assert mine[key] == report[key], key
    # every figure shown is the CLI report's
    final = report["quality"]["smoothed"]
    text = indicator.text()
    assert text.startswith("AS EXPORTED · 90.0°"), text
    assert f"inverted {final['inverted']} · worst Jacobian {final['jacobian']['worst']:.3f}" in text
    vc = report["volume_change"]["max_element_pct"]
    assert f"largest volume change {vc:+.1f} %" in text
    panel = demo_window.quality_panel
    panel.refresh()
    stats = panel.stats.text()
    assert f"inverted {final['inverted']}" in stats
    assert f"worst Jacobian {final['jacobian']['worst']:.3f}" in stats
    initial = f"{report['initial_flexion']:.1f}°"
    assert demo_window.flexion_panel.info.text() == f"initial {initial}"
    assert demo_window.landmark_panel.labels["flexion"].text() == initial
    for label in demo_window.landmark_panel.labels.values():
        assert "xyz" not in label.text()
    # Export writes what is shown, without solving again
    out = tmp_path / "shown.k"
    assert ws.export(out)
    wait_idle(qtbot, ws)
    assert demo_window.last_error is None, demo_window.last_error
    assert counted_exports == [(90.0, "done")]
    np.testing.assert_allclose(read_deck(out).coords, cli_coords, rtol=0, atol=1e-6)
    # quality against flexion: the live mapping over the validated range, the exported angle
    curve_panel = demo_window.quality_curve_panel
    data = curve_panel.series()
    live_x, live_y, exp_x, exp_y = data["worst_jacobian"]
    assert live_x[0] == -5.0 and live_x[-1] == 140.0 and len(live_y) == len(live_x) == 30
    assert 90.0 in exp_x
    assert exp_y[exp_x.index(90.0)] == final["jacobian"]["worst"]
    j = int(np.flatnonzero(live_x == 90.0)[0])
    assert data["inverted"][1][j] == live.inverted
    assert live_y[j] == live.worst_jacobian
    assert data["max_volume_change_pct"][1][j] == live.max_volume_change_pct
    demo_window.docks["Quality vs flexion"].raise_()
    qtbot.waitUntil(lambda: curve_panel.isVisible(), timeout=5000)
    assert all(len(ax.lines) >= 2 for ax in curve_panel.axes)  # the curve and the angle
    assert curve_panel._markers[0].get_xdata()[0] == pytest.approx(90.0)


def test_dragging_again_cancels_the_export_and_a_stale_result_is_never_shown(
    demo_window, qtbot, monkeypatch, counted_exports
):
    ws = demo_window.ws
    demo_window.set_rest_export(True)
    wait_idle(qtbot, ws)
    counted_exports.clear()
    gate = threading.Event()
    counting = app.smoothing.pose_model

    def held(repositioner, flexion_deg, **kwargs):
        gate.wait(60)  # the test moves the slider while this export is under way
        return counting(repositioner, flexion_deg, **kwargs)

    monkeypatch.setattr(app.smoothing, "pose_model", held)
    shown = []
    ws.coords_changed.connect(lambda: shown.append((ws.flexion, ws.view_kind)))
    slider = demo_window.flexion_panel.slider
    slider.setValue(900)
    qtbot.waitUntil(lambda: ws.preview.running_for == 90.0, timeout=10000)
    # the live pose and the indicator follow through queued signals (late on a loaded machine)
    qtbot.waitUntil(lambda: "exporting" in demo_window.indicator.text(), timeout=10000)
    assert ws.view_kind == "live mapping" and ws.flexion == 90.0
    slider.setValue(200)  # dragging again (to an angle the export poses quickly)
    gate.set()
    wait_idle(qtbot, ws)
    assert demo_window.last_error is None, demo_window.last_error
    assert counted_exports == [(90.0, "cancelled"), (20.0, "done")]
    assert (90.0, "as exported") not in shown
    assert ws.view_kind == "as exported" and ws.flexion == 20.0
    np.testing.assert_array_equal(ws.coords, ws.exported.coords)
    assert 20.0 in ws.preview.exported_points and 90.0 not in ws.preview.exported_points


def test_a_stage_of_the_export_is_shown_marked_and_never_written(demo_window, qtbot, tmp_path):
    """The pose a stage of the running export ends on is shown for its request alone, marked
    'relaxing', and File > Export refuses it (even forced): it is not the chain's end."""
    ws, indicator = demo_window.ws, demo_window.indicator
    demo_window.set_rest_export(False)  # no export runs on its own: the test hands the stage
    demo_window.flexion_panel.slider.setValue(600)
    wait_idle(qtbot, ws)
    live, generation = ws.coords.copy(), ws.pose_generation
    assert not ws.show_stage(generation - 1, 60.0, "untangle", live + 1.0)  # a stale request
    assert ws.view_kind == "live mapping"
    assert ws.show_stage(generation, 60.0, "untangle", live + 1.0)
    assert ws.view_kind == "relaxing" and ws.stage == "untangle"
    np.testing.assert_array_equal(ws.coords, live + 1.0)
    indicator.refresh()
    assert indicator.text().startswith("RELAXING · 60.0° · inverted "), indicator.text()
    assert "untangled, not yet exported" in indicator.text()
    with pytest.raises(KneeguiError, match="untangled pose of the export at 60°"):
        ws.export(tmp_path / "refused.k", force=True)
    assert not (tmp_path / "refused.k").exists()
    ws._apply_pose(60.0, live, generation=generation)  # a late live pose of that request
    assert ws.view_kind == "relaxing"
    demo_window.flexion_panel.slider.setValue(500)  # a new request replaces it
    wait_idle(qtbot, ws)
    assert ws.view_kind == "live mapping" and ws.stage is None and ws.flexion == 50.0


def test_an_export_that_fails_after_a_stage_leaves_the_live_mapping_not_the_stage(
    demo_window, qtbot, monkeypatch
):
    """A stage is shown while its export runs; when that export fails, the view goes back to
    the live mapping of the angle (and says why), instead of keeping a pose nothing exports."""
    ws, indicator = demo_window.ws, demo_window.indicator
    demo_window.set_rest_export(False)
    demo_window.flexion_panel.slider.setValue(700)
    wait_idle(qtbot, ws)
    live = ws.coords.copy()

    def failing(repositioner, flexion_deg, stage_done=None, **kwargs):
        stage_done("untangle", repositioner.pose(flexion_deg) + 0.5)
        raise RuntimeError("solver blew up")

    monkeypatch.setattr(app.smoothing, "pose_model", failing)
    kinds = []
    ws.coords_changed.connect(lambda: kinds.append(ws.view_kind))
    demo_window.set_rest_export(True)  # the export of the resting angle runs now
    wait_idle(qtbot, ws)
    assert kinds == ["relaxing", "live mapping"]
    assert ws.view_kind == "live mapping" and ws.stage is None and ws.flexion == 70.0
    np.testing.assert_array_equal(ws.coords, live)
    indicator.refresh()
    assert "the export failed: RuntimeError: solver blew up" in indicator.text()
    assert demo_window.last_error is None  # not asked for explicitly: no dialog


def test_back_at_an_exported_angle_the_view_shows_its_export_without_solving_again(
    demo_window, qtbot, counted_exports
):
    ws, indicator = demo_window.ws, demo_window.indicator
    demo_window.set_rest_export(True)
    slider = demo_window.flexion_panel.slider
    slider.setValue(200)
    wait_idle(qtbot, ws)
    counted_exports.clear()
    ws.preview.kept.clear()
    slider.setValue(100)
    wait_idle(qtbot, ws)
    first = np.array(ws.exported.coords)
    first_report = ws.exported.posed.report
    slider.setValue(200)
    wait_idle(qtbot, ws)
    assert counted_exports == [(10.0, "done"), (20.0, "done")]
    assert list(ws.preview.kept) == [10.0, 20.0]
    shown = []
    ws.coords_changed.connect(lambda: shown.append((ws.flexion, ws.view_kind)))
    slider.setValue(100)
    wait_idle(qtbot, ws)
    assert demo_window.last_error is None, demo_window.last_error
    assert counted_exports == [(10.0, "done"), (20.0, "done")]  # no third solve
    assert shown[-1] == (10.0, "as exported")
    np.testing.assert_array_equal(ws.coords, first)
    assert ws.exported.posed.report is first_report
    assert indicator.text().startswith("AS EXPORTED · 10.0°")
    assert list(ws.preview.kept) == [20.0, 10.0]  # the most recently shown last
    ws.preview.reset()  # a new poser: nothing kept
    assert not ws.preview.kept


def test_restore_volume_switch_reexports_with_the_volume_step_and_writes_it(
    demo_window, qtbot, tmp_path, counted_exports
):
    """Mesh > Restore the soft tissue's volume: the poser keeps its precompute, the shown
    export runs again with the volume step (its report says so, as ``kneegui pose
    --restore-volume``'s does), Export writes that one without solving again, and switching
    it off brings back the plain export."""
    ws = demo_window.ws
    demo_window.set_rest_export(True)
    demo_window.flexion_panel.slider.setValue(600)
    wait_idle(qtbot, ws)
    assert ws.view_kind == "as exported"
    plain = np.array(ws.exported.coords)
    assert ws.exported.posed.report["volume_correction"] is None
    weights = ws.poser._weights
    counted_exports.clear()
    demo_window.restore_volume_action.trigger()
    wait_idle(qtbot, ws)
    assert demo_window.last_error is None, demo_window.last_error
    assert ws.restore_volume and ws.poser._weights is weights  # no second precompute
    assert counted_exports == [(60.0, "done")]
    assert ws.view_kind == "as exported"
    step = ws.exported.posed.report["volume_correction"]
    assert step is not None and step["aimed"] > 0 and step["largest_move"] > 0
    restored = np.array(ws.exported.coords)
    assert np.abs(restored - plain).max() > 1e-3
    demo_window.indicator.refresh()
    assert demo_window.indicator.text().endswith(" · volume restored before relaxing")
    assert list(ws.preview.kept) == [60.0]  # the plain export is not kept for this poser
    out = tmp_path / "restored.k"
    assert ws.export(out)
    wait_idle(qtbot, ws)
    assert demo_window.last_error is None, demo_window.last_error
    assert counted_exports == [(60.0, "done")]  # written as shown
    np.testing.assert_allclose(read_deck(out).coords, restored, rtol=0, atol=1e-6)
    demo_window.restore_volume_action.trigger()
    wait_idle(qtbot, ws)
    assert not ws.restore_volume and ws.exported.posed.report["volume_correction"] is None
    demo_window.indicator.refresh()
    assert "volume restored" not in demo_window.indicator.text()
    np.testing.assert_array_equal(ws.exported.coords, plain)


def test_restore_volume_switched_while_a_deck_opens_reaches_its_poser(window, qtbot, leg_files):
    """Switched on while the deck is still being read (no poser yet): the poser that arrives
    has the volume step."""
    deck, setup = leg_files
    window.open_deck(deck, setup)
    window.restore_volume_action.setChecked(True)  # before the poser is ready
    qtbot.waitUntil(lambda: window.ws.poser is not None, timeout=60000)
    wait_idle(qtbot, window.ws)
    assert window.last_error is None, window.last_error
    assert window.ws.restore_volume
    assert window.ws.poser.options.volume_correction is not None


def test_kept_exports_stay_within_their_count_and_node_budget(monkeypatch):
    from app import preview

    class Exported:
        def __init__(self, flexion: float, nodes: int):
            self.flexion, self.coords = flexion, np.zeros((nodes, 3))

    keeper = preview.ExportPreview.__new__(preview.ExportPreview)
    keeper.kept = preview.OrderedDict()
    monkeypatch.setattr(preview, "KEPT_EXPORTS", 3)
    monkeypatch.setattr(preview, "KEPT_EXPORT_NODES", 1000)
    for angle in (0.0, 30.0, 60.0, 90.0):
        keeper._keep(Exported(angle, 100))
    assert list(keeper.kept) == [30.0, 60.0, 90.0]  # the count: the oldest dropped
    keeper._keep(Exported(30.0, 100))
    assert list(keeper.kept) == [60.0, 90.0, 30.0]  # kept again: now the most recent
    for angle in (0.0, 120.0):
        keeper._keep(Exported(angle, 400))  # 3 x 400 nodes would pass the budget
    assert list(keeper.kept) == [0.0, 120.0]
    keeper._keep(Exported(45.0, 5000))  # larger than the budget alone: kept, alone
    assert list(keeper.kept) == [45.0]


def test_file_open_with_progress_recent_decks_and_title(window, qtbot, leg_files, tmp_path):
    deck, setup = leg_files
    ws = window.ws
    window.open_deck(deck, setup)
    dialog = window.open_progress
    assert dialog is not None and dialog.isVisible()
    assert deck.name in dialog.labelText()
    wait_idle(qtbot, ws)
    qtbot.waitUntil(lambda: ws.poser is not None, timeout=60000)
    assert not dialog.isVisible()
    assert window.recent_files()[0] == str(deck)
    assert next(a.text() for a in window.recent_menu.actions()) == str(deck)
    assert window.windowTitle().startswith(deck.name)
    assert not window.isWindowModified()
    lateral = ws.condyle_ids("lateral_condyle")
    ws.remove_condyle_ids("lateral_condyle", lateral[:1])
    assert window.isWindowModified()  # the title shows '*'
    assert ws.tasks.busy  # the repositioner is rebuilt for the edit, without the dialog
    assert not window.open_progress.isVisible()
    ws.save_setup(tmp_path / "saved.setup.json")
    assert not window.isWindowModified()
    wait_idle(qtbot, ws)
    # a deck that fails to read joins no list and keeps the title
    bad = tmp_path / "bad.k"
    bad.write_text("*KEYWORD\n*NODE\n       1     abc     0.0     0.0\n*END\n")
    window.open_deck(bad)
    wait_idle(qtbot, ws)
    assert window.last_error is not None and "line 3" in window.last_error
    assert str(bad) not in window.recent_files()
    assert window.windowTitle().startswith(deck.name)
    assert not window.open_progress.isVisible()


def test_status_line_of_an_export_whose_smoother_had_nothing_to_move():
    report = {
        "relaxation": None,
        "smoothing": {
            "moved_nodes": 0,
            "worst_jacobian_before": None,
            "worst_jacobian_after": None,
            "inverted_before": 0,
            "inverted_after": 0,
            "seconds": 0.001,
        },
        "warnings": [],
    }
    assert app.smoothing.status_line(report) == "smoothed: nothing to move"


def test_status_line_quotes_the_tet_collapse_and_the_jacobian_where_it_says_something():
    quality = {
        "free_nodes": 10,
        "worst_before": 1.0,
        "worst_after": 1.0,
        "collapse_worst_before": 0.05,
        "collapse_worst_after": 0.11,
    }
    relax = {"free_nodes": 20, "inverted_corners_before": 3, "inverted_corners_after": 0}
    report = {"relaxation": {**relax, "seconds": 1.0, "quality": quality}, "smoothing": None}
    tets_only = app.smoothing.status_line(report, jacobian=False)
    assert "quality optimised: worst tet collapse 0.050 -> 0.110," in tets_only
    assert "Jacobian" not in tets_only
    mixed = app.smoothing.status_line(report, jacobian=True)
    assert "worst tet collapse 0.050 -> 0.110, worst Jacobian 1.000 -> 1.000" in mixed
    quality.update(collapse_worst_before=None, collapse_worst_after=None)  # no tets
    assert "quality optimised: worst Jacobian 1.000 -> 1.000," in app.smoothing.status_line(
        report, jacobian=False
    )
    quality.update(beyond_region_nodes=148)  # the pass beyond the relaxed region ran
    assert "worst Jacobian 1.000 -> 1.000, 148 nodes beyond the relaxed region," in (
        app.smoothing.status_line(report, jacobian=False)
    )
    quality.update(held_nodes=11)  # the stage ran around elements the untangling left inverted
    assert "148 nodes beyond the relaxed region, 11 nodes of inverted elements held," in (
        app.smoothing.status_line(report, jacobian=False)
    )
    quality.update(bone_settled_nodes=240)  # tissue left in a bone was settled on its own
    assert "148 nodes beyond the relaxed region, 240 nodes settled out of a bone, 11 nodes" in (
        app.smoothing.status_line(report, jacobian=False)
    )
