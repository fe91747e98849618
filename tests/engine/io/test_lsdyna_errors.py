"""Malformed cards and broken decks: a DeckError naming the file and the line, never a traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from kneegui.errors import DeckError
from kneegui.io.lsdyna import read_deck

NODES = "".join(
    f"{i:8d}{x:16.3f}{y:16.3f}{z:16.3f}\n"
    for i, (x, y, z) in enumerate(
        [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)],
        1,
    )
)
HEX = "       1       1       1       2       3       4       5       6       7       8\n"


def deck(tmp_path: Path, text: str, name: str = "bad.k") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


CASES = {
    # name: (deck text, expected line, message fragment)
    "letters in node id": (
        "*KEYWORD\n*NODE\n     1a2             0.0             0.0             0.0\n",
        3,
        "node id",
    ),
    "letters in coordinate": (
        "*KEYWORD\n*NODE\n       1             0.0          abc.de             0.0\n",
        3,
        "y coordinate",
    ),
    "nan coordinate": (
        "*KEYWORD\n*NODE\n       1             nan             0.0             0.0\n",
        3,
        "nan",
    ),
    "comma line garbage": ("*KEYWORD\n*NODE\n1,0.0,zero,0.0\n", 3, "y coordinate"),
    "duplicate node id": (
        "*KEYWORD\n*NODE\n" + NODES + "       3             5.0\n",
        11,
        "node id 3 is defined twice",
    ),
    "zero node id": ("*KEYWORD\n*NODE\n       0             0.0\n", 3, "positive"),
    "element refers to missing node": (
        "*KEYWORD\n*NODE\n" + NODES + "*ELEMENT_SOLID\n" + HEX.replace("       8\n", "      99\n"),
        12,
        "node 99",
    ),
    "element with 5 nodes": (
        "*KEYWORD\n*NODE\n" + NODES + "*ELEMENT_SOLID\n"
        "       1       1       1       2       3       4       5\n",
        12,
        "5 node ids",
    ),
    "element with a gap": (
        "*KEYWORD\n*NODE\n" + NODES + "*ELEMENT_SOLID\n"
        "       1       1       1       2       0       4       5       6"
        "       7       8\n",
        12,
        "without blanks",
    ),
    "element part id zero": (
        "*KEYWORD\n*NODE\n"
        + NODES
        + "*ELEMENT_SOLID\n"
        + HEX.replace("       1       1", "       1       0", 1),
        12,
        "part id 0",
    ),
    "float where int expected": (
        "*KEYWORD\n*NODE\n" + NODES + "*ELEMENT_SOLID\n"
        "     1.0       1       1       2       3       4       5"
        "       6       7       8\n",
        12,
        "not an integer",
    ),
    "incomplete two-card solid": (
        "*KEYWORD\n*NODE\n" + NODES + "*ELEMENT_SOLID\n       1"
        "       1\n" + HEX[16:] + "       2       1\n",
        14,
        "incomplete",
    ),
    "incomplete shell thickness": (
        "*KEYWORD\n*NODE\n" + NODES + "*ELEMENT_SHELL_THICKNESS\n"
        "       1       1       1       2       3       4\n",
        12,
        "incomplete",
    ),
    "part without pid card": ("*KEYWORD\n*PART\ntitle only\n", 3, "PID card"),
    "part defined twice": (
        "*KEYWORD\n*PART\na\n         1\n*PART\nb\n         1\n",
        7,
        "defined twice",
    ),
    "tab in card": ("*KEYWORD\n*NODE\n       1\t0.0,\n", 3, "tab"),
    "missing include": ("*KEYWORD\n*INCLUDE\nnot_there.k\n*END\n", 3, "not_there.k"),
    "data before keyword": ("       1             0.0\n*KEYWORD\n", 1, "before the first keyword"),
    "set refers to missing node": (
        "*KEYWORD\n*NODE\n" + NODES + "*SET_NODE_LIST\n         5\n         1        77\n",
        12,
        "node 77",
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_malformed_card_names_file_and_line(tmp_path, case):
    text, line, fragment = CASES[case]
    path = deck(tmp_path, text)
    with pytest.raises(DeckError) as info:
        read_deck(path)
    err = info.value
    assert err.path is not None and err.path.name == "bad.k"
    assert err.line == line, str(err)
    assert fragment in str(err)
    assert str(err).startswith(f"{err.path}:{line}: ")


def test_error_in_include_names_the_include(tmp_path):
    deck(tmp_path, "*KEYWORD\n*INCLUDE\nsub.k\n*END\n", "main.k")
    deck(tmp_path, "*NODE\n       1             0.0          0.0.0\n", "sub.k")
    with pytest.raises(DeckError) as info:
        read_deck(tmp_path / "main.k")
    assert info.value.path.name == "sub.k" and info.value.line == 2


def test_include_cycle(tmp_path):
    deck(tmp_path, "*KEYWORD\n*INCLUDE\nb.k\n", "a.k")
    deck(tmp_path, "*KEYWORD\n*INCLUDE\na.k\n", "b.k")
    with pytest.raises(DeckError, match="include cycle"):
        read_deck(tmp_path / "a.k")


def test_binary_and_missing_files(tmp_path):
    (tmp_path / "bin.k").write_bytes(b"*KEYWORD\n\x00\x01\x02")
    with pytest.raises(DeckError, match="binary"):
        read_deck(tmp_path / "bin.k")
    with pytest.raises(DeckError, match="not found"):
        read_deck(tmp_path / "nope.k")


def test_fortran_exponents_are_read(tmp_path):
    path = deck(
        tmp_path,
        "*KEYWORD\n*NODE\n       1          1.5+3          1.D-2         -2.5E-1"
        "\n       2,1.5d2,-.5,7.\n",
    )
    model = read_deck(path)
    assert model.coords.tolist() == [[1500.0, 0.01, -0.25], [150.0, -0.5, 7.0]]


def run_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "kneegui.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_cli_bad_input_one_line_exit_2_no_output(tmp_path):
    path = deck(tmp_path, CASES["element refers to missing node"][0])
    out = tmp_path / "out.k"
    result = run_cli("convert", str(path), "--out", str(out), cwd=tmp_path)
    assert result.returncode == 2
    assert result.stdout == ""
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr
    assert f"{path}:12:" in lines[0]
    assert not out.exists()
    assert list(tmp_path.iterdir()) == [path]


def test_cli_info_and_convert_on_a_deck(tmp_path):
    path = deck(
        tmp_path,
        "*KEYWORD\n*PART\nLX-Flesh-R\n         1\n*NODE\n"
        + NODES
        + "*ELEMENT_SOLID\n"
        + HEX
        + "*END\n",
    )
    result = run_cli("info", str(path), "--json", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    import json

    info = json.loads(result.stdout)
    assert info["nodes"] == 8 and info["elements_by_type"] == {"hex8": 1}
    assert info["parts"][0]["title"] == "LX-Flesh-R"
    for fmt, name in (("lsdyna", "o.k"), ("abaqus", "o.inp"), ("vtu", "o.vtu")):
        result = run_cli(
            "convert", str(path), "--out", str(tmp_path / name), "--format", fmt, cwd=tmp_path
        )
        assert result.returncode == 0, result.stderr
        assert (tmp_path / name).stat().st_size > 0
    assert (tmp_path / "o.k").read_bytes() == path.read_bytes()
    inp = (tmp_path / "o.inp").read_text()
    assert "*ELEMENT, TYPE=C3D8R, ELSET=PART_1" in inp and "1, 1, 2, 3, 4, 5, 6, 7, 8" in inp
