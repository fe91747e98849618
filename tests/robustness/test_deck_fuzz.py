"""Fuzzing the deck reader: every mutated card or deck ends in a DeckError naming file and line,
or in a documented accepted reading — never another exception, a hang, or a silently wrong model.

Each test records how many cases it ran in ``FUZZ_COUNTS`` (printed in the session summary and
quoted in docs/reliability.md).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kneegui.errors import DeckError
from kneegui.io.fields import FieldError, parse_float_field
from kneegui.io.lsdyna import read_deck

FUZZ = settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
FUZZ_COUNTS: dict[str, int] = {}

CUBE = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]


def count(name: str) -> None:
    FUZZ_COUNTS[name] = FUZZ_COUNTS.get(name, 0) + 1


def node_block(coords) -> str:
    return "".join(f"{i:8d}{x:16.4f}{y:16.4f}{z:16.4f}\n" for i, (x, y, z) in enumerate(coords, 1))


BASE = (
    "*KEYWORD\n*PART\nflesh\n         1         1         1\n*NODE\n"
    + node_block(CUBE)
    + "*ELEMENT_SOLID\n"
    "       1       1       1       2       3       4       5       6       7       8\n*END\n"
)


def read_or_error(path: Path):
    """Read; a DeckError must name the file and (when it is about a line) a valid line."""
    try:
        return read_deck(path)
    except DeckError as err:
        assert err.path is not None
        text = str(err)
        assert "\n" not in text
        if err.line is not None:
            n_lines = max(1, len(path.read_bytes().split(b"\n")))
            assert 1 <= err.line <= n_lines + 1, text
        return None


# ----------------------------------------------------------------------------- field level
_float_text = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False, width=64).map(repr),
    st.floats(min_value=-1e6, max_value=1e6, allow_nan=False).map(lambda v: f"{v:.6e}"),
    st.builds(
        lambda m, e, d: f"{m:.3f}{d}{e:+d}",
        st.floats(-99, 99),
        st.integers(-30, 30),
        st.sampled_from(["e", "E", "d", "D", ""]),
    ),
    st.text(alphabet="0123456789+-.eEdD ", max_size=16),
)


@FUZZ
@given(_float_text)
def test_real_field_parser_accepts_or_raises(text):
    count("real field texts")
    try:
        value = parse_float_field(text)
    except FieldError:
        return
    assert math.isfinite(value)
    # what it accepted is a number written the Fortran way
    assert re.fullmatch(r"\s*[+-]?(\d+\.?\d*|\.\d+)([eEdD]?[+-]?\d+)?\s*|\s*", text)


@FUZZ
@given(
    x=st.floats(-1e9, 1e9, allow_nan=False),
    y=st.floats(-1e-9, 1e-9, allow_nan=False),
    z=st.floats(-1e30, 1e30, allow_nan=False),
    nid=st.integers(1, 99_999_999),
    style=st.sampled_from(["fixed", "comma", "long", "i10"]),
    crlf=st.booleans(),
)
def test_node_cards_read_back_exactly(tmp_path, x, y, z, nid, style, crlf):
    count("node cards (fixed/comma/long/i10, CRLF)")
    if style == "fixed":
        card = f"{nid:8d}{x!r:>16.16}{y!r:>16.16}{z!r:>16.16}"
        header = "*NODE"
    elif style == "comma":
        card = f"{nid},{x!r},{y!r},{z!r}"
        header = "*NODE"
    elif style == "long":
        card = f"{nid:20d}{x!r:>20.20}{y!r:>20.20}{z!r:>20.20}"
        header = "*NODE +"
    else:
        card = f"{nid:10d}{x!r:>16.16}{y!r:>16.16}{z!r:>16.16}"
        header = "*NODE %"
    nl = "\r\n" if crlf else "\n"
    path = tmp_path / "n.k"
    path.write_text(nl.join(["*KEYWORD", header, card, "*END", ""]))
    model = read_or_error(path)
    if model is None:
        return  # a field repr longer than the column was cut: must then be an error
    assert model.node_ids.tolist() == [nid]
    fields = [x, y, z]
    for j, v in enumerate(fields):
        text = repr(v)
        width = 16 if style in ("fixed", "i10") else 20
        if style == "comma" or len(text) <= width:
            assert model.coords[0, j] == v


@FUZZ
@given(
    garbage=st.text(
        alphabet=st.characters(min_codepoint=32, max_codepoint=126), min_size=1, max_size=12
    ),
    column=st.integers(0, 79),
)
def test_garbage_in_an_element_card(tmp_path, garbage, column):
    count("element cards with garbage")
    lines = BASE.split("\n")
    row = lines.index("*ELEMENT_SOLID") + 1
    card = lines[row].ljust(80)
    lines[row] = card[:column] + garbage + card[column + len(garbage) :]
    path = tmp_path / "e.k"
    path.write_text("\n".join(lines))
    model = read_or_error(path)
    if model is not None and lines[row].startswith("$"):
        assert not model.blocks  # the card became a comment, as LS-DYNA reads it
    elif model is not None and lines[row].startswith("*"):
        # it became an unknown keyword: accepted only with a warning naming it
        assert not model.blocks
        assert any(f":{row + 1}: " in w for w in model.source.warnings)
    elif model is not None:
        # accepted: then it must be a consistent reading of the card by columns
        blocks = model.blocks
        assert sum(len(b) for b in blocks.values()) == 1
        fields = [lines[row][k : k + 8].strip() for k in range(0, 80, 8)]
        assert [int(f or 0) for f in fields[:2]] == [
            next(iter(blocks.values())).ids[0],
            next(iter(blocks.values())).part_ids[0],
        ]


# ----------------------------------------------------------------------------- deck level
def _mutations():
    return st.one_of(
        st.tuples(st.just("truncate"), st.integers(0, len(BASE))),
        st.tuples(st.just("drop_line"), st.integers(0, BASE.count("\n"))),
        st.tuples(st.just("duplicate_line"), st.integers(0, BASE.count("\n"))),
        st.tuples(
            st.just("insert_bytes"), st.integers(0, len(BASE)), st.binary(min_size=1, max_size=8)
        ),
        st.tuples(st.just("flip_byte"), st.integers(0, len(BASE) - 1), st.integers(0, 255)),
    )


@FUZZ
@given(st.lists(_mutations(), min_size=1, max_size=4))
def test_whole_deck_mutations(tmp_path, mutations):
    count("whole-deck mutations")
    data = bytearray(BASE.encode())
    for m in mutations:
        kind = m[0]
        lines = bytes(data).split(b"\n")
        if kind == "truncate":
            data = data[: m[1]]
        elif kind == "drop_line" and m[1] < len(lines):
            del lines[m[1]]
            data = bytearray(b"\n".join(lines))
        elif kind == "duplicate_line" and m[1] < len(lines):
            lines.insert(m[1], lines[m[1]])
            data = bytearray(b"\n".join(lines))
        elif kind == "insert_bytes":
            pos = min(m[1], len(data))
            data[pos:pos] = m[2]
        elif kind == "flip_byte" and m[1] < len(data):
            data[m[1]] = m[2]
    path = tmp_path / "m.k"
    path.write_bytes(bytes(data))
    model = read_or_error(path)
    if model is not None:
        # accepted readings are self-consistent
        assert np.all(np.isfinite(model.coords))
        for block in model.blocks.values():
            assert block.conn.min() >= 0 and block.conn.max() < model.n_nodes


@pytest.mark.parametrize(
    "text",
    [
        BASE.replace("*END\n", ""),  # missing *END
        BASE + "\x80\xff non-UTF-8 bytes after END\n",
        BASE.replace("*END\n", "*PART\nlonely\n         9         1         1\n*END\n"),
    ],
)
def test_accepted_degenerate_decks(tmp_path, text):
    count("accepted degenerate decks")
    path = tmp_path / "d.k"
    path.write_bytes(text.encode("latin-1"))
    model = read_deck(path)
    assert model.n_nodes == 8


@pytest.mark.parametrize(
    "text",
    [
        "",  # empty file
        "*KEYWORD\n",  # no data at all
        "*KEYWORD\n*NODE\n",  # empty block
        "*KEYWORD\n*PART\nlonely\n         9         1         1\n*END\n",  # a part only
    ],
)
def test_decks_without_nodes_or_elements_are_refused(tmp_path, text):
    count("refused empty decks")
    path = tmp_path / "d.k"
    path.write_bytes(text.encode("latin-1"))
    with pytest.raises(DeckError, match="no nodes and no elements") as err:
        read_deck(path)
    assert err.value.path == path


def test_non_utf8_title_is_kept_byte_for_byte(tmp_path):
    count("accepted degenerate decks")
    path = tmp_path / "latin.k"
    path.write_bytes(BASE.replace("flesh", "Fl\xe9sh").encode("latin-1"))
    model = read_deck(path)
    assert model.parts[1].title == "Fl\xe9sh"
    from kneegui.io.lsdyna import write_deck

    write_deck(model, tmp_path / "o" / "latin.k")
    assert (tmp_path / "o" / "latin.k").read_bytes() == path.read_bytes()


def test_huge_ids_and_exponents(tmp_path):
    count("accepted degenerate decks")
    path = tmp_path / "h.k"
    path.write_text(
        "*KEYWORD\n*NODE +\n" + f"{10**18:20d}" + "               1.5+3               1.D-2"
        "              -2.5E1\n"
    )
    model = read_deck(path)
    assert model.node_ids.tolist() == [10**18]
    assert model.coords.tolist() == [[1500.0, 0.01, -25.0]]


def pytest_sessionfinish():  # pragma: no cover - reporting only
    pass
