"""Read LS-DYNA keyword decks into a :class:`kneegui.model.Model`, vectorised.

What is parsed: ``*KEYWORD`` (``LONG=Y/S``, ``I10=Y``), ``*NODE``, ``*ELEMENT_SOLID`` (one-
and two-card layouts, 4/6/8/10 nodes, degenerate 8-node wedges/pyramids/tets),
``*ELEMENT_SOLID_ORTHO``, ``*ELEMENT_SHELL`` (with ``_THICKNESS``, ``_BETA``, ``_MCID``,
``_OFFSET``), ``*ELEMENT_BEAM`` (with its one-card options), ``*ELEMENT_DISCRETE``, ``*PART``
(with ``_CONTACT``, ``_PRINT``, ``_INERTIA``, ``_ATTACHMENT_NODES``),
``*SET_NODE(_LIST)(_TITLE)``, ``*SET_PART(_LIST)(_TITLE)``, ``*INCLUDE``,
``*INCLUDE_PATH(_RELATIVE)``, ``$`` comments and ``*END``. Every other keyword is kept verbatim
in the file bytes, which the lossless writer reuses.

Card formats: a card with a comma is free format; otherwise fixed columns: standard (I8 / E16, sets
and parts I10), ``I10`` (``%`` suffix or ``*KEYWORD I10=Y``) or long (``+`` suffix or
``*KEYWORD LONG=Y``: every field 20 wide). Blank lines inside data blocks are skipped.

Large fixed-format blocks are cut into (n, width) byte arrays and parsed column-wise; any card the
fast path cannot read is re-parsed exactly, and a card that is wrong raises :class:`DeckError`
naming the file and line.
"""

from __future__ import annotations

import os
import re
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import DeckError
from kneegui.io.fields import (
    FieldError,
    parse_float_columns,
    parse_float_field,
    parse_int_columns,
    parse_int_field,
)
from kneegui.model import ElementBlock, Model, NodeSet, Part, PartSet
from kneegui.topology import split_degenerate_solids

_NL, _CR, _STAR, _DOLLAR, _SPACE, _COMMA, _TAB = 10, 13, 42, 36, 32, 44, 9

STANDARD, I10, LONG = "standard", "i10", "long"
_CHUNK = 262_144  # cards parsed per vectorised step
_KEYWORD_NAME = re.compile(r"^[A-Z][A-Z0-9_]*$")
#: First word of every LS-DYNA keyword family (R14 manual volumes I-III); others get a warning.
_KEYWORD_FAMILIES = frozenset(
    "AIRBAG ALE BATTERY BOUNDARY CASE CESE CHANGE CHEMISTRY COMMENT COMPONENT CONSTRAINED "
    "CONTACT CONTROL COSIM DAMPING DATABASE DEFINE DEFORMABLE DELETE DUALCESE EF ELEMENT EM END "
    "EOS FATIGUE FREQUENCY HOURGLASS ICFD IGA INCLUDE INITIAL INTEGRATION INTERFACE KEYWORD LOAD "
    "LSO MAT MESH MODULE NODE PARAMETER PART PERTURBATION RIGID RIGIDWALL RVE SECTION SENSOR SET "
    "STOCHASTIC TERMINATION TITLE TRANSLATE USER ISPG PARTICLE SPH".split()
)


@dataclass
class DeckFile:
    """One file of a deck: where it is, where it goes on output, and its bytes.

    The bytes stay in memory while the deck is read; :func:`read_deck` then lets them go
    (:meth:`release`), because a whole-body deck is hundreds of MB that only the lossless
    writer needs again. :attr:`data` reads them back from disk then, checked against the
    size and CRC-32 taken when the file was read: a file that changed since is refused rather
    than patched at stale byte offsets.
    """

    path: Path
    rel_path: Path
    resident: bytes | None = field(repr=False)
    line_starts: NDArray[np.int64] | None = field(repr=False)
    line_ends: NDArray[np.int64] | None = field(repr=False)  # exclusive, without "\r\n"
    includes: list[tuple[int, int, list[int]]] = field(default_factory=list, repr=False)
    end_offset: int | None = None  # byte offset of the *END line, if any
    size: int = field(init=False, default=0)
    crc32: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        if self.resident is not None:
            self.size = len(self.resident)
            self.crc32 = zlib.crc32(self.resident)

    @property
    def data(self) -> bytes | bytearray:
        """The file's bytes as they were read (from memory, or read back and checked)."""
        return self.resident if self.resident is not None else self.read_back()

    def writable_copy(self) -> bytearray:
        """A fresh, mutable copy of the file's bytes for the writer to patch."""
        return bytearray(self.resident) if self.resident is not None else self.read_back()

    def read_back(self) -> bytearray:
        """The file's bytes read again from disk, checked against the read.

        Raises
        ------
        DeckError
            If the file cannot be read or its size or CRC-32 differ from the read's.
        """
        buf = bytearray(self.size + 1)  # one more byte than expected: a longer file shows
        try:
            with open(self.path, "rb") as fh:
                n = fh.readinto(buf)
        except OSError as exc:
            raise DeckError(
                f"cannot read it again to write the deck: {exc.strerror}", self.path, None
            ) from None
        if n != self.size or zlib.crc32(memoryview(buf)[:n]) != self.crc32:
            raise DeckError(
                "changed on disk since it was read; open the deck again before writing",
                self.path,
                None,
            )
        del buf[n:]
        return buf

    def release(self) -> None:
        """Drop the bytes and line tables from memory (:attr:`data` reads them back)."""
        self.resident = None
        self.line_starts = None
        self.line_ends = None

    def line_number(self, offset: int) -> int:
        """1-based line number of a byte offset."""
        if self.line_starts is None:
            return self.data.count(b"\n", 0, offset) + 1
        return int(np.searchsorted(self.line_starts, offset, side="right"))


