"""Write LS-DYNA decks: a lossless rewrite of a deck that was read, or a fresh deck of a model.

Lossless rewrite (:func:`write_deck`): every byte of every file is copied from the input except the
coordinate fields of nodes whose coordinates changed. Fixed-format fields are overwritten in place
with a number of exactly the same width (as many digits as fit); free-format (comma) lines are
rebuilt with the shortest exact text. Include files are written under the output folder with their
relative layout, or inlined with ``flatten=True``. All files are written atomically as a group.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import DeckError, OutputConflictError, raise_if_cancelled
from kneegui.io.atomic import atomic_write_many
from kneegui.io.fields import FieldError, format_fixed_width, format_free_float
from kneegui.io.lsdyna_read import DeckFile, DeckSource
from kneegui.io.output_plan import plan_writes
from kneegui.model import Model

#: Changed coordinate fields formatted at a time by :func:`write_deck`.
WRITE_BLOCK = 1 << 16

_SPACE = 32


def _changed_fields(model: Model, src: DeckSource) -> NDArray[np.bool_]:
    if model.coords.shape != src.coords_read.shape:
        raise DeckError(
            f"the model has {len(model.coords)} nodes but the deck it came from has "
            f"{len(src.coords_read)}: only node coordinates may change before a lossless write"
        )
    if not np.all(np.isfinite(model.coords)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(model.coords), axis=1))[0])
        raise DeckError(f"node {model.node_ids[bad]} has a non-finite coordinate; nothing written")
    return model.coords != src.coords_read


def _patched_file(
    fi: int,
    model: Model,
    src: DeckSource,
    changed: NDArray[np.bool_],
    cancel: Callable[[], bool] | None = None,
) -> tuple[bytearray, list[tuple[int, int, bytes]]]:
    """The file's bytes with fixed-width fields patched in place, plus line-level edits."""
    f = src.files[fi]
    data = f.writable_copy()
    edits: list[tuple[int, int, bytes]] = []
    nodes = np.flatnonzero((src.node_file == fi) & changed.any(axis=1))
    if len(nodes) == 0:
        return data, edits
    width = src.node_width[nodes]
    col = src.node_col[nodes]
    start = src.node_line_start[nodes]
    length = src.node_line_end[nodes] - start
    in_place = (width > 0) & (length >= col + 3 * width)
    buf = np.frombuffer(data, dtype=np.uint8)
    for w in np.unique(width[in_place]).tolist():
        sel = nodes[in_place & (width == w)]
        sel_mask = in_place & (width == w)
        for j in range(3):
            rows = sel[changed[sel, j]]
            if len(rows) == 0:
                continue
            offs = start[sel_mask][changed[sel, j]] + col[sel_mask][changed[sel, j]] + j * w
            # a block of nodes at a time: formatting keeps a dozen temporaries per value, and
            # the byte offsets are w per value (a whole-body deck has millions of nodes)
            for lo in range(0, len(rows), WRITE_BLOCK):
                raise_if_cancelled(cancel, "write cancelled; nothing written")
                block = slice(lo, lo + WRITE_BLOCK)
                text = _format(model, rows[block], j, w, src, fi)
                buf[offs[block, None] + np.arange(w)[None, :]] = text
    for k in np.flatnonzero(~in_place).tolist():
        node = int(nodes[k])
        s, e = int(start[k]), int(src.node_line_end[node])
        line = bytes(data[s:e])  # lines patched in place above are other lines
        if width[k] == 0:
            fields = line.decode("latin-1").split(",")
            while len(fields) < 4:
                fields.append("")
            for j in range(3):
                if changed[node, j]:
                    fields[1 + j] = format_free_float(model.coords[node, j])
            new = ",".join(fields).encode("latin-1")
        else:
            w, c = int(width[k]), int(col[k])
            last = max(j for j in range(3) if changed[node, j])
            padded = bytearray(line.ljust(c + (last + 1) * w))
            for j in range(3):
                if changed[node, j]:
                    padded[c + j * w : c + (j + 1) * w] = _format(
                        model, np.array([node]), j, w, src, fi
                    )[0].tobytes()
            new = bytes(padded)
        edits.append((s, e, new))
    return data, edits


