"""Round trips of small decks written in the tests: every format variant reads right and writes
back byte-identical; moved nodes change only their coordinate fields."""

from __future__ import annotations

import difflib
from pathlib import Path

import numpy as np
import pytest

from kneegui.io.lsdyna import read_deck, write_deck, write_model
from kneegui.model import ElementBlock, Model, Part

CUBE = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]


def write(tmp_path: Path, name: str, text: str, newline: str = "\n") -> Path:
    path = tmp_path / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(text.replace("\n", newline).encode("latin-1"))
    return path


def fixed_nodes(coords, start=1, idw=8, w=16) -> str:
    return "".join(
        f"{i:{idw}d}" + "".join(f"{c:{w}.6f}" for c in xyz) + "\n"
        for i, xyz in enumerate(coords, start=start)
    )


def part_cards(*pids: int) -> str:
    """``*PART`` cards for the given ids (LS-DYNA refuses elements of undefined parts)."""
    return "*PART\n" + "".join(f"part {p}\n{p:10d}{1:10d}{1:10d}\n" for p in pids)


def assert_roundtrip_identical(deck: Path, tmp_path: Path) -> None:
    model = read_deck(deck)
    out = tmp_path / "out" / deck.name
    written = write_deck(model, out)
    for f in model.source.files:
        target = out.parent / f.rel_path
        assert target in written
        assert target.read_bytes() == f.path.read_bytes(), f"{f.rel_path} differs"


HEX_DECK = (
    "*KEYWORD\n$ comment line\n*TITLE\nunit cube\n*PART\ncube\n         1         1         1\n"
    "*NODE\n" + fixed_nodes(CUBE) + "*ELEMENT_SOLID\n"
    "       1       1       1       2       3       4       5       6       7       8\n"
    "*MAT_ELASTIC\n$#     mid        ro         e        pr\n         1    1.0E-6      10.0"
    "       0.3\n*END\n"
)


def test_fixed_format_hex_reads_and_roundtrips(tmp_path):
    deck = write(tmp_path, "cube.k", HEX_DECK)
    model = read_deck(deck)
    assert model.node_ids.tolist() == list(range(1, 9))
    np.testing.assert_array_equal(model.coords, np.array(CUBE, float))
    assert list(model.blocks) == ["hex8"]
    assert model.blocks["hex8"].conn.tolist() == [list(range(8))]
    assert model.parts[1].title == "cube"
    assert (model.parts[1].secid, model.parts[1].mid) == (1, 1)
    assert_roundtrip_identical(deck, tmp_path)


def test_crlf_and_missing_final_newline_roundtrip(tmp_path):
    deck = write(tmp_path, "crlf.k", HEX_DECK.rstrip("\n"), newline="\r\n")
    model = read_deck(deck)
    assert model.n_nodes == 8 and len(model.blocks["hex8"]) == 1
    assert_roundtrip_identical(deck, tmp_path)


def test_comma_format_nodes_and_elements(tmp_path):
    text = (
        "*KEYWORD\n"
        + part_cards(7)
        + "*NODE\n"
        + "".join(f"{i},{x},{y},{z}\n" for i, (x, y, z) in enumerate(CUBE, 1))
        + "*ELEMENT_SOLID\n1,7,1,2,3,4,5,6,7,8\n*END\n"
    )
    deck = write(tmp_path, "comma.k", text)
    model = read_deck(deck)
    np.testing.assert_array_equal(model.coords, np.array(CUBE, float))
    assert model.blocks["hex8"].part_ids.tolist() == [7]
    assert_roundtrip_identical(deck, tmp_path)


@pytest.mark.parametrize("style", ["plus", "keyword_long"])
def test_long_format(tmp_path, style):
    header = "*KEYWORD LONG=Y\n*NODE\n" if style == "keyword_long" else "*KEYWORD\n*NODE +\n"
    solid = "*ELEMENT_SOLID\n" if style == "keyword_long" else "*ELEMENT_SOLID +\n"
    big = 1_234_567_890
    text = (
        header
        + fixed_nodes(CUBE, start=big, idw=20, w=20)
        + f"*PART +\nbig\n{123456789012:20d}{1:20d}{1:20d}\n"
        + solid
        + f"{1:20d}{123456789012:20d}"
        + "".join(f"{big + k:20d}" for k in range(8))
        + "\n*END\n"
    )
    deck = write(tmp_path, "long.k", text)
    model = read_deck(deck)
    assert model.node_ids[0] == big
    assert model.blocks["hex8"].part_ids.tolist() == [123456789012]
    assert_roundtrip_identical(deck, tmp_path)
    moved = model.with_coords(model.coords + 0.5)
    write_deck(moved, tmp_path / "m" / "long.k")
    back = read_deck(tmp_path / "m" / "long.k")
    np.testing.assert_allclose(back.coords, moved.coords, rtol=0, atol=1e-15)


