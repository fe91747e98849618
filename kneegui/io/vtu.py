"""Export a model to VTK's unstructured-grid format (``.vtu``) through pyvista.

pyvista/VTK are imported inside the function so that ``import kneegui`` stays free of them.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from kneegui.io.atomic import atomic_write_bytes
from kneegui.model import Model
from kneegui.topology import MIRRORED_NODE_ORDER

#: VTK cell type numbers, and the permutation from this package's node order to VTK's (VTK
#: lists a wedge's triangles the other way round: the mirrored order of kneegui.topology).
VTK_CELLS: dict[str, tuple[int, list[int]]] = {
    "hex8": (12, [0, 1, 2, 3, 4, 5, 6, 7]),
    "wedge6": (13, list(MIRRORED_NODE_ORDER["wedge6"])),
    "pyramid5": (14, [0, 1, 2, 3, 4]),
    "tet4": (10, [0, 1, 2, 3]),
    "tet10": (24, [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]),
    "quad4": (9, [0, 1, 2, 3]),
    "tri3": (5, [0, 1, 2]),
    "beam2": (3, [0, 1]),
    "discrete": (3, [0, 1]),
}


def vtk_cell_arrays(model: Model) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Cells, cell types and per-cell data (element id, part id, type index) in VTK's layout.

    Returns
    -------
    cells : (K,) ndarray of int64
        VTK legacy cell array (``n, i0, i1, ...`` per cell).
    celltypes : (M,) ndarray of uint8
    cell_data : dict
        ``element_id``, ``part_id`` and ``block_row`` (row within its block) per cell, plus
        ``etype_index`` (index into the model's ``blocks`` keys order).
    """
    cells, types, eids, pids, rows, tindex = [], [], [], [], [], []
    for t, (etype, block) in enumerate(model.blocks.items()):
        vtk_type, perm = VTK_CELLS[etype]
        k = len(perm)
        m = len(block)
        cells.append(np.column_stack([np.full(m, k), block.conn[:, perm]]).reshape(-1))
        types.append(np.full(m, vtk_type, dtype=np.uint8))
        eids.append(block.ids)
        pids.append(block.part_ids)
        rows.append(np.arange(m))
        tindex.append(np.full(m, t))
    if not cells:
        empty = np.zeros(0, dtype=np.int64)
        return empty, np.zeros(0, np.uint8), {}
    data = {
        "element_id": np.concatenate(eids),
        "part_id": np.concatenate(pids),
        "block_row": np.concatenate(rows),
        "etype_index": np.concatenate(tindex),
    }
    return np.concatenate(cells).astype(np.int64), np.concatenate(types), data


def write_vtu(model: Model, path: str | os.PathLike[str]) -> Path:
    """Write ``model`` as a ``.vtu`` file with node ids, element ids and part ids (atomically)."""
    import tempfile

    import pyvista as pv

    cells, types, data = vtk_cell_arrays(model)
    grid = pv.UnstructuredGrid(cells, types, model.coords)
    grid.point_data["node_id"] = model.node_ids
    for name, values in data.items():
        if name in ("element_id", "part_id"):
            grid.cell_data[name] = values
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        tmp_file = Path(tmp) / "model.vtu"
        grid.save(tmp_file)
        return atomic_write_bytes(target, tmp_file.read_bytes())
