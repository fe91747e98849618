"""The welded-joint variant of the demo leg: one volume of flesh across the knee.

Human-body models meshed as one volume around a joint have no sliding interface: the flesh shares
its nodes with the femur above and the tibia below, and fills the joint gap between them, one
element deep. :func:`weld_joint` turns the demo grid into that:

* the node layers between the tibial plateau and the femur's distal surface are merged into the
  femur's bottom layer, so the first slab above the plateau (menisci, cruciate ligaments, flesh)
  reaches from the tibia to the femur and the slabs above it are dropped (label
  :data:`DROPPED`);
* every cell of the joint cavity (the gap between the condyles and the plateau outside the
  menisci and ligaments, the intercondylar notch and the patello-femoral gap) becomes flesh.

The capsule keeps its place as shells between the former cavity and the surrounding soft tissue,
now embedded in the flesh. The generator does not detach the soft tissue from the bones for this
variant, so flesh elements in the gap have nodes on both bones.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from kneegui.demo import grid as g

#: Label of the cells the weld removes (their nodes were merged away).
DROPPED = -1


def weld_joint(grid: g.Grid) -> g.Grid:
    """Merge the joint gap to one element between tibia and femur and fill the cavity with flesh.

    Parameters
    ----------
    grid : Grid
        A demo grid (:func:`kneegui.demo.grid.build_grid`).

    Returns
    -------
    Grid
        Same lattice nodes (the merged ones become unused), new connectivity, labels and shells.
    """
    lay = grid.layout
    ix = g._Index(lay)
    k_tp = lay.slabs.start("men")  # tibia top layer
    k_fb = lay.slabs.stop("void")  # femur bottom layer
    node = np.arange(ix.n_nodes)
    layer = node // ix.per_layer
    merged = (layer > k_tp) & (layer < k_fb)
    target = np.where(merged, node + (k_fb - layer) * ix.per_layer, node)
    conn = target[grid.cell_conn]
    slab = np.arange(len(conn)) // ix.slot_per_slab
    dropped = (slab > k_tp) & (slab < k_fb)
    cavity = grid.cell_label == g.VOID
    labels = np.where(cavity, g.FLESH, grid.cell_label)
    labels[dropped] = DROPPED
    # shells: the cavity still counts as void (capsule), dropped cells match nothing
    shell_conn = conn.copy()
    shell_conn[dropped] = ix.n_nodes + np.arange(8 * int(dropped.sum())).reshape(-1, 8)
    shell_labels = np.where(cavity | dropped, g.VOID, labels)
    shells = g._shells(lay, ix, shell_conn, shell_labels)
    return replace(grid, cell_conn=conn, cell_label=labels, shells=shells)
