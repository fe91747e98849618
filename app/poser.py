"""The one adapter between the window and the engine's posing: the precomputed repositioner.

:func:`make_poser` builds :class:`kneegui.reposition.Repositioner` (bones, skin and soft tissue
re-posed; the slider calls its ``pose(flexion_deg) -> (N, 3)``, Relax + smooth runs the export
through it).
"""

from __future__ import annotations

from collections.abc import Callable

from kneegui.model import Model
from kneegui.reposition import Repositioner
from kneegui.setup import JointSetup

#: What the window poses with.
Poser = Repositioner


def make_poser(
    model: Model,
    setup: JointSetup,
    progress: Callable[[float, str], None] | None = None,
    cancelled: Callable[[], bool] | None = None,
) -> Poser:
    """Precompute the repositioner for ``model`` and ``setup`` (seconds: run it off the GUI
    thread); ``progress(fraction, message)`` and ``cancelled()`` are passed to it."""
    return Repositioner(model, setup, progress=progress, cancel=cancelled)
