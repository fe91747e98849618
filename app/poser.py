"""The one adapter between the slider and the engine's posing.

:func:`make_poser` returns the engine's precomputed ``kneegui.reposition.Repositioner`` when the
engine has it (bones, skin and soft tissue re-posed), else :class:`BonePoser`, which moves the
bones only through :func:`kneegui.kinematics.pose_bones`. Both have ``pose(flexion_deg) -> (N, 3)``,
``initial_flexion`` (degrees) and ``axes`` (:class:`~kneegui.geometry.JointAxes`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from kneegui.geometry import JointAxes, compute_joint_axes
from kneegui.kinematics import pose_bones
from kneegui.model import Model
from kneegui.setup import JointSetup


class Poser(Protocol):
    """What the workspace needs from a repositioner."""

    initial_flexion: float
    axes: JointAxes

    def pose(self, flexion_deg: float) -> NDArray[np.float64]: ...


class BonePoser:
    """Bones-only posing (soft tissue stays): the fallback until the repositioner exists."""

    kind = "bones only"

    def __init__(self, model: Model, setup: JointSetup):
        self._model = model
        self._setup = setup
        self.axes = compute_joint_axes(model.coords, setup)
        self.initial_flexion = float(self.axes.initial_flexion_deg)

    def pose(self, flexion_deg: float) -> NDArray[np.float64]:
        """(N, 3) coordinates with the bones at ``flexion_deg`` degrees."""
        return pose_bones(self._model, self._setup, float(flexion_deg), axes=self.axes)


def repositioner_class():
    """The engine's ``Repositioner`` class, or ``None`` while the engine has none."""
    try:
        from kneegui.reposition import Repositioner
    except ImportError:
        return None
    return Repositioner


def make_poser(
    model: Model,
    setup: JointSetup,
    progress: Callable[[float, str], None] | None = None,
    cancelled: Callable[[], bool] | None = None,
) -> Poser:
    """Precompute the poser for ``model`` and ``setup`` (may take seconds: run off the GUI thread).

    ``progress`` and ``cancelled`` are passed to the repositioner when it accepts them.
    """
    cls = repositioner_class()
    if cls is None:
        if progress is not None:
            progress(0.5, "computing joint axes")
        return BonePoser(model, setup)
    kwargs = {}
    try:
        import inspect

        params = inspect.signature(cls).parameters
        if "progress" in params and progress is not None:
            kwargs["progress"] = progress
        if "cancel" in params and cancelled is not None:
            kwargs["cancel"] = cancelled
        if "cancelled" in params and cancelled is not None:
            kwargs["cancelled"] = cancelled
    except (TypeError, ValueError):
        kwargs = {}
    poser = cls(model, setup, **kwargs)
    if not hasattr(poser, "kind"):
        try:
            poser.kind = "repositioner"
        except AttributeError:
            pass
    return poser