def test_i10_format(tmp_path):
    text = (
        "*KEYWORD\n"
        + part_cards(2)
        + "*NODE %\n"
        + fixed_nodes(CUBE, start=1_000_000_001, idw=10)
        + "*ELEMENT_SOLID %\n"
        + f"{5:10d}{2:10d}"
        + "".join(f"{1_000_000_001 + k:10d}" for k in range(8))
        + "\n*END\n"
    )
    deck = write(tmp_path, "i10.k", text)
    model = read_deck(deck)
    assert model.node_ids[-1] == 1_000_000_008
    assert model.blocks["hex8"].ids.tolist() == [5]
    assert_roundtrip_identical(deck, tmp_path)


def test_two_card_solids_and_tet10(tmp_path):
    tet10 = [
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
    text = (
        "*KEYWORD\n"
        + part_cards(1, 3)
        + "*NODE\n"
        + fixed_nodes(CUBE)
        + fixed_nodes(tet10, start=101)
        + "*ELEMENT_SOLID\n       1       1\n"
        "       1       2       3       4       5       6       7       8\n"
        "       2       3\n" + "".join(f"{101 + k:8d}" for k in range(10)) + "\n*END\n"
    )
    deck = write(tmp_path, "two.k", text)
    model = read_deck(deck)
    assert model.blocks["hex8"].ids.tolist() == [1]
    assert model.blocks["tet10"].ids.tolist() == [2]
    assert model.node_ids[model.blocks["tet10"].conn[0]].tolist() == list(range(101, 111))
    assert_roundtrip_identical(deck, tmp_path)


def test_degenerate_solids_become_wedges_pyramids_tets(tmp_path):
    rows = [
        (1, [1, 2, 3, 3, 5, 6, 7, 7]),  # LS-DYNA wedge
        (2, [1, 2, 2, 4, 5, 6, 6, 8]),  # another writer's wedge
        (3, [1, 2, 3, 4, 5, 5, 5, 5]),  # pyramid
        (4, [1, 2, 3, 5, 5, 5, 5, 5]),  # tet, LS-DYNA style
        (5, [1, 2, 3, 3, 5, 5, 5, 5]),  # tet, another pattern
        (6, [1, 2, 4]),  # explicit 4-node tet written with 3 nodes? (invalid, see below)
    ]
    body = "".join(
        f"{eid:8d}{1:8d}" + "".join(f"{n:8d}" for n in nodes) + "\n" for eid, nodes in rows[:5]
    )
    text = (
        "*KEYWORD\n" + part_cards(1) + "*NODE\n" + fixed_nodes(CUBE) + "*ELEMENT_SOLID\n" + body
    ) + "*END\n"
    model = read_deck(write(tmp_path, "degen.k", text))
    assert sorted(model.blocks["wedge6"].ids.tolist()) == [1, 2]
    assert model.blocks["pyramid5"].ids.tolist() == [3]
    assert sorted(model.blocks["tet4"].ids.tolist()) == [4, 5]
    # every rebuilt element is positively oriented
    x = model.coords
    for etype, top in (("wedge6", 3), ("pyramid5", 4), ("tet4", 3)):
        c = model.blocks[etype].conn
        vol = np.einsum(
            "ij,ij->i",
            np.cross(x[c[:, 1]] - x[c[:, 0]], x[c[:, 2]] - x[c[:, 0]]),
            x[c[:, top]] - x[c[:, 0]],
        )
        assert np.all(vol > 0), etype
    # 4- and 6-node solids written with blank trailing fields
    text = (
        "*KEYWORD\n" + part_cards(1) + "*NODE\n" + fixed_nodes(CUBE) + "*ELEMENT_SOLID\n"
        "       1       1       1       2       3       5\n"
        "       2       1       1       2       3       5       6       7\n*END\n"
    )
    model = read_deck(write(tmp_path, "short.k", text))
    assert model.blocks["tet4"].ids.tolist() == [1]
    assert model.blocks["wedge6"].ids.tolist() == [2]


def test_solid_ortho_shell_variants_beam_discrete(tmp_path):
    text = (
        "*KEYWORD\n"
        + part_cards(1, 2, 3, 4)
        + "*NODE\n"
        + fixed_nodes(CUBE)
        + "*ELEMENT_SOLID_ORTHO\n"
        "       1       1       1       2       3       4       5       6       7       8\n"
        "             1.0             0.0             0.0\n"
        "             0.0             1.0             0.0\n"
        "*ELEMENT_SHELL_THICKNESS\n"
        "      11       2       1       2       3       4\n"
        "             1.0             1.0             1.0             1.0\n"
        "      12       2       5       6       7       7\n"
        "             1.0             1.0             1.0             1.0\n"
        "*ELEMENT_SHELL_BETA\n"
        "      13       2       1       2       6       5\n"
        "             1.0             1.0             1.0             1.0            30.0\n"
        "*ELEMENT_SHELL\n      14       2       4       3       7\n"
        "*ELEMENT_BEAM\n      21       3       1       7       0\n"
        "*ELEMENT_BEAM_THICKNESS\n      22       3       2       8       0\n"
        "             1.0             1.0             1.0             1.0\n"
        "*ELEMENT_DISCRETE\n      31       4       1       8       0             1.0\n"
        "*END\n"
    )
    deck = write(tmp_path, "mixed.k", text)
    model = read_deck(deck)
    assert model.blocks["hex8"].ids.tolist() == [1]
    assert sorted(model.blocks["quad4"].ids.tolist()) == [11, 13]
    assert sorted(model.blocks["tri3"].ids.tolist()) == [12, 14]
    assert sorted(model.blocks["beam2"].ids.tolist()) == [21, 22]
    assert model.blocks["discrete"].ids.tolist() == [31]
    assert_roundtrip_identical(deck, tmp_path)


def test_parts_with_options_and_sets(tmp_path):
    text = (
        "*KEYWORD\n*NODE\n"
        + fixed_nodes(CUBE)
        + "*PART_CONTACT\nskin with contact\n         5         2         3\n"
        "       0.1       0.1\n"
        "skin 2\n         6         2         3\n       0.1       0.1\n"
        "*PART\nbone\n         7         1         1         0         0\n"
        "*SET_NODE_LIST_TITLE\ncondyle nodes\n       100       0.0\n"
        "         1         2         3         4         5         6         7         8\n"
        "         3\n"
        "*SET_PART_LIST\n       200\n         5         6         7\n"
        "*SET_NODE_LIST\n101,0.0\n1,2,3\n*END\n"
    )
    deck = write(tmp_path, "parts.k", text)
    model = read_deck(deck)
    assert {p: model.parts[p].title for p in model.parts} == {
        5: "skin with contact",
        6: "skin 2",
        7: "bone",
    }
    assert model.node_sets[100].title == "condyle nodes"
    assert model.node_ids[model.node_sets[100].node_indices].tolist() == [1, 2, 3, 4, 5, 6, 7, 8, 3]
    assert model.part_sets[200].part_ids.tolist() == [5, 6, 7]
    assert model.node_ids[model.node_sets[101].node_indices].tolist() == [1, 2, 3]
    assert "*PART_CONTACT" in model.parts[5].card_text
    assert_roundtrip_identical(deck, tmp_path)


def test_nested_includes_and_include_path(tmp_path):
    write(
        tmp_path,
        "deck/main.k",
        "*KEYWORD\n"
        + part_cards(1)
        + "*INCLUDE_PATH\nlib\n*INCLUDE\nmesh/nodes.k\nparts.k\n*END\n",
    )
    write(
        tmp_path,
        "deck/mesh/nodes.k",
        "*KEYWORD\n*NODE\n" + fixed_nodes(CUBE[:4]) + "*INCLUDE\nmore/nodes2.k\n*END\n"
        "junk after end is ignored\n",
    )
    write(tmp_path, "deck/mesh/more/nodes2.k", "*NODE\n" + fixed_nodes(CUBE[4:], start=5))
    write(
        tmp_path,
        "deck/lib/parts.k",
        "*ELEMENT_SOLID\n"
        "       1       1       1       2       3       4       5       6       7       8\n",
    )
    deck = tmp_path / "deck" / "main.k"
    model = read_deck(deck)
    assert model.n_nodes == 8 and len(model.blocks["hex8"]) == 1
    rels = [f.rel_path.as_posix() for f in model.source.files]
    assert rels == ["main.k", "mesh/nodes.k", "mesh/more/nodes2.k", "lib/parts.k"]
    assert_roundtrip_identical(deck, tmp_path)


def test_moved_nodes_change_only_coordinate_fields(tmp_path):
    write(
        tmp_path,
        "deck/main.k",
        "*KEYWORD\n$ header\n*NODE\n" + fixed_nodes(CUBE[:4]) + "5,0.0,0.0,1.0,0,0\n"
        "       6             1.0             0.0             1.0       7       3\n"
        "       7             1.0             1.0\n"
        "*INCLUDE\ninc/rest.k\n" + part_cards(1) + "*ELEMENT_SOLID\n"
        "       1       1       1       2       3       4       5       6       7       8\n*END\n",
    )
    write(tmp_path, "deck/inc/rest.k", "*NODE\n" + fixed_nodes(CUBE[7:], start=8), "\r\n")
    deck = tmp_path / "deck" / "main.k"
    model = read_deck(deck)
    coords = model.coords.copy()
    coords[:, 0] += 100.123456789  # every x moves
    coords[1, 2] = -7.25  # one z moves
    moved = model.with_coords(coords)
    out = tmp_path / "out" / "main.k"
    write_deck(moved, out)
    for src_file in model.source.files:
        old = src_file.path.read_bytes().decode().splitlines(keepends=True)
        new = (out.parent / src_file.rel_path).read_bytes().decode().splitlines(keepends=True)
        assert len(old) == len(new)
        for a, b in zip(old, new, strict=True):
            if a == b:
                continue
            assert not a.startswith("*") and not a.startswith("$")
            if "," in a:
                fa, fb = a.rstrip("\r\n").split(","), b.rstrip("\r\n").split(",")
                assert fa[0] == fb[0] and fa[4:] == fb[4:]
            else:
                assert a[:8] == b[:8] and a[56:] == b[56:], (a, b)
                assert a.endswith("\r\n") == b.endswith("\r\n")
    back = read_deck(out)
    np.testing.assert_allclose(back.coords, coords, rtol=1e-13, atol=1e-12)
    # unchanged y fields of fixed lines are kept verbatim
    text = out.read_text()
    assert "       6" in text and "             0.0             1.0       7       3" in text


def _deck_with_include(tmp_path: Path, include: str = "inc/a.k") -> Path:
    """``d/main.k`` with one hex whose nodes are in the include ``d/<include>``."""
    write(
        tmp_path,
        "d/main.k",
        f"*KEYWORD\n*INCLUDE\n{include}\n" + part_cards(1) + "*ELEMENT_SOLID\n"
        "       1       1       1       2       3       4       5       6       7       8\n*END\n",
    )
    write(tmp_path, f"d/{include}", "*KEYWORD\n*NODE\n" + fixed_nodes(CUBE) + "*END\n")
    return tmp_path / "d" / "main.k"


def test_flatten_inlines_includes(tmp_path):
    model = read_deck(_deck_with_include(tmp_path, "a.k"))
    moved = model.with_coords(model.coords * 2)
    written = write_deck(moved, tmp_path / "flat" / "one.k", flatten=True)
    assert written == [tmp_path / "flat" / "one.k"]
    text = written[0].read_text()
    assert "*INCLUDE" not in text and text.count("*END") == 1 and text.count("*KEYWORD") == 1
    back = read_deck(written[0])
    np.testing.assert_allclose(back.coords, moved.coords)
    assert len(back.source.files) == 1


def test_never_overwrites_input_and_leaves_no_partial_file(tmp_path):
    deck = write(tmp_path, "cube.k", HEX_DECK)
    model = read_deck(deck)
    before = deck.read_bytes()
    from kneegui.errors import DeckError

    with pytest.raises(DeckError, match="overwrite"):
        write_deck(model.with_coords(model.coords + 1), deck)
    assert deck.read_bytes() == before
    bad = model.coords.copy()
    bad[3, 1] = np.nan
    with pytest.raises(DeckError, match="non-finite"):
        write_deck(model.with_coords(bad), tmp_path / "o" / "x.k")
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_value_too_wide_raises_instead_of_truncating(tmp_path):
    deck = write(tmp_path, "cube.k", HEX_DECK)
    model = read_deck(deck)
    coords = model.coords.copy()
    coords[0, 0] = -1.5e300  # "-1.50000e+300" fits 16 only with few digits; 1e300 fits
    moved = model.with_coords(coords)
    write_deck(moved, tmp_path / "ok" / "cube.k")
    back = read_deck(tmp_path / "ok" / "cube.k")
    assert back.coords[0, 0] == pytest.approx(-1.5e300, rel=1e-6)


def test_write_model_fresh_deck_roundtrip(tmp_path):
    coords = np.array([*CUBE, (2, 0, 0), (2, 1, 0)], float) * 10.0 + 0.1
    blocks = {
        "hex8": ElementBlock("hex8", [1], [10], [list(range(8))]),
        "wedge6": ElementBlock("wedge6", [2], [10], [[0, 1, 2, 4, 5, 6]]),
        "tet4": ElementBlock("tet4", [3], [11], [[0, 1, 3, 4]]),
        "quad4": ElementBlock("quad4", [4], [12], [[0, 1, 2, 3]]),
        "tri3": ElementBlock("tri3", [5], [12], [[1, 8, 9]]),
        "beam2": ElementBlock("beam2", [6], [13], [[0, 6]]),
    }
    parts = {
        10: Part(10, "LX-Flesh-R", 1, 1),
        11: Part(11, "tets", 1, 1),
        12: Part(12, "LX-Skin-R", 2, 2),
        13: Part(13, "beam", 3, 3),
    }
    model = Model(np.arange(1, 11) * 3, coords, blocks, parts)
    path = write_model(model, tmp_path / "fresh.k")
    back = read_deck(path)
    np.testing.assert_array_equal(back.node_ids, model.node_ids)
    np.testing.assert_array_equal(back.coords, model.coords)
    for etype, block in blocks.items():
        got = back.blocks[etype]
        assert got.ids.tolist() == block.ids.tolist()
        assert got.part_ids.tolist() == block.part_ids.tolist()
        assert got.conn.tolist() == block.conn.tolist(), etype
    assert {p: back.parts[p].title for p in back.parts} == {p: parts[p].title for p in parts}
    # deterministic: same model, same bytes
    path2 = write_model(model, tmp_path / "fresh2.k")
    assert path.read_bytes() == path2.read_bytes()


def test_unknown_keywords_kept_verbatim(tmp_path):
    deck = write(
        tmp_path,
        "k.k",
        HEX_DECK.replace(
            "*END",
            "*CONTACT_AUTOMATIC_SURFACE_TO_SURFACE_ID\n$ odd   spacing   kept\n"
            "       1contact\n  1  2  3\n*DEFINE_CURVE\n1\n0.0,0.0\n1.0,1.0\n*END",
        ),
    )
    assert_roundtrip_identical(deck, tmp_path)
    model = read_deck(deck)
    moved = model.with_coords(model.coords + 3)
    write_deck(moved, tmp_path / "mv" / "k.k")
    diff = list(
        difflib.unified_diff(
            deck.read_text().splitlines(), (tmp_path / "mv" / "k.k").read_text().splitlines(), n=0
        )
    )
    changed = [d for d in diff if d.startswith(("+", "-")) and not d.startswith(("+++", "---"))]
    assert len(changed) == 16  # 8 node lines out, 8 in


def test_coordinates_formatted_in_blocks_give_the_same_bytes(tmp_path, monkeypatch):
    import kneegui.io.lsdyna_write as writer

    deck = write(tmp_path, "cube.k", HEX_DECK)
    model = read_deck(deck)
    moved = model.with_coords(model.coords * 1.7 + 0.123456789)
    whole = write_deck(moved, tmp_path / "whole" / "cube.k")[0].read_bytes()
    monkeypatch.setattr(writer, "WRITE_BLOCK", 3)  # 8 nodes: blocks of 3, 3 and 2
    blocks = write_deck(moved, tmp_path / "blocks" / "cube.k")[0].read_bytes()
    assert blocks == whole and blocks != deck.read_bytes()


def test_a_value_that_does_not_fit_names_its_own_node(tmp_path):
    from kneegui.errors import DeckError
    from kneegui.io.lsdyna_write import _format

    model = read_deck(write(tmp_path, "cube.k", HEX_DECK))
    coords = model.coords.copy()
    coords[:3, 0] = [0.5, 0.25, 1e300]  # the third does not fit 4 characters
    with pytest.raises(DeckError, match=r"node 3\b") as err:
        _format(model.with_coords(coords), np.arange(3), 0, 4, model.source, 0)
    assert "cube.k:11:" in str(err.value)  # node 3's line in the deck
    assert "value 1e+300 does not fit" in str(err.value)


def test_a_cancelled_write_leaves_nothing_and_an_uncancelled_one_the_same_bytes(
    tmp_path, monkeypatch
):
    """``write_deck(cancel=...)`` asks between blocks of formatted values and of written bytes
    (blocks of 2 nodes and 64 bytes here): a cancel at any question leaves no deck and no
    temporary file; answering False all along writes the bytes a write without it writes."""
    from kneegui.errors import Cancelled
    from kneegui.io import atomic, lsdyna_write

    monkeypatch.setattr(lsdyna_write, "WRITE_BLOCK", 2)
    monkeypatch.setattr(atomic, "WRITE_CHUNK", 64)
    model = read_deck(write(tmp_path, "cube.k", HEX_DECK))
    moved = model.with_coords(model.coords + 0.25)
    reference = write_deck(moved, tmp_path / "ref" / "cube.k")[0].read_bytes()
    asked = [0]

    def count() -> bool:
        asked[0] += 1
        return False

    out = tmp_path / "out" / "cube.k"
    write_deck(moved, out, cancel=count)
    assert out.read_bytes() == reference
    questions = asked[0]
    assert questions >= 3 * 4 + len(reference) // 64  # 8 nodes x 3 coordinates, the chunks
    for call in range(1, questions + 1):
        asked[0] = 0
        target = tmp_path / f"cancelled{call}" / "cube.k"

        def cancel(call=call) -> bool:
            asked[0] += 1
            return asked[0] >= call

        with pytest.raises(Cancelled):
            write_deck(moved, target, cancel=cancel)
        assert not target.parent.exists() or list(target.parent.iterdir()) == []


def test_the_read_lets_the_bytes_go_and_the_write_reads_them_back(tmp_path):
    deck = _deck_with_include(tmp_path)
    model = read_deck(deck)
    for f in model.source.files:  # a whole-body deck's bytes are hundreds of MB
        assert f.resident is None and f.line_starts is None and f.line_ends is None
        assert f.size == f.path.stat().st_size
    assert_roundtrip_identical(deck, tmp_path)
    moved = model.with_coords(model.coords + 0.5)
    write_deck(moved, tmp_path / "o" / "main.k")
    np.testing.assert_allclose(read_deck(tmp_path / "o" / "main.k").coords, moved.coords)


@pytest.mark.parametrize("change", ["same size", "longer", "shorter", "deleted"])
def test_a_file_changed_on_disk_since_the_read_is_refused_and_nothing_written(tmp_path, change):
    from kneegui.errors import DeckError

    deck = _deck_with_include(tmp_path)
    model = read_deck(deck)
    inc = tmp_path / "d" / "inc" / "a.k"
    text = inc.read_bytes()
    if change == "same size":  # the node block's offsets would still be in range: CRC-32 tells
        inc.write_bytes(text.replace(b"1.000000", b"2.000000", 1))
    elif change == "longer":
        inc.write_bytes(b"$ edited\n" + text)
    elif change == "shorter":
        inc.write_bytes(text[:-5])
    else:
        inc.unlink()
    out = tmp_path / "o" / "main.k"
    message = "cannot read it again" if change == "deleted" else "changed on disk since it was read"
    with pytest.raises(DeckError, match=message) as err:
        write_deck(model.with_coords(model.coords + 1.0), out)
    assert "a.k" in str(err.value)
    assert not out.parent.exists() or not any(out.parent.iterdir())
