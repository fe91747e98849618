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
    enclosures : tuple of frozenset of int, or None
        When every face of the part is also a face of other parts (a shell drawn over it, or
        the solid on the other side of an interface), the distinct sets of those other parts,
        one set per group of faces: the part cannot be seen from outside while each set has a
        part that is shown (:func:`enclosed_parts`). None when the part has a face no other
        part shares, or shells or lines of its own.
    """

    part_id: int
    mesh: pv.PolyData
    model_index: NDArray[np.int64]
    cell_index: NDArray[np.int64]
    n_elements: int
    enclosures: tuple[frozenset[int], ...] | None = None


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


def _face_keys(faces: NDArray[np.int64]) -> NDArray[np.int64]:
    """Each face's sorted nodes, padded with -1 to four columns (the same face, the same key)."""
    keys = np.full((len(faces), 4), -1, dtype=np.int64)
    keys[:, : faces.shape[1]] = np.sort(faces, axis=1)
    if faces.shape[1] == 4:  # a quad shell with its last two nodes equal is a triangle
        tri = faces[:, 3] == faces[:, 2]
        keys[tri, :3] = np.sort(faces[tri, :3], axis=1)
        keys[tri, 3] = -1
    return keys


def _enclosures(
    faces_of: dict[int, list[NDArray[np.int64]]], solid_only: set[int]
) -> dict[int, tuple[frozenset[int], ...]]:
    """For each part of ``solid_only`` (parts drawn with solid boundary faces alone) whose every
    face is a face of another part too: the distinct sets of the other parts sharing a face."""
    pids = [p for p in faces_of if faces_of[p]]
    if not pids:
        return {}
    keys = [_face_keys(f) for p in pids for f in faces_of[p]]
    owner = np.concatenate([np.full(len(f), p, dtype=np.int64) for p in pids for f in faces_of[p]])
    _, group = np.unique(np.concatenate(keys), axis=0, return_inverse=True)
    group = group.ravel()
    order = np.lexsort((owner, group))
    group, owner = group[order], owner[order]
    out: dict[int, tuple[frozenset[int], ...]] = {}
    shared = np.zeros(len(group), dtype=bool)
    shared[1:] |= group[1:] == group[:-1]
    shared[:-1] |= group[:-1] == group[1:]
    for pid in solid_only:
        mine = owner == pid
        if not mine.any() or not shared[mine].all():
            continue
        others = np.isin(group, group[mine]) & ~mine
        sets = {}
        for g, p in zip(group[others].tolist(), owner[others].tolist(), strict=True):
            sets.setdefault(g, set()).add(p)
        out[pid] = tuple(sorted({frozenset(v) for v in sets.values()}, key=sorted))
    return out


def enclosed_parts(surfaces: dict[int, PartSurface], shown: set[int]) -> set[int]:
    """Parts of ``shown`` that cannot be seen from outside: every face of theirs is a face of a
    shown part as well (a cortical shell over the trabecular bone, flesh around it on every
    side). Hidden parts still hold their place: a part inside a part that is itself enclosed is
    enclosed too. Meaningless while the view is cut open or drawn see-through."""
    return {
        pid
        for pid in shown
        if (cover := surfaces[pid].enclosures) is not None
        and all(not group.isdisjoint(shown) for group in cover)
    }


def part_surfaces(model: Model) -> dict[int, PartSurface]:
    """Boundary surface (and line elements) of every part that has elements."""
    counts = model.element_counts()
    out: dict[int, PartSurface] = {}
    faces_of: dict[int, list[NDArray[np.int64]]] = {}
    solid_only: set[int] = set()
    for pid in sorted(counts):
        faces, owners, kinds = _boundary_faces(model, pid)
        if not faces:
            continue
        faces_of[pid] = [f for f, k in zip(faces, kinds, strict=True) if k == "face"]
        if not any(
            (block.part_ids == pid).any()
            for etype, block in model.blocks.items()
            if etype in SHELL_TYPES or etype in LINE_TYPES
        ):
            solid_only.add(pid)
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
    for pid, cover in _enclosures(faces_of, solid_only).items():
        out[pid].enclosures = cover
    return out
