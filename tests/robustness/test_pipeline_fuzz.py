"""Fuzzing the whole path (issue #22): random valid setups and damaged meshes go through
``kneegui pose`` and ``kneegui quality`` (deck file in, deck file out, as a user runs them) and end
in a result or in one clear ``kneegui: ...`` line with exit code 2 - never a traceback.

The model is the engine's synthetic knee (1,360 nodes, 840 elements; a pose takes about 0.2 s),
moved, mirrored and resized at random; the demo leg (2,000 elements) adds a few cases. Each test
records how many cases it ran in ``FUZZ_COUNTS`` (printed in the session summary and quoted in
docs/reliability.md).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kneegui.cli import main as cli
from kneegui.geometry.transforms import rotation_matrix
from kneegui.io.lsdyna import read_deck, write_model
from kneegui.model import ElementBlock, Model
from kneegui.setup.kinematic_tables import table_names
from kneegui.setup.synthetic import build_synthetic_knee

FUZZ = settings(
    max_examples=50,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
FUZZ_COUNTS: dict[str, int] = {}
OPTIONAL_ROLES = ("fibula", "patella", "skin", "flesh", "ligament")
SOFT_ROLES = ("flesh", "ligament", "meniscus", "tendon", "capsule", "fixed")


def count(name: str) -> None:
    FUZZ_COUNTS[name] = FUZZ_COUNTS.get(name, 0) + 1


def run_cli(capsys, *args: str) -> tuple[int, str]:
    """Run the CLI in-process: a traceback fails the test; an error must be one line."""
    status = cli(list(args))
    err = capsys.readouterr().err
    assert status in (0, 2, 3), (status, err)
    if status == 2:
        lines = [ln for ln in err.splitlines() if ln.startswith("kneegui: ")]
        assert len(lines) == 1 and len(lines[0]) > len("kneegui: "), err
    return status, err


def pose_and_quality(tmp: Path, capsys, model: Model, setup: dict, flexion: float, smooth: bool):
    """Write the deck and setup, pose, and measure the result; returns the pose's exit code."""
    tmp.mkdir(parents=True, exist_ok=True)
    deck = write_model(model, tmp / "knee.k")
    setup_path = tmp / "knee.setup.json"
    setup_path.write_text(json.dumps(dict(setup, model=deck.name)))
    out = tmp / "posed" / "knee.k"
    args = ["pose", str(deck), "--setup", str(setup_path), f"--flexion={flexion!r}"]
    args += ["--out", str(out), "--force"] + ([] if smooth else ["--no-smooth"])
    status, err = run_cli(capsys, *args)
    if status != 2:
        back = read_deck(out)
        assert back.n_nodes == model.n_nodes and np.all(np.isfinite(back.coords))
        q, _ = run_cli(
            capsys, "quality", str(out), "--initial", str(deck), "--setup", str(setup_path)
        )
        assert q == 0
    return status, err


