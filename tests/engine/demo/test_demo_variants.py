"""Demo leg variants (issue 23, item 1): tet / mixed / tet10 meshes, welded joint, initial
flexion, metre units. Each variant is generated, written, read back and checked for what makes
it that variant."""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
import pytest

from kneegui.cli import main as cli_main
from kneegui.demo import PARTS, generate_demo_leg
from kneegui.demo import tetmesh as tm
from kneegui.demo.generator import DECK_NAME, SETUP_NAME, Variant, build_demo_leg
from kneegui.errors import KneeguiError
from kneegui.geometry.axes import compute_joint_axes, measure_flexion
from kneegui.io.atomic import atomic_write_text
from kneegui.io.lsdyna import write_model
from kneegui.io.lsdyna_read import read_deck
from kneegui.quality import compute_quality
from kneegui.setup.format import load_setup, setup_to_json

SMALL = 7_000  # the coarsest grid: every variant in seconds


@functools.cache
def _leg(elements=SMALL, side="right", **variant):
    return generate_demo_leg(elements, side, **variant)


def _pids(role):
    return [s.pid for s in PARTS if s.role == role]


def _nodes(model, role, etypes=None):
    return set(model.part_node_indices(_pids(role), etypes).tolist())


def _tet_block(model):
    return model.blocks.get("tet4") or model.blocks.get("tet10")


VARIANTS = [
    pytest.param({"element_type": "tet"}, id="tet"),
    pytest.param({"element_type": "mixed"}, id="mixed"),
    pytest.param({"joint": "welded"}, id="welded-hex"),
    pytest.param({"unit": "m"}, id="hex-m"),
    pytest.param({"initial_flexion": 0.0}, id="hex-0deg"),
    pytest.param({"element_type": "tet10"}, id="tet10", marks=pytest.mark.slow),
    pytest.param(
        {"element_type": "tet", "joint": "welded"}, id="welded-tet", marks=pytest.mark.slow
    ),
    pytest.param(
        {"element_type": "mixed", "side": "left", "unit": "m"},
        id="mixed-left-m",
        marks=pytest.mark.slow,
    ),
]


@pytest.mark.parametrize("variant", VARIANTS)
def test_variant_writes_reads_back_and_has_no_inverted_element(variant, tmp_path):
    variant = dict(variant)
    side = variant.pop("side", "right")
    leg = _leg(SMALL, side, **variant)
    # the files write_demo writes for this leg (generation is deterministic; the CLI and
    # write_demo themselves are tested below on a fast variant)
    deck = write_model(leg.model, tmp_path / DECK_NAME)
    setup_path = tmp_path / SETUP_NAME
    atomic_write_text(setup_path, setup_to_json(dict(leg.setup, model=DECK_NAME)))
    model = read_deck(deck)
    assert {t: len(b) for t, b in model.blocks.items()} == {
        t: len(b) for t, b in leg.model.blocks.items()
    }
    scale = 1e-3 if variant.get("unit") == "m" else 1.0
    assert np.abs(model.coords - leg.model.coords).max() < 1e-6 * scale
    quality = compute_quality(model.coords, model.blocks)
    assert quality.n_inverted == 0
    tets = _tet_block(model)
    if variant.get("element_type", "hex") != "hex":
        q = tm.tet_quality(model.coords, tets.conn)
        # no tet inverted or flat, and the worst ones are slivers of a measured, bounded kind
        assert q["volume"].min() > 0.0
        assert q["min_dihedral"].min() > 3.0
        assert q["collapse"].min() > 0.03
    setup = load_setup(setup_path, model)
    assert setup.roles["femur"] and setup.roles["tibia"]
    # element types as asked
    etype = variant.get("element_type", "hex")
    solids = {t for t in model.blocks if t in ("hex8", "tet4", "tet10")}
    expected = {"hex": {"hex8"}, "tet": {"tet4"}, "mixed": {"hex8", "tet4"}, "tet10": {"tet10"}}
    assert solids == expected[etype]


