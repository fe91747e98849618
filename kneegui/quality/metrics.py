"""Per-element quality of every solid and shell block: Jacobians, aspect, warpage, skew, volume.

``compute_quality(coords, blocks)`` measures a whole model; ``QualityEvaluator(blocks)``
precomputes what does not depend on the coordinates so that ``evaluate(coords, rows=...)`` is
cheap enough to call on every slider step for the elements that moved. Definitions: QUALITY.md
(and :mod:`kneegui.quality.kernels`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kneegui.errors import raise_if_cancelled
from kneegui.model import ElementBlock
from kneegui.quality.kernels import (
    FACE_METRICS,
    KERNEL_EXTRA_METRICS,
    KERNELS,
    TET10_METRICS,
    TET_METRICS,
    corner_jacobian_only,
    tet_collapse_only,
    tet_measures_only,
)

#: Metric arrays every :class:`ElementQuality` holds, in display order.
METRICS: tuple[str, ...] = (
    "jacobian_corner",
    "jacobian_gauss",
    "aspect",
    "warpage",
    "skew",
    "volume",
)
#: Measures only tetrahedra have (the 10-node tet's mid-side offsets last), in display order;
#: an :class:`ElementQuality` of another type holds ``None`` for them.
TET_ONLY_METRICS: tuple[str, ...] = TET_METRICS + TET10_METRICS
#: Element types that have quality metrics (lines and springs have none).
MEASURED_TYPES: tuple[str, ...] = tuple(KERNELS)
#: The metrics :meth:`QualityEvaluator.evaluate` can measure alone (``only=``): every one a
#: heat-map shows (``volume`` is a solid's volume and a shell's area).
ONLY_METRICS: tuple[str, ...] = (
    "jacobian_corner",
    *TET_METRICS,
    *FACE_METRICS,
    "volume",
    *TET10_METRICS,
)

_CHUNK = 8192  # elements per kernel call: keeps the temporaries in cache
_PARALLEL_MIN = 4 * _CHUNK
#: ``cancel`` is asked before every this many chunks (a whole-body model: about 0.1 s each)
_WAVE = 16


@dataclass(frozen=True)
class ElementQuality:
    """Metrics of the elements of one type.

    Attributes
    ----------
    etype : str
        Element type.
    rows : (m,) ndarray of int64
        Rows of the block these values belong to (``arange(len(block))`` for a full evaluation).
    jacobian_corner, jacobian_gauss : (m,) ndarray of float
        Ratio of determinants at the corners / Gauss points; ``<= 0`` is invalid.
    aspect : (m,) ndarray of float
        Worst face's longest / shortest edge (>= 1, ``inf`` for a zero-length edge).
    warpage, skew : (m,) ndarray of float
        Worst face's values, degrees.
    volume : (m,) ndarray of float
        Signed volume of solids; area (>= 0) of shells. Model units cubed / squared.
    inverted : (m,) ndarray of bool
        ``jacobian_corner <= 0``: inverted, partly inverted or collapsed.
    tet_collapse, dihedral_min, dihedral_max, vol_skew, tet_aspect : (m,) ndarray or None
        Tetrahedra (tet4, and tet10 on its corner tet): HyperMesh's tet collapse (signed like
        the volume), the smallest / largest dihedral angle (degrees), the volumetric skew and
        the altitude aspect ratio (docs/quality.md). ``None`` for other types.
    midside_normal, midside_tangent : (m,) ndarray or None
        10-node tets: the largest mid-side-node offset normal to / along its edge, over the
        edge length. ``None`` for other types.
    measured : tuple of str or None
        ``None``: every metric of the type was measured. Otherwise the only ones that were
        (``QualityEvaluator.evaluate(..., only=...)``); asking for another raises.
    """

    etype: str
    rows: NDArray[np.int64]
    jacobian_corner: NDArray[np.float64]
    jacobian_gauss: NDArray[np.float64]
    aspect: NDArray[np.float64]
    warpage: NDArray[np.float64]
    skew: NDArray[np.float64]
    volume: NDArray[np.float64]
    inverted: NDArray[np.bool_]
    tet_collapse: NDArray[np.float64] | None = None
    dihedral_min: NDArray[np.float64] | None = None
    dihedral_max: NDArray[np.float64] | None = None
    vol_skew: NDArray[np.float64] | None = None
    tet_aspect: NDArray[np.float64] | None = None
    midside_normal: NDArray[np.float64] | None = None
    midside_tangent: NDArray[np.float64] | None = None
    measured: tuple[str, ...] | None = None

    def __len__(self) -> int:
        return len(self.rows)

    def has(self, name: str) -> bool:
        """Whether this element type has the metric (the tet-only ones are ``None`` elsewhere)
        and it was measured."""
        key = "jacobian_corner" if name == "jacobian" else name
        if self.measured is not None and key not in self.measured:
            return False
        return getattr(self, key) is not None

    def metric(self, name: str) -> NDArray:
        """One metric array by name (``"jacobian"`` is the corner Jacobian); NaN for a metric
        this element type does not have."""
        key = "jacobian_corner" if name == "jacobian" else name
        if self.measured is not None and key not in self.measured:
            raise ValueError(f"{key} was not measured (only {', '.join(self.measured)})")
        values = getattr(self, key)
        return np.full(len(self.rows), np.nan) if values is None else values


@dataclass(frozen=True)
class QualityResult:
    """Quality of a model's solid and shell elements, one :class:`ElementQuality` per type."""

    by_type: Mapping[str, ElementQuality] = field(default_factory=dict)

    def __getitem__(self, etype: str) -> ElementQuality:
        return self.by_type[etype]

    def __contains__(self, etype: object) -> bool:
        return etype in self.by_type

    def __iter__(self):
        return iter(self.by_type)

    @property
    def n_elements(self) -> int:
        """Number of measured elements."""
        return sum(len(q) for q in self.by_type.values())

    @property
    def n_inverted(self) -> int:
        """Number of elements with ``jacobian_corner <= 0``."""
        return int(sum(np.count_nonzero(q.inverted) for q in self.by_type.values()))

    def worst_jacobian(self, kind: str = "corner") -> float:
        """Smallest Jacobian ratio over every element (``nan`` if there are none)."""
        name = f"jacobian_{kind}"
        values = [q.metric(name) for q in self.by_type.values() if len(q)]
        return float(min(v.min() for v in values)) if values else float("nan")

    def has_metric(self, name: str) -> bool:
        """Whether any measured element type has the metric (a tet measure needs tets)."""
        return any(q.has(name) for q in self.by_type.values() if len(q))

    def concatenated(self, name: str) -> NDArray:
        """One metric over every type, concatenated in the order of ``by_type`` (NaN for the
        elements of types that do not have it)."""
        arrays = [q.metric(name) for q in self.by_type.values()]
        return np.concatenate(arrays) if arrays else np.zeros(0)


