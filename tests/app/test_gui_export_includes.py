"""The window's export follows the engine's rule: a second posed deck exported into the folder of
a first never changes the first deck's include files (issue #22)."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.io.lsdyna import read_deck

from .conftest import wait_idle
from .test_gui_window import set_slider

pytestmark = pytest.mark.gui


@pytest.fixture
def split_leg(leg_files, tmp_path):
    """The demo leg with its *NODE block moved to an include file, nodes.k."""
    deck, setup = leg_files
    text = deck.read_text()
    head, rest = text.split("*NODE\n", 1)
    body, tail = rest.split("*", 1)
    folder = tmp_path / "split"
    folder.mkdir()
    (folder / "nodes.k").write_text("*NODE\n" + body)
    main = folder / "leg.k"
    main.write_text(head + "*INCLUDE\nnodes.k\n*" + tail)
    return main, setup


def test_second_export_into_one_folder_is_refused(window, qtbot, split_leg, tmp_path):
    main, setup = split_leg
    window.open_deck(main, setup)
    wait_idle(qtbot, window.ws)
    qtbot.waitUntil(lambda: window.ws.poser is not None, timeout=60000)
    assert window.last_error is None, window.last_error
    ws = window.ws
    out = tmp_path / "out"
    set_slider(window, qtbot, 60.0)
    at60 = ws.coords.copy()
    assert ws.export(out / "at60.k", force=True)
    wait_idle(qtbot, ws)
    assert window.last_error is None, window.last_error
    shared = out / "nodes.k"
    before = shared.read_bytes()
    set_slider(window, qtbot, 90.0)
    ws.export(out / "at90.k", force=True)
    wait_idle(qtbot, ws)
    assert window.last_error is not None and "would overwrite" in window.last_error
    assert "nodes.k" in window.last_error
    assert shared.read_bytes() == before and not (out / "at90.k").exists()
    np.testing.assert_allclose(read_deck(out / "at60.k").coords, at60, rtol=0, atol=1e-6)
