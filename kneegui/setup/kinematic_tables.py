"""Kinematic tables: a coupled angle (degrees) as a function of knee flexion (degrees).

Three quantities drive the bones (ALGORITHM.md §2):

``tibial_rotation``
    Tibial *internal* rotation about the longitudinal-rotation (L-R) axis. Positive = internal
    (screw-home: the tibia rotates internally as the knee flexes).
``patellar_flexion``
    Patellar flexion about the flexion-extension (F-E) axis, in the same sense as knee flexion.
``patellar_tilt``
    Patellar tilt about the patella's own proximal-distal axis. Positive = medial tilt (the
    anterior face turns towards the medial side).

Sign convention (right knee, subject frame x anterior, y to the subject's left, z superior along
the tibial axis): flexion is a positive rotation of the tibia about +y; internal tibial rotation
and medial patellar tilt are positive about +z. A left knee mirrors the model through the sagittal
plane: flexion stays positive about the subject's left, internal rotation and medial tilt become
positive about -z. :mod:`kneegui.kinematics.posing` applies this with one sign ``s = +1`` (right)
or ``-1`` (left) on rotations expressed about the lateral-to-medial and superior directions.

A table is a CSV file with a header ``flexion_deg,value_deg,source`` (``source`` optional in a
user's file); rows sorted by increasing flexion. Values are interpolated linearly and held
constant beyond the first and last rows. The shipped tables are listed in
``resources/kinematics/index.csv`` (quantity, name, file, default flag, description, source).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kneegui.errors import SetupError
from kneegui.resources import RESOURCES_DIR

#: The quantities a setup's ``kinematics`` object may choose a table for.
QUANTITIES: tuple[str, ...] = ("tibial_rotation", "patellar_flexion", "patellar_tilt")

#: Target flexion the engine poses to (degrees): the range the shipped cubic tables sample
#: (:data:`kneegui.kinematics.build_tables.CUBIC_GRID`); the repositioner refuses targets
#: outside it.
SUPPORTED_FLEXION_DEG: tuple[float, float] = (-10.0, 150.0)
#: Flexion over which the posed demo leg is measured and reported (``python -m
#: kneegui.kinematics.report``, docs/kinematics.md), inside the supported range: the GUI's
#: slider offers this range so that every angle it shows has been checked.
VALIDATED_FLEXION_DEG: tuple[float, float] = (-5.0, 140.0)
#: Folder of the shipped tables.
TABLES_DIR = RESOURCES_DIR / "kinematics"


@dataclass(frozen=True, eq=False)
class KinematicTable:
    """A piecewise-linear curve ``value_deg(flexion_deg)``.

    Attributes
    ----------
    name : str
        Shipped table name, or the file path of a user's table.
    quantity : str
        One of :data:`QUANTITIES`.
    flexion_deg : (K,) ndarray of float
        Strictly increasing knee flexion angles, degrees.
    value_deg : (K,) ndarray of float
        The coupled angle at each flexion, degrees.
    sources : tuple of str
        The distinct ``source`` entries of the rows.
    path : Path
        The file it was read from.
    """

    name: str
    quantity: str
    flexion_deg: NDArray[np.float64]
    value_deg: NDArray[np.float64]
    sources: tuple[str, ...]
    path: Path

    def value_at(self, flexion_deg: ArrayLike) -> NDArray[np.float64] | float:
        """Interpolated value(s) in degrees; constant beyond the table's ends."""
        out = np.interp(np.asarray(flexion_deg, dtype=np.float64), self.flexion_deg, self.value_deg)
        return float(out) if np.ndim(out) == 0 else out

    def change(self, from_deg: float, to_deg: float) -> float:
        """``value(to) - value(from)`` in degrees: the rotation applied when posing."""
        return float(self.value_at(to_deg)) - float(self.value_at(from_deg))


@dataclass(frozen=True)
class ShippedTable:
    """One row of ``resources/kinematics/index.csv``."""

    quantity: str
    name: str
    file: str
    default: bool
    description: str
    source: str


@lru_cache(maxsize=1)
def shipped_tables() -> tuple[ShippedTable, ...]:
    """Every table shipped in ``resources/kinematics`` (from its ``index.csv``)."""
    rows = []
    with open(TABLES_DIR / "index.csv", newline="", encoding="utf-8") as fh:
        for row in csv.DictReader(fh):
            rows.append(
                ShippedTable(
                    quantity=row["quantity"],
                    name=row["name"],
                    file=row["file"],
                    default=row["default"].strip().lower() in ("1", "yes", "true"),
                    description=row["description"],
                    source=row["source"],
                )
            )
    return tuple(rows)


def table_names(quantity: str) -> list[str]:
    """Names of the shipped tables for ``quantity`` (``"default"`` is always accepted too)."""
    return [t.name for t in shipped_tables() if t.quantity == quantity]


