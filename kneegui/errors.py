"""Typed errors raised by the engine.

Every error that comes from user input carries the file and line it was found at, so the CLI can
print one line ``file:line: message`` and the GUI can show it in a dialog.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path


class KneeguiError(Exception):
    """Base class of every error the engine raises on purpose."""


class DeckError(KneeguiError):
    """A solver deck could not be read or written.

    Parameters
    ----------
    message : str
        What is wrong, in one line.
    path : str or Path, optional
        The file the problem is in.
    line : int, optional
        1-based line number in ``path``.
    """

    def __init__(self, message: str, path: str | Path | None = None, line: int | None = None):
        self.message = message
        self.path = None if path is None else Path(path)
        self.line = line
        super().__init__(self.location_message())

    def location_message(self) -> str:
        """``file:line: message`` (or as much of it as is known)."""
        if self.path is None:
            return self.message
        if self.line is None:
            return f"{self.path}: {self.message}"
        return f"{self.path}:{self.line}: {self.message}"


class SetupError(KneeguiError):
    """A joint setup (roles, landmarks, kinematics) is invalid.

    Parameters
    ----------
    message : str
        What is wrong.
    key : str, optional
        Dotted path of the offending key in the setup, e.g. ``landmarks.lr_axis``.
    path : str or Path, optional
        The setup file, when it came from one.
    """

    def __init__(self, message: str, key: str | None = None, path: str | Path | None = None):
        self.message = message
        self.key = key
        self.path = None if path is None else Path(path)
        prefix = f"{self.path}: " if self.path is not None else ""
        where = f"{key}: " if key else ""
        super().__init__(f"{prefix}{where}{message}")


class GeometryError(KneeguiError):
    """Geometry is unusable (NaN coordinates, zero-length axis, collinear points, ...)."""


class QualityGateError(KneeguiError):
    """A posed model fails the mesh-quality gate."""


class Cancelled(KneeguiError):
    """A long operation was cancelled through its callback."""


def raise_if_cancelled(cancel: Callable[[], bool] | None, message: str) -> None:
    """Raise :class:`Cancelled` with ``message`` when ``cancel`` is given and returns True."""
    if cancel is not None and cancel():
        raise Cancelled(message)


class PlanError(KneeguiError):
    """A batch plan (``kneegui batch PLAN``) is invalid.

    Parameters
    ----------
    message : str
        What is wrong, in one line (naming the key when there is one).
    path : str or Path, optional
        The plan file.
    line : int, optional
        1-based line number in ``path``.
    """

    def __init__(self, message: str, path: str | Path | None = None, line: int | None = None):
        self.message = message
        self.path = None if path is None else Path(path)
        self.line = line
        if self.path is None:
            super().__init__(message)
        elif line is None:
            super().__init__(f"{self.path}: {message}")
        else:
            super().__init__(f"{self.path}:{line}: {message}")


class OutputConflictError(DeckError):
    """A write would replace a file it must not (an input, another deck's include, a file the
    user did not name); nothing was written. ``path`` is the first such file."""