@dataclass
class DeckSource:
    """What the lossless writer needs to reproduce a deck: its files and where node fields are.

    ``node_*`` arrays are aligned with ``Model.node_ids``.
    """

    files: list[DeckFile]
    coords_read: NDArray[np.float64]
    node_file: NDArray[np.int32]
    node_line_start: NDArray[np.int64]
    node_line_end: NDArray[np.int64]
    node_col: NDArray[np.int32]  # column where the x field starts (fixed format)
    node_width: NDArray[np.int32]  # field width; 0 = free-format (comma) line
    warnings: list[str] = field(default_factory=list)
    #: what LS-DYNA would refuse (read with ``check_references=False``; else the first raises)
    problems: list[str] = field(default_factory=list)

    @property
    def main(self) -> DeckFile:
        """The file that was opened."""
        return self.files[0]


# ---------------------------------------------------------------------------------- keywords
_ELEMENT_KEYWORDS = ("ELEMENT_SOLID", "ELEMENT_SHELL", "ELEMENT_BEAM", "ELEMENT_DISCRETE")
_SHELL_EXTRA = {"THICKNESS": 1, "BETA": 1, "MCID": 1, "OFFSET": 1}
_BEAM_EXTRA = {
    "THICKNESS": 1,
    "SCALAR": 1,
    "SCALR": 1,
    "SECTION": 1,
    "PID": 1,
    "OFFSET": 1,
    "ORIENTATION": 1,
    "WARPAGE": 1,
    "ELBOW": 1,
}
#: Cards each *PART option adds after the PID card (LS-DYNA manual, *PART); INERTIA adds a
#: fourth card when its IRCS field (card 3, field 5) is 1.
_PART_EXTRA = {"INERTIA": 3, "REPOSITION": 1, "CONTACT": 1, "PRINT": 1, "ATTACHMENT_NODES": 1}


def _part_options(name: str) -> list[str] | None:
    """The options of a ``*PART...`` keyword name, or None when one is not in ``_PART_EXTRA``."""
    rest = name[5:].replace("ATTACHMENT_NODES", "ATTACHMENT-NODES")
    opts = [o.replace("-", "_") for o in rest.split("_") if o]
    return opts if all(o in _PART_EXTRA for o in opts) else None


@dataclass
class _Block:
    file: int
    keyword: str  # upper-case name without options
    fmt: str
    line_index: int  # index of the keyword line
    data_lines: NDArray[np.int64]  # indices of the non-comment, non-blank data lines
    card_lines: NDArray[np.int64]  # the same with blank lines (blank cards)
    decoration: str = ""  # text after the keyword name and format modifier, kept verbatim


