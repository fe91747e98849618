"""Batch plans: which decks to pose at which angles with which kinematic tables (docs/batch.md).

A plan is a TOML file read with the standard library's :mod:`tomllib`. tomllib reports syntax
errors with their line but gives no line numbers for the keys it read, so :func:`key_lines` scans
the (already valid) text once for where every key and array item starts; every semantic error
then names ``plan.toml:LINE``. :func:`load_plan` checks everything that can be checked without
reading a deck (files exist, tables and options are known, angles are in range, no two postures
write the same file) and expands the plan into one :class:`Posture` per output deck.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from kneegui.errors import PlanError, SetupError
from kneegui.reposition.pipeline import angle_tag
from kneegui.reposition.repositioner import METHODS
from kneegui.setup.kinematic_tables import QUANTITIES, SUPPORTED_FLEXION_DEG, resolve_table

#: Posture options a plan may set in ``[defaults]`` or per deck, with their type and default.
OPTION_DEFAULTS: dict[str, Any] = {
    "smooth": True,
    "relax": True,
    "method": "",  # "" = the repositioner's default method
    "force": False,
    "flatten": False,
    "restore_volume": False,
}
TOP_KEYS = ("output", "defaults", "deck")
OUTPUT_KEYS = ("folder",)
DECK_KEYS = ("name", "deck", "setup", "flexion", "kinematics", *OPTION_DEFAULTS)
RANGE_KEYS = ("from", "to", "step")
#: Folder name of the postures that use the setup's own tables.
SETUP_TABLES_TAG = "setup"
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]*$")

Key = tuple[str | int, ...]


@dataclass(frozen=True)
class PostureOptions:
    """How one posture is made and written (the plan's ``[defaults]`` and deck overrides).

    Attributes
    ----------
    smooth : bool
        Run the smoother after the relaxation (``kneegui pose`` without ``--no-smooth``).
    relax : bool
        Relax the degraded tissue after the mapping (off: the slider's mapping alone, a quick
        preview that usually fails the quality gate).
    method : str
        Soft-tissue method; ``""`` for the default.
    force : bool
        Write the deck even if it fails the quality gate.
    flatten : bool
        Inline every ``*INCLUDE``.
    restore_volume : bool
        Restore the soft solids' volumes before the relaxation (``kneegui pose
        --restore-volume``; :mod:`kneegui.meshopt.volume_correction`).
    """

    smooth: bool = True
    relax: bool = True
    method: str = ""
    force: bool = False
    flatten: bool = False
    restore_volume: bool = False


@dataclass(frozen=True)
class Posture:
    """One posed deck to make: a deck, its setup, kinematic tables, an angle, an output folder.

    Attributes
    ----------
    deck_name : str
        The deck's folder name in the output.
    deck, setup : Path
        Absolute paths of the input deck and its setup file.
    tables_tag : str
        Folder name of the kinematic-table choice (``"setup"``: the setup's own).
    kinematics : tuple of (str, str)
        Quantity -> table choice overriding the setup's (a shipped name or an absolute CSV
        path), in :data:`QUANTITIES` order.
    flexion : float
        Target flexion, degrees.
    options : PostureOptions
    folder : Path
        Absolute output folder: ``OUT/<deck_name>/<tables_tag>/flex_<angle>``.
    plan_key : tuple
        Where the posture's angle is in the plan (``("deck", 0, "flexion", 2)``), for messages.
    """

    deck_name: str
    deck: Path
    setup: Path
    tables_tag: str
    kinematics: tuple[tuple[str, str], ...]
    flexion: float
    options: PostureOptions
    folder: Path
    plan_key: tuple[str | int, ...] = ()

    @property
    def id(self) -> str:
        """``<deck>/<tables>/flex_<angle>``: the posture's folder relative to the output."""
        return f"{self.deck_name}/{self.tables_tag}/{self.folder.name}"

    @property
    def deck_out(self) -> Path:
        """The posed deck (its includes, if any, are written beside it)."""
        return self.folder / self.deck.name

    @property
    def report_out(self) -> Path:
        """The posture's JSON report."""
        return self.folder / "report.json"


@dataclass(frozen=True)
class Plan:
    """A validated plan: the file, the output folder and every posture in plan order."""

    path: Path
    out: Path
    postures: tuple[Posture, ...] = field(default_factory=tuple)


