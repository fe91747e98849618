"""Statistics, thresholds, volume change, the quality table and the CLI command."""

from __future__ import annotations

import json

import numpy as np
import pytest

from kneegui.quality import (
    compute_quality,
    format_quality_table,
    jsonable,
    load_thresholds,
    quality_gate,
    summarize_quality,
    volume_change,
)
from kneegui.quality.thresholds import ThresholdsError

ROLES = {"bone": [1], "flesh": [2], "skin": [3]}


def _distorted(model, seed=0, amplitude=0.3):
    """Interior flesh nodes moved at random (same topology)."""
    rng = np.random.default_rng(seed)
    coords = model.coords.copy()
    flesh = model.part_node_indices([2], etypes=["hex8"])
    skin = model.part_node_indices([3])
    bone = model.part_node_indices([1])
    free = np.setdiff1d(flesh, np.union1d(skin, bone))
    coords[free] += rng.uniform(-amplitude, amplitude, (len(free), 3))
    return model.with_coords(coords)


def test_summary_shape_and_numbers_by_hand(block_model):
    model = block_model(4, 4, 4)
    posed = _distorted(model, amplitude=0.35)
    q = compute_quality(posed.coords, posed.blocks)
    s = summarize_quality(posed, q, ROLES)
    assert set(s) >= {"model", "parts", "roles", "thresholds", "metrics"}
    assert set(s["parts"]) == {"1", "2", "3"} and set(s["roles"]) == {"bone", "flesh", "skin"}
    flesh_rows = np.flatnonzero(posed.blocks["hex8"].part_ids == 2)
    j = q["hex8"].jacobian_corner[flesh_rows]
    entry = s["roles"]["flesh"]["jacobian"]
    assert entry["worst"] == pytest.approx(j.min())
    assert entry["mean"] == pytest.approx(j.mean()) and entry["std"] == pytest.approx(j.std())
    assert entry["warn"] == np.count_nonzero(j < 0.6) and entry["fail"] == np.count_nonzero(j < 0.3)
    assert s["roles"]["flesh"]["inverted"] == np.count_nonzero(j <= 0)
    skew = s["parts"]["2"]["skew"]
    assert skew["worst"] == pytest.approx(q["hex8"].skew[flesh_rows].max())
    assert s["parts"]["2"]["title"] == "Flesh" and s["parts"]["2"]["role"] == "flesh"
    # bone is untouched: perfect
    assert s["roles"]["bone"]["jacobian"]["worst"] == pytest.approx(1.0)
    assert s["model"]["elements"] == len(model.blocks["hex8"]) + len(model.blocks["quad4"])
    json.dumps(jsonable(s), allow_nan=False)


def test_role_override_changes_only_that_roles_counts(block_model):
    model = block_model(4, 4, 4)
    posed = _distorted(model, amplitude=0.35)
    q = compute_quality(posed.coords, posed.blocks)
    base = load_thresholds()
    strict = base.with_override("flesh", "aspect", warn=1.01, fail=1.05)
    s0 = summarize_quality(posed, q, ROLES, base)
    s1 = summarize_quality(posed, q, ROLES, strict)
    assert s1["roles"]["flesh"]["aspect"]["warn"] > s0["roles"]["flesh"]["aspect"]["warn"]
    assert s1["roles"]["skin"]["aspect"] == s0["roles"]["skin"]["aspect"]
    assert s1["model"]["aspect"]["warn"] > s0["model"]["aspect"]["warn"]
    assert s1["thresholds"]["flesh"]["aspect"]["warn"] == 1.01
    # each element judged by its own part's role: the counts by hand
    flesh = np.isin(posed.blocks["hex8"].part_ids, ROLES["flesh"])
    aspect = q["hex8"].aspect
    assert s1["roles"]["flesh"]["aspect"]["warn"] == int(np.sum(aspect[flesh] > 1.01))
    assert s1["roles"]["flesh"]["aspect"]["fail"] == int(np.sum(aspect[flesh] > 1.05))
    default = base.default["aspect"]
    others = s1["model"]["aspect"]["warn"] - s1["roles"]["flesh"]["aspect"]["warn"]
    assert others == int(np.sum(aspect[~flesh] > default.warn)) + sum(
        int(np.sum(q[t].aspect > default.warn)) for t in q if t != "hex8"
    )


def test_volume_change_against_initial(block_model):
    model = block_model(3, 3, 3, skin=False)
    coords = model.coords.copy()
    top = coords[:, 2] == coords[:, 2].max()
    coords[top, 2] += 0.3  # top layer of elements grows by 30 %
    posed = model.with_coords(coords)
    q0 = compute_quality(model.coords, model.blocks)
    q1 = compute_quality(posed.coords, posed.blocks)
    s = summarize_quality(posed, q1, ROLES, initial=q0)
    vc = s["model"]["volume_change"]
    assert vc["max_element_pct"] == pytest.approx(30.0)
    assert vc["total_pct"] == pytest.approx(10.0)
    assert vc["max_element_id"] in posed.blocks["hex8"].ids[posed.blocks["hex8"].conn[:, 4] >= 0]
    aspect = s["model"]["aspect"]
    assert aspect["initial_worst"] == pytest.approx(1.0)
    assert aspect["worse_than_initial"] == 9
    assert quality_gate(s) == []
    v = volume_change(np.array([1.0, 2.0]), np.array([1.0, 1.0]), np.array([7, 8]))
    assert v == {"max_element_pct": 100.0, "max_element_id": 8, "total_pct": 50.0}