def _format(model: Model, rows: NDArray, j: int, w: int, src: DeckSource, fi: int) -> NDArray:
    try:
        return format_fixed_width(model.coords[rows, j], w)
    except FieldError as exc:
        # name the node whose value does not fit, not the first of the block
        bad, message = rows[0], exc
        for row in rows.tolist():
            try:
                format_fixed_width(model.coords[[row], j], w)
            except FieldError as one:
                bad, message = row, one
                break
        f = src.files[fi]
        line = f.line_number(int(src.node_line_start[bad]))
        raise DeckError(f"node {model.node_ids[bad]}: {message}", f.path, line) from None


def _apply_edits(data: bytearray, edits: list[tuple[int, int, bytes]]) -> bytes | bytearray:
    if not edits:
        return data  # not copied: a whole-body deck is hundreds of MB
    out, pos = [], 0
    for s, e, new in sorted(edits, key=lambda t: t[0]):
        out.append(bytes(data[pos:s]))
        out.append(new)
        pos = e
    out.append(bytes(data[pos:]))
    return b"".join(out)


def _strip_for_inline(f: DeckFile, text: bytes, shift_edits: list) -> bytes:
    """Content of an included file for inlining: without its *KEYWORD line and after *END."""
    del shift_edits
    lines = text.split(b"\n")
    out = []
    for line in lines:
        head = line.lstrip()[:9].upper()
        if head.startswith(b"*END") and line.strip().upper() == b"*END":
            break
        if head.startswith(b"*KEYWORD"):
            opts = line.strip()[8:].upper().replace(b" ", b"")
            if b"LONG=" in opts or b"I10=" in opts:
                raise DeckError(
                    "cannot flatten: this include sets its own card format on *KEYWORD",
                    f.path,
                    None,
                )
            continue
        out.append(line)
    body = b"\n".join(out)
    if body and not body.endswith(b"\n"):
        body += b"\n"
    return body


def write_deck(
    model: Model,
    out_path: str | os.PathLike[str],
    *,
    flatten: bool = False,
    overwrite: bool = False,
    allow_overwrite_input: bool = False,
    cancel: Callable[[], bool] | None = None,
) -> list[Path]:
    """Write a model read by :func:`kneegui.io.lsdyna.read_deck` back out, losslessly.

    Parameters
    ----------
    model : Model
        A model whose ``source`` is the deck it was read from; only its coordinates may differ.
    out_path : str or PathLike
        Path of the main output file. Include files are written beside it with the same relative
        layout as in the input (unless ``flatten``).
    flatten : bool
        Write one self-contained file with every include inlined.
    overwrite : bool
        Replace existing files other than ``out_path`` (include files another deck written in
        the same folder may refer to) when their bytes would change; without it such a write is
        refused (:mod:`kneegui.io.output_plan`).
    allow_overwrite_input : bool
        Permit an output path that is one of the input files (off by default).
    cancel : callable, optional
        Asked between blocks of formatted values and of written bytes; True raises
        :class:`~kneegui.errors.Cancelled` and nothing is written (no file replaced, no
        temporary file left).

    Returns
    -------
    list of Path
        The deck's files (an existing include that already held the same bytes is left
        untouched and listed).

    Raises
    ------
    DeckError
        If the model cannot be written losslessly (different node count, non-finite coordinate,
        a value that does not fit its field, an include outside the deck folder with changed
        nodes); :class:`~kneegui.errors.OutputConflictError` (a ``DeckError``) if it would
        overwrite an input or, without ``overwrite``, change an existing file other than
        ``out_path``. Nothing is written then.
    """
    src = model.source
    if not isinstance(src, DeckSource):
        raise DeckError("this model was not read from a deck; use write_model() to write it")
    out_main = Path(out_path)
    changed = _changed_fields(model, src)
    rendered: dict[int, tuple[bytearray, list]] = {
        fi: _patched_file(fi, model, src, changed, cancel) for fi in range(len(src.files))
    }
    outputs: dict[Path, bytes | bytearray] = {}
    if flatten:

        def render(fi: int, stack: tuple[int, ...]) -> bytes | bytearray:
            data, edits = rendered[fi]
            f = src.files[fi]
            all_edits = list(edits)
            for start, end, children in f.includes:
                parts = [b"$ kneegui --flatten: the include that stood here is inlined below\n"]
                for child in children:
                    body = _strip_for_inline(src.files[child], render(child, (*stack, fi)), [])
                    name = src.files[child].rel_path.as_posix().encode("latin-1", "replace")
                    parts += [b"$ --- begin " + name + b"\n", body, b"$ --- end " + name + b"\n"]
                all_edits.append((start, end, b"".join(parts).rstrip(b"\n")))
            return _apply_edits(data, all_edits)

        outputs[out_main] = render(0, ())
    else:
        main_dir = out_main.parent
        for fi, f in enumerate(src.files):
            data, edits = rendered[fi]
            file_changed = bool(np.any(changed[src.node_file == fi]))
            if fi == 0:
                target = out_main
            elif f.rel_path.is_absolute() or (f.rel_path.parts and f.rel_path.parts[0] == ".."):
                if file_changed:
                    raise DeckError(
                        f"include {f.path} lies outside the deck's folder and has moved nodes; "
                        "write with flatten=True (--flatten)"
                    )
                continue
            else:
                target = main_dir / f.rel_path
            text = _apply_edits(data, edits)
            if target in outputs and outputs[target] != text:
                # an include named like the output (or two includes on one path)
                raise OutputConflictError(
                    f"two files of the deck would be written to {target}; choose another output "
                    "name or use --flatten",
                    target,
                )
            outputs[target] = text
    todo = plan_writes(
        outputs,
        out_main,
        inputs=[f.path for f in src.files],
        overwrite=overwrite,
        allow_overwrite_input=allow_overwrite_input,
    )
    atomic_write_many(todo, cancel)
    return list(outputs)


