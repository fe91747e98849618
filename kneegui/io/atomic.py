"""Crash-safe file writing: temp file in the target folder, flush + fsync, then rename.

A reader of the target path sees either the old file or the complete new one, never a half-written
file, even if the process is killed mid-write.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path

from kneegui.errors import raise_if_cancelled

#: Bytes written between two cancel checks (a whole-body deck is hundreds of MB).
WRITE_CHUNK = 1 << 24


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _write_temp(target: Path, data: bytes, cancel: Callable[[], bool] | None = None) -> Path:
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
    try:
        # mkstemp makes the file private (0600); give it the mode the file it replaces had,
        # or the usual mode for a new file (0666 less the umask)
        try:
            mode = target.stat().st_mode & 0o7777
        except FileNotFoundError:
            mode = 0o666 & ~_current_umask()
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as fh:
            view = memoryview(data)
            for start in range(0, len(view), WRITE_CHUNK):
                raise_if_cancelled(cancel, f"write of {target} cancelled; nothing written")
                fh.write(view[start : start + WRITE_CHUNK])
            fh.flush()
            os.fsync(fh.fileno())
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return Path(tmp)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    return next(iter(atomic_write_many({Path(path): data})))


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically; returns the path."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_many(
    files: Mapping[Path, bytes], cancel: Callable[[], bool] | None = None
) -> list[Path]:
    """Write several files so that none is replaced unless all were written completely.

    Every file is first written to a temp file beside its target; only when all temp files are
    on disk are they renamed into place. On any failure the temp files are removed and no
    target is touched. ``cancel()`` is asked before every :data:`WRITE_CHUNK` bytes and before
    the renames; True raises :class:`kneegui.errors.Cancelled` the same way.
    """
    temps: list[tuple[Path, Path]] = []
    try:
        for target in files:
            if Path(target).is_dir():
                raise IsADirectoryError(f"{target} is a folder; cannot write a file there")
        for target, data in files.items():
            temps.append((_write_temp(Path(target), data, cancel), Path(target)))
        raise_if_cancelled(cancel, "write cancelled; nothing written")
    except BaseException:
        for tmp, _ in temps:
            tmp.unlink(missing_ok=True)
        raise
    for tmp, target in temps:
        os.replace(tmp, target)
    return [target for _, target in temps]
