"""The demo made larger far from the knee (bench/far_block.py), for the 2M-node memory target."""

from __future__ import annotations

import numpy as np

from bench.far_block import OFFSET_MM, add_far_block, far_block
from kneegui.demo import write_demo
from kneegui.io.lsdyna import read_deck
from kneegui.quality import compute_quality
from kneegui.reposition import Repositioner
from kneegui.setup import load_setup


def test_the_far_block_adds_its_nodes_as_valid_cubes_that_stay_where_they_are(tmp_path):
    xyz, hexes = far_block(4)
    assert xyz.shape == (64, 3) and hexes.shape == (27, 8)
    deck, _ = write_demo(tmp_path / "demo", elements=2000)
    bigger = add_far_block(deck.parent, tmp_path / "bigger", nodes_per_side=4)
    demo, model = read_deck(deck), read_deck(bigger)
    assert model.n_nodes == demo.n_nodes + 64
    added = model.blocks["hex8"].part_ids == 990_001
    assert int(added.sum()) == 27
    q = compute_quality(model.coords, {"hex8": model.blocks["hex8"]})["hex8"]
    np.testing.assert_allclose(q.jacobian_corner[added], 1.0)  # unit cubes, right-handed
    far = model.coords[:, 0] >= OFFSET_MM
    assert int(far.sum()) == 64
    setup = load_setup(bigger.parent / "demo_leg.setup.json", model)
    rep = Repositioner(model, setup)
    posed = rep.pose(60.0)
    np.testing.assert_array_equal(posed[far], model.coords[far])  # an unnamed part stays
