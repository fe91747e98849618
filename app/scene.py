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
from kneegui.model import Model
from kneegui.topology import LINE_TYPES, SHELL_TYPES, block_offsets, boundary_faces, sorted_unique


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
    quads, tris, quad_cells, tri_cells = boundary_faces(model.blocks, [pid], with_cells=True)
    faces, owners, kinds = [tris, quads], [tri_cells, quad_cells], ["face", "face"]
    offsets = block_offsets(model.blocks)
    for etype, block in model.blocks.items():
        if etype not in SHELL_TYPES and etype not in LINE_TYPES:
            continue
        rows = np.flatnonzero(block.part_ids == pid)
        if len(rows):
            faces.append(block.conn[rows][:, : 2 if etype in LINE_TYPES else None])
            owners.append(offsets[etype] + rows)
            kinds.append("line" if etype in LINE_TYPES else "face")
    keep = [i for i, f in enumerate(faces) if len(f)]
    return [faces[i] for i in keep], [owners[i] for i in keep], [kinds[i] for i in keep]


def part_surfaces(model: Model) -> dict[int, PartSurface]:
    """Boundary surface (and line elements) of every part that has elements."""
    counts = model.element_counts()
    out: dict[int, PartSurface] = {}
    for pid in sorted(counts):
        faces, owners, kinds = _boundary_faces(model, pid)
        if not faces:
            continue
        used = sorted_unique(np.concatenate([f.reshape(-1) for f in faces]))
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
