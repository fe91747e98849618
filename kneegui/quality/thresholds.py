"""Warn / fail thresholds of the quality metrics, read from ``resources/quality_thresholds.csv``.

Each row gives a metric's direction (``min``: smaller is worse, ``max``: larger is worse), its
``fail`` and ``warn`` limits, an optional ``hard_fail`` limit and the source. The ``role`` column
is ``*`` for the defaults or a role name (``flesh``, ``skin``, ...) whose rows override the
defaults for the parts of that role. An element is *over* a limit when it is strictly worse than
it (``value < limit`` for ``min`` metrics, ``value > limit`` for ``max`` metrics). The
tetrahedron measures' rows (``tet_collapse`` ...) may be left out of a user's table; the shipped
table's rows then apply.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import KneeguiError
from kneegui.resources import resource_path

#: Metrics of every element type; a thresholds table must give their default (``*``) rows.
REQUIRED_METRICS: tuple[str, ...] = ("jacobian", "jacobian_gauss", "aspect", "warpage", "skew")
#: Tetrahedron measures (tet collapse, dihedral angles, volumetric skew, tet aspect ratio, the
#: 10-node tet's mid-side offsets); a table without their rows takes the shipped ones.
TET_THRESHOLD_METRICS: tuple[str, ...] = (
    "tet_collapse",
    "dihedral_min",
    "dihedral_max",
    "vol_skew",
    "tet_aspect",
    "midside_normal",
    "midside_tangent",
)
#: Metrics that have thresholds, in display order.
THRESHOLD_METRICS: tuple[str, ...] = REQUIRED_METRICS + TET_THRESHOLD_METRICS
DEFAULT_ROLE = "*"


class ThresholdsError(KneeguiError):
    """A thresholds table is malformed."""


@dataclass(frozen=True)
class MetricThreshold:
    """Limits of one metric.

    Attributes
    ----------
    metric : str
        Metric name (``jacobian`` is the corner Jacobian).
    direction : {"min", "max"}
        ``min``: small values are bad; ``max``: large values are bad.
    fail, warn : float
        An element strictly worse than ``fail`` fails; strictly worse than ``warn`` warns.
    hard_fail : float or None
        Values at or beyond it are invalid (Jacobian <= 0).
    source : str
        Where the numbers come from.
    """

    metric: str
    direction: str
    fail: float
    warn: float
    hard_fail: float | None = None
    source: str = ""

    def worse_than(self, values: NDArray[np.float64], limit: float) -> NDArray[np.bool_]:
        """Mask of values strictly worse than ``limit``."""
        return values < limit if self.direction == "min" else values > limit

    def worst(self, values: NDArray[np.float64]) -> float:
        """The worst of ``values`` (min or max by direction)."""
        return float(values.min() if self.direction == "min" else values.max())


@dataclass(frozen=True)
class Thresholds:
    """Default thresholds and per-role overrides."""

    default: Mapping[str, MetricThreshold]
    by_role: Mapping[str, Mapping[str, MetricThreshold]] = field(default_factory=dict)

    def for_role(self, role: str | None) -> dict[str, MetricThreshold]:
        """Thresholds that apply to a role (defaults overridden by the role's rows)."""
        out = dict(self.default)
        if role is not None:
            out.update(self.by_role.get(role, {}))
        return out

    def with_override(
        self, role: str, metric: str, *, fail: float | None = None, warn: float | None = None
    ) -> Thresholds:
        """A copy with one metric's limits changed for one role (``"*"`` for the defaults)."""
        base = self.for_role(None if role == DEFAULT_ROLE else role)[metric]
        new = replace(
            base,
            fail=base.fail if fail is None else float(fail),
            warn=base.warn if warn is None else float(warn),
            source="user override",
        )
        if role == DEFAULT_ROLE:
            return replace(self, default={**self.default, metric: new})
        roles = {r: dict(v) for r, v in self.by_role.items()}
        roles.setdefault(role, {})[metric] = new
        return replace(self, by_role=roles)

    def to_dict(self, metrics: Iterable[str] | None = None) -> dict:
        """JSON-ready: ``{role: {metric: {direction, fail, warn, hard_fail, source}}}``, for
        ``metrics`` only when given (a summary lists the metrics it reports)."""
        wanted = None if metrics is None else set(metrics)

        def one(t: MetricThreshold) -> dict:
            return {
                "direction": t.direction,
                "fail": t.fail,
                "warn": t.warn,
                "hard_fail": t.hard_fail,
                "source": t.source,
            }

        def keep(table: Mapping[str, MetricThreshold]) -> dict:
            return {m: one(t) for m, t in table.items() if wanted is None or m in wanted}

        out = {DEFAULT_ROLE: keep(self.default)}
        for role, table in self.by_role.items():
            kept = keep(table)
            if kept:
                out[role] = kept
        return out


def load_thresholds(path: str | Path | None = None) -> Thresholds:
    """Read a thresholds table.

    Parameters
    ----------
    path : str or Path, optional
        CSV with columns ``role, metric, direction, hard_fail, fail, warn, source``. Default: the
        shipped ``resources/quality_thresholds.csv``.

    Raises
    ------
    ThresholdsError
        Unknown metric or direction, missing default rows, or a value that is not a number
        (the message names the file and line).
    """
    path = resource_path("quality_thresholds.csv") if path is None else Path(path)
    default: dict[str, MetricThreshold] = {}
    by_role: dict[str, dict[str, MetricThreshold]] = {}
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise ThresholdsError(f"{path}: cannot read thresholds ({exc.strerror})") from exc
    required = {"role", "metric", "direction", "fail", "warn"}
    if rows and not required <= set(rows[0]):
        raise ThresholdsError(f"{path}: columns {sorted(required)} are required")
    for line, row in enumerate(rows, start=2):
        where = f"{path}:{line}"
        metric = (row.get("metric") or "").strip()
        direction = (row.get("direction") or "").strip()
        if metric not in THRESHOLD_METRICS:
            raise ThresholdsError(f"{where}: unknown metric {metric!r}")
        if direction not in ("min", "max"):
            raise ThresholdsError(f"{where}: direction must be 'min' or 'max', not {direction!r}")
        try:
            fail = float(row["fail"])
            warn = float(row["warn"])
            hard = (row.get("hard_fail") or "").strip()
            hard_fail = float(hard) if hard else None
        except (TypeError, ValueError) as exc:
            raise ThresholdsError(f"{where}: {exc}") from exc
        t = MetricThreshold(metric, direction, fail, warn, hard_fail, (row.get("source") or ""))
        role = (row.get("role") or DEFAULT_ROLE).strip() or DEFAULT_ROLE
        if role == DEFAULT_ROLE:
            default[metric] = t
        else:
            by_role.setdefault(role, {})[metric] = t
    missing = [m for m in REQUIRED_METRICS if m not in default]
    if missing:
        raise ThresholdsError(f"{path}: no default ('*') row for {', '.join(missing)}")
    shipped = resource_path("quality_thresholds.csv")
    if any(m not in default for m in TET_THRESHOLD_METRICS) and path != shipped:
        # an older table without the tet rows: the shipped defaults apply to tetrahedra
        base = default_thresholds().default
        for m in TET_THRESHOLD_METRICS:
            default.setdefault(m, base[m])
    missing = [m for m in THRESHOLD_METRICS if m not in default]
    if missing:
        raise ThresholdsError(f"{path}: no default ('*') row for {', '.join(missing)}")
    return Thresholds(default, by_role)


@lru_cache(maxsize=1)
def default_thresholds() -> Thresholds:
    """The shipped ``resources/quality_thresholds.csv``, read once (callers must not mutate it)."""
    return load_thresholds()


#: The default (``*``) corner-Jacobian warn level of the shipped table: the quality the mesh
#: improvement (smoother, relaxation goals, degraded-element selection) aims at.
JACOBIAN_WARN: float = default_thresholds().default["jacobian"].warn
