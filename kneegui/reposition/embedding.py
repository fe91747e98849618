"""Embedding nodes in a Delaunay tetrahedralisation of control points (ALGORITHM.md §4).

Each embedded node keeps the tetrahedron it lies in and its barycentric ("volume") coordinates;
after the control points move, the node is the same weighted sum of the moved vertices.

Fallback for a node outside every tetrahedron (outside the control points' convex hull): it is
given the tetrahedron that owns its nearest control point, with barycentric weights clamped to
``>= 0`` and renormalised, i.e. it moves like the nearest point of that tetrahedron. The number
of such nodes is reported, never hidden.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import Delaunay, QhullError, cKDTree

from kneegui.errors import GeometryError
from kneegui.topology import sorted_unique


@dataclass(frozen=True)
class Embedding:
    """Barycentric embedding of ``nodes`` in tetrahedra of ``control`` points.

    Attributes
    ----------
    nodes : (M,) ndarray of int
        Embedded node indices.
    control : (C,) ndarray of int
        Control-point node indices (the tetrahedra's vertices).
    vertices : (M, 4) ndarray of int
        For each embedded node, its tetrahedron's vertices as positions into ``control``.
    weights : (M, 4) ndarray of float
        Barycentric coordinates (sum 1).
    outside : (M,) ndarray of bool
        Nodes that took the nearest-tetrahedron fallback.
    """

    nodes: NDArray[np.int64]
    control: NDArray[np.int64]
    vertices: NDArray[np.int64]
    weights: NDArray[np.float64]
    outside: NDArray[np.bool_]

    def apply(self, control_positions: NDArray[np.float64]) -> NDArray[np.float64]:
        """Positions (M, 3) of the embedded nodes for control points at ``control_positions``
        (C, 3), in the order of ``control``."""
        v = control_positions[self.vertices]  # (M, 4, 3)
        return np.einsum("mk,mkj->mj", self.weights, v)


def embed_nodes(
    coords: NDArray[np.float64], control: NDArray[np.int64], nodes: NDArray[np.int64]
) -> Embedding:
    """Tetrahedralise ``control`` points (Qhull Delaunay) and embed ``nodes`` in it.

    Raises
    ------
    GeometryError
        If the control points are too few or all coplanar.
    """
    control = sorted_unique(np.asarray(control, dtype=np.int64))
    nodes = np.asarray(nodes, dtype=np.int64)
    pts = coords[control]
    if len(control) < 4:
        raise GeometryError(f"need at least 4 control points to tetrahedralise, got {len(control)}")
    try:
        tri = Delaunay(pts)
    except QhullError as exc:
        raise GeometryError(
            f"Delaunay tetrahedralisation failed: {str(exc).splitlines()[0]}"
        ) from None
    x = coords[nodes]
    simplex = tri.find_simplex(x)
    outside = simplex < 0
    if outside.any():
        # nearest control point's first tetrahedron
        _, nearest = cKDTree(pts).query(x[outside])
        owner = np.full(len(pts), -1, dtype=np.int64)
        owner[tri.simplices.reshape(-1)] = np.repeat(np.arange(len(tri.simplices)), 4)
        simplex = simplex.copy()
        simplex[outside] = owner[nearest]
    t = tri.transform[simplex]  # (M, 4, 3)
    b = np.einsum("mij,mj->mi", t[:, :3, :], x - t[:, 3, :])
    w = np.column_stack([b, 1.0 - b.sum(axis=1)])
    if outside.any():
        w[outside] = np.clip(w[outside], 0.0, None)
        w[outside] /= w[outside].sum(axis=1, keepdims=True)
    return Embedding(nodes, control, tri.simplices[simplex].astype(np.int64), w, outside)
