"""pyvista data for the viewport, built straight from the model arrays (no reader library).

- :func:`build_grid`: the whole model as one ``pyvista.UnstructuredGrid`` carrying node ids,
  element ids, part ids and each cell's (element type, block row).
- :func:`part_surfaces`: per part, the boundary faces of its elements as a ``pyvista.PolyData``
  whose points are a gather of model nodes (``model_index``) and whose faces know the global cell
  they come from (``cell_index``), so the viewport can move points in place from the coordinate
  array and colour faces by any per-element value without rebuilding anything.
- :func:`hidden_faces`: which of those faces two shown parts share (no one sees them from
  outside; the viewport does not draw them).

Global cell index = position in the concatenation of ``model.blocks`` in their order, the same
order as :func:`kneegui.io.vtu.vtk_cell_arrays` and :meth:`QualityResult.concatenated`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pyvista as pv
from numpy.typing import NDArray

from kneegui.io.vtu import vtk_cell_arrays
from kneegui.model import Model
from kneegui.topology import (
    LINE_TYPES,
    SHELL_TYPES,
    block_offsets,
    boundary_faces,
    row_groups,
    sorted_unique,
)


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
    face_group : (P,) ndarray of int64
        Per face (polygon) of ``mesh``, in its order after the lines: an index shared by every
        part's copy of the same face (the same corner nodes), so that :func:`hidden_faces` can
        tell the faces between two parts from those on the outside.
    shell_face : (P,) ndarray of bool
        Per face: a shell element's (else a solid's boundary face).
    """

    part_id: int
    mesh: pv.PolyData
    model_index: NDArray[np.int64]
    cell_index: NDArray[np.int64]
    n_elements: int
    face_group: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    shell_face: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=bool))


def _boundary_faces(model: Model, pid: int) -> tuple[list[NDArray], list[NDArray], list[NDArray]]:
    """Faces used once within the part (solids, kind "face"), all shell faces ("shell"), and
    line elements ("line")."""
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
            kinds.append("line" if etype in LINE_TYPES else "shell")
    keep = [i for i, f in enumerate(faces) if len(f)]
    return [faces[i] for i in keep], [owners[i] for i in keep], [kinds[i] for i in keep]


def _face_keys(faces: NDArray[np.int64]) -> NDArray[np.int64]:
    """Each face's sorted nodes, padded with -1 to four columns (the same face, the same key)."""
    keys = np.full((len(faces), 4), -1, dtype=np.int64)
    keys[:, : faces.shape[1]] = np.sort(faces, axis=1)
    if faces.shape[1] == 4:  # a quad shell with its last two nodes equal is a triangle
        tri = faces[:, 3] == faces[:, 2]
        keys[tri, :3] = np.sort(faces[tri, :3], axis=1)
        keys[tri, 3] = -1
    return keys


def _face_groups(faces_of: dict[int, list[NDArray[np.int64]]]) -> dict[int, NDArray[np.int64]]:
    """Per part, for each of its faces (in ``faces_of`` order), an index shared by every
    part's copy of the same face."""
    pids = [p for p in faces_of if faces_of[p]]
    if not pids:
        return {}
    group = row_groups(np.concatenate([_face_keys(f) for p in pids for f in faces_of[p]]))
    sizes = np.cumsum([0] + [sum(len(f) for f in faces_of[p]) for p in pids])
    return {p: group[a:b] for p, a, b in zip(pids, sizes[:-1], sizes[1:], strict=True)}


def hidden_faces(surfaces: dict[int, PartSurface], shown: set[int]) -> dict[int, NDArray[np.bool_]]:
    """Per shown part, which of its faces no one can see from outside while the parts
    ``shown`` are drawn opaque and whole (no cut): a solid's boundary face that another shown
    part also has (a shell drawn over it, or the solid on the other side of an interface); a
    shell face between two shown solids (a cortical shell with flesh outside and trabecular bone
    inside), and of shells on the same face all but the one of the smallest part id."""
    pids = [p for p in sorted(shown) if len(surfaces[p].face_group)]
    if not pids:
        return {p: np.zeros(len(surfaces[p].face_group), dtype=bool) for p in shown}
    group = np.concatenate([surfaces[p].face_group for p in pids])
    shell = np.concatenate([surfaces[p].shell_face for p in pids])
    owner = np.concatenate([np.full(len(surfaces[p].face_group), p) for p in pids])
    size = int(group.max()) + 1
    solids = np.bincount(group[~shell], minlength=size)
    shells = np.bincount(group[shell], minlength=size)
    first_shell = np.full(size, np.iinfo(np.int64).max)
    np.minimum.at(first_shell, group[shell], owner[shell])
    hidden = np.where(
        shell,
        (solids[group] >= 2) | ((shells[group] >= 2) & (owner != first_shell[group])),
        solids[group] + shells[group] >= 2,
    )
    out = {p: np.zeros(len(surfaces[p].face_group), dtype=bool) for p in shown}
    bounds = np.cumsum([0] + [len(surfaces[p].face_group) for p in pids])
    for p, a, b in zip(pids, bounds[:-1], bounds[1:], strict=True):
        out[p] = hidden[a:b]
    return out


def part_surfaces(model: Model) -> dict[int, PartSurface]:
    """Boundary surface (and line elements) of every part that has elements."""
    counts = model.element_counts()
    out: dict[int, PartSurface] = {}
    faces_of: dict[int, list[NDArray[np.int64]]] = {}
    shell_of: dict[int, NDArray[np.bool_]] = {}
    for pid in sorted(counts):
        faces, owners, kinds = _boundary_faces(model, pid)
        if not faces:
            continue
        polygons = [(f, k) for f, k in zip(faces, kinds, strict=True) if k != "line"]
        faces_of[pid] = [f for f, _ in polygons]
        shell_of[pid] = np.concatenate(
            [np.full(len(f), k == "shell") for f, k in polygons] or [np.zeros(0, dtype=bool)]
        )
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
    for pid, group in _face_groups(faces_of).items():
        out[pid].face_group = group
        out[pid].shell_face = shell_of[pid]
    return out
