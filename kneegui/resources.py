"""Where the shipped data files (kinematic tables, thresholds, patterns) live."""

from __future__ import annotations

from pathlib import Path

#: The repository's ``resources/`` folder (the package is installed in editable mode).
RESOURCES_DIR = Path(__file__).resolve().parent.parent / "resources"


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
