"""The progress line: drawn in place on a terminal, silent elsewhere."""

from __future__ import annotations

import io

from kneegui.batch import BatchProgress
from kneegui.commands.batch import ProgressBar


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_the_progress_line_shows_done_failed_remaining_and_time_left():
    stream = Terminal()
    bar = ProgressBar(stream, width=10)
    bar(BatchProgress(total=8))
    bar(BatchProgress(total=8, done=3, failed=1, elapsed_s=40.0, eta_s=125.0))
    bar.close()
    lines = stream.getvalue().split("\r")
    assert lines[-1].startswith("[#####.....] 3 done, 1 failed, 4 remaining, about 2m05s left")
    assert stream.getvalue().endswith("\n")


def test_no_progress_line_when_not_a_terminal():
    stream = io.StringIO()
    bar = ProgressBar(stream)
    bar(BatchProgress(total=8, done=3))
    bar.close()
    assert stream.getvalue() == ""
