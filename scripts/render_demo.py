"""Render the README pictures of the demo leg (off-screen, pyvista).

    python scripts/render_demo.py [--elements 20000] [--out docs/images]

Writes ``demo_leg.png`` (whole leg, parts coloured by role) and ``demo_leg_knee_cut.png``
(the knee cut in the sagittal plane through the lateral condyle and in the mid-sagittal plane,
showing the condyle arc, menisci, cruciate ligaments, patella and tendon).
"""

from __future__ import annotations

import kneegui.reproducible  # noqa: F401  (before numpy: the same kernels on every machine)

import argparse
from pathlib import Path

import numpy as np
import pyvista as pv
import vtk

from kneegui.demo import PARTS, generate_demo_leg

ROLE_COLOURS = {
    "femur": "#f2e6c9",
    "tibia": "#eadcb0",
    "fibula": "#e0c98f",
    "patella": "#f5d76e",
    "flesh": "#e9a3a0",
    "skin": "#f3c6b0",
    "ligament": "#3b6fd1",
    "meniscus": "#9b59b6",
    "tendon": "#2e8b57",
    "capsule": "#58b7c9",
}


def _grid(model, etype, rows):
    block = model.blocks[etype]
    conn = block.conn[rows]
    k = conn.shape[1]
    cells = np.hstack([np.full((len(conn), 1), k), conn]).ravel()
    ctype = vtk.VTK_HEXAHEDRON if etype == "hex8" else vtk.VTK_QUAD
    return pv.UnstructuredGrid(cells, np.full(len(conn), ctype), model.coords)


def role_meshes(model):
    """One pyvista grid per role (solids and shells of that role's parts)."""
    out = {}
    for role in ROLE_COLOURS:
        pids = [s.pid for s in PARTS if s.role == role]
        grids = []
        for etype in ("hex8", "quad4"):
            rows = np.flatnonzero(np.isin(model.blocks[etype].part_ids, pids))
            if len(rows):
                grids.append(_grid(model, etype, rows))
        if grids:
            out[role] = grids[0] if len(grids) == 1 else grids[0].merge(grids[1:])
    return out


def render(elements: int, out: Path) -> list[Path]:
    pv.OFF_SCREEN = True
    leg = generate_demo_leg(elements)
    meshes = role_meshes(leg.model)
    out.mkdir(parents=True, exist_ok=True)
    written = []

    # whole leg: skin half transparent over the rest
    p = pv.Plotter(off_screen=True, window_size=(900, 1400))
    for role, mesh in meshes.items():
        if role in ("flesh", "capsule"):
            continue
        opacity = 0.25 if role == "skin" else 1.0
        p.add_mesh(
            mesh,
            color=ROLE_COLOURS[role],
            opacity=opacity,
            show_edges=role != "skin",
            edge_color="#555555",
            line_width=0.3,
        )
    p.camera_position = [(900, -700, 150), (0, 0, 0), (0, 0, 1)]
    p.add_text("kneegui demo leg (right, 9° flexion)", font_size=12)
    path = out / "demo_leg.png"
    p.screenshot(str(path))
    p.close()
    written.append(path)

    # knee cut-away: everything clipped at the plane through the lateral condyle (y = -25)
    p = pv.Plotter(off_screen=True, window_size=(1400, 900), shape=(1, 2))
    for col, (y_cut, title) in enumerate(
        ((-25.0, "sagittal cut, lateral condyle"), (2.0, "sagittal cut, notch (ACL/PCL)"))
    ):
        p.subplot(0, col)
        for role, mesh in meshes.items():
            clipped = mesh.clip(normal=(0, 1, 0), origin=(0, y_cut, 0), invert=False, crinkle=True)
            clipped = clipped.clip_box(
                (-150, 150, -150, 150, -110, 110), invert=False, crinkle=True
            )
            if clipped.n_cells:
                p.add_mesh(
                    clipped,
                    color=ROLE_COLOURS[role],
                    show_edges=True,
                    edge_color="#444444",
                    line_width=0.4,
                )
        p.camera_position = [(0, -600, -10), (0, 0, -10), (0, 0, 1)]
        p.add_text(title, font_size=11)
    path = out / "demo_leg_knee_cut.png"
    p.screenshot(str(path))
    p.close()
    written.append(path)
    return written


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--elements", type=int, default=20_000)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent.parent / "docs/images"))
    args = ap.parse_args()
    for path in render(args.elements, Path(args.out)):
        print(path)


if __name__ == "__main__":
    main()
