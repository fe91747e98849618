"""Patellar tracking: after its tables, the patella is lifted off the femur to its rest clearance.

The patella's tables turn it about the F-E axis and tilt it about its own axis; the trochlea is
not a circle about the F-E axis, so the turned patella can ride into the femur: on the demo leg
2.0 mm at 0 deg, 0.8 mm at 30 deg and 3.5 mm at -5 deg of flexion, crushing the tissue between
them (a real patella glides on the trochlear cartilage, the quadriceps pressing it on). After the
tables the patella is therefore moved away from the F-E axis (radially, in the plane normal to
the axis, through its centroid) by the smallest distance that gives back its rest clearance:
every patella surface node near the femur keeps at least the smallest patella-femur gap of the
rest pose from the femur's surface, and every femur surface node near the patella as much from
the patella's (as far as it was, where the model already had them closer). The signed distances
are measured in the rest frame of the bone they are measured to
(:class:`kneegui.reposition.contact.BoneSurfaceDistance`) and linearised along its surface
normal; a few such steps converge. A patella that does not reach the femur is not moved.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kneegui.geometry.transforms import RigidTransform
from kneegui.reposition.contact import BoneSurfaceDistance

#: A node closer to the other bone than its target by less than this is clear (model units of a
#: knee of the reference size; ``PatellaSeating``'s ``length_scale`` scales this and the next).
SEATING_TOLERANCE = 1e-3
#: The smallest clear lift is found to within this (model units).
LIFT_PRECISION = 0.01
#: Nodes whose distance changes slower than this per unit of lift are not used to size the step
#: (a surface nearly parallel to the lift cannot be cleared by lifting).
MIN_RATE = 0.05


@dataclass(frozen=True)
class _Watched:
    """Surface nodes of one bone near the other, their rest clearance targets."""

    nodes: NDArray[np.float64]  # (K, 3) at rest
    target: NDArray[np.float64]  # (K,)


def _watched(
    nodes: NDArray[np.float64], rest: NDArray[np.float64], band: float, gap: float
) -> _Watched:
    """The nodes within ``band`` of the rest gap, each aiming at its rest distance ``rest`` or
    the gap, whichever is smaller."""
    near = rest < gap + band
    return _Watched(nodes[near], np.minimum(rest[near], gap))


class PatellaSeating:
    """Precomputed seating of a model's patella on its femur (see the module docstring).

    Parameters
    ----------
    patella, femur : BoneSurfaceDistance
        The two bones' outer surfaces at rest.
    axis_point, axis_direction : (3,) array_like
        The F-E axis at rest (moves with the femur).
    band : float
        Only surface nodes closer than this (model units) to the other bone at rest are
        watched: the far side of a bone cannot reach the other.
    length_scale : float
        Model units per millimetre of a knee of the reference size: scales the seating's
        tolerance and precision (:data:`SEATING_TOLERANCE`, :data:`LIFT_PRECISION`).
    """

    def __init__(
        self,
        patella: BoneSurfaceDistance,
        femur: BoneSurfaceDistance,
        axis_point: NDArray[np.float64],
        axis_direction: NDArray[np.float64],
        band: float,
        length_scale: float = 1.0,
    ) -> None:
        self.patella, self.femur = patella, femur
        self._tolerance = SEATING_TOLERANCE * length_scale
        self._precision = LIFT_PRECISION * length_scale
        on_femur = femur.query(patella.node_xyz)[0]
        on_patella = patella.query(femur.node_xyz)[0]
        #: The smallest patella-femur distance at rest (0 if they touch or overlap).
        self.rest_gap = max(min(float(on_femur.min()), float(on_patella.min())), 0.0)
        self._on_femur = _watched(patella.node_xyz, on_femur, band, self.rest_gap)
        self._on_patella = _watched(femur.node_xyz, on_patella, band, self.rest_gap)
        self._centroid = patella.node_xyz.mean(axis=0)
        self._axis_point = np.asarray(axis_point, dtype=np.float64)
        direction = np.asarray(axis_direction, dtype=np.float64)
        self._axis_direction = direction / np.linalg.norm(direction)

    def _lift_direction(self, patella: RigidTransform, femur: RigidTransform) -> NDArray:
        """Unit vector from the posed F-E axis to the posed patella centroid, normal to it."""
        point, direction = femur.apply(self._axis_point), femur.apply_vector(self._axis_direction)
        radial = patella.apply(self._centroid) - point
        radial -= (radial @ direction) * direction
        return radial / max(float(np.linalg.norm(radial)), 1e-300)

    def _shortfalls(
        self, patella: RigidTransform, femur: RigidTransform, lift: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Per watched node: how much closer than its target it is, and how fast its distance
        grows per unit of lift along ``lift``."""
        out_short, out_rate = [], []
        w = self._on_femur
        if len(w.nodes):
            depth, _, normal, _ = self.femur.query(femur.inverse().apply(patella.apply(w.nodes)))
            out_short.append(w.target - depth)
            out_rate.append(femur.apply_vector(normal) @ lift)
        w = self._on_patella
        if len(w.nodes):
            depth, _, normal, _ = self.patella.query(patella.inverse().apply(femur.apply(w.nodes)))
            out_short.append(w.target - depth)
            out_rate.append(-(patella.apply_vector(normal) @ lift))
        if not out_short:
            return np.zeros(0), np.zeros(0)
        return np.concatenate(out_short), np.concatenate(out_rate)

    def lifted(
        self, patella: RigidTransform, femur: RigidTransform, distance: float
    ) -> RigidTransform:
        """``patella`` moved ``distance`` away from the F-E axis (see :meth:`lift`)."""
        if distance == 0.0:
            return patella
        lift = self._lift_direction(patella, femur)
        return patella.then(RigidTransform(np.eye(3), distance * lift))

    def lift(self, patella: RigidTransform, femur: RigidTransform, iterations: int = 12) -> float:
        """The smallest lift (model units) that gives the patella its rest clearance back.

        Parameters
        ----------
        patella, femur : RigidTransform
            The two bones' motions from the initial pose (the tables' result).
        """
        direction = self._lift_direction(patella, femur)

        def measure(distance: float) -> tuple[float, float]:
            """Worst shortfall of the nodes a lift can clear, and the lift that clears them
            all if the distances change linearly."""
            moved = patella.then(RigidTransform(np.eye(3), distance * direction))
            short, rate = self._shortfalls(moved, femur, direction)
            liftable = rate > MIN_RATE
            if not liftable.any():
                return -np.inf, 0.0
            short, rate = short[liftable], rate[liftable]
            return float(short.max()), float(np.max(np.maximum(short, 0.0) / rate))

        worst, step = measure(0.0)
        if worst <= self._tolerance:
            return 0.0
        # lift by the linearised step until clear (the surfaces curve, so a step may fall
        # short or overshoot), then close in on the smallest clear lift by regula falsi
        # (Illinois): the worst shortfall decreases as the patella rises
        low, worst_low, high, worst_high = 0.0, worst, 0.0, worst
        for _ in range(iterations):
            low, worst_low = high, worst_high
            high = high + max(step, self._precision)
            worst_high, step = measure(high)
            if worst_high <= self._tolerance:
                break
        else:
            return high
        # interpolation weights: the true shortfalls, the stalled side's halved (Illinois)
        weight_low, weight_high = worst_low - self._tolerance, worst_high - self._tolerance
        side = 0
        for _ in range(iterations):
            if high - low <= self._precision or worst_high >= -self._precision:
                break
            middle = high - weight_high * (high - low) / (weight_high - weight_low)
            if not np.isfinite(middle):  # a side with nothing liftable weighs -inf: bisect
                middle = 0.5 * (low + high)
            middle = min(max(middle, low + 0.05 * (high - low)), high - 0.05 * (high - low))
            worst_middle, _ = measure(middle)
            if worst_middle <= self._tolerance:
                high, worst_high = middle, worst_middle
                weight_high = worst_middle - self._tolerance
                weight_low *= 0.5 if side == +1 else 1.0
                side = +1
            else:
                low, weight_low = middle, worst_middle - self._tolerance
                weight_high *= 0.5 if side == -1 else 1.0
                side = -1
        return high

    def seat(
        self, patella: RigidTransform, femur: RigidTransform, iterations: int = 12
    ) -> tuple[RigidTransform, float]:
        """The patella's transform lifted to its rest clearance, and the lift (model units)."""
        distance = self.lift(patella, femur, iterations)
        return self.lifted(patella, femur, distance), distance