class _DeckReader:
    def __init__(self, main_path: Path, strict: bool = True):
        self.main_path = main_path
        self.strict = strict
        self.main_dir = main_path.parent
        self.files: list[DeckFile] = []
        self.include_dirs: list[Path] = []
        self.global_fmt = STANDARD
        self.warnings: list[str] = []
        # accumulated results
        self.node_chunks: list[tuple] = []
        self.solid_chunks: list[tuple] = []  # (ids, pids, conn(M,10) ids, nnodes(M,), file, starts)
        self.shell_chunks: list[tuple] = []
        self.beam_chunks: list[tuple] = []
        self.discrete_chunks: list[tuple] = []
        self.parts: dict[int, Part] = {}
        self.part_where: dict[int, tuple[int, int]] = {}
        self.node_sets: list[tuple[int, str, NDArray[np.int64], int, int]] = []
        self.part_sets: list[tuple[int, str, NDArray[np.int64], int, int]] = []
        self.unread_parts: list[str] = []  # keywords that may define parts kneegui does not read

    # ------------------------------------------------------------------ files
    def read_file(self, path: Path, rel: Path, stack: tuple[Path, ...], ref: tuple | None) -> int:
        resolved = path.resolve()
        if resolved in stack:
            chain = " -> ".join(p.name for p in (*stack, resolved))
            raise self._error_at(ref, f"include cycle: {chain}")
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise self._error_at(ref, f"file not found: {path}") from None
        except IsADirectoryError:
            raise self._error_at(ref, f"is a directory, not a deck: {path}") from None
        except OSError as exc:
            raise self._error_at(ref, f"cannot read {path}: {exc.strerror}") from None
        if b"\x00" in data[:65536] or b"\x00" in data:
            raise DeckError("binary data (NUL bytes): not a keyword deck", path, None)
        arr = np.frombuffer(data, dtype=np.uint8)
        nl = np.flatnonzero(arr == _NL)
        starts = np.concatenate([[0], nl + 1]).astype(np.int64)
        ends = np.concatenate([nl, [len(data)]]).astype(np.int64)
        if data.endswith(b"\n") or not data:
            starts, ends = starts[:-1], ends[:-1]
        has_cr = (ends > starts) & (arr[np.maximum(ends - 1, 0)] == _CR) if len(arr) else ends > 0
        ends = ends - has_cr.astype(np.int64)
        deck_file = DeckFile(resolved, rel, data, starts, ends)
        index = len(self.files)
        self.files.append(deck_file)
        self._parse_file(index, arr, (*stack, resolved))
        return index

    def _error_at(self, ref: tuple | None, message: str) -> DeckError:
        if ref is None:
            return DeckError(message, self.main_path, None)
        file_index, line_index = ref
        return DeckError(message, self.files[file_index].path, line_index + 1)

    def _line(self, f: DeckFile, i: int) -> bytes:
        return f.data[f.line_starts[i] : f.line_ends[i]]

    def _fail(self, file_index: int, line_index: int, message: str) -> DeckError:
        return DeckError(message, self.files[file_index].path, int(line_index) + 1)

    # ------------------------------------------------------------------ structure
    def _parse_file(self, fi: int, arr: NDArray[np.uint8], stack: tuple[Path, ...]) -> None:
        f = self.files[fi]
        n_lines = len(f.line_starts)
        if n_lines == 0:
            return
        nonempty = f.line_ends > f.line_starts
        first = np.where(nonempty, arr[np.minimum(f.line_starts, max(len(arr) - 1, 0))], _SPACE)
        is_kw = first == _STAR
        is_comment = first == _DOLLAR
        is_blank = ~nonempty
        # lines of white space only are blank too: look at the first 16 characters of each
        # candidate vectorised, and only the rare undecided lines one by one
        cand = np.flatnonzero(
            nonempty & ~is_kw & ~is_comment & ((first == _SPACE) | (first == _TAB))
        )
        if len(cand):
            # most lines end in a visible character: decided by one gather
            last = arr[np.maximum(f.line_ends[cand] - 1, 0)]
            cand = cand[(last == _SPACE) | (last == _TAB)]
        if len(cand):
            probe = 16
            cols = np.arange(probe)
            pos = f.line_starts[cand][:, None] + cols[None, :]
            inside = cols[None, :] < (f.line_ends[cand] - f.line_starts[cand])[:, None]
            chars = arr[np.minimum(pos, len(arr) - 1)]
            visible = inside & (chars != _SPACE) & (chars != _TAB)
            decided = visible.any(axis=1)
            short = ~decided & (f.line_ends[cand] - f.line_starts[cand] <= probe)
            is_blank[cand[short]] = True
            for i in cand[~decided & ~short].tolist():
                if not self._line(f, i).strip():
                    is_blank[i] = True
        kw_lines = np.flatnonzero(is_kw)
        card_mask = ~is_kw & ~is_comment
        data_mask = card_mask & ~is_blank
        if len(kw_lines) == 0 or np.any(data_mask[: kw_lines[0]]):
            first_data = int(np.flatnonzero(data_mask)[0]) if data_mask.any() else 0
            if data_mask.any():
                raise self._fail(fi, first_data, "data line before the first keyword")
        bounds = np.concatenate([kw_lines, [n_lines]])
        for k, kw_line in enumerate(kw_lines.tolist()):
            header = self._line(f, kw_line).decode("latin-1")
            name, fmt, options = self._keyword(header)
            if not _KEYWORD_NAME.match(name):
                raise self._fail(fi, kw_line, f"{header.strip()[:40]!r} is not a keyword name")
            self._check_keyword_family(fi, kw_line, name)
            lo, hi = kw_line + 1, int(bounds[k + 1])
            data_lines = lo + np.flatnonzero(data_mask[lo:hi])
            # a blank line is a card (all fields default), as LS-DYNA counts cards
            card_lines = lo + np.flatnonzero(card_mask[lo:hi])
            decoration = "" if name == "KEYWORD" else options.strip()
            block = _Block(fi, name, fmt, kw_line, data_lines, card_lines, decoration)
            if name == "END":
                f.end_offset = int(f.line_starts[kw_line])
                break
            self._dispatch(block, options, stack)

    def _check_keyword_family(self, fi: int, line: int, name: str) -> None:
        """Warn on a keyword outside the LS-DYNA families (it is kept verbatim)."""
        family = name.split("_", 1)[0]
        if family not in _KEYWORD_FAMILIES:
            self.warnings.append(
                f"{self.files[fi].path}:{line + 1}: *{name} is not a keyword family kneegui "
                "knows; kept verbatim"
            )

    def _keyword(self, header: str) -> tuple[str, str, str]:
        """Name, card format and the rest of a keyword line.

        The name is the first word after ``*``; a ``+`` (long), ``-`` (standard) or ``%`` (I10)
        at its end or as the next word sets the card format of this keyword. What follows is
        text LS-DYNA does not read as part of the name (``*KEYWORD`` options, or a label such as
        LS-PrePost's ``(ten nodes format)``): it is returned as is and written back verbatim.
        """
        text = header.rstrip()
        token, _, options = text[1:].partition(" ")
        token = token.strip()
        fmt = self.global_fmt
        modifiers = {"+": LONG, "%": I10, "-": STANDARD}
        if token[-1:] in modifiers:
            token, fmt = token[:-1], modifiers[token[-1]]
        else:
            first, _, after = options.strip().partition(" ")
            if first in modifiers:
                fmt, options = modifiers[first], after
        return token.upper(), fmt, options

    def _dispatch(self, b: _Block, options: str, stack: tuple[Path, ...]) -> None:
        name = b.keyword
        if name == "KEYWORD":
            opts = options.upper().replace(" ", "")
            if re.search(r"LONG=Y", opts):
                self.global_fmt = LONG
            elif re.search(r"I10=Y", opts):
                self.global_fmt = I10
            elif re.search(r"LONG=S|LONG=N", opts):
                self.global_fmt = STANDARD
        elif name == "NODE":
            self._parse_nodes(b)
        elif name.startswith("ELEMENT_"):
            self._parse_elements(b)
        elif name == "PART" or (name.startswith("PART_") and _part_options(name) is not None):
            self._parse_parts(b)
        elif name.startswith("PART_") and not name.startswith("PART_SENSOR"):
            # a part kneegui cannot read defines ids it does not know: undefined part ids in
            # elements are then listed as warnings, not refused
            self.unread_parts.append(f"{self.files[b.file].path}:{b.line_index + 1}: *{name}")
        elif name in ("SET_NODE", "SET_NODE_LIST", "SET_NODE_TITLE", "SET_NODE_LIST_TITLE"):
            self._parse_set(b, self.node_sets)
        elif name in ("SET_PART", "SET_PART_LIST", "SET_PART_TITLE", "SET_PART_LIST_TITLE"):
            self._parse_set(b, self.part_sets)
        elif name in ("INCLUDE_PATH", "INCLUDE_PATH_RELATIVE"):
            f = self.files[b.file]
            for i in b.data_lines.tolist():
                text = self._line(f, i).decode("latin-1").strip()
                p = Path(text)
                self.include_dirs.append(p if p.is_absolute() else self.main_dir / p)
        elif name == "INCLUDE":
            self._parse_include(b, stack)
        elif name.startswith("INCLUDE"):
            self.unread_parts.append(f"{self.files[b.file].path}:{b.line_index + 1}: *{name}")
            self.warnings.append(
                f"{self.files[b.file].path}:{b.line_index + 1}: *{name} is kept verbatim; "
                "the files it names are not read"
            )

    # ------------------------------------------------------------------ cards
    def _card_groups(self, b: _Block, per: int) -> NDArray[np.int64]:
        """Card lines of a keyword with ``per`` cards per item, blank cards included.

        Blank lines after the last data line end the block unless they complete its last item
        (a blank last card, e.g. a blank thickness card)."""
        lines = b.card_lines
        if per == 1 or len(b.data_lines) == 0:
            return b.data_lines
        n_trailing = int(np.count_nonzero(lines > b.data_lines[-1]))
        keep = len(lines) - n_trailing
        missing = (-keep) % per
        return lines[: keep + (missing if missing <= n_trailing else 0)]

    def _card_texts(self, b: _Block) -> list[bytes]:
        f = self.files[b.file]
        return [self._line(f, i) for i in b.data_lines.tolist()]

    def _fixed_array(self, b: _Block, lines: NDArray[np.int64], width: int) -> NDArray[np.uint8]:
        """(n, width) bytes of the given lines, padded with spaces (may be a read-only view)."""
        f = self.files[b.file]
        arr = np.frombuffer(f.data, dtype=np.uint8)
        n = len(lines)
        if n == 0 or len(arr) == 0:
            return np.full((n, width), _SPACE, dtype=np.uint8)
        starts = f.line_starts[lines]
        lengths = f.line_ends[lines] - starts
        full = bool(np.all(lengths >= width))
        if full and n > 1:
            stride = np.diff(starts)
            if np.all(stride == stride[0]) and stride[0] > 0:
                # equally long lines (machine-written decks): a zero-copy strided view
                return np.lib.stride_tricks.as_strided(
                    arr[starts[0] :], shape=(n, width), strides=(int(stride[0]), 1), writeable=False
                )
        idx = starts[:, None] + np.arange(width)[None, :]
        out = np.take(arr, np.minimum(idx, len(arr) - 1))
        if not full:
            out[np.arange(width)[None, :] >= lengths[:, None]] = _SPACE
        return out

    def _has_free_or_tab(self, b: _Block, lines: NDArray[np.int64]) -> bool:
        if len(lines) == 0:
            return False
        f = self.files[b.file]
        lo, hi = int(f.line_starts[lines[0]]), int(f.line_ends[lines[-1]])
        chunk = f.data[lo:hi]
        return b"," in chunk or b"\t" in chunk

    def _split_free(self, b: _Block, line: int) -> list[str]:
        text = self._line(self.files[b.file], line).decode("latin-1")
        return [t.strip() for t in text.split(",")]

    def _fixed_fields(self, text: bytes, widths: list[int]) -> list[bytes]:
        out, pos = [], 0
        for w in widths:
            out.append(text[pos : pos + w])
            pos += w
        return out

    def _card_fields(self, b: _Block, line: int, widths: list[int]) -> list[str]:
        """Fields of one card (free or fixed format), as stripped strings."""
        text = self._line(self.files[b.file], line)
        if b"\t" in text:
            raise self._fail(b.file, line, "tab character in a card: use spaces or commas")
        if b"," in text:
            fields = self._split_free(b, line)
            return fields + [""] * max(0, len(widths) - len(fields))
        return [t.decode("latin-1").strip() for t in self._fixed_fields(text, widths)]

    def _int(self, b: _Block, line: int, text: str, what: str) -> int:
        try:
            return parse_int_field(text)
        except FieldError as exc:
            raise self._fail(b.file, line, f"{what}: {exc}") from None

    def _float(self, b: _Block, line: int, text: str, what: str) -> float:
        try:
            return parse_float_field(text)
        except FieldError as exc:
            raise self._fail(b.file, line, f"{what}: {exc}") from None

    # ------------------------------------------------------------------ *NODE
    def _node_widths(self, fmt: str) -> tuple[int, int]:
        return {STANDARD: (8, 16), I10: (10, 16), LONG: (20, 20)}[fmt]

    def _parse_nodes(self, b: _Block) -> None:
        lines = b.data_lines
        n = len(lines)
        if n == 0:
            return
        wid, wx = self._node_widths(b.fmt)
        f = self.files[b.file]
        ids = np.zeros(n, dtype=np.int64)
        xyz = np.zeros((n, 3), dtype=np.float64)
        col = np.full(n, wid, dtype=np.int32)
        width = np.full(n, wx, dtype=np.int32)
        slow = np.zeros(n, dtype=bool)
        if self._has_free_or_tab(b, lines):
            f_data = f.data
            for k, i in enumerate(lines.tolist()):
                text = f_data[f.line_starts[i] : f.line_ends[i]]
                if b"," in text or b"\t" in text:
                    slow[k] = True
        fast = np.flatnonzero(~slow)
        if len(fast):
            chars = self._fixed_array(b, lines[fast], wid + 3 * wx)
            vals, bad = parse_int_columns(chars[:, :wid])
            ids[fast] = vals
            slow[fast[bad]] = True
            for j in range(3):
                colv = parse_float_columns(chars[:, wid + j * wx : wid + (j + 1) * wx])
                if colv is None:
                    # find the offending rows exactly
                    for k in fast.tolist():
                        slow[k] = True
                    break
                xyz[fast, j] = colv
        for k in np.flatnonzero(slow).tolist():
            line = int(lines[k])
            text = self._line(f, line)
            if b"," in text:
                fields = self._card_fields(b, line, [wid, wx, wx, wx])
                width[k] = 0
            else:
                fields = self._card_fields(b, line, [wid, wx, wx, wx])
            ids[k] = self._int(b, line, fields[0], "node id")
            for j in range(3):
                xyz[k, j] = self._float(
                    b, line, fields[1 + j] if len(fields) > 1 + j else "", "xyz"[j] + " coordinate"
                )
        if np.any(ids <= 0):
            k = int(np.flatnonzero(ids <= 0)[0])
            raise self._fail(b.file, lines[k], f"node id must be positive, got {ids[k]}")
        if not np.all(np.isfinite(xyz)):
            k = int(np.flatnonzero(~np.all(np.isfinite(xyz), axis=1))[0])
            raise self._fail(b.file, lines[k], "coordinate is not a finite number")
        self.node_chunks.append(
            (
                ids,
                xyz,
                np.full(n, b.file, dtype=np.int32),
                f.line_starts[lines],
                f.line_ends[lines],
                col,
                width,
            )
        )

    # ------------------------------------------------------------------ *ELEMENT_...
    def _int_width(self, fmt: str) -> int:
        return {STANDARD: 8, I10: 10, LONG: 20}[fmt]

    def _parse_elements(self, b: _Block) -> None:
        name = b.keyword
        base = next((k for k in _ELEMENT_KEYWORDS if name == k or name.startswith(k + "_")), None)
        suffix = name[len(base) + 1 :] if base and name != base else ""
        opts = [o for o in suffix.split("_") if o]
        f = self.files[b.file]
        if base == "ELEMENT_SOLID" and opts in ([], ["ORTHO"], ["TET4TOTET10"], ["H8TOH20"]):
            # _TET4TOTET10 / _H8TOH20 use the *ELEMENT_SOLID cards; LS-DYNA makes the mid-edge
            # nodes from the corners at run time, so moving the corners is all a pose needs
            self._parse_solids(b, extra_cards=2 if opts == ["ORTHO"] else 0)
        elif base == "ELEMENT_SHELL" and all(o in _SHELL_EXTRA for o in opts):
            extra = int(any(o in ("THICKNESS", "BETA", "MCID") for o in opts))
            extra += int("OFFSET" in opts)
            self._parse_simple(b, 1 + extra, 6, self.shell_chunks)
        elif base == "ELEMENT_BEAM" and all(o in _BEAM_EXTRA for o in opts):
            self._parse_simple(b, 1 + len(opts), 4, self.beam_chunks)
        elif base == "ELEMENT_DISCRETE" and opts in ([], ["LCO"]):
            self._parse_simple(b, 1 + len(opts), 4, self.discrete_chunks)
        else:
            self.warnings.append(
                f"{f.path}:{b.line_index + 1}: *{name} is not a mesh element kneegui reads; "
                "kept verbatim"
            )

    def _parse_simple(self, b: _Block, cards: int, n_fields: int, sink: list) -> None:
        """Elements whose first card is EID PID N1..N(n_fields-2) followed by ``cards-1`` cards.

        With several cards per element a blank line is a card (e.g. a blank thickness card).
        """
        lines = self._card_groups(b, cards)
        if len(lines) % cards:
            raise self._fail(
                b.file, lines[-1], f"*{b.keyword}: incomplete element (expected {cards} cards each)"
            )
        first = lines[::cards]
        w = self._int_width(b.fmt)
        vals = self._int_table(b, first, [w] * n_fields)
        f = self.files[b.file]
        sink.append((vals[:, 0], vals[:, 1], vals[:, 2:], b.file, f.line_starts[first], first))

    def _int_table(self, b: _Block, lines: NDArray[np.int64], widths: list[int]) -> NDArray:
        """Integer fields of the given cards as an (n, len(widths)) array."""
        n = len(lines)
        out = np.zeros((n, len(widths)), dtype=np.int64)
        if n == 0:
            return out
        slow = np.zeros(n, dtype=bool)
        if self._has_free_or_tab(b, lines):
            f = self.files[b.file]
            for k, i in enumerate(lines.tolist()):
                text = f.data[f.line_starts[i] : f.line_ends[i]]
                slow[k] = b"," in text or b"\t" in text
        fast = np.flatnonzero(~slow)
        if len(fast) and len(set(widths)) == 1:
            # equal widths: all fields of all cards in one vectorised call
            w, nf = widths[0], len(widths)
            for lo in range(0, len(fast), _CHUNK):  # chunks bound the temporaries' memory
                rows = fast[lo : lo + _CHUNK]
                chars = self._fixed_array(b, lines[rows], w * nf)
                vals, bad = parse_int_columns(np.ascontiguousarray(chars).reshape(-1, w))
                out[rows] = vals.reshape(len(rows), nf)
                slow[rows[bad.reshape(len(rows), nf).any(axis=1)]] = True
        elif len(fast):
            chars = self._fixed_array(b, lines[fast], sum(widths))
            pos = 0
            for j, w in enumerate(widths):
                vals, bad = parse_int_columns(chars[:, pos : pos + w])
                out[fast, j] = vals
                slow[fast[bad]] = True
                pos += w
        for k in np.flatnonzero(slow).tolist():
            line = int(lines[k])
            fields = self._card_fields(b, line, widths)
            for j in range(len(widths)):
                out[k, j] = self._int(b, line, fields[j] if j < len(fields) else "", "field")
        return out

    def _parse_solids(self, b: _Block, extra_cards: int) -> None:
        if len(b.data_lines) == 0:
            return
        w = self._int_width(b.fmt)
        f = self.files[b.file]
        # two-card layout: the first card holds EID and PID only; LS-PrePost labels it
        # "*ELEMENT_SOLID (ten nodes format)"
        head = self._int_table(b, b.data_lines[:1], [w] * 10)
        two_card = bool(np.all(head[0, 2:] == 0)) or "TEN NODES" in b.decoration.upper()
        per = (2 if two_card else 1) + extra_cards
        # one card per element: blank lines are skipped; several: a blank line is a card
        lines = self._card_groups(b, per)
        if len(lines) % per:
            raise self._fail(b.file, lines[-1], f"*{b.keyword}: incomplete element card group")
        first = lines[::per]
        if two_card:
            ep = self._int_table(b, first, [w, w])
            nodes = self._int_table(b, lines[1::per], [w] * 10)
        else:
            vals = self._int_table(b, first, [w] * 10)
            ep, nodes = (
                vals[:, :2],
                np.concatenate([vals[:, 2:], np.zeros((len(first), 2), dtype=np.int64)], 1),
            )
        self.solid_chunks.append((ep[:, 0], ep[:, 1], nodes, b.file, f.line_starts[first], first))

    # ------------------------------------------------------------------ *PART
    def _parse_parts(self, b: _Block) -> None:
        """``*PART`` and its options; the heading card may be blank and still counts."""
        f = self.files[b.file]
        opts = _part_options(b.keyword) or []
        lines = b.card_lines.tolist()
        last_data = int(b.data_lines[-1]) if len(b.data_lines) else -1
        w = 20 if b.fmt == LONG else 10
        k = 0
        while k < len(lines):
            if lines[k] > last_data:
                break  # blank lines after the last part
            if k + 1 >= len(lines):
                raise self._fail(b.file, lines[k], "*PART: heading card without a PID card")
            title = self._line(f, lines[k]).decode("latin-1").rstrip()
            fields = self._card_fields(b, lines[k + 1], [w] * 8)
            pid = self._int(b, lines[k + 1], fields[0], "part id (PID)")
            secid = self._int(b, lines[k + 1], fields[1], "SECID")
            mid = self._int(b, lines[k + 1], fields[2], "MID")
            n_cards = 2 + sum(_PART_EXTRA[o] for o in opts)
            if "INERTIA" in opts and k + 2 < len(lines):
                # card 3: XC YC ZC TM IRCS NODEID; IRCS = 1 adds the local-axes card
                card3 = self._card_fields(b, lines[k + 2], [w] * 8)
                if self._float(b, lines[k + 2], card3[4], "IRCS") == 1:
                    n_cards += 1
            if pid <= 0:
                raise self._fail(b.file, lines[k + 1], f"part id must be positive, got {pid}")
            if pid in self.parts:
                pf, pl = self.part_where[pid]
                raise self._fail(
                    b.file,
                    lines[k + 1],
                    f"part {pid} is defined twice (first at {self.files[pf].path}:{pl + 1})",
                )
            end = lines[min(k + n_cards, len(lines)) - 1]
            card_text = f.data[f.line_starts[b.line_index] : f.line_ends[end]].decode("latin-1")
            self.parts[pid] = Part(pid, title.strip(), secid, mid, card_text)
            self.part_where[pid] = (b.file, lines[k + 1])
            k += n_cards

    # ------------------------------------------------------------------ *SET_...
    def _parse_set(self, b: _Block, sink: list) -> None:
        f = self.files[b.file]
        lines = b.card_lines.tolist()  # the title card may be blank
        if not lines:
            raise self._fail(b.file, b.line_index, f"*{b.keyword} without a set id card")
        k = 0
        title = ""
        if b.keyword.endswith("_TITLE"):
            title = self._line(f, lines[0]).decode("latin-1").strip()
            k = 1
        if k >= len(lines):
            raise self._fail(b.file, lines[-1], f"*{b.keyword} without a set id card")
        w = 20 if b.fmt == LONG else 10
        head = self._card_fields(b, lines[k], [w] * 6)
        sid = self._int(b, lines[k], head[0], "set id (SID)")
        if sid <= 0:
            raise self._fail(b.file, lines[k], f"set id must be positive, got {sid}")
        # blank id cards are eight zeros: skipped like zero ids
        rest = b.data_lines[b.data_lines > lines[k]]
        if len(rest):
            vals = self._int_table(b, rest, [w] * 8)
            ids = vals[vals != 0]
        else:
            ids = np.zeros(0, dtype=np.int64)
        sink.append((sid, title, ids, b.file, lines[k]))

    # ------------------------------------------------------------------ *INCLUDE
    def _parse_include(self, b: _Block, stack: tuple[Path, ...]) -> None:
        f = self.files[b.file]
        lines = b.data_lines.tolist()
        names: list[tuple[str, int]] = []
        pending = ""
        for i in lines:
            text = self._line(f, i).decode("latin-1").rstrip()
            # long names continue on the next line when a line ends with " +"
            if text.endswith(" +"):
                pending += text[:-2].strip()
                continue
            names.append((pending + text.strip(), i))
            pending = ""
        if pending:
            names.append((pending, lines[-1]))
        included = []
        for name, i in names:
            path = self._resolve_include(name, f.path.parent)
            if path is None:
                raise self._fail(b.file, i, f"include file not found: {name}")
            try:
                rel = path.resolve().relative_to(self.main_dir.resolve())
            except ValueError:
                rel = Path(os.path.relpath(path.resolve(), self.main_dir.resolve()))
            included.append(self.read_file(path, rel, stack, (b.file, i)))
        f.includes.append(
            (
                int(f.line_starts[b.line_index]),
                int(f.line_ends[lines[-1]]) if lines else int(f.line_ends[b.line_index]),
                included,
            )
        )

    def _resolve_include(self, name: str, here: Path) -> Path | None:
        p = Path(name)
        if p.is_absolute():
            return p if p.exists() else None
        for base in (here, self.main_dir, *self.include_dirs):
            cand = base / p
            if cand.is_file():
                return cand
        return None

    # ------------------------------------------------------------------ model
    def build(self) -> Model:
        if self.node_chunks:
            ids, xyz, nfile, nstart, nend, ncol, nwidth = (
                np.concatenate([c[j] for c in self.node_chunks]) for j in range(7)
            )
        else:
            ids = np.zeros(0, dtype=np.int64)
            xyz = np.zeros((0, 3))
            nfile = np.zeros(0, dtype=np.int32)
            nstart = nend = np.zeros(0, dtype=np.int64)
            ncol = nwidth = np.zeros(0, dtype=np.int32)
        order = np.argsort(ids, kind="stable")
        sids = ids[order]
        dup = np.flatnonzero(sids[1:] == sids[:-1])
        if len(dup):
            second = order[dup[0] + 1]
            first_ = order[dup[0]]
            raise DeckError(
                f"node id {sids[dup[0]]} is defined twice (first at "
                f"{self.files[nfile[first_]].path}:"
                f"{self.files[nfile[first_]].line_number(nstart[first_])})",
                self.files[nfile[second]].path,
                self.files[nfile[second]].line_number(nstart[second]),
            )

        contiguous = len(sids) > 0 and sids[-1] - sids[0] + 1 == len(sids)

        def lookup(node_ids: NDArray[np.int64], chunk: tuple, allow_zero_tail: bool = False):
            if contiguous and node_ids.size and node_ids.min() >= sids[0]:
                # ids are a range (the usual case): index arithmetic, no search
                if node_ids.max() <= sids[-1]:
                    return order[node_ids - sids[0]]
            if contiguous:
                pos_c = np.clip(node_ids - sids[0], 0, len(sids) - 1)
                ok = (node_ids >= sids[0]) & (node_ids <= sids[-1])
            else:
                pos = np.searchsorted(sids, node_ids)
                pos_c = np.minimum(pos, max(len(sids) - 1, 0))
                ok = (sids[pos_c] == node_ids) if len(sids) else np.zeros(node_ids.shape, bool)
            if allow_zero_tail:
                ok |= node_ids == 0
            if not np.all(ok):
                r, c = np.argwhere(~ok)[0]
                fi, starts = chunk[3], chunk[4]
                fobj = self.files[fi]
                raise DeckError(
                    f"element {chunk[0][r]} refers to node {node_ids[r, c]}, which is not defined",
                    fobj.path,
                    fobj.line_number(starts[r]),
                )
            return np.where(node_ids == 0, -1, order[pos_c])

        blocks: dict[str, list] = {}

        def add(etype: str, eids, pids, conn):
            if len(eids):
                blocks.setdefault(etype, []).append((eids, pids, conn))

        for chunk in self.solid_chunks:
            eids, pids, nodes, fi, starts, _lines = chunk
            nnz = np.count_nonzero(nodes, axis=1)
            # nodes must be a prefix (no zero followed by a node)
            last_nz = np.where(nnz > 0, 10 - np.argmax(nodes[:, ::-1] != 0, axis=1), 0)
            gap = last_nz != nnz
            if np.any(gap) or np.any(~np.isin(nnz, (4, 6, 8, 10))):
                r = int(np.flatnonzero(gap | ~np.isin(nnz, (4, 6, 8, 10)))[0])
                raise DeckError(
                    f"solid element {eids[r]} has {nnz[r]} node ids (expected 4, 6, 8 or 10, "
                    "without blanks between them)",
                    self.files[fi].path,
                    self.files[fi].line_number(starts[r]),
                )
            if np.all(nnz == 8):
                idx = lookup(nodes[:, :8], chunk)
            else:
                idx = lookup(nodes, chunk, allow_zero_tail=True)
            self._check_pids(pids, chunk)
            for k, etype in ((4, "tet4"), (6, "wedge6")):
                m = nnz == k
                add(etype, eids[m], pids[m], idx[m][:, :k])
            m = nnz == 10
            add("tet10", eids[m], pids[m], idx[m])
            m = np.flatnonzero(nnz == 8)
            if len(m):
                for etype, (rows, conn) in split_degenerate_solids(idx[m][:, :8]).items():
                    add(etype, eids[m][rows], pids[m][rows], conn)
        for chunk in self.shell_chunks:
            eids, pids, nodes, fi, starts, _lines = chunk
            nodes4 = nodes[:, :4]
            self._check_pids(pids, chunk)
            idx = lookup(nodes4, chunk, allow_zero_tail=True)
            tri = (nodes4[:, 3] == 0) | (nodes4[:, 3] == nodes4[:, 2])
            if np.any(nodes4[:, :3] == 0):
                r = int(np.flatnonzero(np.any(nodes4[:, :3] == 0, axis=1))[0])
                raise DeckError(
                    f"shell element {eids[r]} has fewer than 3 nodes",
                    self.files[fi].path,
                    self.files[fi].line_number(starts[r]),
                )
            add("quad4", eids[~tri], pids[~tri], idx[~tri])
            add("tri3", eids[tri], pids[tri], idx[tri][:, :3])
        for sink, etype in ((self.beam_chunks, "beam2"), (self.discrete_chunks, "discrete")):
            for chunk in sink:
                eids, pids, nodes, _fi, _starts, _lines = chunk
                if etype == "beam2":
                    self._check_pids(pids, chunk)
                idx = lookup(nodes[:, :2], chunk)
                add(etype, eids, pids, idx)
        element_blocks = {}
        for etype, parts in blocks.items():
            element_blocks[etype] = ElementBlock(
                etype,
                np.concatenate([p[0] for p in parts]),
                np.concatenate([p[1] for p in parts]),
                np.concatenate([p[2] for p in parts]),
            )
        node_sets = {}
        for sid, title, nids, fi, line in self.node_sets:
            try:
                pos = np.searchsorted(sids, nids)
                pos_c = np.minimum(pos, max(len(sids) - 1, 0))
                ok = sids[pos_c] == nids if len(sids) else np.zeros(len(nids), bool)
                if not np.all(ok):
                    raise KeyError(int(nids[~ok][0]))
            except KeyError as exc:
                raise DeckError(
                    f"node set {sid} refers to node {exc.args[0]}, which is not defined",
                    self.files[fi].path,
                    line + 1,
                ) from None
            node_sets[sid] = NodeSet(sid, title, order[pos_c])
        part_sets = {
            sid: PartSet(sid, title, pids) for sid, title, pids, _fi, _line in self.part_sets
        }
        problems = self._reference_problems(len(ids))
        if problems and self.strict:
            raise problems[0]
        source = DeckSource(
            files=self.files,
            coords_read=xyz.copy(),
            node_file=nfile,
            node_line_start=nstart,
            node_line_end=nend,
            node_col=ncol,
            node_width=nwidth,
            warnings=self.warnings,
            problems=[p.location_message() for p in problems],
        )
        source.coords_read.flags.writeable = False
        return Model(ids, xyz, element_blocks, self.parts, node_sets, part_sets, source)

    def _reference_problems(self, n_nodes: int) -> list[DeckError]:
        """What LS-DYNA refuses in a deck whose cards are each fine, first found first.

        An empty deck, two elements of one kind (solid, shell, beam, discrete) with the same id,
        an element whose part is not defined.
        """
        problems: list[DeckError] = []
        kinds = (
            ("solid", self.solid_chunks),
            ("shell", self.shell_chunks),
            ("beam", self.beam_chunks),
            ("discrete", self.discrete_chunks),
        )
        if n_nodes == 0 and not any(chunks for _, chunks in kinds):
            problems.append(DeckError("the deck defines no nodes and no elements", self.main_path))

        def where(chunks: list, row: int) -> tuple[Path, int]:
            for chunk in chunks:
                if row < len(chunk[0]):
                    fobj = self.files[chunk[3]]
                    return fobj.path, fobj.line_number(chunk[4][row])
                row -= len(chunk[0])
            raise IndexError(row)  # pragma: no cover - rows come from the chunks

        for kind, chunks in kinds:
            if not chunks:
                continue
            eids = np.concatenate([c[0] for c in chunks])
            order = np.argsort(eids, kind="stable")
            dup = np.flatnonzero(eids[order][1:] == eids[order][:-1])
            if len(dup):
                first, second = int(order[dup[0]]), int(order[dup[0] + 1])
                (p1, l1), (p2, l2) = where(chunks, first), where(chunks, second)
                problems.append(
                    DeckError(
                        f"{kind} element id {eids[second]} is used twice (first at {p1}:{l1})",
                        p2,
                        l2,
                    )
                )
            pids = np.concatenate([c[1] for c in chunks])
            undefined = ~np.isin(
                pids, np.fromiter(self.parts, dtype=np.int64, count=len(self.parts))
            )
            if np.any(undefined):
                row = int(np.flatnonzero(undefined)[0])
                path, line = where(chunks, row)
                message = (
                    f"{kind} element {eids[row]} refers to part {pids[row]}, which is not defined"
                )
                if self.unread_parts:
                    self.warnings.append(
                        f"{path}:{line}: {message} here; it may be in {self.unread_parts[0]}, "
                        "which kneegui does not read"
                    )
                else:
                    problems.append(DeckError(message, path, line))
        return problems

    def _check_pids(self, pids: NDArray[np.int64], chunk: tuple) -> None:
        if np.any(pids <= 0):
            r = int(np.flatnonzero(pids <= 0)[0])
            fi, starts = chunk[3], chunk[4]
            raise DeckError(
                f"element {chunk[0][r]} has part id {pids[r]} (must be positive)",
                self.files[fi].path,
                self.files[fi].line_number(starts[r]),
            )


def read_deck(path: str | os.PathLike[str], *, check_references: bool = True) -> Model:
    """Read an LS-DYNA keyword deck (with its ``*INCLUDE`` files) into a model.

    Parameters
    ----------
    path : str or PathLike
        The main deck file (``.k``, ``.key``, ``.dyn``, ...).
    check_references : bool
        Refuse what LS-DYNA refuses in a deck whose cards are each readable: no nodes and no
        elements, an element id used twice within solids (shells, beams, discretes), an element
        whose part is not defined. ``False`` lists them in ``model.source.problems`` instead
        (``kneegui info``).

    Returns
    -------
    Model
        Nodes, element blocks, parts and sets; ``model.source`` keeps every file's path, size
        and CRC-32 and the position of each node's coordinate fields for
        :func:`kneegui.io.lsdyna.write_deck`, which reads the files' bytes again (a file changed
        on disk since is refused; :class:`DeckFile`).

    Raises
    ------
    DeckError
        With the file and line of the first problem found.
    """
    main = Path(path)
    if not main.exists():
        raise DeckError("file not found", main, None)
    reader = _DeckReader(main, strict=check_references)
    reader.read_file(main, Path(main.name), (), None)
    model = reader.build()
    for f in reader.files:
        f.release()
    return model
