"""Decks written by other tools (issue #22): decorated keyword lines, blank cards, and what LS-DYNA
refuses (empty decks, undefined parts, element ids used twice) - each read as LS-DYNA reads it,
written back byte for byte, or refused with one ``file:line: what`` line and exit code 2."""

from __future__ import annotations

import difflib
import json
from pathlib import Path

import numpy as np
import pytest

from kneegui.cli import main as cli
from kneegui.errors import DeckError
from kneegui.io.lsdyna import read_deck, write_deck

CUBE = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
TET10 = [
    (0, 0, 0),
    (1, 0, 0),
    (0, 1, 0),
    (0, 0, 1),
    (0.5, 0, 0),
    (0.5, 0.5, 0),
    (0, 0.5, 0),
    (0, 0, 0.5),
    (0.5, 0, 0.5),
    (0, 0.5, 0.5),
]


def nodes(coords, start=1) -> str:
    return "".join(
        f"{i:8d}" + "".join(f"{c:16.6f}" for c in xyz) + "\n" for i, xyz in enumerate(coords, start)
    )


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(text.encode("latin-1"))
    return path


def changed_lines(a: Path, b: Path) -> list[str]:
    diff = difflib.unified_diff(
        a.read_text("latin-1").splitlines(), b.read_text("latin-1").splitlines(), n=0
    )
    return [d for d in diff if d[:1] in "+-" and not d.startswith(("+++", "---"))]