def test_tet_variant_is_a_bcc_mesh_not_split_hexes():
    leg = _leg(element_type="tet")
    model = leg.model
    assert "hex8" not in model.blocks
    tets = model.blocks["tet4"].conn
    # the same grid as hexahedra: the tet mesh has one node more per cell (its centre), which no
    # split of the hexes has. Node ids follow the grid: the grid's nodes, then the centres, then
    # the sliding interface's coincident copies (as many as in the hex mesh).
    hexes, problems = build_demo_leg(leg.layout, leg.design, "right")
    assert not problems
    n_cells = len(hexes.model.blocks["hex8"])
    assert model.n_nodes - hexes.model.n_nodes == n_cells == leg.stats["tet_cells"]
    copies = len(model.coords) - len(np.unique(model.coords, axis=0))
    assert copies == len(hexes.model.coords) - len(np.unique(hexes.model.coords, axis=0)) > 0
    first = hexes.model.n_nodes - copies
    centre = np.zeros(model.n_nodes, dtype=bool)
    centre[first : first + n_cells] = True
    # the centres lie inside the mesh, on no shell
    shells = np.concatenate([b.conn.ravel() for t, b in model.blocks.items() if t == "tri3"])
    assert not centre[shells].any()
    per_tet = centre[tets].sum(axis=1)
    assert set(np.unique(per_tet).tolist()) == {1, 2}
    assert (per_tet == 2).mean() > 0.6
    # every centre is a BCC node: its tets cross faces to (up to) 6 neighbour centres
    incident = np.bincount(tets.ravel(), minlength=model.n_nodes)[centre]
    assert incident.min() >= 12
    assert len(tets) == 12 * n_cells


def test_tet_variant_is_conforming():
    tets = _leg(element_type="tet").model.blocks["tet4"].conn
    faces = np.sort(tets[:, [[0, 1, 2], [0, 1, 3], [1, 2, 3], [0, 2, 3]]].reshape(-1, 3), axis=1)
    _, count = np.unique(faces, axis=0, return_counts=True)
    assert count.max() <= 2  # no face shared by three tets; every interior face by exactly two


def test_mixed_variant_has_tet_flesh_and_hex_bones_sharing_nodes():
    model = _leg(element_type="mixed").model
    tet_pids = set(np.unique(model.blocks["tet4"].part_ids).tolist())
    hex_pids = set(np.unique(model.blocks["hex8"].part_ids).tolist())
    assert tet_pids == set(_pids("flesh"))
    assert set(_pids("femur")) & hex_pids and set(_pids("ligament")) <= hex_pids
    tet_nodes = set(model.blocks["tet4"].conn.ravel().tolist())
    hex_nodes = set(model.blocks["hex8"].conn.ravel().tolist())
    assert len(tet_nodes & hex_nodes) > 100


@pytest.mark.slow
def test_tet10_has_mid_edge_nodes_on_straight_edges():
    model = _leg(element_type="tet10").model
    conn = model.blocks["tet10"].conn
    c = model.coords
    for k, (a, b) in enumerate(tm.TET_EDGES):
        assert np.abs(c[conn[:, 4 + k]] - 0.5 * (c[conn[:, a]] + c[conn[:, b]])).max() < 1e-9


@pytest.mark.parametrize("element_type", ["hex", pytest.param("tet", marks=pytest.mark.slow)])
def test_welded_flesh_shares_nodes_with_both_bones_and_bridges_the_gap(element_type):
    model = _leg(joint="welded", element_type=element_type).model
    flesh = _nodes(model, "flesh")
    femur, tibia = _nodes(model, "femur"), _nodes(model, "tibia")
    assert len(flesh & femur) > 50 and len(flesh & tibia) > 50
    femur_mask = np.zeros(model.n_nodes, bool)
    tibia_mask = np.zeros(model.n_nodes, bool)
    femur_mask[list(femur)] = True
    tibia_mask[list(tibia)] = True
    bridging = 0
    for block in model.blocks.values():
        if block.etype in ("hex8", "tet4"):
            is_flesh = np.isin(block.part_ids, _pids("flesh"))
            conn = block.conn[is_flesh]
            bridging += int(np.sum(femur_mask[conn].any(1) & tibia_mask[conn].any(1)))
    assert bridging >= 20

    # one volume: no coincident node pairs (the sliding variant has hundreds)
    def coincident(m):
        return len(m.coords) - len(np.unique(np.round(m.coords, 6), axis=0))

    assert coincident(model) == 0
    assert coincident(_leg().model) > 100


