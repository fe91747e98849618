"""Tetrahedron measures (docs/quality.md): known answers, a slow re-derivation, TET10 mid-side
offsets, and their place in the summary, the Table-I text, the gate and ``kneegui quality``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from kneegui.model import ElementBlock
from kneegui.quality import (
    TET_THRESHOLD_METRICS,
    compute_quality,
    format_quality_table,
    jsonable,
    load_thresholds,
    quality_gate,
    summarize_quality,
)
from kneegui.quality.kernels import TET10_MIDSIDE

REGULAR = np.array(
    [(0, 0, 0), (1, 0, 0), (0.5, np.sqrt(3) / 2, 0), (0.5, np.sqrt(3) / 6, np.sqrt(2 / 3))]
)
TET_NAMES = ("tet_collapse", "dihedral_min", "dihedral_max", "vol_skew", "tet_aspect", "volume")
#: The six tetrahedra of a hexahedron around its diagonal 0-6 (Kuhn), all positive.
KUHN = ((0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6))


def _one(pts, etype: str = "tet4") -> dict[str, float]:
    pts = np.asarray(pts, dtype=float)
    block = ElementBlock(etype, [1], [1], [list(range(len(pts)))])
    q = compute_quality(pts, {etype: block})[etype]
    names = (*TET_NAMES, "jacobian_corner", "aspect", "midside_normal", "midside_tangent")
    out = {k: float(q.metric(k)[0]) for k in names}
    out["inverted"] = bool(q.inverted[0])
    return out


def _tet_model(block_model, nx=3, ny=3, nz=3, seed=0, amplitude=0.15):
    """A box of hexes split into Kuhn tets, interior nodes moved at random; skin quads kept."""
    from kneegui.model import Model

    box = block_model(nx, ny, nz)
    hexes = box.blocks["hex8"]
    conn = hexes.conn[:, np.array(KUHN)].reshape(-1, 4)
    part_ids = np.repeat(hexes.part_ids, len(KUHN))
    blocks = {"tet4": ElementBlock("tet4", np.arange(1, len(conn) + 1), part_ids, conn)}
    quads = box.blocks["quad4"]
    blocks["quad4"] = ElementBlock("quad4", quads.ids + len(conn), quads.part_ids, quads.conn)
    coords = box.coords.copy()
    lo, hi = coords.min(0), coords.max(0)
    interior = np.all((coords > lo) & (coords < hi), axis=1)
    rng = np.random.default_rng(seed)
    coords[interior] += rng.uniform(-amplitude, amplitude, (interior.sum(), 3))
    return Model(box.node_ids, coords, blocks, box.parts)


# ---------------------------------------------------------------------- known answers
def test_regular_tet():
    r = _one(REGULAR)
    assert r["tet_collapse"] == pytest.approx(1.0, abs=1e-12)
    assert r["dihedral_min"] == pytest.approx(np.degrees(np.arccos(1 / 3)), abs=1e-9)
    assert r["dihedral_max"] == pytest.approx(70.5288, abs=1e-4)
    assert r["vol_skew"] == pytest.approx(0.0, abs=1e-12)
    assert r["tet_aspect"] == pytest.approx(1.0, abs=1e-12)
    assert r["jacobian_corner"] == 1.0 and not r["inverted"]


def test_measures_do_not_depend_on_size_position_or_node_numbering():
    base = _one(REGULAR)
    tilted = REGULAR * 37.0 + (5.0, -3.0, 2.0)
    for order in ((0, 1, 2, 3), (1, 2, 0, 3), (3, 1, 0, 2)):  # even permutations keep the sign
        r = _one(tilted[list(order)])
        for k in ("tet_collapse", "dihedral_min", "dihedral_max", "vol_skew", "tet_aspect"):
            assert r[k] == pytest.approx(base[k], abs=1e-9), (order, k)


# LaGriT's table of characteristic bad tets (lagrit.lanl.gov, QUALITY_sliver_cap_needle_wedge):
# coordinates and their published min / max dihedral angles (degrees, six digits).
LAGRIT = {
    "sliver": ([(1, 0, 0.1), (-1, 0, 0.1), (0, 1, -0.1), (0, -1, -0.1)], 15.9424, 157.380),
    "cap": ([(1, 0, 0), (1, 1, 0), (0, 0, 0), (0.75, 0.25, 0.1)], 15.7932, 149.550),
    "needle": ([(0.1, -0.1, 0), (0.1, 0.1, 0), (-0.1, 0, 0), (0, 0, 1)], 53.3585, 87.4394),
    "wedge": ([(1, 0, 0), (-1, 0, 0), (0, 1, 0.1), (0, 1, -0.1)], 11.4212, 90.0),
}


@pytest.mark.parametrize("name", LAGRIT)
def test_dihedral_angles_of_lagrits_sliver_cap_needle_wedge(name):
    pts, lo, hi = LAGRIT[name]
    r = _one(pts)
    assert r["dihedral_min"] == pytest.approx(lo, abs=2e-4)
    assert r["dihedral_max"] == pytest.approx(hi, abs=2e-3)
    # each is a poor tet by the other measures too (regular: collapse 1, skew 0, aspect 1)
    assert r["tet_collapse"] < 0.5 and r["vol_skew"] > 0.7 and r["tet_aspect"] > 4


@pytest.mark.parametrize("t", [1.0, 0.5, 0.1, 0.01])
def test_regular_tet_with_its_apex_lowered(t):
    """Apex at fraction t of the regular height over the base centroid (a cap as t -> 0).

    The base stays the largest face for t <= 1, so the collapse is h / sqrt(A_base) / 1.2408
    = t exactly; the base edges carry the smallest dihedral, atan(h / inradius) = atan(2 sqrt2
    t); the shortest altitude is the apex's, so the tet aspect is 1 / t."""
    pts = REGULAR.copy()
    pts[3, 2] *= t
    r = _one(pts)
    assert r["tet_collapse"] == pytest.approx(t, rel=1e-12)
    assert r["dihedral_min"] == pytest.approx(np.degrees(np.arctan(2 * np.sqrt(2) * t)), abs=1e-9)
    assert r["tet_aspect"] == pytest.approx(1 / t, rel=1e-12)
    if t < 0.05:
        assert r["dihedral_max"] > 170 and r["vol_skew"] > 0.999