def random_rotation(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    return rotation_matrix(axis / np.linalg.norm(axis), float(rng.uniform(0, 360)))


# ------------------------------------------------------------------ valid setups
@st.composite
def knees(draw):
    """A synthetic knee in a random place and size, with its (valid) setup."""
    seed = draw(st.integers(0, 2**16))
    scale_lat = draw(st.floats(17.0, 24.0))
    knee = build_synthetic_knee(
        side=draw(st.sampled_from(["right", "left"])),
        flexion_deg=draw(st.floats(0.0, 30.0)),
        rotation=random_rotation(seed),
        translation=draw(st.lists(st.floats(-2000, 2000), min_size=3, max_size=3)),
        lateral_radius=scale_lat,
        medial_radius=scale_lat + draw(st.floats(0.5, 4.0)),
        noise_mm=draw(st.sampled_from([0.0, 0.0, 0.05, 0.3])),
        seed=seed,
        coordinate_landmarks=draw(st.booleans()),
        distal_flat_deg=draw(st.sampled_from([0.0, 0.0, 10.0])),
    )
    return knee


@st.composite
def setups(draw, knee):
    """Random roles (optional ones dropped or merged into flesh), condyle subsets, tables."""
    setup = json.loads(json.dumps(knee.setup))
    roles = setup["roles"]
    for role in OPTIONAL_ROLES:
        what = draw(st.sampled_from(["keep", "keep", "drop", "to_flesh", "to_fixed"]))
        if what == "keep" or role == "flesh":
            continue
        parts = roles[role]
        roles[role] = []
        if what == "to_flesh":
            roles["flesh"] = sorted(set(roles["flesh"]) | set(parts))
        elif what == "to_fixed":
            roles["fixed"] = sorted(set(roles["fixed"]) | set(parts))
    lm = setup["landmarks"]
    for key in ("lateral_condyle", "medial_condyle"):
        nodes = lm[key]
        keep = draw(st.integers(5, len(nodes)))
        start = draw(st.integers(0, len(nodes) - keep))
        lm[key] = nodes[start : start + keep]
    for quantity in setup["kinematics"]:
        names = ["default", *table_names(quantity), "csv"]
        setup["kinematics"][quantity] = draw(st.sampled_from(names))
    return setup


@st.composite
def tables(draw):
    """A valid kinematic table: strictly increasing flexion, finite values."""
    n = draw(st.integers(2, 8))
    steps = draw(st.lists(st.floats(1.0, 40.0), min_size=n - 1, max_size=n - 1))
    start = draw(st.floats(-20.0, 0.0))
    flex = start + np.concatenate([[0.0], np.cumsum(steps)])
    values = draw(st.lists(st.floats(-30.0, 30.0), min_size=n, max_size=n))
    return "flexion_deg,value_deg\n" + "".join(
        f"{f!r},{v!r}\n" for f, v in zip(flex, values, strict=True)
    )


@FUZZ
@given(data=st.data())
def test_random_valid_setups_pose_and_measure(tmp_path_factory, capsys, data):
    count("valid setups through pose + quality")
    knee = data.draw(knees())
    setup = data.draw(setups(knee))
    tmp = tmp_path_factory.mktemp("setup")
    for quantity, choice in setup["kinematics"].items():
        if choice == "csv":
            (tmp / f"{quantity}.csv").write_text(data.draw(tables()))
            setup["kinematics"][quantity] = f"{quantity}.csv"
    flexion = data.draw(st.floats(-10.0, 150.0))
    status, err = pose_and_quality(
        tmp, capsys, knee.model, setup, flexion, smooth=data.draw(st.booleans())
    )
    # a valid setup poses (exit 0, or 3 when the result fails the quality gate); an error is
    # only acceptable for geometry the setup cannot describe, and must say what
    assert status in (0, 3) or "kneegui: " in err


# ------------------------------------------------------------------ damaged meshes
def _append_block(model: Model, etype: str, pid: int, coords: np.ndarray, conn: np.ndarray):
    """A model with extra nodes and one more element block of ``etype``."""
    n0 = model.n_nodes
    node_ids = np.concatenate([model.node_ids, model.node_ids.max() + 1 + np.arange(len(coords))])
    blocks = dict(model.blocks)
    eid0 = max(int(b.ids.max()) for b in blocks.values()) + 1
    new = ElementBlock(etype, eid0 + np.arange(len(conn)), np.full(len(conn), pid), conn + n0)
    if etype in blocks:
        old = blocks[etype]
        new = ElementBlock(
            etype,
            np.concatenate([old.ids, new.ids]),
            np.concatenate([old.part_ids, new.part_ids]),
            np.concatenate([old.conn, new.conn]),
        )
    blocks[etype] = new
    return Model(
        node_ids, np.concatenate([model.coords, coords]), blocks, model.parts, model.node_sets
    )


UNIT_HEX = np.array(
    [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)], float
)


@st.composite
def damages(draw):
    kinds = st.sampled_from(
        ["collapse", "flatten", "coincident", "island", "island_in_bone", "sliver", "far_node"]
    )
    return draw(st.lists(st.tuples(kinds, st.integers(0, 10**6), st.floats(0, 1)), max_size=3))