def test_welded_setup_loads_and_the_engine_finds_the_axes():
    leg = _leg(joint="welded")
    setup = load_setup(leg.setup, leg.model)
    axes = compute_joint_axes(leg.model.coords, setup)
    assert abs(axes.lateral_fit.radius - leg.design.lateral_radius) <= 0.3
    assert abs(measure_flexion(leg.model.coords, setup) - 9.0) <= 1.0


def test_metre_variant_is_the_millimetre_variant_scaled():
    mm, m = _leg(), _leg(unit="m")
    assert np.array_equal(mm.model.node_ids, m.model.node_ids)
    for t, b in mm.model.blocks.items():
        assert np.array_equal(b.conn, m.model.blocks[t].conn)
    assert np.allclose(m.model.coords, mm.model.coords * 1e-3, rtol=1e-12, atol=1e-15)
    assert m.setup["units"] == "m" and mm.setup["units"] == "mm"
    for key in ("femur_axis", "tibia_axis"):
        assert np.allclose(
            np.array(m.setup["landmarks"][key]),
            np.array(mm.setup["landmarks"][key]) * 1e-3,
            rtol=0,
            atol=1e-9,
        )
    assert m.setup["landmarks"]["lateral_condyle"] == mm.setup["landmarks"]["lateral_condyle"]
    # the engine reads the setup and measures the same knee in metres
    setup = load_setup(m.setup, m.model)
    axes = compute_joint_axes(m.model.coords, setup)
    assert abs(axes.lateral_fit.radius - 1e-3 * m.design.lateral_radius) <= 0.3e-3
    assert abs(measure_flexion(m.model.coords, setup) - 9.0) <= 1.0


@pytest.mark.parametrize(
    "flexion, elements",
    [(0.0, SMALL), (15.0, SMALL), pytest.param(20.0, 20_000, marks=pytest.mark.slow)],
)
def test_initial_flexion_variant_is_built_at_that_angle(flexion, elements):
    leg = _leg(elements, initial_flexion=flexion)
    setup = load_setup(leg.setup, leg.model)
    axes = compute_joint_axes(leg.model.coords, setup)
    assert abs(axes.initial_flexion_deg - flexion) <= 1.0
    assert abs(measure_flexion(leg.model.coords, setup) - flexion) <= 1.0
    assert abs(axes.lateral_fit.radius - leg.design.lateral_radius) <= 0.3
    assert compute_quality(leg.model.coords, leg.model.blocks).n_inverted == 0


def test_bad_variant_options_are_one_line_errors():
    for kwargs in (
        {"element_type": "wedge"},
        {"joint": "glued"},
        {"unit": "inch"},
        {"initial_flexion": 25.0},
        {"initial_flexion": -1.0},
    ):
        with pytest.raises(KneeguiError) as err:
            generate_demo_leg(SMALL, **kwargs)
        assert "\n" not in str(err.value)


def test_default_variant_is_the_plain_demo():
    assert Variant() == Variant("hex", "sliding", "mm")
    assert "variant" not in _leg().stats
    assert replace(Variant(), element_type="tet").has_tets


def test_cli_writes_a_variant(tmp_path):
    out = tmp_path / "demo"
    argv = [
        "demo",
        str(out),
        "--elements",
        str(SMALL),
        "--joint",
        "welded",
        "--unit",
        "m",
        "--initial-flexion",
        "5",
        "--side",
        "left",
    ]
    assert cli_main(argv) == 0
    leg = _leg(SMALL, "left", joint="welded", unit="m", initial_flexion=5.0)
    model = read_deck(out / DECK_NAME)
    assert np.abs(model.coords - leg.model.coords).max() < 1e-9
    text = (out / DECK_NAME).read_text().splitlines()
    assert text[2] == "kneegui demo leg (left, 7224 solids, hex welded, 5 deg, m)"
    assert load_setup(out / SETUP_NAME, model).side == "left"
    with pytest.raises(SystemExit):
        cli_main(["demo", str(out), "--element-type", "prism"])
