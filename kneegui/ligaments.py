"""Ligament fibre stretch: per-element stretch along the fibre and each ligament's length.

A ligament's *fibre direction* is the principal axis (largest spread) of its nodes in the initial
pose. For every element of the ligament the edge most nearly parallel to that direction is the
element's *fibre edge*; its stretch is ``current length / initial length`` (1 = unchanged,
> 1 stretched, < 1 shortened). The ligament's *length* is the distance between the centroids of
its two end caps: the nodes within ``end_fraction`` of the fibre extent from either end, in the
initial pose. The paper (Jani et al. 2012, Fig. 8) shows the collateral ligaments' anterior edges
stretching and their posterior edges shortening in flexion; the per-element stretch shows that.

Everything is precomputed once by :func:`ligament_fibres`; evaluating a pose is a gather and a
norm, cheap enough for every slider step.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kneegui.errors import GeometryError
from kneegui.model import Model
from kneegui.topology import ELEMENT_EDGES

#: Short names recognised in part titles, in the order they are tried.
_SHORT_NAMES: tuple[tuple[str, str], ...] = (
    ("ACL", r"(?<![a-z])acl(?![a-z])|anterior[ _-]*cruciat"),
    ("PCL", r"(?<![a-z])pcl(?![a-z])|posterior[ _-]*cruciat"),
    ("MCL", r"(?<![a-z])mcl(?![a-z])|medial[ _-]*collat"),
    ("LCL", r"(?<![a-z])lcl(?![a-z])|lateral[ _-]*collat|fibular[ _-]*collat"),
)


def ligament_short_name(title: str) -> str | None:
    """``"ACL"``, ``"PCL"``, ``"MCL"`` or ``"LCL"`` when a part title names one, else ``None``."""
    text = title.lower()
    for name, pattern in _SHORT_NAMES:
        if re.search(pattern, text):
            return name
    return None


@dataclass(frozen=True)
class Ligament:
    """One ligament part and its precomputed fibre geometry.

    Attributes
    ----------
    part_id : int
        The part.
    name : str
        Short name (ACL, PCL, MCL, LCL) or the part title.
    direction : (3,) ndarray of float
        Unit fibre direction (principal axis of the nodes), initial pose.
    element_types : tuple of str
        Element type of each entry of ``rows`` (one per block the part has elements in).
    rows : tuple of (m,) ndarray of int64
        Rows of the part's elements in each block.
    fibre_edges : (M, 2) ndarray of int64
        Node indices of every element's fibre edge (blocks concatenated in ``element_types``
        order).
    initial_edge_length : (M,) ndarray of float
        Their lengths in the initial pose (model units).
    end_caps : tuple of two (k,) ndarrays of int64
        Node indices of the two end caps.
    initial_length : float
        Distance between the end-cap centroids in the initial pose (model units).
    """

    part_id: int
    name: str
    direction: NDArray[np.float64]
    element_types: tuple[str, ...]
    rows: tuple[NDArray[np.int64], ...]
    fibre_edges: NDArray[np.int64]
    initial_edge_length: NDArray[np.float64]
    end_caps: tuple[NDArray[np.int64], NDArray[np.int64]]
    initial_length: float

    def element_stretch(self, coords: ArrayLike) -> NDArray[np.float64]:
        """Fibre-edge stretch of every element, ``(M,)``, current / initial length."""
        xyz = np.asarray(coords, dtype=np.float64)
        a, b = self.fibre_edges[:, 0], self.fibre_edges[:, 1]
        return np.linalg.norm(xyz[a] - xyz[b], axis=1) / self.initial_edge_length

    def length(self, coords: ArrayLike) -> float:
        """Distance between the end-cap centroids at ``coords`` (model units)."""
        xyz = np.asarray(coords, dtype=np.float64)
        c0 = xyz[self.end_caps[0]].mean(axis=0)
        c1 = xyz[self.end_caps[1]].mean(axis=0)
        return float(np.linalg.norm(c1 - c0))


def _principal_axis(points: NDArray[np.float64]) -> NDArray[np.float64]:
    centred = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    return vt[0] / np.linalg.norm(vt[0])


def ligament_fibres(
    model: Model, part_ids: Iterable[int], end_fraction: float = 0.15
) -> tuple[Ligament, ...]:
    """Precompute the fibre geometry of ligament parts in the model's (initial) pose.

    Parameters
    ----------
    model : Model
        The model in the pose that defines "unstretched".
    part_ids : iterable of int
        Ligament parts (e.g. ``setup.roles["ligament"]``).
    end_fraction : float
        Thickness of each end cap as a fraction of the fibre extent (0 < f < 0.5).

    Returns
    -------
    tuple of Ligament
        One per part that has elements, in ``part_ids`` order.

    Raises
    ------
    GeometryError
        If a ligament has a zero-length fibre edge or no extent along its axis.
    """
    if not 0.0 < end_fraction < 0.5:
        raise ValueError(f"end_fraction must be in (0, 0.5), got {end_fraction}")
    coords = model.coords
    out = []
    for pid in part_ids:
        pid = int(pid)
        nodes = model.part_node_indices([pid])
        if len(nodes) < 2:
            continue
        direction = _principal_axis(coords[nodes])
        types, rows, edges = [], [], []
        for etype, block in model.blocks.items():
            sel = np.flatnonzero(block.part_ids == pid)
            if not len(sel):
                continue
            pairs = np.array(ELEMENT_EDGES[etype], dtype=np.int64)  # (E, 2)
            conn = block.conn[sel]
            a, b = conn[:, pairs[:, 0]], conn[:, pairs[:, 1]]  # (m, E)
            vec = coords[b] - coords[a]  # (m, E, 3)
            lengths = np.linalg.norm(vec, axis=2)
            with np.errstate(invalid="ignore", divide="ignore"):
                alignment = np.abs(vec @ direction) / lengths
            alignment = np.where(lengths > 0, alignment, -1.0)
            best = np.argmax(alignment, axis=1)
            take = np.arange(len(sel))
            edges.append(np.column_stack([a[take, best], b[take, best]]))
            types.append(etype)
            rows.append(sel.astype(np.int64))
        if not edges:
            continue
        fibre_edges = np.concatenate(edges)
        initial = np.linalg.norm(coords[fibre_edges[:, 0]] - coords[fibre_edges[:, 1]], axis=1)
        if np.any(initial <= 0):
            raise GeometryError(f"ligament part {pid} has a zero-length element edge")
        t = (coords[nodes] - coords[nodes].mean(axis=0)) @ direction
        lo, hi = float(t.min()), float(t.max())
        if hi - lo <= 0:
            raise GeometryError(f"ligament part {pid} has no extent along its fibre")
        cap = end_fraction * (hi - lo)
        caps = (nodes[t <= lo + cap], nodes[t >= hi - cap])
        title = model.parts[pid].title if pid in model.parts else ""
        name = ligament_short_name(title) or title or f"part {pid}"
        length = float(np.linalg.norm(coords[caps[1]].mean(axis=0) - coords[caps[0]].mean(axis=0)))
        direction.flags.writeable = False
        out.append(
            Ligament(
                pid, name, direction, tuple(types), tuple(rows), fibre_edges, initial, caps, length
            )
        )
    return tuple(out)


def length_curve(
    ligaments: Sequence[Ligament],
    pose: Callable[[float], NDArray[np.float64]],
    flexions: ArrayLike,
    cancelled: Callable[[], bool] | None = None,
    progress: Callable[[float, str], None] | None = None,
) -> NDArray[np.float64]:
    """Each ligament's length over a range of flexion angles.

    Parameters
    ----------
    ligaments : sequence of Ligament
        From :func:`ligament_fibres`.
    pose : callable
        ``pose(flexion_deg) -> (N, 3)`` coordinates (e.g. ``Repositioner.pose``).
    flexions : (F,) array_like of float
        Flexion angles (degrees).
    cancelled : callable, optional
        Returns true to stop early (raises :class:`kneegui.errors.Cancelled`).
    progress : callable, optional
        ``progress(fraction, message)``.

    Returns
    -------
    (F, L) ndarray of float
        Length of ligament ``j`` at flexion ``i`` (model units).
    """
    from kneegui.errors import Cancelled

    angles = np.asarray(flexions, dtype=np.float64).reshape(-1)
    out = np.empty((len(angles), len(ligaments)))
    for i, deg in enumerate(angles):
        if cancelled is not None and cancelled():
            raise Cancelled("ligament length curve cancelled")
        xyz = pose(float(deg))
        out[i] = [lig.length(xyz) for lig in ligaments]
        if progress is not None:
            progress((i + 1) / len(angles), f"ligament lengths at {deg:.0f}°")
    return out
