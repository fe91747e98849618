"""`kneegui check`: the pre-flight summary, its JSON, and the exit codes."""

from __future__ import annotations

import json

import pytest

from kneegui import cli
from kneegui.io.lsdyna import read_deck, write_model
from kneegui.quality import jsonable
from kneegui.reposition import Repositioner
from kneegui.reposition.preflight import preflight_of
from kneegui.setup import load_setup


@pytest.fixture(scope="module")
def welded_files(welded_leg, tmp_path_factory):
    model, setup = welded_leg
    folder = tmp_path_factory.mktemp("welded")
    deck = write_model(model, folder / "welded.k")
    setup_path = folder / "welded.setup.json"
    setup_path.write_text(json.dumps(setup), encoding="utf-8")
    return deck, setup_path


def test_check_json_round_trips_the_preflight(welded_files, capsys):
    deck, setup = welded_files
    assert cli.main(["check", str(deck), "--setup", str(setup), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    model = read_deck(deck)
    expected = jsonable(preflight_of(Repositioner(model, load_setup(setup, model))).to_dict())
    printed.pop("seconds"), expected.pop("seconds")
    assert printed == expected
    locked = printed["locked"]
    assert locked["count"] == len(locked["elements"]) >= 5
    assert all(len(e["segments"]) >= 2 for e in locked["elements"])
    assert printed["coincident_pairs"]["count"] == 0
    assert printed["movable"]["nodes"] > 0


def test_check_summary_caps_the_table(welded_files, capsys):
    deck, setup = welded_files
    assert cli.main(["check", str(deck), "--setup", str(setup), "--rows", "3"]) == 0
    out = capsys.readouterr().out
    n = int(out.split("locked elements: ")[1].split()[0])
    assert n >= 5
    assert f"and {n - 3} more (--json lists them all)" in out
    rows = [line for line in out.splitlines() if "inverts at" in line or "whole range" in line]
    assert len(rows) == 3
    assert "movable region:" in out and "coincident node pairs (sliding interfaces): 0" in out


def test_check_on_the_sliding_demo(tmp_path, capsys):
    assert cli.main(["demo", str(tmp_path), "--elements", "2000"]) == 0
    capsys.readouterr()
    deck, setup = tmp_path / "demo_leg.k", tmp_path / "demo_leg.setup.json"
    assert cli.main(["check", str(deck), "--setup", str(setup)]) == 0
    out = capsys.readouterr().out
    assert "locked elements: none" in out
    pairs = int(out.split("coincident node pairs (sliding interfaces): ")[1].split()[0])
    assert pairs > 100
    assert "femur | movable" in out and "tibia | movable" in out


def test_a_bad_setup_exits_2_with_one_line(welded_files, tmp_path, capsys):
    deck, setup = welded_files
    data = json.loads(setup.read_text())
    data["roles"]["femur"] = [999999]
    bad = tmp_path / "bad.setup.json"
    bad.write_text(json.dumps(data), encoding="utf-8")
    assert cli.main(["check", str(deck), "--setup", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("kneegui: ")
