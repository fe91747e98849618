"""The finite-element model: nodes, element blocks, parts and sets held as numpy arrays.

One source of truth for geometry: ``Model.coords`` is one (N, 3) float64 array, and every element
block refers to nodes by their *index* into it (not by node id). ``Model.node_ids`` maps index to
id; :meth:`Model.node_index` maps ids back to indices (vectorised).

Node ordering conventions (LS-DYNA's, which VTK shares except for the wedge):

- ``hex8``: 0-3 bottom face counter-clockwise seen from the top, 4-7 the top face above them.
- ``wedge6``: triangle 0,1,2 counter-clockwise seen from triangle 3,4,5; edges i -> i+3.
  (VTK's wedge lists the base triangle clockwise; the viewer swaps 1<->2 and 4<->5.)
- ``pyramid5``: quad base 0-3 counter-clockwise seen from apex 4.
- ``tet4``: triangle 0,1,2 counter-clockwise seen from apex 3. ``tet10``: 4 corners + 6 mid-edge
  nodes (0-1, 1-2, 2-0, 0-3, 1-3, 2-3).
- ``quad4``/``tri3`` shells, ``beam2`` and ``discrete`` two-node elements.

A positive element therefore has ``((x1 - x0) x (x2 - x0)) . (x_top - x0) > 0``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kneegui.errors import KneeguiError

#: Nodes per element, for every element type the model holds.
NODES_PER_ELEMENT: dict[str, int] = {
    "hex8": 8,
    "wedge6": 6,
    "pyramid5": 5,
    "tet4": 4,
    "tet10": 10,
    "quad4": 4,
    "tri3": 3,
    "beam2": 2,
    "discrete": 2,
}
ELEMENT_TYPES: tuple[str, ...] = tuple(NODES_PER_ELEMENT)

_HEX_EDGES = (
    (0, 1),
    (1, 2),
    (2, 3),
    (3, 0),
    (4, 5),
    (5, 6),
    (6, 7),
    (7, 4),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
)
#: Edges of each element type as pairs of local node numbers (this module's node order); a
#: 10-node tet's edges run through its mid-edge nodes.
ELEMENT_EDGES: dict[str, tuple[tuple[int, int], ...]] = {
    "hex8": _HEX_EDGES,
    "wedge6": ((0, 1), (1, 2), (2, 0), (3, 4), (4, 5), (5, 3), (0, 3), (1, 4), (2, 5)),
    "pyramid5": ((0, 1), (1, 2), (2, 3), (3, 0), (0, 4), (1, 4), (2, 4), (3, 4)),
    "tet4": ((0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)),
    "tet10": (
        (0, 4),
        (4, 1),
        (1, 5),
        (5, 2),
        (2, 6),
        (6, 0),
        (0, 7),
        (7, 3),
        (1, 8),
        (8, 3),
        (2, 9),
        (9, 3),
    ),
    "quad4": ((0, 1), (1, 2), (2, 3), (3, 0)),
    "tri3": ((0, 1), (1, 2), (2, 0)),
    "beam2": ((0, 1),),
    "discrete": ((0, 1),),
}
#: Faces of each solid type as local node cycles, outward for a positive element (a 10-node
#: tet's faces by their corner nodes).
SOLID_FACES: dict[str, tuple[tuple[int, ...], ...]] = {
    "hex8": ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)),
    "wedge6": ((0, 2, 1), (3, 4, 5), (0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5)),
    "pyramid5": ((0, 3, 2, 1), (0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4)),
    "tet4": ((0, 2, 1), (0, 1, 3), (1, 2, 3), (2, 0, 3)),
    "tet10": ((0, 2, 1), (0, 1, 3), (1, 2, 3), (2, 0, 3)),
}
#: Corners of each element type as (corner, a, b, c): the corner determinant is
#: ``det(p[a] - p[i], p[b] - p[i], p[c] - p[i])`` (positive for a valid element); for quad shells
#: ``c`` is -1 and the element's mean normal takes its place. A 10-node tet uses its corners.
CORNER_TRIPLES: dict[str, tuple[tuple[int, int, int, int], ...]] = {
    "hex8": (
        (0, 1, 3, 4),
        (1, 2, 0, 5),
        (2, 3, 1, 6),
        (3, 0, 2, 7),
        (4, 7, 5, 0),
        (5, 4, 6, 1),
        (6, 5, 7, 2),
        (7, 6, 4, 3),
    ),
    "wedge6": ((0, 1, 2, 3), (1, 2, 0, 4), (2, 0, 1, 5), (3, 5, 4, 0), (4, 3, 5, 1), (5, 4, 3, 2)),
    "pyramid5": ((0, 1, 3, 4), (1, 2, 0, 4), (2, 3, 1, 4), (3, 0, 2, 4)),
    "tet4": ((0, 1, 2, 3),),
    "tet10": ((0, 1, 2, 3),),
    "quad4": ((0, 1, 3, -1), (1, 2, 0, -1), (2, 3, 1, -1), (3, 0, 2, -1)),
}
SOLID_TYPES: tuple[str, ...] = ("hex8", "wedge6", "pyramid5", "tet4", "tet10")
SHELL_TYPES: tuple[str, ...] = ("quad4", "tri3")
LINE_TYPES: tuple[str, ...] = ("beam2", "discrete")


@dataclass(frozen=True)
class ElementBlock:
    """All elements of one type.

    Attributes
    ----------
    etype : str
        One of :data:`ELEMENT_TYPES`.
    ids : (M,) ndarray of int64
        Element ids.
    part_ids : (M,) ndarray of int64
        Part id of each element.
    conn : (M, k) ndarray of int64
        Node *indices* (into ``Model.coords``), ``k = NODES_PER_ELEMENT[etype]``.
    """

    etype: str
    ids: NDArray[np.int64]
    part_ids: NDArray[np.int64]
    conn: NDArray[np.int64]

    def __post_init__(self) -> None:
        if self.etype not in NODES_PER_ELEMENT:
            raise ValueError(f"unknown element type {self.etype!r}")
        k = NODES_PER_ELEMENT[self.etype]
        ids = np.asarray(self.ids, dtype=np.int64).reshape(-1)
        part_ids = np.asarray(self.part_ids, dtype=np.int64).reshape(-1)
        conn = np.asarray(self.conn, dtype=np.int64).reshape(-1, k)
        if not (len(ids) == len(part_ids) == len(conn)):
            raise ValueError(
                f"{self.etype}: {len(ids)} ids, {len(part_ids)} part ids and {len(conn)} "
                "connectivity rows differ"
            )
        for name, arr in (("ids", ids), ("part_ids", part_ids), ("conn", conn)):
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return len(self.ids)

    def select(self, mask: NDArray[np.bool_]) -> ElementBlock:
        """Return the block restricted to the rows where ``mask`` is true."""
        return ElementBlock(self.etype, self.ids[mask], self.part_ids[mask], self.conn[mask])


@dataclass(frozen=True)
class Part:
    """A ``*PART``: id, title, section and material ids, and the card text as read."""

    id: int
    title: str = ""
    secid: int = 0
    mid: int = 0
    card_text: str = ""


@dataclass(frozen=True)
class NodeSet:
    """A node set: id, title, and node *indices*."""

    id: int
    title: str
    node_indices: NDArray[np.int64]


@dataclass(frozen=True)
class PartSet:
    """A part set: id, title, and part ids."""

    id: int
    title: str
    part_ids: NDArray[np.int64]


class UnknownIdError(KneeguiError, KeyError):
    """An id (node, part, element) that the model does not have."""

    def __str__(self) -> str:  # KeyError quotes its message; we want it plain.
        return str(self.args[0]) if self.args else ""


@dataclass(frozen=True)
class Model:
    """A finite-element model held as numpy arrays.

    Attributes
    ----------
    node_ids : (N,) ndarray of int64
        Node ids, in the order of ``coords`` rows.
    coords : (N, 3) ndarray of float64
        Node coordinates (model units, usually mm).
    blocks : dict of str to ElementBlock
        Element blocks keyed by element type; only types present are keys.
    parts : dict of int to Part
        Parts keyed by id.
    node_sets, part_sets : dict
        Sets keyed by id.
    source : object, optional
        The reader's record of the deck text, used by the lossless writer. ``None`` for a model
        built in memory.
    """

    node_ids: NDArray[np.int64]
    coords: NDArray[np.float64]
    blocks: Mapping[str, ElementBlock] = field(default_factory=dict)
    parts: Mapping[int, Part] = field(default_factory=dict)
    node_sets: Mapping[int, NodeSet] = field(default_factory=dict)
    part_sets: Mapping[int, PartSet] = field(default_factory=dict)
    source: Any = None

    def __post_init__(self) -> None:
        node_ids = np.asarray(self.node_ids, dtype=np.int64).reshape(-1)
        coords = np.asarray(self.coords, dtype=np.float64)
        if coords.shape != (len(node_ids), 3):
            raise ValueError(f"coords has shape {coords.shape}, expected ({len(node_ids)}, 3)")
        order = np.argsort(node_ids, kind="stable")
        sorted_ids = node_ids[order]
        if len(sorted_ids) > 1 and np.any(sorted_ids[1:] == sorted_ids[:-1]):
            dup = sorted_ids[1:][sorted_ids[1:] == sorted_ids[:-1]][0]
            raise ValueError(f"node id {dup} is defined more than once")
        for arr in (node_ids, coords, order, sorted_ids):
            arr.flags.writeable = False
        object.__setattr__(self, "node_ids", node_ids)
        object.__setattr__(self, "coords", coords)
        object.__setattr__(self, "_order", order)
        object.__setattr__(self, "_sorted_ids", sorted_ids)
        blocks = {k: v for k, v in self.blocks.items() if len(v)}
        for etype, block in blocks.items():
            if block.etype != etype:
                raise ValueError(f"block keyed {etype!r} holds {block.etype!r} elements")
            if len(block) and (block.conn.min() < 0 or block.conn.max() >= len(node_ids)):
                raise ValueError(f"{etype} connectivity refers to a node index out of range")
        object.__setattr__(self, "blocks", blocks)
        object.__setattr__(self, "parts", dict(self.parts))
        object.__setattr__(self, "node_sets", dict(self.node_sets))
        object.__setattr__(self, "part_sets", dict(self.part_sets))

    # ------------------------------------------------------------------ ids and indices
    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return len(self.node_ids)

    @property
    def n_elements(self) -> int:
        """Number of elements of every type."""
        return sum(len(b) for b in self.blocks.values())

    def node_index(self, ids: ArrayLike) -> NDArray[np.int64]:
        """Indices of the given node ids.

        Parameters
        ----------
        ids : int or array_like of int
            Node ids.

        Returns
        -------
        ndarray of int64
            Same shape as ``ids``.

        Raises
        ------
        UnknownIdError
            If an id is not in the model (the first missing id is named).
        """
        ids_arr = np.asarray(ids, dtype=np.int64)
        pos = np.searchsorted(self._sorted_ids, ids_arr)
        pos_clipped = np.minimum(pos, max(len(self._sorted_ids) - 1, 0))
        if len(self._sorted_ids) == 0:
            found = np.zeros(ids_arr.shape, dtype=bool)
        else:
            found = self._sorted_ids[pos_clipped] == ids_arr
        if not np.all(found):
            missing = ids_arr[~found].reshape(-1)[0]
            raise UnknownIdError(f"node id {int(missing)} is not in the model")
        return self._order[pos_clipped]

    def has_nodes(self, ids: ArrayLike) -> NDArray[np.bool_]:
        """Boolean mask: which of ``ids`` are node ids of this model."""
        ids_arr = np.asarray(ids, dtype=np.int64)
        if len(self._sorted_ids) == 0:
            return np.zeros(ids_arr.shape, dtype=bool)
        pos = np.minimum(np.searchsorted(self._sorted_ids, ids_arr), len(self._sorted_ids) - 1)
        return self._sorted_ids[pos] == ids_arr

    # ------------------------------------------------------------------ derived models
    def with_coords(self, coords: ArrayLike) -> Model:
        """A new model with the same topology and new node coordinates.

        Parameters
        ----------
        coords : (N, 3) array_like of float
            New coordinates, in the order of ``node_ids``.
        """
        return replace(self, coords=np.array(coords, dtype=np.float64, copy=True))

    # ------------------------------------------------------------------ queries
    def part_ids(self) -> NDArray[np.int64]:
        """Sorted ids of every part that is declared or has elements."""
        ids = set(self.parts)
        for block in self.blocks.values():
            ids.update(np.unique(block.part_ids).tolist())
        return np.array(sorted(ids), dtype=np.int64)

    def element_counts(self) -> dict[int, dict[str, int]]:
        """Number of elements of each type per part id."""
        counts: dict[int, dict[str, int]] = {}
        for etype, block in self.blocks.items():
            pids, n = np.unique(block.part_ids, return_counts=True)
            for pid, c in zip(pids.tolist(), n.tolist(), strict=True):
                counts.setdefault(pid, {})[etype] = c
        return counts

    def part_node_indices(
        self, part_ids: Iterable[int], etypes: Iterable[str] | None = None
    ) -> NDArray[np.int64]:
        """Sorted unique indices of the nodes used by elements of the given parts.

        Parameters
        ----------
        part_ids : iterable of int
            Part ids.
        etypes : iterable of str, optional
            Restrict to these element types (default: all).
        """
        wanted = np.array(sorted(set(int(p) for p in part_ids)), dtype=np.int64)
        chunks = []
        types = self.blocks.keys() if etypes is None else [t for t in etypes if t in self.blocks]
        for etype in types:
            block = self.blocks[etype]
            mask = np.isin(block.part_ids, wanted)
            if mask.any():
                chunks.append(block.conn[mask].reshape(-1))
        if not chunks:
            return np.zeros(0, dtype=np.int64)
        return np.unique(np.concatenate(chunks))

    def bounding_box(self) -> NDArray[np.float64]:
        """(2, 3) array: minimum and maximum corner of the node cloud."""
        if self.n_nodes == 0:
            return np.zeros((2, 3))
        return np.stack([self.coords.min(axis=0), self.coords.max(axis=0)])


# ---------------------------------------------------------------------- degenerate solids
_HEX_FACES = np.array(
    [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
)


def _wedge_patterns() -> list[tuple[tuple[int, int], tuple[int, int], tuple[int, ...]]]:
    """For each way an 8-node hex collapses into a wedge, the two merged edges and the wedge order.

    A wedge stored as a hex has two opposite edges of one face merged (that face becomes a line).
    The two faces that contain exactly one merged edge are the wedge's triangles; their third
    direction gives the i -> i+3 edges. Orientation follows the hex: a positive hex gives a
    positive wedge.
    """
    # hex faces listed with outward normals; "bottom" (0,1,2,3) inward is the reference.
    faces = [(0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    opposite = {0: 1, 1: 0, 2: 4, 4: 2, 3: 5, 5: 3}
    patterns = []
    for fi, face in enumerate(faces):
        for k in (0, 1):
            e1 = (face[k], face[k + 1])
            e2 = (face[(k + 2) % 4], face[(k + 3) % 4])
            # triangle faces: the two other faces containing e1 and e2 respectively
            tri_faces = []
            for e in (e1, e2):
                for fj, f in enumerate(faces):
                    if fj != fi and e[0] in f and e[1] in f:
                        tri_faces.append(fj)
            fa, fb = tri_faces
            assert opposite[fa] == fb
            # map each node of face fa to its neighbour on face fb along the connecting edges
            edges = set(_HEX_EDGES)
            edges |= {(b, a) for a, b in edges}
            fa_nodes, fb_nodes = faces[fa], faces[fb]
            partner = {a: next(b for b in fb_nodes if (a, b) in edges) for a in fa_nodes}
            # walk face fa in the hex's positive sense: the sense in which the *bottom* face
            # (0,1,2,3) is listed, i.e. counter-clockwise seen from the opposite face.
            ring = list(fa_nodes)
            # make ring counter-clockwise seen from fb: faces[] are listed so that face 0 is ccw
            # seen from inside; outward-listed faces (1..5 as written) need reversal except 0.
            if fa != 0:
                ring = ring[::-1]
            merged = e1 if e1[0] in ring and e1[1] in ring else e2
            # drop the second node of the merged edge (it equals the first)
            drop = merged[1]
            tri = [n for n in ring if n != drop]
            order = tuple(tri + [partner[n] for n in tri])
            patterns.append((e1, e2, order))
    return patterns


_WEDGE_PATTERNS = _wedge_patterns()


def split_degenerate_solids(
    conn8: NDArray[np.int64],
) -> dict[str, tuple[NDArray[np.int64], NDArray[np.int64]]]:
    """Recognise 8-node solids with repeated nodes as wedges, pyramids or tetrahedra.

    Parameters
    ----------
    conn8 : (M, 8) ndarray of int
        Node ids or indices of 8-node solids as written in the deck.

    Returns
    -------
    dict
        ``etype -> (rows, conn)``: for each recognised type, the row numbers into ``conn8`` and
        the rebuilt connectivity in this module's node order. Rows that fit no pattern (for
        example an element collapsed to a plane) stay ``hex8`` so that quality checks flag them.
    """
    conn8 = np.asarray(conn8)
    m = len(conn8)
    # every degenerate pattern merges at least one hex edge: count distinct nodes only there
    merged = np.zeros(m, dtype=bool)
    for a, b in _HEX_EDGES:
        merged |= conn8[:, a] == conn8[:, b]
    n_distinct = np.full(m, 8, dtype=np.int64)
    rows_merged = np.flatnonzero(merged)
    if len(rows_merged):
        srt = np.sort(conn8[rows_merged], axis=1)
        n_distinct[rows_merged] = 1 + np.count_nonzero(srt[:, 1:] != srt[:, :-1], axis=1)
    result: dict[str, tuple[NDArray[np.int64], NDArray[np.int64]]] = {}
    assigned = n_distinct == 8
    # wedges: exactly 6 distinct nodes and a known merged-edge pattern
    cand = np.flatnonzero(n_distinct == 6)
    wedge_rows, wedge_conn = [], []
    if len(cand):
        c = conn8[cand]
        done = np.zeros(len(cand), dtype=bool)
        for e1, e2, order in _WEDGE_PATTERNS:
            hit = ~done & (c[:, e1[0]] == c[:, e1[1]]) & (c[:, e2[0]] == c[:, e2[1]])
            if hit.any():
                wedge_rows.append(cand[hit])
                wedge_conn.append(c[hit][:, list(order)])
                done |= hit
    if wedge_rows:
        rows = np.concatenate(wedge_rows)
        result["wedge6"] = (rows, np.concatenate(wedge_conn))
        assigned[rows] = True
    # pyramids: 5 distinct, top face fully merged to one apex (pattern 1,2,3,4,5,5,5,5)
    cand = np.flatnonzero(n_distinct == 5)
    if len(cand):
        c = conn8[cand]
        top_merged = (c[:, 4] == c[:, 5]) & (c[:, 5] == c[:, 6]) & (c[:, 6] == c[:, 7])
        if top_merged.any():
            rows = cand[top_merged]
            result["pyramid5"] = (rows, conn8[rows][:, [0, 1, 2, 3, 4]])
            assigned[rows] = True
    # tetrahedra: 4 distinct nodes, in order of first appearance (1,2,3,3,4,4,4,4 -> 1,2,3,4)
    cand = np.flatnonzero(n_distinct == 4)
    if len(cand):
        c = conn8[cand]
        first = np.ones_like(c, dtype=bool)
        for j in range(1, 8):
            first[:, j] = np.all(c[:, :j] != c[:, j : j + 1], axis=1)
        tets = c[first].reshape(-1, 4)
        result["tet4"] = (cand, tets)
        assigned[cand] = True
    rest = np.flatnonzero(assigned & (n_distinct == 8))
    rest = np.concatenate([rest, np.flatnonzero(~assigned)])
    rest.sort()
    if len(rest) or m == 0:
        result["hex8"] = (rest, conn8[rest])
    return result