def read_table_csv(path: str | Path, quantity: str, name: str | None = None) -> KinematicTable:
    """Read a table file.

    Parameters
    ----------
    path : str or Path
        CSV with columns ``flexion_deg``, ``value_deg`` and optionally ``source``.
    quantity : str
        One of :data:`QUANTITIES` (recorded on the table; used in error messages).
    name : str, optional
        Name to give the table (default: the path).

    Raises
    ------
    SetupError
        Missing file or columns, non-numeric or non-finite values, fewer than 2 rows, or flexion
        angles not strictly increasing. ``key`` is ``kinematics.<quantity>``.
    """
    key = f"kinematics.{quantity}"
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            fields = [f.strip() for f in (reader.fieldnames or [])]
            for col in ("flexion_deg", "value_deg"):
                if col not in fields:
                    raise SetupError(f"table {str(path)!r} has no column {col!r}", key=key)
            flex, val, src = [], [], []
            for lineno, raw in enumerate(reader, start=2):
                row = {k.strip(): (v or "").strip() for k, v in raw.items() if k is not None}
                if not row.get("flexion_deg") and not row.get("value_deg"):
                    continue
                try:
                    f, v = float(row["flexion_deg"]), float(row["value_deg"])
                except ValueError:
                    raise SetupError(
                        f"table {str(path)!r} line {lineno}: not a number "
                        f"({row.get('flexion_deg')!r}, {row.get('value_deg')!r})",
                        key=key,
                    ) from None
                if not (np.isfinite(f) and np.isfinite(v)):
                    raise SetupError(f"table {str(path)!r} line {lineno}: not finite", key=key)
                flex.append(f)
                val.append(v)
                if row.get("source"):
                    src.append(row["source"])
    except OSError as exc:
        raise SetupError(
            f"cannot read table {str(path)!r}: {exc.strerror or exc}", key=key
        ) from None
    if len(flex) < 2:
        raise SetupError(f"table {str(path)!r} needs at least 2 rows, has {len(flex)}", key=key)
    flex_arr = np.array(flex)
    if np.any(np.diff(flex_arr) <= 0):
        raise SetupError(f"table {str(path)!r}: flexion_deg must be strictly increasing", key=key)
    val_arr = np.array(val)
    flex_arr.flags.writeable = False
    val_arr.flags.writeable = False
    return KinematicTable(
        name=name if name is not None else str(path),
        quantity=quantity,
        flexion_deg=flex_arr,
        value_deg=val_arr,
        sources=tuple(dict.fromkeys(src)),
        path=path,
    )


def resolve_table(quantity: str, choice: str, base_dir: str | Path | None = None) -> KinematicTable:
    """The table a setup names: ``"default"``, a shipped table name, or a CSV path.

    Parameters
    ----------
    quantity : str
        One of :data:`QUANTITIES`.
    choice : str
        ``"default"``, a name from :func:`table_names`, or a path (absolute, or relative to
        ``base_dir``).
    base_dir : str or Path, optional
        Folder relative paths are resolved against (the setup file's folder).

    Raises
    ------
    SetupError
        Unknown quantity, unknown name or unreadable file (``key = kinematics.<quantity>``).
    """
    key = f"kinematics.{quantity}"
    if quantity not in QUANTITIES:
        raise SetupError(f"unknown kinematic quantity {quantity!r}", key="kinematics")
    if not isinstance(choice, str) or not choice.strip():
        raise SetupError(f"expected a table name or path, got {choice!r}", key=key)
    choice = choice.strip()
    shipped = _shipped_table(quantity, choice)
    if shipped is not None:
        return shipped
    if choice == "default":
        raise SetupError("no default table is shipped", key=key)
    # a user's file is read every time (it may have been edited since)
    path = Path(choice).expanduser()
    if not path.is_absolute() and base_dir:
        path = Path(base_dir) / path
    looks_like_path = path.suffix.lower() == ".csv" or "/" in choice or "\\" in choice
    if not path.exists():
        if looks_like_path:
            raise SetupError(f"table file {choice!r} not found", key=key)
        names = ", ".join(["default", *table_names(quantity)])
        raise SetupError(f"unknown table {choice!r} (shipped: {names})", key=key)
    return read_table_csv(path, quantity, name=str(path))


@lru_cache(maxsize=32)
def _shipped_table(quantity: str, choice: str) -> KinematicTable | None:
    """The shipped table named ``choice`` (or the default), read once; None if not shipped."""
    for t in shipped_tables():
        if t.quantity != quantity:
            continue
        if (choice == "default" and t.default) or choice == t.name:
            return read_table_csv(TABLES_DIR / t.file, quantity, name=t.name)
    return None