# ---------------------------------------------------------------------------------- fresh decks
def _int_lines(fmt: str, rows: NDArray[np.int64]) -> str:
    if len(rows) == 0:
        return ""
    flat = rows.reshape(-1).tolist()
    return (fmt * len(rows)) % tuple(flat)


def write_model(model: Model, path: str | os.PathLike[str], *, title: str | None = None) -> Path:
    """Write a model built in memory as a fresh, standard-format LS-DYNA keyword deck.

    Solids are written as 8-node ``*ELEMENT_SOLID`` cards (wedges, pyramids and tets with the
    usual repeated nodes: ``n1 n2 n3 n3 n4 n5 n6 n6``, ``n1..n5 n5 n5 n5``, ``n1 n2 n3 n4 n4 n4 n4
    n4``), 10-node tets in the two-card layout, triangles as 4-node shells with ``n4 = n3``.
    Long format is used when an id needs more than 8 digits.

    Returns
    -------
    Path
        The file written (atomically).
    """
    ids_max = max(
        [int(model.node_ids.max()) if model.n_nodes else 0]
        + [int(b.ids.max()) for b in model.blocks.values() if len(b)]
        + [int(b.part_ids.max()) for b in model.blocks.values() if len(b)]
    )
    long = ids_max > 99_999_999
    iw, fw = (20, 20) if long else (8, 16)
    sw = 20 if long else 10
    suffix = " +" if long else ""
    out: list[str] = ["*KEYWORD\n"]
    if title:
        out.append(f"*TITLE\n{title[:80]}\n")
    for pid in sorted(model.parts):
        p = model.parts[pid]
        out.append(f"*PART{suffix}\n{p.title[:70]}\n")
        out.append(f"{p.id:{sw}d}{p.secid:{sw}d}{p.mid:{sw}d}\n")
    declared = set(model.parts)
    for pid in model.part_ids().tolist():
        if pid not in declared:
            out.append(f"*PART{suffix}\npart {pid}\n{pid:{sw}d}{0:{sw}d}{0:{sw}d}\n")
    # nodes
    n = model.n_nodes
    if n:
        out.append(f"*NODE{suffix}\n")
        ids_txt = _int_lines(f"%{iw}d", model.node_ids[:, None]).encode("ascii")
        rows = np.full((n, iw + 3 * fw + 1), _SPACE, dtype=np.uint8)
        rows[:, :iw] = np.frombuffer(ids_txt, dtype=np.uint8).reshape(n, iw)
        for j in range(3):
            rows[:, iw + j * fw : iw + (j + 1) * fw] = format_fixed_width(model.coords[:, j], fw)
        rows[:, -1] = 10
        out.append(rows.tobytes().decode("ascii"))
    node_ids = model.node_ids
    fmt8 = f"%{iw}d"
    solid_patterns = {
        "hex8": [0, 1, 2, 3, 4, 5, 6, 7],
        "wedge6": [0, 1, 2, 2, 3, 4, 5, 5],
        "pyramid5": [0, 1, 2, 3, 4, 4, 4, 4],
        "tet4": [0, 1, 2, 3, 3, 3, 3, 3],
    }
    solid_text = []
    for etype, pattern in solid_patterns.items():
        b = model.blocks.get(etype)
        if b is None:
            continue
        table = np.column_stack([b.ids, b.part_ids, node_ids[b.conn[:, pattern]]])
        solid_text.append(_int_lines(fmt8 * 10 + "\n", table))
    if solid_text:
        out.append(f"*ELEMENT_SOLID{suffix}\n")
        out.extend(solid_text)
    b = model.blocks.get("tet10")
    if b is not None:
        out.append(f"*ELEMENT_SOLID{suffix}\n")
        table = np.column_stack([b.ids, b.part_ids, node_ids[b.conn]])
        out.append(_int_lines(fmt8 * 2 + "\n" + fmt8 * 10 + "\n", table))
    shell_text = []
    for etype, pattern in (("quad4", [0, 1, 2, 3]), ("tri3", [0, 1, 2, 2])):
        b = model.blocks.get(etype)
        if b is not None:
            table = np.column_stack([b.ids, b.part_ids, node_ids[b.conn[:, pattern]]])
            shell_text.append(_int_lines(fmt8 * 6 + "\n", table))
    if shell_text:
        out.append(f"*ELEMENT_SHELL{suffix}\n")
        out.extend(shell_text)
    b = model.blocks.get("beam2")
    if b is not None:
        out.append(f"*ELEMENT_BEAM{suffix}\n")
        table = np.column_stack([b.ids, b.part_ids, node_ids[b.conn], np.zeros(len(b), int)])
        out.append(_int_lines(fmt8 * 5 + "\n", table))
    b = model.blocks.get("discrete")
    if b is not None:
        out.append(f"*ELEMENT_DISCRETE{suffix}\n")
        table = np.column_stack([b.ids, b.part_ids, node_ids[b.conn], np.zeros(len(b), int)])
        out.append(_int_lines(fmt8 * 5 + f"{'1.0':>{fw}}" + "\n", table))
    for sid in sorted(model.node_sets):
        s = model.node_sets[sid]
        out.append(
            _set_text("SET_NODE_LIST_TITLE", suffix, s.id, s.title, node_ids[s.node_indices], sw)
        )
    for sid in sorted(model.part_sets):
        s = model.part_sets[sid]
        out.append(_set_text("SET_PART_LIST_TITLE", suffix, s.id, s.title, s.part_ids, sw))
    out.append("*END\n")
    target = Path(path)
    atomic_write_many({target: "".join(out).encode("ascii", "replace")})
    return target


def _set_text(keyword: str, suffix: str, sid: int, title: str, ids: NDArray, sw: int) -> str:
    ids = np.asarray(ids, dtype=np.int64)
    head = f"*{keyword}{suffix}\n{title[:80]}\n{sid:{sw}d}\n"
    full = len(ids) // 8 * 8
    body = _int_lines(f"%{sw}d" * 8 + "\n", ids[:full].reshape(-1, 8))
    tail = "".join(f"{i:{sw}d}" for i in ids[full:].tolist())
    return head + body + (tail + "\n" if tail else "")