class QualityEvaluator:
    """Evaluate element quality of fixed blocks for changing coordinates.

    Parameters
    ----------
    blocks : mapping of str to ElementBlock
        The model's blocks; types without metrics (beams, springs) are ignored.
    threads : int, optional
        Worker threads for large evaluations (default: the number of CPUs, at most 8).

    Examples
    --------
    >>> ev = QualityEvaluator(model.blocks)                       # doctest: +SKIP
    >>> q = ev.evaluate(posed_coords, rows={"hex8": moved_rows})  # doctest: +SKIP
    """

    def __init__(self, blocks: Mapping[str, ElementBlock], threads: int | None = None):
        self._conn: dict[str, NDArray[np.int64]] = {}
        for etype, block in blocks.items():
            if etype in KERNELS and len(block):
                columns = KERNELS[etype][1]
                self._conn[etype] = np.ascontiguousarray(block.conn[:, list(columns)])
        self._threads = threads or min(os.cpu_count() or 1, 8)
        # what a kernel returns when asked for one measure, per (type, measure): worked out once
        # (on no elements), not with every slider pose
        self._only_names: dict[tuple[str, str], tuple[str, ...]] = {}

    @property
    def etypes(self) -> tuple[str, ...]:
        """The measured element types present."""
        return tuple(self._conn)

    def evaluate(
        self,
        coords: ArrayLike,
        rows: Mapping[str, ArrayLike] | None = None,
        only: str | None = None,
        cancel: Callable[[], bool] | None = None,
    ) -> QualityResult:
        """Measure the elements at the given node coordinates.

        Parameters
        ----------
        coords : (N, 3) array_like of float
            Node coordinates (not modified).
        rows : mapping of str to array_like of int, optional
            Evaluate only these rows of each block (types not named are skipped). Default:
            every element.
        only : str, optional
            One of :data:`ONLY_METRICS`: measure this metric (and the corner Jacobian, which
            says what is inverted) alone, bit-identical to the full evaluation's, for a
            heat-map redrawn with every slider pose: about a third of the cost for the
            Jacobian, a sixth for the tet collapse, two thirds for the other tet measures
            (measured together: a tet's result then has all of :data:`TET_METRICS`), the
            face measures and the volume without the rest of the kernel (what comes with
            them, the Gauss-point Jacobian with a volume, is kept and marked measured). The
            other metrics of the result are NaN and marked as not measured (a type without
            the metric, a hex for a tet measure, has it NaN as always).
        cancel : callable, optional
            Asked between waves of chunks (a whole-body model's elements: over a second in
            all); True raises :class:`~kneegui.errors.Cancelled`.

        Returns
        -------
        QualityResult
        """
        if only is not None and only not in ONLY_METRICS:
            raise ValueError(f"only= takes one of {', '.join(ONLY_METRICS)}, not {only!r}")
        xyz = np.asarray(coords, dtype=np.float64)
        n_selected = sum(
            len(c) if rows is None else (len(np.atleast_1d(rows[t])) if t in rows else 0)
            for t, c in self._conn.items()
        )
        # component-major copy of every node pays off only when most elements are measured
        xyz_t = np.ascontiguousarray(xyz.T) if 4 * n_selected > len(xyz) else None
        out: dict[str, ElementQuality] = {}
        for etype, conn in self._conn.items():
            if rows is None:
                sel = np.arange(len(conn), dtype=np.int64)
                sub = conn
            elif etype in rows:
                sel = np.asarray(rows[etype], dtype=np.int64).reshape(-1)
                sub = conn[sel]
            else:
                continue
            if only is not None:
                values = self._run(etype, xyz, xyz_t, sub, only=only, cancel=cancel)
                jac = values["jacobian_corner"]
                out[etype] = ElementQuality(
                    etype=etype,
                    rows=sel,
                    inverted=jac <= 0.0,
                    **{k: values.get(k, np.full(len(sel), np.nan)) for k in METRICS},
                    **{k: values.get(k) for k in TET_ONLY_METRICS},
                    measured=tuple(dict.fromkeys(("jacobian_corner", only, *values))),
                )
                continue
            values = self._run(etype, xyz, xyz_t, sub, cancel=cancel)
            out[etype] = ElementQuality(
                etype=etype, rows=sel, inverted=values["jacobian_corner"] <= 0.0, **values
            )
        return QualityResult(out)

    def _run(
        self,
        etype: str,
        xyz: NDArray[np.float64],
        xyz_t: NDArray[np.float64] | None,
        conn: NDArray[np.int64],
        only: str | None = None,
        cancel: Callable[[], bool] | None = None,
    ) -> dict[str, NDArray[np.float64]]:
        if only in (*FACE_METRICS, "volume", *TET10_METRICS):
            # the type's own kernel, working out that measure (and the corner Jacobian) alone
            full_kernel = KERNELS[etype][0]

            def kernel(pts):
                return full_kernel(pts, want=(only,))

            names = self._only_names.get((etype, only), ())
            if not names:
                with np.errstate(invalid="ignore", divide="ignore"):
                    names = tuple(kernel([np.zeros((3, 0)) for _ in range(conn.shape[1])]))
                self._only_names[(etype, only)] = names
        elif only is not None:
            tets = etype in ("tet4", "tet10")
            if etype == "tet10":
                conn = conn[:, :4]  # the corner tetrahedron
            # a tet measure of a tet: the collapse alone, or the shape measures together
            extra = None
            if tets and only == "tet_collapse":
                extra = lambda pts: {"tet_collapse": tet_collapse_only(pts)}  # noqa: E731
            elif tets and only in TET_METRICS:
                extra = tet_measures_only
            names = ("jacobian_corner",)
            if extra is not None:
                names += ("tet_collapse",) if only == "tet_collapse" else TET_METRICS

            def kernel(pts):
                out = {"jacobian_corner": corner_jacobian_only(pts, etype)}
                return out if extra is None else {**out, **extra(pts)}

        else:
            kernel = KERNELS[etype][0]
            names = METRICS + KERNEL_EXTRA_METRICS.get(etype, ())
        m = len(conn)
        result = {k: np.empty(m) for k in names}

        def work(start: int) -> None:
            block = conn[start : start + _CHUNK]
            if xyz_t is not None:
                pts = [xyz_t[:, block[:, k]] for k in range(block.shape[1])]
            else:
                pts = [np.ascontiguousarray(xyz[block[:, k]].T) for k in range(block.shape[1])]
            with np.errstate(invalid="ignore", divide="ignore"):
                values = kernel(pts)
            for k in names:
                result[k][start : start + len(block)] = values[k]

        starts = range(0, m, _CHUNK)
        if m >= _PARALLEL_MIN and self._threads > 1:
            with ThreadPoolExecutor(self._threads) as pool:
                for wave in range(0, len(starts), _WAVE):
                    raise_if_cancelled(cancel, "cancelled while measuring the quality")
                    list(pool.map(work, starts[wave : wave + _WAVE]))
        else:
            for k, s in enumerate(starts):
                if k % _WAVE == 0:
                    raise_if_cancelled(cancel, "cancelled while measuring the quality")
                work(s)
        return result


def compute_quality(
    coords: ArrayLike,
    blocks: Mapping[str, ElementBlock],
    rows: Mapping[str, ArrayLike] | None = None,
    cancel: Callable[[], bool] | None = None,
) -> QualityResult:
    """Quality metrics of every solid and shell element.

    Parameters
    ----------
    coords : (N, 3) array_like of float
        Node coordinates.
    blocks : mapping of str to ElementBlock
        Element blocks (``Model.blocks``); beams and springs are skipped.
    rows : mapping of str to array_like of int, optional
        Only these rows per type (see :meth:`QualityEvaluator.evaluate`).
    cancel : callable, optional
        As for :meth:`QualityEvaluator.evaluate`.

    Returns
    -------
    QualityResult
        Per element type, arrays aligned with the block's rows (or with ``rows``).
    """
    return QualityEvaluator(blocks).evaluate(coords, rows, cancel=cancel)


def element_quality(model, rows: Mapping[str, ArrayLike] | None = None) -> QualityResult:
    """Quality metrics of a :class:`kneegui.model.Model` (``compute_quality`` on its arrays)."""
    return compute_quality(model.coords, model.blocks, rows)
