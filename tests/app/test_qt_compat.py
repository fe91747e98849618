"""The PySide6 6.12.0 work-around keeps None alive through many Qt calls."""

from __future__ import annotations

import sys

import pytest

pytestmark = pytest.mark.gui


def test_none_survives_many_void_qt_calls(qapp):
    from PySide6.QtCore import QTimer

    from app.qt_compat import protect_singletons, pyside_is_defective

    protect_singletons()
    before = sys.getrefcount(None)
    timer = QTimer()
    for _ in range(20000):
        timer.start(1000)
        timer.stop()
    after = sys.getrefcount(None)
    if pyside_is_defective():
        assert before > 1 << 39  # made effectively immortal
        assert after > 1 << 39
    else:
        assert after > before - 1000  # no systematic loss with a fixed PySide6
    assert protect_singletons() is False  # idempotent
