"""Plan files: expansion into postures, and one clear ``plan.toml:LINE`` error per mistake."""

from __future__ import annotations

import subprocess
import sys
import tomllib

import pytest

from kneegui.batch.plan import key_lines, load_plan
from kneegui.errors import KneeguiError, PlanError


@pytest.fixture
def files(tmp_path):
    """A deck and a setup file (contents are not read by the plan check)."""
    (tmp_path / "leg.k").write_text("*KEYWORD\n*END\n")
    (tmp_path / "leg.setup.json").write_text("{}\n")
    return tmp_path


def plan_text(body: str, defaults: str = "") -> str:
    return f"""[output]
folder = "out"
{defaults}
[[deck]]
deck = "leg.k"
setup = "leg.setup.json"
{body}
"""


def load(files, text: str):
    path = files / "plan.toml"
    path.write_text(text)
    return load_plan(path)


def error_of(files, text: str) -> PlanError:
    with pytest.raises(PlanError) as info:
        load(files, text)
    return info.value


def test_a_plan_expands_into_one_posture_per_deck_table_and_angle(files):
    plan = load(
        files,
        plan_text(
            "flexion = [10, {from = 30, to = 90, step = 30}, 37.5]\n"
            'kinematics = [{}, {tibial_rotation = "asano2001"}, '
            '{name = "flat", patellar_tilt = "none"}]\n'
            "smooth = false\n"
        ),
    )
    assert plan.out == (files / "out").resolve()
    assert len(plan.postures) == 3 * 5
    ids = [p.id for p in plan.postures]
    assert ids[:5] == [f"leg/setup/flex_{t}" for t in ("10", "30", "60", "90", "37p5")]
    assert "leg/asano2001/flex_60" in ids and "leg/flat/flex_90" in ids
    p = plan.postures[5]
    assert p.kinematics == (("tibial_rotation", "asano2001"),)
    assert p.deck_out == files.resolve() / "out/leg/asano2001/flex_10/leg.k"
    assert p.report_out.name == "report.json"
    assert not p.options.smooth and p.options.relax


def test_key_lines_finds_keys_headers_and_array_items():
    text = """# c
[output]
folder = "o"  # x

[[deck]]
name = "a"
flexion = [
  10,   # first
  {from = 20, to = 40, step = 10},
]
kinematics = [{}, {"tibial_rotation" = 'x.csv', patellar_tilt = "none"}]

[[deck]]
s = \"\"\"two
lines\"\"\"
flexion = 5
"""
    tomllib.loads(text)
    lines = key_lines(text)
    assert lines[("output", "folder")] == 3
    assert lines[("deck", 0)] == 5 and lines[("deck", 1)] == 13
    assert lines[("deck", 0, "flexion", 0)] == 8
    assert lines[("deck", 0, "flexion", 1, "step")] == 9
    assert lines[("deck", 0, "kinematics", 1, "patellar_tilt")] == 11
    assert lines[("deck", 1, "flexion")] == 16


@pytest.mark.parametrize(
    ("body", "line", "words"),
    [
        ("flexion = [10, 20\n", 7, "TOML syntax: Unclosed array"),
        ("flexion = [10]\nsmooth = 1\n", 8, "deck[0].smooth: expected bool"),
        ("flexion = [10]\nmoothing = true\n", 8, "deck[0].moothing: unknown key"),
        ("flexion = [10,\n  200]\n", 8, "deck[0].flexion[1]: flexion 200 deg is outside"),
        ("flexion = [{from = 0, to = 90}]\n", 7, "missing step"),
        (
            'flexion = [10]\nkinematics = [\n  {},\n  {tibial_rotation = "walker"},\n]\n',
            10,
            "deck[0].kinematics[1].tibial_rotation: unknown table 'walker' (shipped: default,",
        ),
        (
            'flexion = [10]\nkinematics = [{}, {patellar_tilt = "missing.csv"}]\n',
            8,
            "table file 'missing.csv' not found",
        ),
        (
            "flexion = [10,\n 30,\n 10.0]\n",
            9,
            "deck[0].flexion[2]: posture leg/setup/flex_10 writes",
        ),
        ('flexion = [10]\nmethod = "rigid"\n', 8, "unknown method 'rigid'"),
    ],
)
def test_a_bad_plan_names_the_file_line_and_key(files, body, line, words):
    err = error_of(files, plan_text(body))
    assert str(err).startswith(f"{files / 'plan.toml'}:{line}: "), str(err)
    assert words in str(err)


def test_missing_files_and_repeated_decks_are_plan_errors(files):
    err = error_of(files, plan_text("flexion = 10\n").replace("leg.setup.json", "nope.json"))
    assert str(err).startswith(f"{files / 'plan.toml'}:6: deck[0].setup: file not found")
    twice = plan_text("flexion = 10\n") + '\n[[deck]]\ndeck = "leg.k"\nsetup = "leg.setup.json"\n'
    err = error_of(files, twice + "flexion = [20, 10]\n")
    assert err.line == 13 and "as posture leg/setup/flex_10 (line 7)" in str(err)
    err = error_of(files, "[output]\nfolder = 'o'\n[defaults]\nforce = 'yes'\n")
    assert err.line == 4 and "defaults.force: expected bool" in str(err)
    err = error_of(files, "[output]\nfolder = 'o'\n")
    assert "no [[deck]] entry" in str(err)
    assert isinstance(err, KneeguiError)


def test_the_cli_prints_one_line_and_exits_2_on_a_bad_plan(files):
    path = files / "plan.toml"
    path.write_text(plan_text('flexion = [10]\nkinematics = [{tibial_rotation = "walker"}]\n'))
    result = subprocess.run(
        [sys.executable, "-m", "kneegui.cli", "batch", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    assert result.stdout == ""
    assert result.stderr.count("\n") == 1
    assert result.stderr.startswith(f"kneegui: {path}:8: deck[0].kinematics[0].tibial_rotation:")
    assert not (files / "out").exists()