def test_flat_tet_on_a_square():
    """Four nodes of a square: zero volume, dihedrals 0 and 180, skew 1, aspect inf."""
    r = _one([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    assert r["tet_collapse"] == 0.0 and r["vol_skew"] == 1.0 and r["tet_aspect"] == np.inf
    assert r["dihedral_min"] == pytest.approx(0.0, abs=1e-6)
    assert r["dihedral_max"] == pytest.approx(180.0, abs=1e-6)
    assert r["inverted"]


def test_near_flat_sliver_has_both_extreme_dihedrals():
    """A sliver: four nodes near one plane on a square (the design note's reference case)."""
    r = _one([(0, 0, 0), (1, 0, 0), (1, 1, -0.01), (0, 1, 0)])
    assert 0 < r["dihedral_min"] < 2 and 178 < r["dihedral_max"] < 180
    assert 0 < r["tet_collapse"] < 0.02 and r["vol_skew"] > 0.99
    # yet every face is a good triangle: the face aspect ratio sees nothing
    assert r["aspect"] < 1.5


def test_inverted_tet_is_signed_by_collapse_and_skew_only():
    mirrored = REGULAR[[1, 0, 2, 3]]
    r = _one(mirrored)
    assert r["inverted"] and r["jacobian_corner"] == -1.0
    assert r["tet_collapse"] == pytest.approx(-1.0, abs=1e-12)
    assert r["vol_skew"] == pytest.approx(2.0, abs=1e-12)  # 1 - V / V_ideal with V < 0
    assert r["dihedral_min"] == pytest.approx(70.5288, abs=1e-4)
    assert r["tet_aspect"] == pytest.approx(1.0, abs=1e-12)


def _slow_reference(p: np.ndarray) -> dict[str, float]:
    """Each measure from its literal definition, one tet at a time."""
    volume = np.dot(np.cross(p[1] - p[0], p[2] - p[0]), p[3] - p[0]) / 6
    ratios, altitudes = [], []
    for i in range(4):
        a, b, c = (p[j] for j in range(4) if j != i)
        n = np.cross(b - a, c - a)
        area = np.linalg.norm(n) / 2
        height = np.dot(p[i] - a, n / np.linalg.norm(n))  # signed: + on the side of n
        altitudes.append(abs(height))
        ratios.append(abs(height) / np.sqrt(area))
    collapse = np.sign(volume) * min(ratios) / (np.sqrt(2 / 3) / np.sqrt(np.sqrt(3) / 4))
    angles = []
    for i in range(4):
        for j in range(i + 1, 4):
            k, m = (x for x in range(4) if x not in (i, j))
            edge = p[j] - p[i]
            edge /= np.linalg.norm(edge)
            u = p[k] - p[i] - np.dot(p[k] - p[i], edge) * edge
            w = p[m] - p[i] - np.dot(p[m] - p[i], edge) * edge
            cos = np.dot(u, w) / np.linalg.norm(u) / np.linalg.norm(w)
            angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    # circumcentre: |x - p_i|^2 equal for all i
    A = 2 * (p[1:] - p[0])
    rhs = (p[1:] ** 2).sum(1) - (p[0] ** 2).sum()
    centre = np.linalg.solve(A, rhs)
    radius = np.linalg.norm(centre - p[0])
    edges = [np.linalg.norm(p[j] - p[i]) for i in range(4) for j in range(i + 1, 4)]
    return {
        "tet_collapse": collapse,
        "dihedral_min": min(angles),
        "dihedral_max": max(angles),
        "vol_skew": 1 - volume / (8 * radius**3 / (9 * np.sqrt(3))),
        "tet_aspect": max(edges) / min(altitudes) / np.sqrt(1.5),
    }


def test_vectorised_measures_equal_the_literal_definitions_on_random_tets():
    rng = np.random.default_rng(7)
    pts = rng.normal(size=(300, 4, 3))
    pts[:100, 3] = pts[:100, :3].mean(1) + 0.05 * rng.normal(size=(100, 3))  # flattish ones
    conn = np.arange(1200).reshape(300, 4)
    block = ElementBlock("tet4", np.arange(1, 301), np.ones(300, int), conn)
    q = compute_quality(pts.reshape(-1, 3), {"tet4": block})["tet4"]
    for e in range(300):
        ref = _slow_reference(pts[e])
        for k, v in ref.items():
            assert q.metric(k)[e] == pytest.approx(v, rel=1e-8, abs=1e-8), (e, k)
    assert (q.tet_collapse < 0).sum() == (q.volume < 0).sum() > 0  # random tets: both signs


# ---------------------------------------------------------------------- 10-node tets
def _tet10(corners: np.ndarray) -> np.ndarray:
    pts = np.zeros((10, 3))
    pts[:4] = corners
    for i, j, k in TET10_MIDSIDE:
        pts[k] = 0.5 * (corners[i] + corners[j])
    return pts


def test_tet10_shape_measures_are_the_corner_tets_and_centred_nodes_have_no_offset():
    corners = np.array(LAGRIT["sliver"][0], dtype=float)
    r10 = _one(_tet10(corners), "tet10")
    r4 = _one(corners)
    for k in TET_NAMES:
        assert r10[k] == r4[k]
    assert r10["midside_normal"] == pytest.approx(0, abs=1e-15)
    assert r10["midside_tangent"] == pytest.approx(0, abs=1e-15)
    assert np.isnan(r4["midside_normal"])  # a linear tet has no mid-side nodes


def test_tet10_displaced_mid_side_node():
    pts = _tet10(REGULAR)  # all edges of length 1
    edge = REGULAR[1] - REGULAR[0]
    moved = pts.copy()
    moved[4] = REGULAR[0] + 0.75 * edge  # node 4 (edge 0-1) to the quarter point near node 1
    r = _one(moved, "tet10")
    assert r["midside_tangent"] == pytest.approx(0.25, abs=1e-12)
    assert r["midside_normal"] == pytest.approx(0.0, abs=1e-12)
    normal = np.cross(edge, REGULAR[2] - REGULAR[0])
    moved = pts.copy()
    moved[9] += 0.1 * normal / np.linalg.norm(normal)  # node 9 (edge 2-3) off its edge
    r = _one(moved, "tet10")
    offset_normal = 0.1 * np.linalg.norm(
        np.cross(normal / np.linalg.norm(normal), REGULAR[3] - REGULAR[2])
    )
    assert r["midside_normal"] == pytest.approx(offset_normal, rel=1e-12)
    assert r["tet_collapse"] == pytest.approx(1.0, abs=1e-12)  # corners unchanged
    thresholds = load_thresholds().default
    assert r["midside_normal"] < thresholds["midside_normal"].warn  # 0.082 < 0.30
    moved[9] = pts[9] + 0.4 * (REGULAR[3] - REGULAR[2])  # 0.4 of the edge toward node 3
    assert _one(moved, "tet10")["midside_tangent"] > thresholds["midside_tangent"].hard_fail


# ---------------------------------------------------------------------- summary, table, gate
def test_hex_deck_summary_has_no_tet_measures(block_model):
    model = block_model(3, 3, 3)
    s = summarize_quality(model, compute_quality(model.coords, model.blocks))
    assert s["metrics"] == ["jacobian", "jacobian_gauss", "aspect", "warpage", "skew"]
    assert (
        not set(TET_THRESHOLD_METRICS) & set(s["model"])
        and "tet_collapse" not in s["thresholds"]["*"]
    )
    table = format_quality_table({"model": s["model"]})
    assert [line.split("  ")[0] for line in table.splitlines()[2:6]] == [
        "Jacobian (corner)",
        "Aspect ratio",
        "Warpage (deg)",
        "Skew (deg)",
    ]
    assert "Tet" not in table and "tet" not in table


def test_tet_summary_counts_only_tets_and_uses_their_thresholds(block_model):
    model = _tet_model(block_model)
    q = compute_quality(model.coords, model.blocks)
    s = summarize_quality(model, q, {"flesh": [2], "skin": [3]})
    assert s["metrics"][5:] == list(TET_THRESHOLD_METRICS[:5])  # no tet10: no mid-side offsets
    collapse = q["tet4"].tet_collapse
    entry = s["model"]["tet_collapse"]
    assert entry["worst"] == pytest.approx(collapse.min())
    assert entry["mean"] == pytest.approx(collapse.mean())  # the skin quads are not counted
    assert entry["warn"] == np.count_nonzero(collapse < 0.2)
    assert s["roles"]["skin"]["tet_collapse"]["worst"] is None  # shells only
    assert s["model"]["dihedral_max"]["worst"] == pytest.approx(q["tet4"].dihedral_max.max())
    assert 0 < collapse.min() < collapse.max() < 1  # the box is perturbed: a spread of values
    table = format_quality_table({"model": s["model"], "skin": s["roles"]["skin"]})
    assert "Tet collapse" in table and "Over warn / fail (tet collapse)" in table
    row = next(line for line in table.splitlines() if line.startswith("Tet collapse"))
    assert f"{collapse.min():.2f}" in row and "n/a" in row
    json.dumps(s["thresholds"])


def test_gate_fails_a_worse_tet_collapse_and_passes_round_off(block_model):
    initial = _tet_model(block_model)
    q0 = compute_quality(initial.coords, initial.blocks)
    # round-off of a pose at the initial angle: passes
    jitter = initial.with_coords(initial.coords + 1e-10)
    s = summarize_quality(jitter, compute_quality(jitter.coords, jitter.blocks), initial=q0)
    assert quality_gate(s) == []
    # one interior node pushed toward an opposite face: its worst tet flattens, none inverts
    coords = initial.coords.copy()
    tets = initial.blocks["tet4"]
    e = int(np.argmin(q0["tet4"].tet_collapse))
    lo, hi = initial.coords.min(0), initial.coords.max(0)
    node = next(n for n in tets.conn[e] if np.all((coords[n] > lo) & (coords[n] < hi)))
    others = [coords[i] for i in tets.conn[e] if i != node]
    normal = np.cross(others[1] - others[0], others[2] - others[0])
    normal /= np.linalg.norm(normal)
    height = np.dot(coords[node] - others[0], normal)
    coords[node] -= 0.5 * height * normal  # halve its height over the opposite face
    posed = initial.with_coords(coords)
    q1 = compute_quality(posed.coords, posed.blocks)
    s = summarize_quality(posed, q1, initial=q0)
    assert s["model"]["inverted"] == 0
    assert s["model"]["tet_collapse"]["worst"] < 0.9 * s["model"]["tet_collapse"]["initial_worst"]
    reasons = quality_gate(s)
    assert any("tet collapse" in r and "below the initial" in r for r in reasons), reasons
    assert not any("Jacobian" in r for r in reasons)  # a tet's Jacobian cannot see it


def test_thresholds_table_without_tet_rows_takes_the_shipped_ones(tmp_path):
    shipped = load_thresholds()
    for m in TET_THRESHOLD_METRICS:
        t = shipped.default[m]
        assert t.source and t.fail != t.warn
        assert t.worse_than(np.array([t.fail]), t.warn)[0]  # fail is beyond warn
    lines = tmp_path / "t.csv"
    text = [
        "role,metric,direction,hard_fail,fail,warn,source",
        "*,jacobian,min,0,0.2,0.5,a",
        "*,jacobian_gauss,min,0,0.2,0.5,a",
        "*,aspect,max,,12,6,a",
        "*,warpage,max,,30,15,a",
        "*,skew,max,,60,40,a",
    ]
    lines.write_text("\n".join(text) + "\n", encoding="utf-8")
    table = load_thresholds(lines)
    assert table.default["jacobian"].fail == 0.2
    assert table.default["tet_collapse"] == shipped.default["tet_collapse"]


def test_cli_quality_on_a_tet_deck(tmp_path, block_model, capsys):
    from kneegui.cli import main
    from kneegui.io.lsdyna import write_model

    model = _tet_model(block_model)
    deck = write_model(model, tmp_path / "tets.k")
    assert main(["quality", str(deck), "--parts"]) == 0
    out = capsys.readouterr().out
    assert "Tet collapse" in out and "Tet min dihedral (deg)" in out and "TC " in out
    assert main(["quality", str(deck), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    worst = compute_quality(model.coords, model.blocks)["tet4"].tet_collapse.min()
    assert data["model"]["tet_collapse"]["worst"] == pytest.approx(worst, abs=1e-6)


def test_the_model_statistics_read_in_place_equal_those_over_an_index_of_every_element(
    block_model,
):
    """The model's group reads the flat arrays in place (a whole-body model's are hundreds of
    MB); a role over every part takes the indexed path: the same figures, tets and shells
    mixed, per-role limits, an infinite aspect and the initial pose included."""
    model = _tet_model(block_model)
    initial = compute_quality(model.coords, model.blocks)
    coords = model.coords.copy()
    tet = model.blocks["tet4"].conn[0]
    coords[tet[1]] = coords[tet[0]]  # a collapsed tet: infinite aspect
    q = compute_quality(coords, model.blocks)
    assert not np.isfinite(q["tet4"].tet_aspect).all()
    s = summarize_quality(
        model.with_coords(coords), q, {"flesh": [2], "skin": [3], "all": [1, 2, 3]}, initial=initial
    )
    everything = dict(s["roles"]["all"])
    del everything["part_ids"]
    assert json.dumps(jsonable(everything), sort_keys=True) == json.dumps(
        jsonable(s["model"]), sort_keys=True
    )
    assert s["model"]["elements"] == sum(len(b) for b in model.blocks.values())
