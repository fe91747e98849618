"""Fixtures for the GUI tests: a temporary settings/cache location and the real window.

These tests drive the real Qt + VTK window and need a display:
``xvfb-run -a -s "-screen 0 1600x1000x24" python -m pytest tests/app``.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest

os.environ.setdefault("QT_API", "pyside6")

DEMO_ELEMENTS = 2000


@pytest.fixture(scope="session", autouse=True)
def isolated_settings(tmp_path_factory):
    """Settings, the demo cache and autosaves go to a temporary folder, never the user's."""
    from PySide6.QtCore import QSettings

    root = tmp_path_factory.mktemp("gui-settings")
    QSettings.setPath(QSettings.Format.IniFormat, QSettings.Scope.UserScope, str(root))
    os.environ["KNEEGUI_CACHE_DIR"] = str(root / "cache")
    os.environ["KNEEGUI_DATA_DIR"] = str(root / "data")  # autosaves
    yield root


@pytest.fixture(scope="session")
def leg_files(tmp_path_factory, request):
    """Deck and setup of the small demo leg (written once per session).

    ``KNEEGUI_TEST_LEG=synthetic`` runs the same tests on the engine's tiny synthetic knee.
    """
    if not os.environ.get("DISPLAY"):
        pytest.skip("GUI tests need a display (run under xvfb-run)")
    if os.environ.get("KNEEGUI_TEST_LEG") == "synthetic":
        return request.getfixturevalue("synthetic_files")
    from app.demo import demo_files

    return demo_files(DEMO_ELEMENTS, cache_dir=tmp_path_factory.mktemp("demo"))


@pytest.fixture(scope="session")
def synthetic_files(tmp_path_factory):
    """The engine's synthetic knee written as a deck + setup (a second, tiny model)."""
    from kneegui.io.lsdyna import write_model
    from kneegui.setup.synthetic import build_synthetic_knee

    folder = tmp_path_factory.mktemp("synthetic")
    knee = build_synthetic_knee()
    deck = write_model(knee.model, folder / "knee.k")
    setup = folder / "knee.setup.json"
    setup.write_text(json.dumps(knee.setup), encoding="utf-8")
    return Path(deck), setup


def wait_idle(qtbot, ws, timeout: float = 120.0) -> None:
    """Wait until no background task runs (the export of the resting angle included) and
    pending signals are delivered."""
    qtbot.waitUntil(
        lambda: not ws.tasks.busy and not ws.pose_pending and not ws.preview_pending,
        timeout=int(timeout * 1000),
    )
    end = time.monotonic() + 0.05
    from PySide6.QtWidgets import QApplication

    while time.monotonic() < end:
        QApplication.processEvents()


@pytest.fixture
def window(qtbot):
    """The real main window, shown (under Xvfb) and closed after the test.

    It keeps the live mapping when the slider rests (View > "Show the export when the slider
    rests" off), so that the tests of the live path see it; tests/app/test_gui_preview.py
    switches the export at rest on.
    """
    if not os.environ.get("DISPLAY"):
        pytest.skip("GUI tests need a display (run under xvfb-run)")
    from app.main_window import MainWindow

    win = MainWindow()
    win.set_rest_export(False)
    qtbot.addWidget(win)
    win.show()
    qtbot.waitExposed(win)
    yield win
    win.ws.shutdown()
    win.close()


@pytest.fixture
def demo_window(window, qtbot, leg_files):
    """The window with the small demo leg open and its poser ready."""
    deck, setup = leg_files
    window.open_deck(deck, setup)
    wait_idle(qtbot, window.ws)
    qtbot.waitUntil(lambda: window.ws.poser is not None, timeout=60000)
    assert window.last_error is None, window.last_error
    window.viewport.flush()
    return window
