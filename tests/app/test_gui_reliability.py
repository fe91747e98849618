"""The real window under Xvfb: setup autosave offered back after a crash; worker errors shown."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from PySide6.QtWidgets import QMessageBox

from app.autosave import AUTOSAVE_DELAY_MS
from kneegui.setup import load_setup

from .conftest import wait_idle

pytestmark = pytest.mark.gui


def settle(qtbot, ws) -> None:
    """Wait for background work, including a poser rebuild deferred behind another task."""
    qtbot.waitUntil(lambda: not ws._poser_stale, timeout=60000)
    wait_idle(qtbot, ws)
    wait_idle(qtbot, ws)


def test_autosave_is_offered_back_after_a_crash(
    demo_window, qtbot, leg_files, tmp_path, isolated_settings
):
    from app.main_window import MainWindow

    deck, setup = leg_files
    ws = demo_window.ws
    target = ws.autosave_file
    assert target is not None and str(isolated_settings) in str(target)
    assert not target.exists()
    # edits: a role from the part tree, then two nodes off a condyle set
    pid = ws.setup_dict["roles"]["patella"][0]
    demo_window.model_panel.role_boxes[pid].setCurrentText("fixed")
    lateral = ws.condyle_ids("lateral_condyle")
    ws.remove_condyle_ids("lateral_condyle", lateral[:2])
    assert not target.exists()  # debounced: written once the edits pause
    qtbot.waitUntil(target.is_file, timeout=AUTOSAVE_DELAY_MS + 5000)
    edited = json.loads(json.dumps(ws.setup_dict))
    assert json.loads(target.read_text(encoding="utf-8")) == edited
    assert not list(target.parent.glob("*.part"))  # atomic write: no temp file left
    settle(qtbot, ws)
    # a crash leaves the file behind; a normal close removes it
    kept = tmp_path / "left-by-the-crash.json"
    shutil.copy(target, kept)
    demo_window.close()
    assert not target.exists()
    shutil.copy(kept, target)
    # the same deck opened again in a new window: the restore is offered and accepted
    other = MainWindow()
    qtbot.addWidget(other)
    asked = []
    other.restore_answer = lambda d, a: asked.append((d, a)) or True
    other.show()
    other.open_deck(deck, setup)
    settle(qtbot, other.ws)
    assert asked == [(deck, target)]
    assert other.last_error is None, other.last_error
    ows = other.ws
    assert ows.setup_dict == load_setup(edited, ows.model).to_dict()
    assert ows.part_role(pid) == "fixed"
    assert ows.condyle_ids("lateral_condyle") == lateral[2:]
    assert ows.setup_problem is None and ows.poser is not None
    assert ows.setup_path == setup  # the setup file is unchanged: the edits are still unsaved
    qtbot.waitUntil(target.is_file, timeout=AUTOSAVE_DELAY_MS + 5000)
    ows.undo()  # the restore is one undo step back to the setup file
    assert ows.condyle_ids("lateral_condyle") == lateral and ows.part_role(pid) == "patella"
    other.close()
    assert not target.exists()


def test_a_clean_save_or_a_declined_offer_removes_the_autosave(
    demo_window, qtbot, leg_files, tmp_path
):
    deck, _setup = leg_files
    ws = demo_window.ws
    target = ws.autosave_file
    lateral = ws.condyle_ids("lateral_condyle")
    ws.remove_condyle_ids("lateral_condyle", lateral[:1])
    qtbot.waitUntil(target.is_file, timeout=AUTOSAVE_DELAY_MS + 5000)
    saved = ws.save_setup(tmp_path / "clean.setup.json")
    assert not target.exists()
    qtbot.wait(AUTOSAVE_DELAY_MS + 300)
    assert not target.exists()  # no pending write brings it back
    assert (
        json.loads(saved.read_text(encoding="utf-8"))["landmarks"]["lateral_condyle"]
        == (lateral[1:])
    )
    # an undo is an edit like any other; the offer for the same deck, declined, drops the file
    ws.undo()
    qtbot.waitUntil(target.is_file, timeout=AUTOSAVE_DELAY_MS + 5000)
    settle(qtbot, ws)
    demo_window.open_deck(deck, saved)
    settle(qtbot, ws)
    box = demo_window.restore_dialog  # the real question, shown without blocking
    assert box is not None and box.isVisible() and str(target) in box.text()
    offered = target.read_text(encoding="utf-8")
    ws.remove_condyle_ids("lateral_condyle", lateral[1:2])  # edits while the question is open
    qtbot.wait(AUTOSAVE_DELAY_MS + 300)
    assert target.read_text(encoding="utf-8") == offered  # the offered file is not overwritten
    box.button(QMessageBox.StandardButton.No).click()
    assert not target.exists()
    qtbot.waitUntil(target.is_file, timeout=AUTOSAVE_DELAY_MS + 5000)  # the new edit, autosaved
    assert (
        json.loads(target.read_text(encoding="utf-8"))["landmarks"]["lateral_condyle"]
        == (lateral[2:])
    )
    assert ws.condyle_ids("lateral_condyle") == lateral[2:]
    assert demo_window.last_error is None, demo_window.last_error


def test_an_invalid_autosave_shows_the_usual_dialog(demo_window, qtbot, leg_files):
    deck, setup = leg_files
    ws = demo_window.ws
    target = ws.autosave_file
    before = dict(ws.setup_dict)
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(json.dumps({**before, "side": "middle"}), encoding="utf-8")
    demo_window.restore_answer = lambda d, a: True
    demo_window.open_deck(deck, setup)
    settle(qtbot, ws)
    assert demo_window.last_error is not None and str(target) in demo_window.last_error
    assert "Key: side" in demo_window.last_error
    assert ws.setup_dict == before and ws.poser is not None
    assert target.exists()  # kept for the user to look at, until the deck is closed normally


@pytest.mark.parametrize("task", ["smooth", "export"])
def test_an_exception_in_a_worker_is_shown_and_the_window_stays_usable(
    demo_window, qtbot, monkeypatch, tmp_path, task
):
    import app.smoothing
    import kneegui.io.lsdyna

    ws = demo_window.ws
    demo_window.flexion_panel.slider.setValue(600)
    wait_idle(qtbot, ws)
    coords = ws.coords.copy()
    ran = []

    def boom(*args, **kwargs):
        ran.append(task)
        raise RuntimeError("boom")

    out = tmp_path / "posed.k"
    if task == "smooth":
        monkeypatch.setattr(app.smoothing, "smooth_current", boom)
        demo_window.guard(ws.smooth)
    else:
        monkeypatch.setattr(kneegui.io.lsdyna, "write_deck", boom)
        monkeypatch.setattr(kneegui.io.lsdyna, "write_model", boom)
        demo_window.guard(ws.export, out, True)
    assert ws.tasks.busy or ws.preview_pending or ran  # it ran in a worker, not in the guard
    wait_idle(qtbot, ws)
    assert ran == [task]
    assert demo_window.last_error == "RuntimeError: boom"
    box = demo_window.error_dialog
    assert box is not None and box.isVisible() and "boom" in box.text()
    assert "boom" in (ws.preview.tasks if task == "smooth" else ws.tasks).last_traceback
    assert not ws.tasks.busy and not demo_window.progress.isVisible()
    assert not ws.smoothed and not out.exists()
    np.testing.assert_array_equal(ws.coords, coords)
    box.close()
    # the window stays usable: the slider poses, and the same task runs once the fault is gone
    demo_window.last_error = None
    demo_window.flexion_panel.slider.setValue(900)
    wait_idle(qtbot, ws)
    assert ws.flexion == 90.0
    np.testing.assert_allclose(ws.coords, ws.poser.pose(90.0))
    monkeypatch.undo()
    assert ws.export(out, force=True)
    wait_idle(qtbot, ws)
    assert demo_window.last_error is None, demo_window.last_error
    assert out.exists()


def test_an_unanswered_offer_keeps_the_autosave(demo_window, qtbot, leg_files):
    deck, setup = leg_files
    ws = demo_window.ws
    target = ws.autosave_file
    lateral = ws.condyle_ids("lateral_condyle")
    edited = json.loads(json.dumps(ws.setup_dict))
    edited["landmarks"]["lateral_condyle"] = lateral[1:]
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(json.dumps(edited), encoding="utf-8")
    demo_window.open_deck(deck, setup)
    settle(qtbot, ws)
    assert demo_window.restore_dialog is not None and demo_window.restore_dialog.isVisible()
    demo_window.close()  # closed without an answer: offered again next time
    assert json.loads(target.read_text(encoding="utf-8")) == edited
    target.unlink()
