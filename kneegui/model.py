"""The finite-element model: nodes, element blocks, parts and sets held as numpy arrays.

One source of truth for geometry: ``Model.coords`` is one (N, 3) float64 array, and every element
block refers to nodes by their *index* into it (not by node id). ``Model.node_ids`` maps index to
id; :meth:`Model.node_index` maps ids back to indices (vectorised).

Element types, node order, edges, faces and corners live in :mod:`kneegui.topology`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kneegui.errors import KneeguiError
from kneegui.topology import NODES_PER_ELEMENT, sorted_unique


@dataclass(frozen=True)
class ElementBlock:
    """All elements of one type.

    Attributes
    ----------
    etype : str
        One of :data:`kneegui.topology.ELEMENT_TYPES`.
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
        return sorted_unique(np.concatenate(chunks))

    def bounding_box(self) -> NDArray[np.float64]:
        """(2, 3) array: minimum and maximum corner of the node cloud."""
        if self.n_nodes == 0:
            return np.zeros((2, 3))
        return np.stack([self.coords.min(axis=0), self.coords.max(axis=0)])