def damage(model: Model, setup: dict, kind: str, pick: int, amount: float) -> Model:
    coords = model.coords.copy()
    hexes = model.blocks["hex8"]
    soft = [p for r in SOFT_ROLES for p in setup["roles"][r]] or [501]
    if kind == "collapse":  # one element squashed to a point
        row = hexes.conn[pick % len(hexes)]
        coords[row] = coords[row].mean(axis=0)
    elif kind == "flatten":  # near-degenerate: top face pressed onto the bottom face
        row = hexes.conn[pick % len(hexes)]
        coords[row[4:]] = coords[row[:4]] + amount * 1e-9
    elif kind == "coincident":  # two distinct nodes at one place
        a, b = pick % model.n_nodes, (pick * 7919 + 1) % model.n_nodes
        coords[b] = coords[a]
    elif kind == "sliver":  # one node moved far through its element
        row = hexes.conn[pick % len(hexes)]
        coords[row[0]] = coords[row[6]] + (coords[row[6]] - coords[row[0]]) * (1 + 5 * amount)
    elif kind == "far_node":
        coords[pick % model.n_nodes] += 1e5 * (amount + 0.01)
    model = model.with_coords(coords)
    if kind in ("island", "island_in_bone"):  # a disconnected piece in a soft or a bone part
        pid = soft[pick % len(soft)] if kind == "island" else setup["roles"]["femur"][0]
        where = model.coords.min(axis=0) - 500.0 * (1 + amount)
        size = 1e-6 if amount < 0.2 else 5.0
        model = _append_block(model, "hex8", pid, where + UNIT_HEX * size, np.arange(8)[None, :])
    return model


@FUZZ
@given(data=st.data())
def test_damaged_meshes_pose_and_measure(tmp_path_factory, capsys, data):
    count("damaged meshes through pose + quality")
    knee = build_synthetic_knee(side=data.draw(st.sampled_from(["right", "left"])))
    setup = knee.setup
    model = knee.model
    for kind, pick, amount in data.draw(damages()):
        model = damage(model, setup, kind, pick, amount)
    flexion = data.draw(st.floats(-10.0, 150.0))
    pose_and_quality(
        tmp_path_factory.mktemp("damaged"), capsys, model, setup, flexion, data.draw(st.booleans())
    )


@pytest.fixture(scope="module")
def demo_leg():
    demo = pytest.importorskip("kneegui.demo")
    return demo.generate_demo_leg(2000)


@settings(max_examples=2, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_demo_leg_with_damage_poses_or_says_why(tmp_path_factory, capsys, demo_leg, data):
    count("demo leg (2,000 elements) damaged, through pose + quality")
    model = demo_leg.model
    for kind, pick, amount in data.draw(damages()):
        model = damage(model, json.loads(json.dumps(demo_leg.setup)), kind, pick, amount)
    pose_and_quality(
        tmp_path_factory.mktemp("demo"),
        capsys,
        model,
        demo_leg.setup,
        data.draw(st.sampled_from([0.0, 45.0, 90.0, 130.0])),
        smooth=False,
    )


# ------------------------------------------------------------------ regressions found by the fuzz
def test_setup_without_skin_parts_poses(tmp_path, capsys):
    """Found by the fuzz: with no skin part the relaxation's shell-to-solid matching got zero
    shells and raised ValueError from numpy ("need at least one array to concatenate")."""
    knee = build_synthetic_knee()
    setup = json.loads(json.dumps(knee.setup))
    setup["roles"]["skin"] = []
    status, err = pose_and_quality(tmp_path, capsys, knee.model, setup, 0.0, smooth=False)
    assert status in (0, 3), err


def test_coincident_nodes_in_the_relaxed_tissue_give_a_clear_error(tmp_path, capsys):
    """Found by the fuzz: two nodes made coincident flatten an element the relaxation must
    move; the quality optimiser then raised a bare ValueError out of the CLI."""
    knee = build_synthetic_knee()
    model = damage(knee.model, knee.setup, "coincident", 6981, 0.0)
    status, err = pose_and_quality(tmp_path, capsys, model, knee.setup, 0.0, smooth=False)
    assert status == 2 and "cannot untangle" in err and "coincident nodes" in err


def test_a_far_femur_node_does_not_break_the_patella_seating(tmp_path, capsys):
    """Found by the fuzz: with one femur node moved 1 m away, a regula falsi step of the patella
    seating divided -inf by -inf and queried the bone surface at NaN (scipy ValueError)."""
    knee = build_synthetic_knee()
    model = knee.model
    for kind, pick, amount in [("island", 0, 0.99), ("far_node", 2799, 0.0)]:
        model = damage(model, knee.setup, kind, pick, amount)
    status, err = pose_and_quality(tmp_path, capsys, model, knee.setup, 9.0, smooth=False)
    assert status == 3, err  # posed; the input's inverted elements fail the quality gate
