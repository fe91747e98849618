"""Where the setup being edited is autosaved: one file per deck in the per-user data folder."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

#: Quiet time after the last setup edit before the autosave is written (milliseconds).
AUTOSAVE_DELAY_MS = 1000


def autosave_dir() -> Path:
    """Per-user folder of the autosaves (``KNEEGUI_DATA_DIR`` overrides, as tests do)."""
    from PySide6.QtCore import QStandardPaths

    if os.environ.get("KNEEGUI_DATA_DIR"):
        return Path(os.environ["KNEEGUI_DATA_DIR"]) / "autosave"
    base = QStandardPaths.writableLocation(QStandardPaths.StandardLocation.AppDataLocation)
    return Path(base or Path.home() / ".local" / "share" / "kneegui") / "autosave"


def autosave_path(deck: str | Path) -> Path:
    """The autosave file of a deck, keyed by a hash of the deck's absolute path."""
    absolute = str(Path(deck).expanduser().resolve())
    digest = hashlib.sha256(absolute.encode("utf-8")).hexdigest()[:16]
    return autosave_dir() / f"{Path(deck).stem}-{digest}.setup.json"
