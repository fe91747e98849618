"""Bone-to-bone overlap of a pose: how deep one rigid segment's surface went into another's.

Bones move rigidly with the kinematic tables about the fitted axes, so nothing in the method
stops the tibia from passing through the femur when the axes or the tables do not suit the
model's bones (a condyle that is not circular about the F-E axis, a plateau too close to it,
misplaced landmarks). Soft tissue caught between two overlapping bones can only be crushed, and
the solver starts from an initial penetration, so every pose is checked.

A segment's surface nodes are taken into the other segment's rest frame and their signed
distance to its outer surface is measured (:class:`kneegui.reposition.contact.BoneSurfaceDistance`),
in both directions. The rest pose is measured too: a model whose bones already touch or overlap
is not blamed on the pose.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from kneegui.geometry.transforms import RigidTransform
from kneegui.reposition.contact import BoneSurfaceDistance

#: A bone reaching this much deeper into another than at rest is warned about (model units of a
#: knee of the reference size; :func:`kneegui.reposition.pipeline.pose_warnings` scales it).
BONE_OVERLAP_TOLERANCE = 0.1


@dataclass(frozen=True)
class BoneOverlap:
    """How deep segment ``inner``'s surface lies inside segment ``outer`` in one pose.

    Attributes
    ----------
    inner, outer : str
        Segment names (e.g. ``"tibia"`` inside ``"femur"``).
    depth : float
        Deepest surface node of ``inner`` inside ``outer`` (model units; 0 when none is inside).
    nodes : int
        Surface nodes of ``inner`` inside ``outer``.
    rest_depth : float
        The same depth in the initial pose.
    """

    inner: str
    outer: str
    depth: float
    nodes: int
    rest_depth: float

    @property
    def added_depth(self) -> float:
        """How much deeper than at rest (model units, never negative)."""
        return max(0.0, self.depth - self.rest_depth)

    def to_dict(self) -> dict[str, object]:
        """JSON-ready form."""
        return {
            "inner": self.inner,
            "outer": self.outer,
            "depth": self.depth,
            "nodes": self.nodes,
            "rest_depth": self.rest_depth,
        }

    def describe(self) -> str:
        """One line for a user, e.g. ``the tibia reaches 3.18 into the femur (10 surface
        nodes; 0.00 in the initial pose)`` (model units)."""
        return (
            f"the {self.inner} reaches {self.depth:.2f} into the {self.outer} ({self.nodes} "
            f"surface node(s); {self.rest_depth:.2f} in the initial pose)"
        )


class BoneOverlapCheck:
    """Precomputed overlap test between every pair of rigid segments.

    Parameters
    ----------
    surfaces : mapping of segment name to BoneSurfaceDistance
        Each segment's outer surface at rest (its surface nodes are the ones tested against the
        other segments).
    """

    def __init__(self, surfaces: Mapping[str, BoneSurfaceDistance]) -> None:
        self._surfaces = dict(surfaces)
        self._pairs = [
            (a, b) for x, y in combinations(sorted(self._surfaces), 2) for a, b in ((x, y), (y, x))
        ]
        identity = {name: RigidTransform.identity() for name in self._surfaces}
        self._rest_depth = {
            (inner, outer): depth for inner, outer, depth, _ in self._measure(identity)
        }

    def _measure(
        self, transforms: Mapping[str, RigidTransform]
    ) -> Iterator[tuple[str, str, float, int]]:
        """(inner, outer, depth, nodes inside) for every ordered pair."""
        for inner, outer in self._pairs:
            # inner's surface nodes, posed, then taken into outer's rest frame
            to_outer = transforms[inner].then(transforms[outer].inverse())
            nodes = self._surfaces[inner].node_xyz
            signed = self._surfaces[outer].query(to_outer.apply(nodes))[0]
            inside = signed < 0
            depth = float(-signed[inside].min()) if inside.any() else 0.0
            yield inner, outer, depth, int(np.count_nonzero(inside))

    def measure(self, transforms: Mapping[str, RigidTransform]) -> list[BoneOverlap]:
        """Overlap of every ordered pair of segments in a pose (deepest first).

        Parameters
        ----------
        transforms : mapping of segment name to RigidTransform
            Each segment's motion from the initial pose (e.g. ``BonePose.transforms``); a
            segment missing from it stays where it is.
        """
        full = {name: transforms.get(name, RigidTransform.identity()) for name in self._surfaces}
        found = [
            BoneOverlap(inner, outer, depth, nodes, self._rest_depth[inner, outer])
            for inner, outer, depth, nodes in self._measure(full)
        ]
        return sorted(found, key=lambda o: -o.depth)
