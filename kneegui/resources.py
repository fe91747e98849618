"""Where the shipped data files (kinematic tables, thresholds, patterns) live."""

from __future__ import annotations

import sys
import sysconfig
from pathlib import Path


def _find_resources_dir() -> Path:
    """The repository's ``resources/`` (editable install, source checkout), else the copy a
    wheel installs under ``<prefix>/share/kneegui/resources`` (pyproject's data-files)."""
    source = Path(__file__).resolve().parent.parent / "resources"
    if source.is_dir():
        return source
    prefixes = [sysconfig.get_path("data"), sys.prefix, sys.base_prefix]
    for prefix in prefixes:
        installed = Path(prefix) / "share" / "kneegui" / "resources"
        if installed.is_dir():
            return installed
    return source  # resource_path() names it when a file is missing


#: The data folder (see :func:`_find_resources_dir`).
RESOURCES_DIR = _find_resources_dir()


def resource_path(name: str) -> Path:
    """Absolute path of a file in ``resources/``.

    Raises
    ------
    FileNotFoundError
        If the file is not shipped.
    """
    path = RESOURCES_DIR / name
    if not path.exists():
        raise FileNotFoundError(f"resource {name!r} not found in {RESOURCES_DIR}")
    return path