# ---------------------------------------------------------------------------- key lines
class _Scanner:
    """Finds the line of every key and array item of a valid TOML text (see :func:`key_lines`)."""

    def __init__(self, text: str):
        self.s, self.i, self.line = text, 0, 1
        self.lines: dict[Key, int] = {}

    def peek(self, n: int = 1) -> str:
        return self.s[self.i : self.i + n]

    def advance(self, n: int = 1) -> None:
        self.line += self.s.count("\n", self.i, self.i + n)
        self.i += n

    def skip(self, newlines: bool) -> None:
        """Skip blanks and comments (and newlines if asked)."""
        while self.i < len(self.s):
            c = self.s[self.i]
            if c in " \t\r" or (newlines and c == "\n"):
                self.advance()
            elif c == "#":
                end = self.s.find("\n", self.i)
                self.advance((len(self.s) if end < 0 else end) - self.i)
            else:
                return

    def string(self) -> str:
        """Read a string starting at the cursor; returns its (unescaped enough) content."""
        for q in ('"""', "'''"):
            if self.peek(3) == q:
                end = self.s.find(q, self.i + 3)
                while q == '"""' and end > 0 and self.s[end - 1] == "\\":
                    end = self.s.find(q, end + 1)
                end = len(self.s) if end < 0 else end
                while self.s[end + 3 : end + 4] == q[0]:  # up to two quotes end the content
                    end += 1
                text = self.s[self.i + 3 : end]
                self.advance(end + 3 - self.i)
                return text
        q = self.peek()
        j = self.i + 1
        while j < len(self.s) and self.s[j] != q:
            j += 2 if (q == '"' and self.s[j] == "\\") else 1
        text = self.s[self.i + 1 : j]
        self.advance(j + 1 - self.i)
        return text

    def key(self) -> tuple[str, ...]:
        """A (dotted) key."""
        parts = []
        while True:
            self.skip(False)
            if self.peek() in ('"', "'"):
                parts.append(self.string())
            else:
                m = re.compile(r"[A-Za-z0-9_-]+").match(self.s, self.i)
                parts.append(m.group(0) if m else "")
                self.advance(len(parts[-1]))
            self.skip(False)
            if self.peek() != ".":
                return tuple(parts)
            self.advance()

    def value(self, path: Key) -> None:
        self.skip(False)
        c = self.peek()
        if c == "[":
            self.advance()
            index = 0
            while True:
                self.skip(True)
                if self.peek() == "]":
                    self.advance()
                    return
                self.lines.setdefault((*path, index), self.line)
                self.value((*path, index))
                self.skip(True)
                if self.peek() == ",":
                    self.advance()
                    index += 1
        elif c == "{":
            self.advance()
            while True:
                self.skip(False)
                if self.peek() == "}":
                    self.advance()
                    return
                if self.peek() == ",":
                    self.advance()
                    continue
                line, key = self.line, self.key()
                self.lines.setdefault((*path, *key), line)
                self.advance()  # '='
                self.value((*path, *key))
        elif c in ('"', "'"):
            self.string()
        else:
            m = re.compile(r"[^,\]}\n#]*").match(self.s, self.i)
            self.advance(len(m.group(0)) if m else 0)

    def scan(self) -> dict[Key, int]:
        table: Key = ()
        counts: dict[Key, int] = {}
        while True:
            self.skip(True)
            if self.i >= len(self.s):
                return self.lines
            line = self.line
            if self.peek(2) == "[[":
                self.advance(2)
                name = self.key()
                self.advance(2)
                counts[name] = counts.get(name, -1) + 1
                table = (*name, counts[name])
                self.lines.setdefault(name, line)
                self.lines.setdefault(table, line)
            elif self.peek() == "[":
                self.advance()
                table = self.key()
                self.advance()
                self.lines.setdefault(table, line)
            else:
                key = self.key()
                self.lines.setdefault((*table, *key), line)
                self.advance()  # '='
                self.value((*table, *key))


def key_lines(text: str) -> dict[Key, int]:
    """Line (1-based) of every key, table header and array item of a valid TOML text.

    Parameters
    ----------
    text : str
        TOML that :func:`tomllib.loads` accepts.

    Returns
    -------
    dict
        Key path (``("deck", 1, "flexion", 2)``: the third angle of the second ``[[deck]]``) ->
        the line it starts on.
    """
    return _Scanner(text).scan()


# ---------------------------------------------------------------------------- loading
class _Checker:
    def __init__(self, path: Path, lines: Mapping[Key, int]):
        self.path, self.lines = path, lines

    def line_of(self, key: Key) -> int | None:
        while key:
            if key in self.lines:
                return self.lines[key]
            key = key[:-1]
        return None

    def error(self, message: str, key: Key) -> PlanError:
        return PlanError(
            f"{_dotted(key)}: {message}" if key else message, self.path, self.line_of(key)
        )