def test_gate_flags_inverted_and_worse_than_initial(block_model):
    model = block_model(3, 3, 3, skin=False)
    coords = model.coords.copy()
    centre = np.flatnonzero(np.all(coords == (1, 1, 2), axis=1))[0]
    coords[centre] = (1, 1, 0.8)  # pushed down through the element below
    posed = model.with_coords(coords)
    q0 = compute_quality(model.coords, model.blocks)
    q1 = compute_quality(posed.coords, posed.blocks)
    s = summarize_quality(posed, q1, initial=q0)
    reasons = quality_gate(s)
    assert s["model"]["inverted"] > 0
    assert any("inverted" in r for r in reasons) and any("Jacobian" in r for r in reasons)


def test_table_formats_worst_mean_std(block_model):
    model = block_model(3, 3, 3, skin=False)
    q = compute_quality(model.coords, model.blocks)
    s = summarize_quality(model, q, ROLES)
    text = format_quality_table({"initial": s["model"], "flesh": s["roles"]["flesh"]})
    lines = text.splitlines()
    assert lines[0].split() == ["Metric", "initial", "flesh"]
    assert any(
        line.startswith("Jacobian (corner)") and line.count("1.00 (1.00 ± 0.00)") == 2
        for line in lines
    )
    assert any(line.startswith("Elements") and line.split()[-2:] == ["27", "18"] for line in lines)


def test_thresholds_table_has_sources_and_rejects_bad_rows(tmp_path):
    t = load_thresholds()
    assert t.default["jacobian"].warn == 0.6 and t.default["jacobian"].fail == 0.3
    assert t.default["aspect"].fail == 10 and t.default["skew"].warn == 40
    assert all(th.source for th in t.default.values())
    bad = tmp_path / "bad.csv"
    bad.write_text("role,metric,direction,hard_fail,fail,warn,source\n*,jacobian,up,,1,2,x\n")
    with pytest.raises(ThresholdsError, match=r"bad\.csv:2"):
        load_thresholds(bad)
    partial = tmp_path / "partial.csv"
    partial.write_text("role,metric,direction,hard_fail,fail,warn,source\nskin,aspect,max,,9,4,x\n")
    with pytest.raises(ThresholdsError, match="no default"):
        load_thresholds(partial)


# ---------------------------------------------------------------------- kneegui quality
def _write_pair(tmp_path, block_model):
    from kneegui.io.lsdyna import write_model

    model = block_model(4, 4, 4)
    write_model(model, tmp_path / "initial.k")
    c = model.coords.copy()
    c[np.all(c == (2, 2, 2), axis=1)] = (2.3, 2.2, 1.1)  # inverts an element below
    write_model(model.with_coords(c), tmp_path / "posed.k")
    return tmp_path / "initial.k", tmp_path / "posed.k"


def test_cli_table_and_gate(tmp_path, block_model, capsys):
    from kneegui.cli import main

    initial, posed = _write_pair(tmp_path, block_model)
    assert main(["quality", str(initial)]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].split() == ["Metric", "initial.k"]
    assert "1.00 (1.00 ± 0.00)" in out
    code = main(["quality", str(posed), "--initial", str(initial), "--parts", "--gate"])
    out = capsys.readouterr().out
    assert code == 3
    assert "Inverted elements" in out and "quality gate: 1 inverted element(s)" in out
    assert main(["quality", str(posed)]) == 0  # without --gate the exit code stays 0


def test_cli_json_has_model_parts_roles(tmp_path, block_model, capsys):
    from kneegui.cli import main

    _initial, posed = _write_pair(tmp_path, block_model)
    out_file = tmp_path / "q.json"
    assert main(["quality", str(posed), "--json", "--out", str(out_file)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(out_file.read_text())
    assert set(printed) >= {"model", "parts", "roles"}
    assert set(printed["parts"]) == {"1", "2", "3"}
    for metric in ("jacobian", "aspect", "warpage", "skew"):
        assert set(printed["model"][metric]) == {"worst", "mean", "std", "warn", "fail"}
    assert printed["model"]["inverted"] == 1
    assert printed["model"]["jacobian"]["worst"] == pytest.approx(-0.4)


def test_gate_ignores_round_off_below_the_tolerance(block_model):
    """A pose at the initial angle moves nodes by round-off only: that must not fail the gate,
    while a visible loss (1e-4) still does."""
    from kneegui.quality.summary import GATE_JACOBIAN_TOLERANCE

    model = block_model(3, 3, 3, skin=False)
    q0 = compute_quality(model.coords, model.blocks)
    s = summarize_quality(model, q0, initial=q0)
    j = s["model"]["jacobian"]
    j["worst"] = j["initial_worst"] - 0.1 * GATE_JACOBIAN_TOLERANCE
    assert quality_gate(s) == []
    j["worst"] = j["initial_worst"] - 1e-4
    assert any("Jacobian" in r for r in quality_gate(s))