def convert_is_identical(deck: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "converted" / deck.name
    assert cli(["convert", str(deck), "--out", str(out)]) == 0, capsys.readouterr().err
    assert out.read_bytes() == deck.read_bytes()


# ------------------------------------------------------------------ 1. decorated keyword lines
# LS-PrePost writes 10-node tetrahedra under "*ELEMENT_SOLID (ten nodes format)": each element
# on two cards, EID PID, then N1..N10.
LSPP_TET10 = (
    "*KEYWORD\n$# LS-PrePost(R) V4.10 - 10-node tets\n*PART\n$#  title\ntet part\n"
    "$#     pid     secid       mid\n         1         1         1\n"
    "*NODE %\n"
    + "".join(
        f"{i:10d}" + "".join(f"{c:16.6f}" for c in xyz) + "\n" for i, xyz in enumerate(TET10, 1)
    )
    + "*ELEMENT_SOLID (ten nodes format)\n$#   eid     pid\n       7       1\n"
    "$#    n1      n2      n3      n4      n5      n6      n7      n8      n9     n10\n"
    + "".join(f"{k:8d}" for k in range(1, 11))
    + "\n*END\n"
)


def test_lsprepost_ten_node_tets_read_convert_and_move_only_node_fields(tmp_path, capsys):
    deck = write(tmp_path / "lspp.k", LSPP_TET10)
    model = read_deck(deck)
    assert list(model.blocks) == ["tet10"]
    assert model.blocks["tet10"].ids.tolist() == [7]
    assert model.node_ids[model.blocks["tet10"].conn[0]].tolist() == list(range(1, 11))
    convert_is_identical(deck, tmp_path, capsys)
    moved = tmp_path / "moved" / "lspp.k"
    write_deck(model.with_coords(model.coords + np.array([10.0, 0.0, -2.5])), moved)
    changed = changed_lines(deck, moved)
    assert len(changed) == 20  # the ten *NODE lines out and in, nothing else
    node_lines = set(LSPP_TET10.splitlines()[8:18])
    assert all(c[1:] in node_lines for c in changed if c.startswith("-"))


@pytest.mark.parametrize(
    "header",
    [
        "*ELEMENT_SOLID (ten nodes format)",
        "*ELEMENT_SOLID_TET4TOTET10",
        "*ELEMENT_SOLID  $ written by a mesher",
        "*ELEMENT_SOLID    created 2026-01-01 by tool X",
        "*ELEMENT_SOLID - (standard format, labelled)",
    ],
)
def test_decorated_solid_keywords_are_read(tmp_path, header):
    two_card = "ten nodes" in header
    card = "       1       1" + ("\n" if two_card else "") + "".join(f"{k:8d}" for k in range(1, 9))
    text = (
        "*KEYWORD\n*PART\np\n         1         1         1\n*NODE\n"
        + nodes(CUBE)
        + f"{header}\n{card}\n*END\n"
    )
    deck = write(tmp_path / "d.k", text)
    model = read_deck(deck)
    assert model.blocks["hex8"].ids.tolist() == [1]
    out = tmp_path / "o" / "d.k"
    write_deck(model, out)
    assert out.read_bytes() == deck.read_bytes()


def test_tet4_to_tet10_elements_are_read_as_their_corner_tets(tmp_path):
    text = (
        "*KEYWORD\n*PART\np\n         1         1         1\n*NODE\n"
        + nodes(CUBE)
        + "*ELEMENT_SOLID_TET4TOTET10\n       1       1       1       2       4       5"
        "       5       5       5       5\n*END\n"
    )
    model = read_deck(write(tmp_path / "t.k", text))
    assert model.blocks["tet4"].ids.tolist() == [1]


# ------------------------------------------------------------------ 2. blank cards are cards
def inertia_cards(ircs: int, blank: int | None) -> list[str]:
    cards = [
        f"{26.25:10.4f}{1.5:10.4f}{-3.0:10.4f}{2.0:10.4f}{ircs:10d}{0:10d}",
        f"{1.0:10.4f}{0.0:10.4f}{0.0:10.4f}{1.0:10.4f}{0.0:10.4f}{1.0:10.4f}",
        f"{0.0:10.4f}{0.0:10.4f}{0.0:10.4f}",
    ]
    if ircs == 1:
        cards.append(f"{1.0:10.4f}{0.0:10.4f}{0.0:10.4f}{0.0:10.4f}{1.0:10.4f}{0.0:10.4f}")
    if blank is not None:
        cards[blank] = ""
    return cards


def _part_block(keyword: str, extra: list[str], blank_heading: bool, pid: int) -> str:
    heading = "" if blank_heading else f"part {pid}"
    return "\n".join([heading, f"{pid:10d}{1:10d}{1:10d}", *extra]) + "\n"


# (keyword, extra cards of the first part, which of its cards is blank: "heading" or an index)
BLANK_CASES = [
    ("*PART", [], "heading"),
    ("*PART_INERTIA", inertia_cards(0, None), "heading"),
    ("*PART_INERTIA", inertia_cards(0, 0), 0),
    ("*PART_INERTIA", inertia_cards(0, 1), 1),
    ("*PART_INERTIA", inertia_cards(0, 2), 2),
    ("*PART_INERTIA", inertia_cards(1, None), "heading"),
    ("*PART_INERTIA", inertia_cards(1, 3), 3),
    ("*PART_CONTACT", [f"{0.1:10.4f}{0.1:10.4f}"], "heading"),
    ("*PART_CONTACT", [""], 0),
    ("*PART_PRINT", [""], 0),
    ("*PART_ATTACHMENT_NODES", [""], 0),
    ("*PART_REPOSITION", [""], 0),
    ("*PART_INERTIA_CONTACT", [*inertia_cards(0, None), ""], 3),
]


@pytest.mark.parametrize(("keyword", "extra", "blank"), BLANK_CASES)
@pytest.mark.parametrize("first_of_two", [True, False])
def test_blank_part_cards_are_counted(tmp_path, keyword, extra, blank, first_of_two):
    """A blank card in the first part of a block, then a second, complete part after it."""
    first = _part_block(keyword, extra, blank == "heading", 26)
    second_extra = [c or "         0" for c in extra]
    second = _part_block(keyword, second_extra, False, 27)
    parts = first + second if first_of_two else second + first
    text = (
        f"*KEYWORD\n{keyword}\n{parts}*NODE\n"
        + nodes(CUBE)
        + "*ELEMENT_SOLID\n"
        + "".join(
            f"{eid:8d}{pid:8d}" + "".join(f"{k:8d}" for k in range(1, 9)) + "\n"
            for eid, pid in ((1, 26), (2, 27))
        )
        + "*END\n"
    )
    deck = write(tmp_path / "p.k", text)
    model = read_deck(deck)
    assert sorted(model.parts) == [26, 27]
    assert model.parts[26].title == ("" if blank == "heading" else "part 26")
    assert model.parts[27].title == "part 27"
    assert (model.parts[26].secid, model.parts[26].mid) == (1, 1)
    out = tmp_path / "o" / "p.k"
    write_deck(model, out)
    assert out.read_bytes() == deck.read_bytes()


@pytest.mark.parametrize("keyword", ["*SET_NODE_LIST_TITLE", "*SET_PART_LIST_TITLE"])
def test_blank_set_titles_are_cards(tmp_path, keyword):
    text = (
        "*KEYWORD\n*PART\np\n         1         1         1\n*NODE\n"
        + nodes(CUBE)
        + f"{keyword}\n\n        55\n         1         1\n*END\n"
    )
    model = read_deck(write(tmp_path / "s.k", text))
    sets = model.node_sets if "NODE" in keyword else model.part_sets
    assert list(sets) == [55]
    assert sets[55].title == ""


SHELL = "      11       1       1       2       3       4"


@pytest.mark.parametrize(
    ("keyword", "element_card", "blank_cards", "etype"),
    [
        (
            "*ELEMENT_SHELL_THICKNESS",
            "      11       1       1       2       3       4",
            1,
            "quad4",
        ),
        ("*ELEMENT_SHELL_OFFSET", "      11       1       1       2       3       4", 1, "quad4"),
        (
            "*ELEMENT_SHELL_THICKNESS_OFFSET",
            "      11       1       1       2       3       4",
            2,
            "quad4",
        ),
        ("*ELEMENT_BEAM_ORIENTATION", "      11       1       1       7       0", 1, "beam2"),
        ("*ELEMENT_BEAM_OFFSET", "      11       1       1       7       0", 1, "beam2"),
        ("*ELEMENT_DISCRETE_LCO", "      11       1       1       7       0", 1, "discrete"),
        (
            "*ELEMENT_SOLID_ORTHO",
            "      11       1       1       2       3       4       5       6       7       8",
            2,
            "hex8",
        ),
    ],
)
def test_blank_element_cards_are_counted(tmp_path, keyword, element_card, blank_cards, etype):
    """Two elements; the first's optional cards are blank, the second's are not."""
    filled = "             0.0" * 3
    second = element_card.replace("      11", "      12", 1)
    text = (
        "*KEYWORD\n*PART\np\n         1         1         1\n*NODE\n"
        + nodes(CUBE)
        + f"{keyword}\n{element_card}\n"
        + "\n" * blank_cards
        + second
        + "\n"
        + f"{filled}\n" * blank_cards
        + "*END\n"
    )
    deck = write(tmp_path / "e.k", text)
    model = read_deck(deck)
    assert model.blocks[etype].ids.tolist() == [11, 12]


# ------------------------------------------------------------------ 3. what LS-DYNA refuses
HEX = "       1       1       1       2       3       4       5       6       7       8\n"
PART1 = "*PART\np\n         1         1         1\n"


@pytest.mark.parametrize(
    ("text", "line", "fragment"),
    [
        ("", None, "no nodes and no elements"),
        ("*KEYWORD\n*END\n", None, "no nodes and no elements"),
        ("*KEYWORD\n*NODE\n" + nodes(CUBE) + "*ELEMENT_SOLID\n" + HEX, 12, "part 1, which is not"),
        (
            "*KEYWORD\n" + PART1 + "*NODE\n" + nodes(CUBE) + "*ELEMENT_SOLID\n" + HEX + HEX,
            16,
            "solid element id 1 is used twice",
        ),
        (
            "*KEYWORD\n" + PART1 + "*NODE\n" + nodes(CUBE) + "*ELEMENT_SHELL\n"
            "       5       1       1       2       3       4\n"
            "*ELEMENT_SHELL_THICKNESS\n       5       1       5       6       7       8\n\n",
            17,
            "shell element id 5 is used twice",
        ),
    ],
    ids=["empty file", "keywords only", "undefined part", "solid id twice", "shell id twice"],
)
def test_what_ls_dyna_refuses_is_refused(tmp_path, capsys, text, line, fragment):
    deck = write(tmp_path / "bad.k", text)
    with pytest.raises(DeckError, match=fragment) as err:
        read_deck(deck)
    assert err.value.path == deck and err.value.line == line
    out = tmp_path / "out" / "bad.k"
    assert cli(["convert", str(deck), "--out", str(out)]) == 2
    message = capsys.readouterr().err.strip()
    assert message.count("\n") == 0 and fragment in message
    assert message.startswith(f"kneegui: {deck}:{line}: " if line else f"kneegui: {deck}: ")
    assert not out.exists()
    # info lists the problem instead of stopping at it, and says so
    assert cli(["info", str(deck), "--json", "--no-quality"]) == 2
    info = json.loads(capsys.readouterr().out)
    assert any(fragment in p for p in info["problems"])


def test_same_id_in_two_element_kinds_is_accepted(tmp_path):
    text = (
        "*KEYWORD\n"
        + PART1
        + "*NODE\n"
        + nodes(CUBE)
        + "*ELEMENT_SOLID\n"
        + HEX
        + "*ELEMENT_SHELL\n       1       1       1       2       3       4\n*END\n"
    )
    model = read_deck(write(tmp_path / "ok.k", text))
    assert model.blocks["hex8"].ids.tolist() == model.blocks["quad4"].ids.tolist() == [1]


def test_undefined_part_is_a_warning_when_a_part_keyword_is_not_read(tmp_path):
    text = (
        "*KEYWORD\n*PART_COMPOSITE\nlayered\n         1         2\n*NODE\n"
        + nodes(CUBE)
        + "*ELEMENT_SOLID\n"
        + HEX
    )
    model = read_deck(write(tmp_path / "c.k", text))
    assert any("part 1" in w and "PART_COMPOSITE" in w for w in model.source.warnings)


# ------------------------------------------------------------------ end to end
def _lsprepost_style(deck_text: str) -> str:
    """The demo deck as another tool writes it: *PART_INERTIA with blank headings, and solids
    in the labelled two-card layout."""
    out, lines, i = [], deck_text.split("\n"), 0
    while i < len(lines):
        line = lines[i]
        if line == "*PART":
            out += ["*PART_INERTIA", "", lines[i + 2], *inertia_cards(0, 2)]
            i += 3
            continue
        if line == "*ELEMENT_SOLID":
            out.append("*ELEMENT_SOLID (ten nodes format)")
            i += 1
            while i < len(lines) and not lines[i].startswith("*"):
                out += [lines[i][:16], lines[i][16:]]
                i += 1
            continue
        out.append(line)
        i += 1
    return "\n".join(out)


@pytest.fixture(scope="module")
def foreign_demo(tmp_path_factory):
    from kneegui.demo.generator import write_demo

    folder = tmp_path_factory.mktemp("foreign")
    deck, setup = write_demo(folder, elements=2000)
    text = _lsprepost_style(deck.read_text())
    assert "*PART_INERTIA\n\n" in text and "(ten nodes format)" in text
    foreign = write(folder / "foreign.k", text)
    data = json.loads(setup.read_text())
    data["model"] = foreign.name
    setup.write_text(json.dumps(data))
    return foreign, setup


def test_foreign_deck_converts_identically_and_poses_only_node_fields(
    foreign_demo, tmp_path, capsys
):
    deck, setup = foreign_demo
    original = read_deck(deck.parent / "demo_leg.k")
    model = read_deck(deck)
    assert sorted(model.parts) == sorted(original.parts)
    assert all(model.parts[p].title == "" for p in model.parts)
    for etype, block in original.blocks.items():
        np.testing.assert_array_equal(model.blocks[etype].conn, block.conn)
    convert_is_identical(deck, tmp_path, capsys)
    posed = tmp_path / "posed" / "foreign.k"
    status = cli(["pose", str(deck), "--setup", str(setup), "--flexion", "40", "--out", str(posed)])
    assert status == 0, capsys.readouterr()
    changed = changed_lines(deck, posed)
    assert changed
    node_lines = set(deck.read_text().split("*NODE\n", 1)[1].split("*", 1)[0].splitlines())
    assert all(c[1:] in node_lines for c in changed if c.startswith("-"))
    assert read_deck(posed).n_nodes == model.n_nodes