def _dotted(key: Key) -> str:
    out = ""
    for part in key:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else part)
    return out


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def load_plan(path: str | Path) -> Plan:
    """Read and validate a plan; expand it into postures.

    Parameters
    ----------
    path : str or Path
        The TOML plan. Relative paths inside it are relative to its folder.

    Returns
    -------
    Plan

    Raises
    ------
    PlanError
        Unreadable file, TOML syntax error, unknown or missing key, wrong type, missing deck or
        setup file, unknown kinematic table, angle out of range, bad name, or two postures that
        would write the same file; the message names ``file:line`` and the key.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise PlanError(f"not UTF-8 text ({exc.reason})", path) from None
    except OSError as exc:
        raise PlanError(f"cannot read the plan: {exc.strerror or exc}", path) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        msg = str(exc)
        m = re.search(r"\s*\(at (?:line (\d+), column \d+|end of document)\)$", msg)
        if m and m.group(1):
            line = int(m.group(1))
        else:  # "at end of document": the last line
            line = len(text.rstrip().splitlines()) if m else None
        raise PlanError(f"TOML syntax: {msg[: m.start()] if m else msg}", path, line) from None
    chk = _Checker(path, key_lines(text))
    base = path.resolve().parent

    for key in data:
        if key not in TOP_KEYS:
            raise chk.error(f"unknown key (expected one of {', '.join(TOP_KEYS)})", (key,))
    output = data.get("output", {})
    if not isinstance(output, dict):
        raise chk.error("expected a table [output]", ("output",))
    for key in output:
        if key not in OUTPUT_KEYS:
            raise chk.error("unknown key (expected folder)", ("output", key))
    if "folder" not in output:
        raise chk.error('missing: the output folder ([output] folder = "...")', ("output",))
    if not isinstance(output["folder"], str) or not output["folder"].strip():
        raise chk.error("expected a folder path", ("output", "folder"))
    out = (base / Path(output["folder"]).expanduser()).resolve()

    defaults = data.get("defaults", {})
    if not isinstance(defaults, dict):
        raise chk.error("expected a table [defaults]", ("defaults",))
    default_options = _options(chk, defaults, ("defaults",), dict(OPTION_DEFAULTS), strict=True)

    decks = data.get("deck")
    if decks is None:
        raise chk.error("no [[deck]] entry: nothing to pose", ())
    if not isinstance(decks, list) or not all(isinstance(d, dict) for d in decks):
        raise chk.error("expected [[deck]] tables", ("deck",))
    postures: list[Posture] = []
    by_file: dict[Path, tuple[Key, str]] = {}
    inputs = set()
    for i, entry in enumerate(decks):
        inputs.update(_input_paths(chk, entry, ("deck", i), base))
    for i, entry in enumerate(decks):
        for p in _deck_postures(chk, entry, ("deck", i), base, out, default_options):
            for target in (p.deck_out, p.report_out):
                where = p.plan_key
                if target in by_file:
                    first, first_id = by_file[target]
                    raise chk.error(
                        f"posture {p.id} writes {target}, as posture {first_id} "
                        f"(line {chk.line_of(first)}) does; give the decks different names or "
                        "drop the repeated angle or table choice",
                        where,
                    )
                if target in inputs:
                    raise chk.error(f"posture {p.id} would overwrite the input {target}", where)
                by_file[target] = (where, p.id)
            postures.append(p)
    return Plan(path=path, out=out, postures=tuple(postures))


def _options(
    chk: _Checker, table: Mapping[str, Any], key: Key, base: dict[str, Any], strict: bool
) -> dict[str, Any]:
    opts = dict(base)
    for name, value in table.items():
        if name not in OPTION_DEFAULTS:
            if strict:
                raise chk.error(
                    f"unknown option (expected one of {', '.join(OPTION_DEFAULTS)})",
                    (*key, name),
                )
            continue
        want = type(OPTION_DEFAULTS[name])
        if not isinstance(value, want):
            raise chk.error(f"expected {want.__name__}, got {value!r}", (*key, name))
        if name == "method" and value not in ("", *METHODS):
            raise chk.error(f"unknown method {value!r} (one of {', '.join(METHODS)})", (*key, name))
        opts[name] = value
    return opts


def _input_paths(chk: _Checker, entry: Mapping[str, Any], key: Key, base: Path) -> list[Path]:
    paths = []
    for name in ("deck", "setup"):
        if name not in entry:
            raise chk.error(f"missing: the {name} file", key)
        value = entry[name]
        if not isinstance(value, str) or not value.strip():
            raise chk.error("expected a file path", (*key, name))
        p = (base / Path(value).expanduser()).resolve()
        if not p.is_file():
            raise chk.error(f"file not found: {p}", (*key, name))
        paths.append(p)
    return paths


def _deck_postures(
    chk: _Checker,
    entry: Mapping[str, Any],
    key: Key,
    base: Path,
    out: Path,
    defaults: dict[str, Any],
) -> list[Posture]:
    for name in entry:
        if name not in DECK_KEYS:
            raise chk.error(f"unknown key (expected one of {', '.join(DECK_KEYS)})", (*key, name))
    deck, setup = _input_paths(chk, entry, key, base)
    name = entry.get("name", deck.stem)
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise chk.error(
            f"expected a folder name (letters, digits, . _ + -), got {name!r}", (*key, "name")
        )
    options = PostureOptions(**_options(chk, entry, key, defaults, strict=False))
    if "flexion" not in entry:
        raise chk.error("missing: the flexion angles", key)
    angles = _angles(chk, entry["flexion"], (*key, "flexion"))
    choices = entry.get("kinematics", [{}])
    if not isinstance(choices, list) or not choices:
        raise chk.error(
            'expected a list of table choices, e.g. [{}, {tibial_rotation = "asano2001"}]',
            (*key, "kinematics"),
        )
    postures = []
    for j, choice in enumerate(choices):
        tag, overrides = _kinematics(chk, choice, (*key, "kinematics", j), base)
        for deg, where in angles:
            postures.append(
                Posture(
                    deck_name=name,
                    deck=deck,
                    setup=setup,
                    tables_tag=tag,
                    kinematics=overrides,
                    flexion=deg,
                    options=options,
                    folder=out / name / tag / f"flex_{angle_tag(deg)}",
                    plan_key=where,
                )
            )
    return postures


def _angles(chk: _Checker, value: Any, key: Key) -> list[tuple[float, Key]]:
    items = value if isinstance(value, list) else [value]
    if not items:
        raise chk.error("no angle given", key)
    out: list[tuple[float, Key]] = []
    lo, hi = SUPPORTED_FLEXION_DEG
    for k, item in enumerate(items):
        here = (*key, k) if isinstance(value, list) else key
        if isinstance(item, dict):
            for name in item:
                if name not in RANGE_KEYS:
                    raise chk.error(f"unknown key {name!r} in a range (from, to, step)", here)
            missing = [n for n in RANGE_KEYS if n not in item]
            if missing:
                raise chk.error(
                    f"a range needs from, to and step; missing {', '.join(missing)}", here
                )
            a, b, step = (item[n] for n in RANGE_KEYS)
            if not all(_is_number(v) for v in (a, b, step)):
                raise chk.error("from, to and step must be numbers", here)
            if step <= 0 or b < a:
                raise chk.error(f"expected from <= to and step > 0, got {a}, {b}, {step}", here)
            n = math.floor((b - a) / step + 1e-9)
            if n > 10_000:
                raise chk.error(f"a range of {n + 1} angles; is the step right?", here)
            degs = [float(round(a + m * step, 9)) for m in range(n + 1)]
        elif _is_number(item):
            degs = [float(item)]
        else:
            raise chk.error(
                f"expected an angle (degrees) or a range {{from, to, step}}, got {item!r}", here
            )
        for d in degs:
            if not lo <= d <= hi:
                raise chk.error(
                    f"flexion {d:g} deg is outside the supported range {lo:g} to {hi:g} deg", here
                )
        out += [(d, here) for d in degs]
    return out


def _kinematics(
    chk: _Checker, choice: Any, key: Key, base: Path
) -> tuple[str, tuple[tuple[str, str], ...]]:
    if not isinstance(choice, dict):
        raise chk.error('expected a table {quantity = "table name or CSV", ...}', key)
    for name in choice:
        if name != "name" and name not in QUANTITIES:
            raise chk.error(
                f"unknown key (expected name or one of {', '.join(QUANTITIES)})", (*key, name)
            )
    overrides = []
    for q in QUANTITIES:
        if q not in choice:
            continue
        value = choice[q]
        if not isinstance(value, str):
            raise chk.error(f"expected a table name or a CSV path, got {value!r}", (*key, q))
        try:
            table = resolve_table(q, value, base)
        except SetupError as exc:
            raise chk.error(exc.message, (*key, q)) from None
        overrides.append(
            (
                q,
                str(table.path)
                if table.path is not None and table.name == str(table.path)
                else value.strip(),
            )
        )
    if "name" in choice:
        tag = choice["name"]
        if not isinstance(tag, str) or not _NAME_RE.match(tag):
            raise chk.error(
                f"expected a folder name (letters, digits, . _ + -), got {tag!r}", (*key, "name")
            )
    elif overrides:
        tag = "+".join(Path(v).stem if v.lower().endswith(".csv") else v for _, v in overrides)
    else:
        tag = SETUP_TABLES_TAG
    return tag, tuple(overrides)
