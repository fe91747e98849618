"""Export a model to an Abaqus input file (``.inp``), keeping node and element ids.

Element types: hex8 -> C3D8R, wedge6 -> C3D6, pyramid5 -> C3D5, tet4 -> C3D4, tet10 -> C3D10,
quad4 -> S4R, tri3 -> S3R, beam2 -> B31, discrete -> SPRINGA. One ``*ELSET`` per part
(``PART_<pid>``), named like the part title in a comment. Abaqus' wedge lists its first triangle
with the same orientation as LS-DYNA's, so no reordering is needed.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from kneegui.io.atomic import atomic_write_bytes
from kneegui.model import Model

ABAQUS_TYPES = {
    "hex8": "C3D8R",
    "wedge6": "C3D6",
    "pyramid5": "C3D5",
    "tet4": "C3D4",
    "tet10": "C3D10",
    "quad4": "S4R",
    "tri3": "S3R",
    "beam2": "B31",
    "discrete": "SPRINGA",
}


def _rows(fmt: str, table: np.ndarray) -> str:
    if len(table) == 0:
        return ""
    return (fmt * len(table)) % tuple(table.reshape(-1).tolist())


def _safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_\-]", "_", text)[:60]


def write_abaqus(model: Model, path: str | os.PathLike[str], heading: str = "kneegui") -> Path:
    """Write ``model`` as an Abaqus ``.inp`` file (atomically).

    Parameters
    ----------
    model : Model
        Any model (read from a deck or built in memory, at any pose).
    path : str or PathLike
        Output file.
    heading : str
        Text of the ``*HEADING`` card.

    Returns
    -------
    Path
        The file written.
    """
    out = [f"*HEADING\n{heading}\n", "*NODE\n"]
    coords = model.coords
    out.append(
        ("%d, %.17g, %.17g, %.17g\n" * model.n_nodes)
        % tuple(
            np.column_stack([model.node_ids.astype(object), coords.astype(object)])
            .reshape(-1)
            .tolist()
        )
        if model.n_nodes
        else ""
    )
    for etype, block in model.blocks.items():
        abaqus_type = ABAQUS_TYPES[etype]
        k = block.conn.shape[1]
        for pid in np.unique(block.part_ids).tolist():
            sel = block.part_ids == pid
            title = model.parts[pid].title if pid in model.parts else ""
            out.append(f"** part {pid}: {title}\n")
            out.append(f"*ELEMENT, TYPE={abaqus_type}, ELSET=PART_{pid}\n")
            table = np.column_stack([block.ids[sel], model.node_ids[block.conn[sel]]])
            out.append(_rows("%d" + ", %d" * k + "\n", table))
    for sid, nset in sorted(model.node_sets.items()):
        name = _safe_name(nset.title) or f"NSET_{sid}"
        out.append(f"*NSET, NSET=N{sid}_{name}\n")
        ids = model.node_ids[nset.node_indices]
        out.extend(
            ", ".join(str(i) for i in ids[s : s + 16].tolist()) + "\n"
            for s in range(0, len(ids), 16)
        )
    return atomic_write_bytes(path, "".join(out).encode("ascii", "replace"))
