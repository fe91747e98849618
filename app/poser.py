"""The one adapter between the window and the engine's posing: the precomputed repositioner.

:func:`make_poser` builds :class:`kneegui.reposition.Repositioner` (bones, skin and soft tissue
re-posed; the slider calls its ``pose(flexion_deg) -> (N, 3)``, Relax + smooth runs the export
through it).
"""

from __future__ import annotations

from collections.abc import Callable

from kneegui.meshopt.volume_correction import VolumeCorrectionOptions
from kneegui.model import Model
from kneegui.reposition import Repositioner, RepositionOptions
from kneegui.setup import JointSetup

#: What the window poses with.
Poser = Repositioner


def make_poser(
    model: Model,
    setup: JointSetup,
    progress: Callable[[float, str], None] | None = None,
    cancelled: Callable[[], bool] | None = None,
    restore_volume: bool = False,
) -> Poser:
    """Precompute the repositioner for ``model`` and ``setup`` (seconds: run it off the GUI
    thread); ``progress(fraction, message)`` and ``cancelled()`` are passed to it.
    ``restore_volume``: the export runs the volume step first (``kneegui pose
    --restore-volume``)."""
    options = RepositionOptions(volume_correction=volume_step(restore_volume))
    return Repositioner(model, setup, options, progress=progress, cancel=cancelled)


def volume_step(restore_volume: bool) -> VolumeCorrectionOptions | None:
    """The repositioner's ``volume_correction`` option for the window's switch (the CLI's
    defaults)."""
    return VolumeCorrectionOptions() if restore_volume else None


def with_volume_step(poser: Poser, restore_volume: bool) -> Poser:
    """``poser`` with the volume step switched on or off, sharing its precompute
    (:meth:`kneegui.reposition.Repositioner.with_options`): instant, on any model size."""
    return poser.with_options(volume_correction=volume_step(restore_volume))
