"""Fixtures shared by the engine and GUI tests: the small demo leg welded across the knee."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from kneegui.model import ElementBlock, Model, NodeSet


def weld_coincident_nodes(model: Model) -> Model:
    """The model with every cluster of coincident nodes merged into its first node and the
    nodes no element uses dropped: a sliding interface (the demo's soft tissue on its own
    copies of the bone nodes) becomes flesh welded to the bones on both sides of the joint,
    as a deck meshed as one volume is. Node ids of the kept nodes are unchanged."""
    n = model.n_nodes
    used = np.zeros(n, dtype=bool)
    for block in model.blocks.values():
        used[block.conn.reshape(-1)] = True
    idx = np.flatnonzero(used)
    box = model.bounding_box()
    pairs = cKDTree(model.coords[idx]).query_pairs(
        1e-9 * float(np.linalg.norm(box[1] - box[0])), output_type="ndarray"
    )
    pairs = idx[pairs]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, component = connected_components(graph, directed=False)
    first = np.full(component.max() + 1, n, dtype=np.int64)
    np.minimum.at(first, component, np.arange(n))
    rep = first[component]
    kept = np.zeros(n, dtype=bool)
    for block in model.blocks.values():
        kept[rep[block.conn].reshape(-1)] = True
    new_index = np.full(n, -1, dtype=np.int64)
    new_index[kept] = np.arange(int(kept.sum()))
    blocks = {
        etype: ElementBlock(etype, b.ids, b.part_ids, new_index[rep[b.conn]])
        for etype, b in model.blocks.items()
    }
    sets = {}
    for sid, s in model.node_sets.items():
        moved = new_index[rep[s.node_indices]]
        sets[sid] = NodeSet(s.id, s.title, np.unique(moved[moved >= 0]))
    return Model(
        model.node_ids[kept], model.coords[kept], blocks, model.parts, sets, model.part_sets
    )


@pytest.fixture(scope="session")
def welded_leg():
    """``(model, setup dict)``: the small demo leg (2,000 solids requested) with its sliding
    interface welded shut."""
    from kneegui import demo

    leg = demo.generate_demo_leg(2000)
    return weld_coincident_nodes(leg.model), leg.setup
