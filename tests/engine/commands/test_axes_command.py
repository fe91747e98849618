"""``kneegui axes MODEL --setup S.json [--json]`` on a deck written by the project's writer."""

from __future__ import annotations

import copy
import json

import pytest

from kneegui.cli import main
from kneegui.io import lsdyna
from kneegui.setup import save_setup
from kneegui.setup.synthetic import build_synthetic_knee, random_rotation


@pytest.fixture(scope="module")
def deck(tmp_path_factory):
    folder = tmp_path_factory.mktemp("axes")
    knee = build_synthetic_knee(side="left", rotation=random_rotation(3), flexion_deg=12.0)
    lsdyna.write_model(knee.model, folder / "knee.k")
    save_setup(knee.setup, folder / "knee.setup.json")
    return folder, knee


def test_axes_json(deck, capsys):
    folder, _knee = deck
    code = main(
        ["axes", str(folder / "knee.k"), "--setup", str(folder / "knee.setup.json"), "--json"]
    )
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert out["lateral_radius"] == pytest.approx(20.5, abs=1e-4)
    assert out["medial_radius"] == pytest.approx(23.3, abs=1e-4)
    assert out["lateral_rms"] < 1e-3 and out["medial_rms"] < 1e-3
    assert out["initial_flexion"] == pytest.approx(12.0, abs=1e-3)
    for key in ("fe_axis", "lr_axis"):
        assert set(out[key]) == {"point", "direction"}
        assert sum(v * v for v in out[key]["direction"]) == pytest.approx(1.0)
    assert out["side"] == "left"
    # exact circles: the axis does not depend on which nodes are left out
    spread = out["sensitivity"]
    assert spread["direction_spread_deg"] < 1e-4
    assert spread["n_subsets"] == 200 and spread["leave_out_fraction"] == 0.2


def test_axes_text(deck, capsys):
    folder, _knee = deck
    assert main(["axes", str(folder / "knee.k"), "--setup", str(folder / "knee.setup.json")]) == 0
    text = capsys.readouterr().out
    assert "lateral condyle: radius 20.50 mm" in text
    assert "medial condyle:  radius 23.30 mm" in text
    assert "initial flexion: 12.00 deg" in text
    assert "F-E axis (GCA)" in text and "L-R axis" in text
    assert "F-E axis spread: 0.00 deg" in text and "over 200 fits" in text


def test_bad_setup_exits_2(deck, capsys, tmp_path):
    folder, knee = deck
    data = copy.deepcopy(knee.setup)
    data["roles"]["femur"] = [4242]
    bad = save_setup(data, tmp_path / "bad.json")
    assert main(["axes", str(folder / "knee.k"), "--setup", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.strip() == f"kneegui: {bad}: roles.femur: unknown part id 4242"


def test_suggest_writes_a_valid_setup(deck, capsys, tmp_path):
    folder, _knee = deck
    out = tmp_path / "suggested.json"
    assert (
        main(["axes", str(folder / "knee.k"), "--suggest", str(out), "--side", "left", "--json"])
        == 0
    )
    result = json.loads(capsys.readouterr().out)
    assert result["lateral_radius"] == pytest.approx(20.5, abs=0.05)
    assert result["medial_radius"] == pytest.approx(23.3, abs=0.05)
    assert result["initial_flexion"] == pytest.approx(12.0, abs=0.5)
    data = json.loads(out.read_text())
    assert data["side"] == "left" and data["roles"]["femur"] == [101, 102]
    # the written file is reusable
    assert main(["axes", str(folder / "knee.k"), "--setup", str(out)]) == 0


def test_suggest_needs_a_side(deck, capsys, tmp_path):
    folder, _ = deck
    assert main(["axes", str(folder / "knee.k"), "--suggest", str(tmp_path / "s.json")]) == 2
    assert "--suggest needs --side" in capsys.readouterr().err
    assert not (tmp_path / "s.json").exists()


def test_unstable_spread_is_said_so():
    from kneegui.commands.axes import format_sensitivity

    spread = {
        "direction_spread_deg": None,
        "percentile": 95.0,
        "n_subsets": 200,
        "leave_out_fraction": 0.2,
        "failed_subsets": 40,
    }
    line = format_sensitivity(spread)
    assert line.startswith("F-E axis spread: unstable") and "40 gave no determined circle" in line
    assert "not measured" in format_sensitivity(None)
