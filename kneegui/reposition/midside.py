"""The mid-side nodes of 10-node tetrahedra in a pose: on their edges as at rest, out of the bones.

Every stage of the export places nodes one by one: the mapping by each node's own weights, the
relaxation and the smoothing by the corner tetrahedra alone. A mid-side node placed that way
ends off its edge, and the gate's mid-side offsets (OptiStruct's "hoe" offsets) measure it:
0.02 edge lengths on the coarse 10-node demo at 90 deg for the nodes the relaxation does not
carry, 0.15 after the mapping alone. :class:`MidsideNodes` puts each movable mid-side node
where its edge's two corners put it at rest (their middle plus the rest offset: a straight edge
stays straight, a curved one keeps its bulge), and moves one that then lies deeper inside a
bone than at rest out of it, at right angles to its edge, so that it stays centred on it.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from kneegui.geometry.transforms import RigidTransform
from kneegui.model import ElementBlock
from kneegui.reposition.contact import BoneSurfaceDistance

#: Mid-side node (local index in a 10-node tet) -> the corner nodes of its edge.
TET10_MIDSIDE: dict[int, tuple[int, int]] = {
    4: (0, 1),
    5: (1, 2),
    6: (2, 0),
    7: (0, 3),
    8: (1, 3),
    9: (2, 3),
}

#: Passes of the push out of a bone: a push at right angles to the edge reaches the wanted
#: depth exactly only where the bone's normal is at right angles to the edge too.
PUSH_PASSES = 3

#: The push at right angles to the edge is at most this many times the depth it must gain
#: (a normal nearly along the edge: the node cannot leave the bone without sliding along it).
PUSH_GAIN_LIMIT = 2.0


def midside_edges(
    block: ElementBlock | None,
    movable: NDArray[np.bool_],
    free_corners: NDArray[np.bool_] | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The ``movable`` mid-side nodes of a 10-node tet block (with ``free_corners``: those
    whose edge has a corner among them), sorted, and the two corner nodes of each one's edge
    ((M,), (M, 2); from the first element that names the node)."""
    if block is None or len(block) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 2), dtype=np.int64)
    mid = block.conn[:, list(TET10_MIDSIDE)].ravel()
    ends = block.conn[:, [list(e) for e in TET10_MIDSIDE.values()]].reshape(-1, 2)
    keep = movable[mid]
    if free_corners is not None:
        keep &= free_corners[ends].any(axis=1)
    mid, first = np.unique(mid[keep], return_index=True)
    return mid.astype(np.int64), ends[keep][first].astype(np.int64)


class MidsideNodes:
    """Mid-side nodes of 10-node tets and their edges (module docstring).

    Parameters
    ----------
    nodes : (M,) int ndarray
        The mid-side nodes.
    ends : (M, 2) int ndarray
        The two corner nodes of each one's edge.
    rest : (N, 3) ndarray
        The model's coordinates.
    """

    def __init__(
        self, nodes: NDArray[np.int64], ends: NDArray[np.int64], rest: NDArray[np.float64]
    ) -> None:
        self.nodes, self.ends = nodes, ends
        self._first, self._second = ends[:, 0].copy(), ends[:, 1].copy()
        self.rest = rest
        self.offset = rest[nodes] - rest[ends].mean(axis=1)
        self._rest_depth: dict[str, NDArray[np.float64]] = {}

    @classmethod
    def of_block(
        cls,
        block: ElementBlock | None,
        movable: NDArray[np.bool_],
        rest: NDArray[np.float64],
        free_corners: NDArray[np.bool_] | None = None,
    ) -> MidsideNodes:
        """The ``movable`` mid-side nodes of a tet10 block (None or empty: none), as
        :func:`midside_edges` picks them."""
        return cls(*midside_edges(block, movable, free_corners), rest)

    def __len__(self) -> int:
        return len(self.nodes)

    def carried(
        self, x: NDArray[np.float64], rows: NDArray[np.int64] | slice = slice(None)
    ) -> NDArray[np.float64]:
        """Where the corners at ``x`` put the mid-side nodes ``rows``: the middle of their
        edges plus the rest offsets. ``(a + b) * 0.5``: the same bits as the mean of the two,
        without its reduction (a tenth of a coarse 10-node deck's slider step)."""
        middle = x[self._first[rows]]
        middle += x[self._second[rows]]
        middle *= 0.5
        middle += self.offset[rows]
        return middle

    def straighten(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """``x`` with each mid-side node at the middle of its edge plus its rest offset (a new
        array when there are any). The rest offset is not rotated with the edge: a straight
        edge stays straight, a curved one keeps its bulge's size and direction."""
        if len(self.nodes) == 0:
            return x
        out = np.array(x, dtype=np.float64, copy=True)
        out[self.nodes] = self.carried(x)
        return out

    def rest_depth(self, name: str, surface: BoneSurfaceDistance) -> NDArray[np.float64]:
        """Each mid-side node's signed distance from bone ``name`` at rest (+ outside; measured
        once). A coarse tet whose corners lie on a curved bone may have its edge, and so its
        mid-side node, inside the bone in the deck itself."""
        if name not in self._rest_depth:
            depth = np.full(len(self.nodes), np.inf)
            p = self.rest[self.nodes]
            boxed = surface.in_box(p)
            depth[boxed] = surface.query(p[boxed])[0]
            self._rest_depth[name] = depth
        return self._rest_depth[name]

    def out_of_bones(
        self,
        x: NDArray[np.float64],
        surfaces: Mapping[str, BoneSurfaceDistance],
        transforms: Mapping[str, RigidTransform],
        tolerance: float,
    ) -> NDArray[np.float64]:
        """``x`` with each mid-side node more than ``tolerance`` deeper inside a posed bone than
        at rest (or than its surface, for a node outside at rest) moved to half ``tolerance``
        deeper than that, at right angles to its edge (a new array when any moves).

        Within ``tolerance`` a node stays: the in-bone check accepts it, and each push curves
        its edge (the gate's mid-side normal offset). At right angles to the edge, because a
        push to the bone's closest point slides the node along its edge too (the coarse
        10-node demo at 0 deg: tangent offsets of 0.32 edge lengths, past the quarter point
        where the quadratic tet's Jacobian vanishes).
        """
        if len(self.nodes) == 0:
            return x
        out = x
        for name, surface in surfaces.items():
            tr = transforms.get(name)
            if tr is None:
                continue
            allowed = np.minimum(self.rest_depth(name, surface), 0.0)
            for _ in range(PUSH_PASSES):
                local = tr.inverse().apply(out[self.nodes])
                boxed = np.flatnonzero(surface.in_box(local))
                depth, _, normal, _ = surface.query(local[boxed])
                deep = depth < allowed[boxed] - tolerance
                if not deep.any():
                    break
                if out is x:
                    out = np.array(x, dtype=np.float64, copy=True)
                rows = boxed[deep]
                gain = allowed[rows] - 0.5 * tolerance - depth[deep]
                n = tr.apply_vector(normal[deep])
                ends = self.ends[rows]
                edge = out[ends[:, 1]] - out[ends[:, 0]]
                edge /= np.linalg.norm(edge, axis=1, keepdims=True)
                along = np.einsum("ij,ij->i", n, edge)
                across = n - along[:, None] * edge
                share = np.maximum(1.0 - along * along, 1.0 / PUSH_GAIN_LIMIT)
                out[self.nodes[rows]] += across * (gain / share)[:, None]
        return out
