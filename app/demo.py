"""The built-in demo leg, written once into a cache folder and opened like any deck."""

from __future__ import annotations

from pathlib import Path

DEFAULT_DEMO_ELEMENTS = 20000


def demo_cache_dir() -> Path:
    """Per-user cache folder for the generated demo decks (``KNEEGUI_CACHE_DIR`` overrides)."""
    import os

    from PySide6.QtCore import QStandardPaths

    if os.environ.get("KNEEGUI_CACHE_DIR"):
        return Path(os.environ["KNEEGUI_CACHE_DIR"]) / "demo"
    base = QStandardPaths.writableLocation(QStandardPaths.StandardLocation.CacheLocation)
    return Path(base or Path.home() / ".cache" / "kneegui") / "demo"


def demo_files(
    elements: int = DEFAULT_DEMO_ELEMENTS,
    side: str = "right",
    cache_dir: Path | None = None,
    element_type: str = "hex",
    joint: str = "sliding",
) -> tuple[Path, Path]:
    """Deck and setup paths of the demo leg, generating them on first use.

    Parameters
    ----------
    elements, side, element_type, joint
        As :func:`kneegui.demo.write_demo` (``kneegui demo``): size, leg, solid element type
        (``hex``, ``tet``, ``mixed``, ``tet10``) and joint meshing (``sliding``, ``welded``).
    cache_dir : Path, optional
        Where the generated decks are kept (default :func:`demo_cache_dir`).

    Returns
    -------
    deck_path, setup_path : Path
    """
    from kneegui.demo import write_demo

    name = f"{side}-{int(elements)}"
    if (element_type, joint) != ("hex", "sliding"):
        name += f"-{element_type}-{joint}"
    folder = (cache_dir or demo_cache_dir()) / name
    deck = folder / "demo_leg.k"
    setup = folder / "demo_leg.setup.json"
    if deck.is_file() and setup.is_file():
        return deck, setup
    folder.mkdir(parents=True, exist_ok=True)
    deck_path, setup_path = write_demo(
        folder, elements=int(elements), side=side, element_type=element_type, joint=joint
    )
    return Path(deck_path), Path(setup_path)
