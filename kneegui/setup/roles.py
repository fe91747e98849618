"""Suggest part roles from part titles, with the pattern table ``resources/role_patterns.csv``.

Each row of the table is ``order, role, pattern, source``; ``pattern`` is a Python regular
expression matched (``re.search``) against the lower-cased title. The first row (by ``order``)
that matches wins, so tendons and ligaments are tested before the bones whose names they contain
("Tendon_Patellar" is a tendon, not the patella; "Rectus_Femoris" is a muscle, not the femur).
A part whose title matches nothing is left unassigned. With ``side`` given, parts whose title
names the *other* side (a token ``L``/``LEFT``/``LT`` or ``R``/``RIGHT``/``RT``) are skipped.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from kneegui.errors import SetupError
from kneegui.model import Model
from kneegui.resources import RESOURCES_DIR
from kneegui.setup.format import ROLES

ROLE_PATTERNS_FILE = RESOURCES_DIR / "role_patterns.csv"

_SIDE_TOKENS = {
    "right": {"r", "rt", "right", "rgt", "ri"},
    "left": {"l", "lt", "left", "lft", "le"},
}


@dataclass(frozen=True)
class RolePattern:
    """One row of the pattern table."""

    order: int
    role: str
    pattern: re.Pattern[str]
    source: str


@lru_cache(maxsize=4)
def load_role_patterns(path: str | Path = ROLE_PATTERNS_FILE) -> tuple[RolePattern, ...]:
    """The pattern table, sorted by ``order``.

    Raises
    ------
    SetupError
        Unknown role or invalid regular expression in the table.
    """
    rows = []
    with open(path, newline="", encoding="utf-8") as fh:
        for line, row in enumerate(csv.DictReader(fh), start=2):
            role = row["role"].strip()
            if role not in ROLES:
                raise SetupError(f"{path}:{line}: unknown role {role!r}")
            try:
                pattern = re.compile(row["pattern"].strip())
            except re.error as exc:
                raise SetupError(f"{path}:{line}: bad pattern: {exc}") from None
            rows.append(RolePattern(int(row["order"]), role, pattern, row.get("source", "")))
    return tuple(sorted(rows, key=lambda r: r.order))


def title_tokens(title: str) -> list[str]:
    """Lower-case word tokens of a title (split at non-letters and at camelCase humps)."""
    spaced = re.sub(r"(?<=[a-z])(?=[A-Z])", " ", title)
    return [t for t in re.split(r"[^A-Za-z]+", spaced.lower()) if t]


def title_side(title: str) -> str | None:
    """``"right"``, ``"left"`` or None: the side a part title names, if any."""
    tokens = set(title_tokens(title))
    found = [side for side, words in _SIDE_TOKENS.items() if tokens & words]
    return found[0] if len(found) == 1 else None


def role_for_title(title: str, patterns: tuple[RolePattern, ...] | None = None) -> str | None:
    """The role whose pattern first matches ``title`` (case-insensitive), or None."""
    text = title.lower()
    for row in patterns if patterns is not None else load_role_patterns():
        if row.pattern.search(text):
            return row.role
    return None


def suggest_roles(
    model: Model, side: str | None = None, patterns_path: str | Path | None = None
) -> dict[str, list[int]]:
    """Suggest a role for every part from its title.

    Parameters
    ----------
    model : Model
        Parts with titles.
    side : {"right", "left"}, optional
        Skip parts whose title names the other side (for whole-body models).
    patterns_path : str or Path, optional
        Another pattern table (same columns as ``resources/role_patterns.csv``).

    Returns
    -------
    dict
        Every role of :data:`~kneegui.setup.format.ROLES` -> sorted part ids (possibly empty).
        Unmatched parts appear in no role.
    """
    if side is not None and side not in _SIDE_TOKENS:
        raise SetupError(f"expected 'right' or 'left', got {side!r}", key="side")
    patterns = load_role_patterns(patterns_path) if patterns_path else load_role_patterns()
    other = {"right": "left", "left": "right"}.get(side or "")
    roles: dict[str, list[int]] = {r: [] for r in ROLES}
    for pid in model.part_ids().tolist():
        part = model.parts.get(pid)
        title = part.title if part is not None else ""
        if not title:
            continue
        if other is not None and title_side(title) == other:
            continue
        role = role_for_title(title, patterns)
        if role is not None:
            roles[role].append(int(pid))
    return roles
