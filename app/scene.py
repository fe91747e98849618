"""pyvista data for the viewport, built straight from the model arrays (no reader library).

- :func:`build_grid`: the whole model as one ``pyvista.UnstructuredGrid`` carrying node ids,
  element ids, part ids and each cell's (element type, block row).
- :func:`part_surfaces`: per part, the boundary faces of its elements as a ``pyvista.PolyData``
  whose points are a gather of model nodes (``model_index``) and whose faces know the global cell
  they come from (``cell_index``), so the viewport can move points in place from the coordinate
  array and colour faces by any per-element value without rebuilding anything.

Global cell index = position in the concatenation of ``model.blocks`` in their order, the same
order as :func:`kneegui.io.vtu.vtk_cell_arrays` and :meth:`QualityResult.concatenated`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyvista as pv
from numpy.typing import NDArray

from kneegui.io.vtu import vtk_cell_arrays
from kneegui.model import LINE_TYPES, SHELL_TYPES, Model

#: Faces of each element type, as node positions (package node order), outward for a positive
#: solid.
ELEMENT_FACES: dict[str, tuple[tuple[int, ...], ...]] = {
    "hex8": ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)),
    "wedge6": ((0, 2, 1), (3, 4, 5), (0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5)),
    "pyramid5": ((0, 3, 2, 1), (0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4)),
    "tet4": ((0, 2, 1), (0, 1, 3), (1, 2, 3), (2, 0, 3)),
    "tet10": ((0, 2, 1), (0, 1, 3), (1, 2, 3), (2, 0, 3)),
    "quad4": ((0, 1, 2, 3),),
    "tri3": ((0, 1, 2),),
}


def block_offsets(model: Model) -> dict[str, int]:
    """Global cell index of the first element of each block."""
    offsets, start = {}, 0
    for etype, block in model.blocks.items():
        offsets[etype] = start
        start += len(block)
    return offsets


def build_grid(model: Model) -> pv.UnstructuredGrid:
    """The model as an unstructured grid (points copied from ``model.coords``).

    Point data ``node_id``; cell data ``element_id``, ``part_id``, ``block_row`` and
    ``etype_index`` (index into ``model.blocks`` order).
    """
    cells, types, data = vtk_cell_arrays(model)
    grid = pv.UnstructuredGrid(cells, types, np.array(model.coords, dtype=np.float64))
    grid.point_data["node_id"] = model.node_ids
    for name, values in data.items():
        grid.cell_data[name] = values
    return grid


@dataclass
class PartSurface:
    """Boundary faces of one part, ready for a VTK actor.

    Attributes
    ----------
    part_id : int
    mesh : pyvista.PolyData
        Points = ``coords[model_index]``; cell data ``cell_index`` (global cell of each face).
    model_index : (P,) ndarray of int64
        Model node index of each point of ``mesh``.
    cell_index : (F,) ndarray of int64
        Global cell index of each face / line.
    n_elements : int
        Elements of the part (all types).
    """

    part_id: int
    mesh: pv.PolyData
    model_index: NDArray[np.int64]
    cell_index: NDArray[np.int64]
    n_elements: int


def _boundary_faces(model: Model, pid: int) -> tuple[list[NDArray], list[NDArray], list[NDArray]]:
    """Faces used once within the part (solids), all shell faces, and line elements."""
    offsets = block_offsets(model)
    solid_faces: dict[int, list[tuple[NDArray, NDArray]]] = {3: [], 4: []}
    shell_faces: list[tuple[NDArray, NDArray]] = []
    lines: list[tuple[NDArray, NDArray]] = []
    for etype, block in model.blocks.items():
        rows = np.flatnonzero(block.part_ids == pid)
        if not len(rows):
            continue
        conn = block.conn[rows]
        gidx = offsets[etype] + rows
        if etype in LINE_TYPES:
            lines.append((conn[:, :2], gidx))
            continue
        for face in ELEMENT_FACES[etype]:
            target = shell_faces if etype in SHELL_TYPES else solid_faces[len(face)]
            target.append((conn[:, list(face)], gidx))
    faces, owners, kinds = [], [], []
    for _k, chunks in solid_faces.items():
        if not chunks:
            continue
        f = np.concatenate([c[0] for c in chunks])
        o = np.concatenate([c[1] for c in chunks])
        key = np.sort(f, axis=1)
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        once = counts[inverse.reshape(-1)] == 1
        faces.append(f[once])
        owners.append(o[once])
        kinds.append("face")
    for f, o in shell_faces:
        faces.append(f)
        owners.append(o)
        kinds.append("face")
    for f, o in lines:
        faces.append(f)
        owners.append(o)
        kinds.append("line")
    return faces, owners, kinds


def part_surfaces(model: Model) -> dict[int, PartSurface]:
    """Boundary surface (and line elements) of every part that has elements."""
    counts = model.element_counts()
    out: dict[int, PartSurface] = {}
    for pid in sorted(counts):
        faces, owners, kinds = _boundary_faces(model, pid)
        if not faces:
            continue
        used = np.unique(np.concatenate([f.reshape(-1) for f in faces]))
        local = np.full(model.n_nodes, -1, dtype=np.int64)
        local[used] = np.arange(len(used))
        poly_faces, poly_lines, face_owner, line_owner = [], [], [], []
        for f, o, kind in zip(faces, owners, kinds, strict=True):
            if not len(f):
                continue
            padded = np.column_stack([np.full(len(f), f.shape[1]), local[f]]).reshape(-1)
            if kind == "line":
                poly_lines.append(padded)
                line_owner.append(o)
            else:
                poly_faces.append(padded)
                face_owner.append(o)
        points = np.array(model.coords[used], dtype=np.float64)
        mesh = pv.PolyData(
            points,
            faces=np.concatenate(poly_faces) if poly_faces else None,
            lines=np.concatenate(poly_lines) if poly_lines else None,
        )
        # VTK orders cells verts, lines, polys, strips: lines come before faces.
        cell_index = np.concatenate(line_owner + face_owner).astype(np.int64)
        mesh.cell_data["cell_index"] = cell_index
        mesh.cell_data["value"] = np.zeros(len(cell_index))
        out[pid] = PartSurface(
            pid, mesh, used.astype(np.int64), cell_index, sum(counts[pid].values())
        )
    return out
