"""Writing several posed decks side by side never changes another deck's files (issue #22)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from kneegui.cli import main as cli
from kneegui.errors import OutputConflictError
from kneegui.io.lsdyna import read_deck, write_deck
from kneegui.io.output_plan import check_distinct_targets, plan_writes

CUBE = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
HEX = "       1       1       1       2       3       4       5       6       7       8\n"


def deck_with_includes(folder: Path) -> Path:
    """main.k with its nodes in inc/nodes.k and its part in inc/parts.k (never moved)."""
    (folder / "inc").mkdir(parents=True)
    main = folder / "main.k"
    main.write_text(
        "*KEYWORD\n*INCLUDE\ninc/nodes.k\ninc/parts.k\n*ELEMENT_SOLID\n" + HEX + "*END\n"
    )
    (folder / "inc" / "nodes.k").write_text(
        "*KEYWORD\n*NODE\n"
        + "".join(f"{i:8d}{x:16.4f}{y:16.4f}{z:16.4f}\n" for i, (x, y, z) in enumerate(CUBE, 1))
        + "*END\n"
    )
    (folder / "inc" / "parts.k").write_text("*PART\ncube\n         1         1         1\n")
    return main


def test_second_posed_deck_in_one_folder_does_not_change_the_first(tmp_path):
    model = read_deck(deck_with_includes(tmp_path / "in"))
    out = tmp_path / "out"
    at60 = model.with_coords(model.coords + 60.0)
    at90 = model.with_coords(model.coords + 90.0)
    write_deck(at60, out / "posed60.k")
    first = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with pytest.raises(OutputConflictError, match=r"inc/nodes\.k") as err:
        write_deck(at90, out / "posed90.k")
    assert "--force" in str(err.value) and "--flatten" in str(err.value)
    assert not (out / "posed90.k").exists()
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == first
    np.testing.assert_allclose(read_deck(out / "posed60.k").coords, at60.coords)
    # the include whose bytes do not change (parts.k) is shared, not a conflict: flattened or
    # with --force the second deck is written
    write_deck(at90, out / "posed90_flat.k", flatten=True)
    np.testing.assert_allclose(read_deck(out / "posed90_flat.k").coords, at90.coords)
    write_deck(at90, out / "posed90.k", overwrite=True)
    np.testing.assert_allclose(read_deck(out / "posed90.k").coords, at90.coords)


def test_rewriting_the_same_deck_is_allowed_and_unmoved_includes_stay_untouched(tmp_path):
    model = read_deck(deck_with_includes(tmp_path / "in"))
    out = tmp_path / "out" / "posed.k"
    write_deck(model.with_coords(model.coords + 1.0), out)
    parts = out.parent / "inc" / "parts.k"
    stamp = parts.stat().st_mtime_ns
    # the named file may be replaced; the identical include is left as it is
    write_deck(model.with_coords(model.coords + 1.0), out)
    assert parts.stat().st_mtime_ns == stamp
    # a different pose to the same name changes nodes.k: refused without --force
    with pytest.raises(OutputConflictError, match=r"nodes\.k"):
        write_deck(model.with_coords(model.coords + 2.0), out)


def test_include_named_like_the_output_is_refused(tmp_path):
    folder = tmp_path / "in"
    main = deck_with_includes(folder)
    main.write_text(main.read_text().replace("inc/nodes.k", "posed.k"))
    (folder / "inc" / "nodes.k").rename(folder / "posed.k")
    model = read_deck(main)
    with pytest.raises(OutputConflictError, match="two files of the deck"):
        write_deck(model.with_coords(model.coords + 1.0), tmp_path / "o" / "posed.k")
    assert not (tmp_path / "o").exists()


def test_plan_refuses_inputs_and_existing_unnamed_files(tmp_path):
    existing = tmp_path / "x.k"
    existing.write_bytes(b"old")
    named = tmp_path / "main.k"
    named.write_bytes(b"older")
    files = {named: b"new main", existing: b"new"}
    with pytest.raises(OutputConflictError, match=r"x\.k"):
        plan_writes(files, named)
    assert plan_writes(files, named, overwrite=True) == files
    with pytest.raises(OutputConflictError, match="input"):
        plan_writes(files, named, inputs=[named], overwrite=True)
    assert plan_writes({named: b"n", existing: b"old"}, named) == {named: b"n"}
    with pytest.raises(OutputConflictError, match="same file"):
        check_distinct_targets([tmp_path / "a" / ".." / "x.k", existing])


def test_cli_convert_and_pose_refuse_and_force_overwrites(tmp_path, capsys):
    main = deck_with_includes(tmp_path / "in")
    out = tmp_path / "out"
    assert cli(["convert", str(main), "--out", str(out / "a.k")]) == 0
    (out / "inc" / "nodes.k").write_text("*NODE\n       1             9.0\n")  # someone's file
    assert cli(["convert", str(main), "--out", str(out / "b.k")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "nodes.k" in err and "--force" in err
    assert (out / "inc" / "nodes.k").read_text().startswith("*NODE\n       1             9.0")
    assert cli(["convert", str(main), "--out", str(out / "b.k"), "--force"]) == 0
    assert (out / "inc" / "nodes.k").read_bytes() == (main.parent / "inc" / "nodes.k").read_bytes()


def test_pose_with_the_same_angle_twice_is_refused_before_any_work(tmp_path, capsys):
    from kneegui.io.lsdyna import write_model
    from kneegui.setup.synthetic import build_synthetic_knee

    knee = build_synthetic_knee()
    deck = write_model(knee.model, tmp_path / "knee.k")
    setup = tmp_path / "knee.setup.json"
    setup.write_text(json.dumps(knee.setup))
    status = cli(
        [
            "pose",
            str(deck),
            "--setup",
            str(setup),
            "--flexion",
            "30",
            "30.0",
            "--out",
            str(tmp_path / "o"),
        ]
    )
    assert status == 2
    assert "same file" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
