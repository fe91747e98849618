"""Long work off the GUI thread: one task at a time, with progress and cancel.

A task is a plain function ``fn(progress, cancelled) -> result`` where ``progress(fraction,
message)`` reports and ``cancelled()`` says whether the user pressed Cancel (the engine raises
:class:`kneegui.errors.Cancelled` when it sees it). The function runs in a ``QThreadPool`` worker
and must not touch VTK or widgets; its result (or exception) is delivered on the GUI thread
through queued signals.
"""

from __future__ import annotations

import threading
import traceback
from collections.abc import Callable
from typing import Any

from PySide6.QtCore import QObject, QRunnable, QThreadPool, Signal, Slot

from kneegui.errors import Cancelled


class _Relay(QObject):
    progress = Signal(int, float, str)
    done = Signal(int, object)
    failed = Signal(int, object, str)


class _Runnable(QRunnable):
    def __init__(self, serial: int, fn, relay: _Relay, cancel_event: threading.Event):
        super().__init__()
        self.setAutoDelete(True)
        self._serial = serial
        self._fn = fn
        self._relay = relay
        self._cancel = cancel_event

    def run(self) -> None:
        def progress(fraction: float, message: str = "") -> None:
            self._relay.progress.emit(self._serial, float(fraction), str(message))

        try:
            result = self._fn(progress, self._cancel.is_set)
        except BaseException as exc:  # delivered to the GUI thread, shown in a dialog there
            self._relay.failed.emit(self._serial, exc, traceback.format_exc())
        else:
            self._relay.done.emit(self._serial, result)


class TaskRunner(QObject):
    """Runs one background task at a time and reports on the GUI thread.

    Signals
    -------
    started(str)
        A task named ``name`` started.
    progress(float, str)
        Fraction done (0..1) and a message.
    finished(str)
        The task ended (success, failure or cancel).
    failed(str, object)
        The task raised (not for a cancel): name and exception.
    """

    started = Signal(str)
    progress = Signal(float, str)
    finished = Signal(str)
    failed = Signal(str, object)

    def __init__(self, parent: QObject | None = None):
        super().__init__(parent)
        self._pool = QThreadPool(self)
        self._pool.setMaxThreadCount(1)
        self._relay = _Relay(self)
        self._relay.progress.connect(self._on_progress)
        self._relay.done.connect(self._on_done)
        self._relay.failed.connect(self._on_failed)
        self._serial = 0
        self._current: tuple[int, str, Callable, Callable | None, threading.Event] | None = None
        self.last_traceback = ""

    @property
    def busy(self) -> bool:
        """Whether a task is running."""
        return self._current is not None

    @property
    def current_name(self) -> str:
        """Name of the running task ('' when idle)."""
        return self._current[1] if self._current else ""

    def start(
        self,
        name: str,
        fn: Callable[[Callable[[float, str], None], Callable[[], bool]], Any],
        on_done: Callable[[Any], None],
        on_error: Callable[[BaseException], None] | None = None,
    ) -> bool:
        """Start ``fn`` in the worker thread; ``on_done(result)`` runs on the GUI thread.

        Returns False (and starts nothing) when another task is running.
        """
        if self._current is not None:
            return False
        self._serial += 1
        event = threading.Event()
        self._current = (self._serial, name, on_done, on_error, event)
        self.started.emit(name)
        self._pool.start(_Runnable(self._serial, fn, self._relay, event))
        return True

    def cancel(self) -> None:
        """Ask the running task to stop (it stops at its next check)."""
        if self._current is not None:
            self._current[4].set()

    def wait(self, msecs: int = -1) -> bool:
        """Block until the worker pool is idle (tests, shutdown)."""
        return self._pool.waitForDone(msecs)

    @Slot(int, float, str)
    def _on_progress(self, serial: int, fraction: float, message: str) -> None:
        if self._current is not None and self._current[0] == serial:
            self.progress.emit(fraction, message)

    @Slot(int, object)
    def _on_done(self, serial: int, result: object) -> None:
        if self._current is None or self._current[0] != serial:
            return
        _, name, on_done, on_error, _ = self._current
        self._current = None
        try:
            on_done(result)
        except Exception as exc:
            self._report(name, exc, on_error)
        finally:
            self.finished.emit(name)

    @Slot(int, object, str)
    def _on_failed(self, serial: int, exc: object, tb: str) -> None:
        if self._current is None or self._current[0] != serial:
            return
        _, name, _, on_error, _ = self._current
        self._current = None
        self.last_traceback = tb
        if not isinstance(exc, Cancelled):
            self._report(name, exc, on_error)
        self.finished.emit(name)

    def _report(self, name: str, exc: BaseException, on_error) -> None:
        if on_error is not None:
            on_error(exc)
        self.failed.emit(name, exc)
