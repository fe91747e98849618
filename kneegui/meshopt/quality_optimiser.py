"""Bring every element around a set of free nodes within its quality aims, all nodes together.

The four metrics of QUALITY.md become soft constraints, each element with its own aims
(:func:`quality_aims`: its initial value, or the warn threshold where that is less demanding):

- corner Jacobian ``J = min_i d_i / max_j d_j`` over the corner determinants: ``J >= t`` exactly
  when every pair of corners has ``log d_i - log d_j >= log t``, so the penalty is
  ``sum_(i != j) max(0, log t - log d_i + log d_j)^2``. Like J itself it is invariant to any
  affine map of the element: a squashed element that keeps its proportions costs nothing;
- aspect ratio of each face: ``max(0, log(l_i / l_j) - log aim)^2`` over its edge pairs;
- warpage of each quad face: ``max(0, theta - aim)^2``, theta the angle between the triangle
  normals of either diagonal split (an angle, not its cosine: the cosine's gradient vanishes on
  a face folded flat);
- skew of each quad face: ``max(0, |theta - 90 deg| - aim)^2``, theta between the mid-side
  lines.

Every term is zero inside the aims and grows smoothly with the shortfall. The corner
determinants must stay positive, so the optimiser runs on an untangled mesh and the line search
refuses a step onto a non-positive corner. L-BFGS minimises the sum over all free nodes
together, plus a weak anchor to the start (``anchor``, per squared edge length, so nodes with
nothing to gain stay put) and optional half-space constraints ``n . x >= offset`` as a quadratic
penalty (the repositioner's bone contact: tissue slides along a bone without entering it),
re-evaluated between rounds.

Why beside the node-by-node smoother (:mod:`kneegui.meshopt.smoother`): that one moves one
node at a time and keeps a move only if no element around it gets worse, so it cannot move a
column of nodes together, which is what flesh pressed between two bones needs. Why all four
metrics: the Jacobian alone can be raised by folding faces (measured on the default demo at 90
degrees: worst warpage 145 -> 161 degrees, aspect 9.6 -> 32; docs/repositioning.md).

Element count, node ids and connectivity never change; only the free nodes move.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import Cancelled
from kneegui.meshopt.lbfgs import minimize_lbfgs, round_monitor
from kneegui.meshopt.parallel import (
    PARALLEL_KERNEL_LOCK,
    PARALLEL_MIN_ELEMENTS,
    PARTS,
    add_in_order,
    part_bounds,
)
from kneegui.meshopt.quality_kernel import (
    LOG_COLLAPSE_SCALE,
    LOG_RATIO_SCALE,
    TET_EDGES,
    TET_OPPOSITE,
    anchor_and_constraints,
    below_floor,
    corner_ratio_penalty,
    face_aims,
    face_shape_penalty,
    penalty_in_parts,
    scatter_free,
)
from kneegui.model import ElementBlock
from kneegui.quality.kernels import corner_determinants, tet_measures_only
from kneegui.quality.metrics import QualityResult, compute_quality
from kneegui.quality.thresholds import Thresholds, default_thresholds
from kneegui.topology import CORNER_NODES, CORNER_TRIPLES, ELEMENT_FACES, sorted_unique

ProgressCallback = Callable[[float, str], None]
#: ``constraints(coords) -> (nodes, normals, offsets)``: node ``nodes[k]`` should satisfy
#: ``normals[k] . x >= offsets[k]`` (global node indices, unit normals). A fourth array,
#: ``partners``, may follow: where ``partners[k]`` is not -1 the plane holds the middle of the
#: two nodes, ``normals[k] . (x[nodes[k]] + x[partners[k]]) / 2 >= offsets[k]`` (an edge's
#: mid-side node carried between its corners: either corner may give way).
ConstraintCallback = Callable[[NDArray[np.float64]], tuple[NDArray, ...]]


#: How far (in log units: a relative 1e-9) a settling floor set at the worst solid now lies
#: below it (:attr:`QualityOptions.settling_floors`), so that rounding cannot put the start
#: below its own floor.
FLOOR_ROUNDING_MARGIN = 1e-9


def with_partners(
    constraints: tuple[NDArray, ...],
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """``(nodes, normals, offsets, partners)`` of a constraint tuple of three or four arrays
    (:data:`ConstraintCallback`; -1 partners for three)."""
    nodes = np.asarray(constraints[0], dtype=np.int64)
    normals = np.asarray(constraints[1], dtype=np.float64).reshape(-1, 3)
    offsets = np.asarray(constraints[2], dtype=np.float64)
    partners = (
        np.asarray(constraints[3], dtype=np.int64)
        if len(constraints) > 3
        else np.full(len(nodes), -1, dtype=np.int64)
    )
    return nodes, normals, offsets, partners


def constraint_gaps(
    constraints: tuple[NDArray, ...], x: NDArray[np.float64]
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Each constraint's nodes (its partner's too, as a second row) and how far the point it
    holds is on the right side of its plane at ``x`` (< 0: past it)."""
    nodes, normals, offsets, partners = with_partners(constraints)
    paired = partners >= 0
    point = x[nodes].copy()
    point[paired] = 0.5 * (point[paired] + x[partners[paired]])
    gap = np.einsum("ij,ij->i", normals, point) - offsets
    return np.concatenate([nodes, partners[paired]]), np.concatenate([gap, gap[paired]])


#: Solid types with corner determinants (a tet has one corner: only its sign counts; a 10-node
#: tet is measured by its corner tetrahedron, its mid-side nodes are the caller's).
SOLID_CORNER_TYPES = ("hex8", "wedge6", "pyramid5", "tet4", "tet10")
#: Types whose shape is held by the tet collapse (their corner Jacobian is 1 by definition).
TET_TYPES = ("tet4", "tet10")
OPTIMISED_TYPES = (*SOLID_CORNER_TYPES, "quad4")
QUAD_TRIPLES = np.array([t[:3] for t in CORNER_TRIPLES["quad4"]], dtype=np.int64)
#: Faces of each type as 4 local nodes, triangles padded with -1 (a shell is its own face).
_FACES = {
    etype: np.array([(*f, -1) if len(f) == 3 else f for f in faces], dtype=np.int64)
    for etype, faces in ELEMENT_FACES.items()
    if etype in OPTIMISED_TYPES
}


@dataclass(frozen=True)
class QualityAims:
    """Per element of each block (arrays aligned with the block's rows): the corner Jacobian to
    reach, and the aspect ratio, warpage and skew (degrees) not to exceed; for solids, the
    reference volume (the mean of the corner determinants at rest) and the relative volume
    change allowed either way, ``1 + volume_change`` (``inf``, or no reference: no limit); for
    tetrahedra (whose corner Jacobian is 1 by definition), the tet collapse to reach and the
    sine every dihedral angle should keep (a dihedral angle between ``asin`` of it and 180 deg
    minus that) and the volumetric skew not to exceed; ``gate``, the initial model's worst of
    what the quality gate holds the export to (``jacobian`` of the solids other than tets,
    ``tet_collapse``, ``dihedral_min``, ``dihedral_max``, ``vol_skew``, ``tet_aspect``): the
    optimiser weighs an element past one of them more heavily each round it stays there."""

    jacobian: Mapping[str, NDArray[np.float64]]
    aspect: Mapping[str, NDArray[np.float64]]
    warpage: Mapping[str, NDArray[np.float64]]
    skew: Mapping[str, NDArray[np.float64]]
    volume: Mapping[str, NDArray[np.float64] | RestVolumes] = field(default_factory=dict)
    volume_change: float = np.inf
    tet_collapse: Mapping[str, NDArray[np.float64]] = field(default_factory=dict)
    tet_dihedral_sine: Mapping[str, NDArray[np.float64]] = field(default_factory=dict)
    tet_vol_skew: Mapping[str, NDArray[np.float64]] = field(default_factory=dict)
    gate: Mapping[str, float] = field(default_factory=dict)


class RestVolumes:
    """The rest volume of each element of a block (the mean of its corner determinants),
    worked out for the rows asked for, when first asked for.

    The optimiser reads the volumes of the elements around the knee only; on a whole-body model
    measuring every element up front cost seconds. The mean of an element's corner
    determinants doesn't depend on which other rows are measured with it, so it is the same
    value in every bit (tested).

    Parameters
    ----------
    rest_coords : (N, 3) ndarray
        The initial coordinates (kept by reference: not to be modified).
    conn : (M, k) ndarray of int
        The block's connectivity.
    etype : str
        A solid type of :data:`kneegui.topology.CORNER_NODES`.
    """

    def __init__(
        self, rest_coords: NDArray[np.float64], conn: NDArray[np.int64], etype: str
    ) -> None:
        self._coords = rest_coords
        self._conn = conn[:, : CORNER_NODES[etype]]
        self._etype = etype
        self._values = np.full(len(conn), np.nan)
        self._known = np.zeros(len(conn), dtype=bool)

    def __len__(self) -> int:
        return len(self._values)

    def __getitem__(self, rows: NDArray[np.int64]) -> NDArray[np.float64]:
        rows = np.asarray(rows)
        if rows.dtype == bool:
            rows = np.flatnonzero(rows)
        missing = np.unique(rows[~self._known[rows]])
        if len(missing):
            points = self._coords[self._conn[missing]]
            self._values[missing] = corner_determinants(points, self._etype).mean(axis=1)
            self._known[missing] = True
        return self._values[rows]

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> NDArray[np.float64]:
        values = self[np.arange(len(self))]
        return values if dtype is None else values.astype(dtype)


def quality_aims(
    initial: QualityResult,
    blocks: Mapping[str, ElementBlock],
    thresholds: Thresholds | None = None,
    jacobian_cap: float | None = None,
    rest_coords: NDArray[np.float64] | None = None,
    volume_change: float | None = None,
) -> QualityAims:
    """Aims that keep every element at least as good as in the initial model, or within the
    warn threshold where that asks less.

    Parameters
    ----------
    initial : QualityResult
        Quality of the initial model (every row of each block).
    blocks : mapping of str to ElementBlock
        The model's blocks (for the row counts).
    thresholds : Thresholds, optional
        Default: ``resources/quality_thresholds.csv``; its default (``*``) warn levels are used.
    jacobian_cap : float, optional
        Highest corner Jacobian asked of any element (default: the warn level).
    rest_coords : (N, 3) ndarray, optional
        The initial coordinates, for the solids' reference volumes.
    volume_change : float, optional
        Relative volume change allowed per solid element either way (0.5: between 1/1.5 and
        1.5 times its initial volume); with ``rest_coords``.

    Returns
    -------
    QualityAims
        Jacobian ``min(initial, cap)``; aspect, warpage and skew ``max(initial, warn)``; tet
        collapse ``min(initial, warn)``; tet dihedral sine the smaller sine of
        ``min(initial smallest, warn)`` and ``max(initial largest, warn)``; tet volumetric skew
        the initial model's worst (a tet's skew swings by decades with its circumcentre: aimed
        at each tet's initial value or the warn level, the coarse tet demo's 95th percentile of
        volume change at 90 deg rose from 20 to 25.7 %).
    """
    levels = (thresholds or default_thresholds()).for_role(None)
    cap = levels["jacobian"].warn if jacobian_cap is None else float(jacobian_cap)
    out: dict[str, dict[str, NDArray[np.float64]]] = {
        m: {} for m in ("jacobian", "aspect", "warpage", "skew")
    }
    for etype in OPTIMISED_TYPES:
        if etype not in initial or etype not in blocks:
            continue
        q = initial[etype]
        n = len(blocks[etype])
        for metric, source, combine, level in (
            ("jacobian", q.jacobian_corner, np.minimum, cap),
            ("aspect", q.aspect, np.maximum, levels["aspect"].warn),
            ("warpage", q.warpage, np.maximum, levels["warpage"].warn),
            ("skew", q.skew, np.maximum, levels["skew"].warn),
        ):
            values = np.full(n, level, dtype=np.float64)
            values[q.rows] = combine(np.nan_to_num(source, nan=level, posinf=1e6), level)
            out[metric][etype] = values
    collapse: dict[str, NDArray[np.float64]] = {}
    sine: dict[str, NDArray[np.float64]] = {}
    skew: dict[str, NDArray[np.float64]] = {}
    for etype in TET_TYPES:
        q = initial[etype] if etype in initial else None
        if etype in blocks and q is not None and q.tet_collapse is not None:
            level = levels["tet_collapse"].warn
            values = np.full(len(blocks[etype]), level, dtype=np.float64)
            values[q.rows] = np.minimum(np.nan_to_num(q.tet_collapse, nan=level), level)
            collapse[etype] = values
        if etype in blocks and q is not None and q.dihedral_min is not None:
            low, high = levels["dihedral_min"].warn, levels["dihedral_max"].warn
            default = min(np.sin(np.radians(low)), np.sin(np.radians(high)))
            values = np.full(len(blocks[etype]), default, dtype=np.float64)
            smallest = np.minimum(np.nan_to_num(q.dihedral_min, nan=low), low)
            largest = np.maximum(np.nan_to_num(q.dihedral_max, nan=high), high)
            values[q.rows] = np.maximum(
                np.minimum(np.sin(np.radians(smallest)), np.sin(np.radians(largest))), 0.0
            )
            sine[etype] = values
    gate: dict[str, float] = {}
    for etype in SOLID_CORNER_TYPES:
        q = initial[etype] if etype in initial else None
        if etype in blocks and q is not None and len(q.rows) and q.jacobian_corner is not None:
            if etype not in TET_TYPES:
                worst = float(np.nanmin(q.jacobian_corner))
                gate["jacobian"] = min(gate.get("jacobian", np.inf), worst)
                continue
            for metric, pick in (
                ("tet_collapse", min),
                ("dihedral_min", min),
                ("dihedral_max", max),
                ("vol_skew", max),
                ("tet_aspect", max),
            ):
                values = getattr(q, metric)
                if values is not None and len(values):
                    worst = float(np.nanmin(values) if pick is min else np.nanmax(values))
                    gate[metric] = pick(gate.get(metric, worst), worst)
    if "vol_skew" in gate:
        for etype in TET_TYPES:
            if etype in blocks:
                skew[etype] = np.full(len(blocks[etype]), gate["vol_skew"])
    volume: dict[str, RestVolumes] = {}
    if rest_coords is not None and volume_change is not None:
        for etype in SOLID_CORNER_TYPES:
            if etype in blocks and len(blocks[etype]):
                volume[etype] = RestVolumes(rest_coords, blocks[etype].conn, etype)
    return QualityAims(
        **out,
        volume=volume,
        volume_change=np.inf if volume_change is None else float(volume_change),
        tet_collapse=collapse,
        tet_dihedral_sine=sine,
        tet_vol_skew=skew,
        gate=gate,
    )


def _blocks_touching(
    blocks: Mapping[str, ElementBlock], node_mask: NDArray[np.bool_]
) -> Iterator[tuple[str, ElementBlock, NDArray[np.int64], NDArray[np.int64]]]:
    """Each optimised block with its corner connectivity and the rows of its elements that have
    a node in ``node_mask`` (blocks with none are skipped)."""
    for etype in OPTIMISED_TYPES:
        block = blocks.get(etype)
        if block is None or len(block) == 0:
            continue
        conn = block.conn[:, : CORNER_NODES[etype]]
        rows = np.flatnonzero(node_mask[conn].any(axis=1))
        if len(rows):
            yield etype, block, conn, rows


#: Elements :func:`shortfall_region` measures between two questions to its ``cancel``.
REGION_CHUNK = 100_000


def shortfall_region(
    coords: NDArray[np.float64],
    blocks: Mapping[str, ElementBlock],
    aims: QualityAims,
    candidates: NDArray[np.int64],
    rings: int = 2,
    seeds: NDArray[np.int64] | None = None,
    misses: bool = True,
    shape_aims: bool = True,
    cancel: Callable[[], bool] | None = None,
) -> NDArray[np.int64]:
    """Candidate nodes within ``rings`` elements of an element that misses one of its aims (or
    of one of ``seeds``).

    Parameters
    ----------
    coords : (N, 3) ndarray
    blocks : mapping of str to ElementBlock
    aims : QualityAims
    candidates : (K,) ndarray of int
        Nodes that may move; only elements touching them are measured.
    rings : int
        Element layers the region grows by around the elements that miss an aim.
    seeds : (S,) ndarray of int, optional
        More nodes to grow the region from (e.g. nodes that break a constraint).
    misses : bool
        False: grow from ``seeds`` alone (no element is measured).
    shape_aims : bool
        False: only the aims of what the quality gate holds to the initial model count: the
        corner Jacobian of every element and, of tetrahedra, their collapse and shape aims
        (the gate checks a tet's collapse, dihedral angles, aspect and volume skew); not the
        other elements' aspect, warpage and skew, nor any volume band.
    cancel : callable, optional
        Asked before each :data:`REGION_CHUNK` elements measured; True raises
        :class:`kneegui.errors.Cancelled`.

    Returns
    -------
    (M,) ndarray of int
        Sorted node indices, a subset of ``candidates``.
    """
    n = len(coords)
    allowed = np.zeros(n, dtype=bool)
    allowed[candidates] = True
    region = np.zeros(n, dtype=bool)
    if seeds is not None:
        region[seeds] = True
    conns = {}
    for etype, block, conn, touching in _blocks_touching(blocks, allowed):
        conns[etype] = conn[touching]
        if not misses:
            continue
        # in chunks: the whole region of a whole-body model is seconds of measuring
        for lo in range(0, len(touching), REGION_CHUNK):
            if cancel is not None and cancel():
                raise Cancelled("quality optimisation cancelled")
            rows = touching[lo : lo + REGION_CHUNK]
            q = compute_quality(coords, {etype: block}, rows={etype: rows})[etype]
            miss = q.jacobian_corner < aims.jacobian.get(etype, np.zeros(len(block)))[rows]
            collapse_aim = aims.tet_collapse.get(etype)
            if collapse_aim is not None and q.tet_collapse is not None:
                miss |= q.tet_collapse < collapse_aim[rows]
            sine_aim = aims.tet_dihedral_sine.get(etype)
            if sine_aim is not None and q.dihedral_min is not None:
                sine = np.minimum(
                    np.sin(np.radians(q.dihedral_min)), np.sin(np.radians(q.dihedral_max))
                )
                miss |= sine < sine_aim[rows]
            skew_aim = aims.tet_vol_skew.get(etype)
            if skew_aim is not None and q.vol_skew is not None:
                miss |= q.vol_skew > skew_aim[rows]
            shape = shape_aims or etype in TET_TYPES
            for metric in ("aspect", "warpage", "skew") if shape else ():
                limit = getattr(aims, metric).get(etype)
                if limit is not None:
                    miss |= q.metric(metric) > limit[rows]
            reference = aims.volume.get(etype)
            if shape_aims and reference is not None and np.isfinite(aims.volume_change):
                volume = corner_determinants(coords[conn[rows]], etype).mean(axis=1)
                with np.errstate(divide="ignore", invalid="ignore"):
                    # an element flat at rest (a damaged deck) misses its aim once it has volume
                    ratio = volume / reference[rows]
                band = 1.0 + aims.volume_change
                miss |= (ratio > band) | (ratio < 1.0 / band)
            region[conn[rows[miss]]] = True
    for _ in range(rings):
        grown = region.copy()
        for conn in conns.values():
            grown[conn[region[conn].any(axis=1)]] = True
        region = grown
    return np.flatnonzero(region & allowed)


@dataclass(frozen=True)
class QualityOptions:
    """Parameters of :func:`optimise_quality`.

    Attributes
    ----------
    margin : float
        Each element aims this much above its Jacobian goal (the penalty is soft, so an element
        settles below its aim where something pulls against it: bone contact pressing flesh).
        With 0.03 an element of the coarse left-leg demo at 90 deg settled 0.013 below its
        initial Jacobian, at 0.3295 against the model's initial worst 0.3304, and the gate
        hinged on the last digits; with 0.08 the worst ends 0.338.
    weights : (float, float, float)
        Weights of the aspect, warpage and skew penalties against the Jacobian's.
    volume_weight : float
        Weight of the volume penalty (where the aims limit the volume change).
    gate_boost, gate_boost_limit : float
        Before each round after the first, the weight of each element past the initial model's
        worst (:attr:`QualityAims.gate`, within ``gate_margin`` of it: the corner Jacobian, the
        tet collapse, dihedral angles, volumetric skew or tet aspect) is multiplied by
        ``gate_boost``, up to ``gate_boost_limit``: the few elements the gate would fail on get
        the pull of the rest of the mesh, the bulk keeps its balance between shape and volume
        (a weight of 3 on every tet's terms passed the coarse tet demo's tet measures at 90 deg
        but its 95th percentile of volume change rose to 25.7 % and the mixed demo's worst hex
        fell to 0.30; 9, without the skew term, took its tets over 25 % volume change from 570
        to 1,610).
    gate_margin : float
        Relative margin over the gate's levels.
    beyond_margin : float
        Relative margin over the gate's levels within which an element outside the caller's
        region that the pose made worse is mended (:func:`gate_shortfall_nodes`; the caller
        lets its nodes move). With 0.01 the coarse demo posed to 0 deg ended with a worst
        Jacobian of 0.334 against the initial 0.330, with 0.03 0.338.
    beyond_aim_margin : float
        ``margin`` of that pass, which only mends: with the region's 0.08 the coarse demo posed
        to 0 deg had calf skin nodes slide up to 9.7 mm along the skin and its 95th percentile
        of volume change went from 16.3 to 17.9 % (worst Jacobian 0.344); with 0.02, 2.7 mm and
        16.3 % (0.346).
    gate_reach : float
        A measure's elements are weighed up only while its worst is within this fraction of
        the gate's level: on the hex demos at 120 deg (worst Jacobian 0.18 against 0.33)
        weighing up every element below 0.33 raised the worst to 0.29 but the 95th percentile
        of volume change from 32 to 50 % (and left a node deeper than 0.5 mm in a bone of the
        leg built at 0 deg), for a gate that failed all the same.
    gate_rounds : int
        After the rounds, at most this many more while an element is past the gate's levels,
        each with those elements weighed up again.
    anchor : float
        Weight of ``|x - x_start|^2 / h^2`` per free node (``h`` its mean edge length at the
        start).
    rounds : int
        Rounds of (update the constraints, then L-BFGS).
    iterations_per_round : int
        L-BFGS iterations per round.
    constraint_stiffness : float
        Penalty per squared model unit of a violated constraint.
    constraint_tolerance : float
        The rounds go on (up to ``rounds``) while a node is farther than this (model units) on
        the wrong side of its constraint, re-evaluated at the end of each round.
    tolerance : float
        Stop when a round lowers the objective by less than this fraction.
    settling_rounds : int
        After the rounds, at most this many more against freshly evaluated constraints, the
        stiffness four times higher each time, while a node is farther than
        ``constraint_tolerance`` on the wrong side of its constraint; if one still is, one
        round over the whole stage and at most this many settling rounds again (kept only if
        it brought the nodes further out).
    settling_floor : float
        No settling round (nor that whole-stage round) may take a solid's corner Jacobian or a
        tet's collapse below this fraction of the worst around the free nodes when the rounds
        ended: a node its planes cannot bring back stays past them rather than flattening the
        elements in its way.
    settling_floors : (float, float) or None
        Instead of ``settling_floor``: the corner Jacobian and the tet collapse the settling may
        take a solid down to, or the worst around the free nodes when the rounds ended where
        that is lower (nothing is made worse than the worst already there). None:
        ``settling_floor`` times that worst.
    active_rings, active_shrink : int, float
        After the first round, each round moves only the free nodes within ``active_rings``
        elements of an element still missing an aim the gate holds to the initial model (the
        corner Jacobian; for tetrahedra also collapse and shape) or of a node past its
        constraint (:func:`shortfall_region` without the shape aims), when they are at most
        ``active_shrink`` of the nodes the round before moved (0 never narrows). The other
        elements' aspect, warpage, skew and volume aims stay in the objective but do not keep
        nodes moving:
        being soft, they miss by a little on thousands of elements (the 20k demo at 90 deg:
        about 2,300 hexes outside the volume band and 2,500 over their warpage aim in every
        round), so counting them kept all 7,294 nodes in all fifteen rounds, while the
        Jacobian misses fell from 471 after the first round to 9. Narrowed, the stage took
        5.4 s instead of 13.5 s with the same worst Jacobian and 95th-percentile volume change.
        Tetrahedra keep their shape aims in the count: without them the coarse tet demo's
        worst collapse at 90 deg fell from 0.106 to 0.102.
    hold_inverted : bool
        Run on a region the untangling left with elements still inverted too: every node of
        those elements held where the untangling left it, and only around the nodes past
        their constraints (the caller finds both; see
        :meth:`kneegui.reposition.relax.ElasticRelaxation.optimise`). False: the stage waits
        for an untangled region. A region that does not untangle never had its bone contact
        stiffened, and the settling of this stage is what brings the tissue out of the bones:
        the 177k demo at 90 deg (three elements never freed) ended with 316 soft-tissue nodes
        up to 4.7 mm inside a bone without it and none with it.
        On such a region the stage runs no gate rounds (the held elements fail the gate
        whatever the others do).
    tangle_pass_nodes : int
        After that, on such a region, a second pass over the region's whole shortfall, the
        nearly flat elements held as well
        (:meth:`kneegui.reposition.relax.ElasticRelaxation._optimise_around_tangles`), when
        it moves at most this many nodes (0: never). The leg built at 20 deg, posed to
        120 deg: 95th percentile of the soft solids' volume change 32 % instead of 75 %, for
        5 s (10,805 nodes). The 1M demo at 90 deg: 59 % instead of 68 %, for 360 s more and
        a 6.7 s wait for a cancel (354,037 nodes): past this bound the pass costs more than it
        brings, until the stage is faster.
    """

    margin: float = 0.08
    weights: tuple[float, float, float] = (1.0, 1.0, 1.0)
    volume_weight: float = 1.0
    gate_boost: float = 10.0
    gate_boost_limit: float = 1000.0
    gate_margin: float = 0.01
    beyond_margin: float = 0.03
    beyond_aim_margin: float = 0.02
    gate_reach: float = 0.25
    gate_rounds: int = 4
    anchor: float = 1e-4
    rounds: int = 6
    iterations_per_round: int = 400
    constraint_stiffness: float = 10.0
    constraint_tolerance: float = 0.05
    tolerance: float = 0.02
    settling_rounds: int = 6
    settling_floor: float = 0.5
    settling_floors: tuple[float, float] | None = None
    active_rings: int = 2
    active_shrink: float = 0.9
    hold_inverted: bool = True
    tangle_pass_nodes: int = 100_000

    def scaled(self, length: float) -> QualityOptions:
        """These options for a model drawn ``length`` times larger (or in other units): the
        constraint tolerance grows with it, and the stiffness per squared model unit shrinks
        with its square, so the penalty of a violation of the same relative depth is the
        same (the other terms are ratios and angles)."""
        return replace(
            self,
            constraint_stiffness=self.constraint_stiffness / (length * length),
            constraint_tolerance=self.constraint_tolerance * length,
        )


@dataclass(frozen=True)
class QualityOptimisationReport:
    """What :func:`optimise_quality` did.

    Attributes
    ----------
    free_nodes, elements : int
        Nodes moved and elements measured (those with a free node).
    below_aim_before, below_aim_after : int
        Elements with a corner Jacobian below their aim (without the margin).
    worst_before, worst_after : float
        Worst corner Jacobian of those elements (1.0 on a tetrahedron, by definition).
    collapse_below_aim_before, collapse_below_aim_after : int
        Tetrahedra with a tet collapse below their aim (without the margin).
    collapse_worst_before, collapse_worst_after : float
        Worst tet collapse of those tetrahedra (nan without any).
    rounds, iterations, evaluations : int
    max_displacement : float
        Largest node displacement (model units).
    seconds : float
    active_nodes : list of int
        Free nodes each round moved (the first round moves them all, later ones only those
        around what still misses an aim).
    beyond_region_nodes : int
        Nodes a second pass moved beyond the caller's region, around elements the pose left
        past the gate's levels (:func:`gate_shortfall_nodes`); its time and iterations are
        added to ``seconds``, ``iterations`` and ``evaluations``, the other figures are the
        region's.
    held_nodes : int
        Nodes of the region held where the untangling left them because an element of theirs
        was still inverted (``QualityOptions.hold_inverted``).
    bone_settled_nodes : int
        Nodes a last settling moved around the contact nodes the region's optimisation left
        deeper in a bone than its constraint tolerance, apart from the rest of the region
        (kneegui.reposition.relax); its time and iterations are added like the second pass's.
    """

    free_nodes: int = 0
    elements: int = 0
    below_aim_before: int = 0
    below_aim_after: int = 0
    worst_before: float = float("nan")
    worst_after: float = float("nan")
    collapse_below_aim_before: int = 0
    collapse_below_aim_after: int = 0
    collapse_worst_before: float = float("nan")
    collapse_worst_after: float = float("nan")
    rounds: int = 0
    iterations: int = 0
    evaluations: int = 0
    max_displacement: float = 0.0
    seconds: float = 0.0
    region_seconds: float = 0.0  # the caller's search for the region (not in ``seconds``)
    active_nodes: list[int] = field(default_factory=list)
    beyond_region_nodes: int = 0
    held_nodes: int = 0
    bone_settled_nodes: int = 0

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return asdict(self)

    def floors(self) -> tuple[float, float]:
        """The worst corner Jacobian and tet collapse this pass left (1.0 where it measured
        none): a later pass's ``QualityOptions.settling_floors``, so that what the gate
        measures does not get worse."""
        jacobian, collapse = self.worst_after, self.collapse_worst_after
        return (
            jacobian if np.isfinite(jacobian) else 1.0,
            collapse if np.isfinite(collapse) else 1.0,
        )

    def with_pass(
        self, other: QualityOptimisationReport, region_seconds: float, **figures: float
    ) -> QualityOptimisationReport:
        """This report with a later pass's time and iterations added (``region_seconds``: that
        pass's search for its nodes) and ``figures`` set; the other figures stay this one's."""
        return replace(
            self,
            seconds=self.seconds + other.seconds,
            region_seconds=self.region_seconds + region_seconds,
            iterations=self.iterations + other.iterations,
            evaluations=self.evaluations + other.evaluations,
            **figures,
        )


@dataclass(frozen=True)
class _Problem:
    """The elements around the free nodes, in local node numbering."""

    nodes: NDArray[np.int64]  # global ids of the local nodes
    free: NDArray[np.int64]  # local rows of the free nodes
    corners: NDArray[np.int64]  # (C, 4) solid corners, grouped by element
    elem_ptr: NDArray[np.int64]  # (E + 1,)
    log_aim: NDArray[np.float64]  # (E,)
    log_collapse_aim: NDArray[np.float64]  # (E,) tets' collapse aim with the margin, -inf others
    log_sine_aim: NDArray[np.float64]  # (E,) tets' dihedral sine aim with the margin, -inf others
    log_ratio_aim: NDArray[np.float64]  # (E,) tets' 1 - volumetric skew aim, margin, -inf others
    element_weight: NDArray[np.float64]  # (E,) weight of each solid's corner and tet terms
    element_index: NDArray[np.int64]  # (E,) the solid's index in the model (_element_offsets)
    collapse_aim: NDArray[np.float64]  # (E,) without the margin, 0 for other solids
    log_volume: NDArray[np.float64]  # (E,) log of the reference volume
    volume_band: NDArray[np.float64]  # (E,) allowed |log(v / v0)|, inf for none
    volume_weight: float
    jacobian_aim: NDArray[np.float64]  # (E + Q,) solids then quads, without the margin
    quads: NDArray[np.int64]  # (Q, 4)
    quad_log_aim: NDArray[np.float64]
    faces: NDArray[np.int64]  # (F, 4), -1 pads triangles
    face_aims: NDArray[np.float64]  # (F, 6), quality_kernel.face_aims
    weights: NDArray[np.float64]

    def corner_args(self) -> tuple:
        """The arguments of :func:`~kneegui.meshopt.quality_kernel.corner_ratio_penalty`
        between the coordinates and the gradient, in its order."""
        return (
            self.corners,
            self.elem_ptr,
            self.log_aim,
            self.log_collapse_aim,
            self.log_sine_aim,
            self.log_ratio_aim,
            self.element_weight,
            self.log_volume,
            self.volume_band,
            self.volume_weight,
            self.quads,
            QUAD_TRIPLES,
            self.quad_log_aim,
        )


def _element_offsets(blocks: Mapping[str, ElementBlock]) -> dict[str, int]:
    """Where each solid type's rows start in one numbering of the model's solids."""
    out, total = {}, 0
    for etype in SOLID_CORNER_TYPES:
        out[etype] = total
        total += len(blocks[etype]) if etype in blocks else 0
    return out


#: The tet measures the gate's weights watch: each as its distance from a flat tet (the
#: dihedral angles' from 0 or 180 deg, the skew's from 1), so that a margin and a reach are
#: fractions of that distance, and whether low values are the bad ones.
_TET_GATE_MEASURES: dict[str, tuple[Callable[[Any], Any], bool]] = {
    "tet_collapse": (lambda v: v, True),
    "dihedral_min": (lambda v: v, True),
    "dihedral_max": (lambda v: 180.0 - v, True),
    "vol_skew": (lambda v: 1.0 - v, True),
    "tet_aspect": (lambda v: v, False),
}


#: The gate's measure of the other solids, as :data:`_TET_GATE_MEASURES`.
_SOLID_GATE_MEASURES: dict[str, tuple[Callable[[Any], Any], bool]] = {
    "jacobian": (lambda v: v, True)
}
#: The quality result's field of a gate measure, where its name differs.
_GATE_FIELDS = {"jacobian": "jacobian_corner"}


def _past_level(
    values: NDArray[np.float64], level: float, low_bad: bool, margin: float
) -> NDArray[np.bool_]:
    """Which ``values`` (a distance from a flat tet, or a Jacobian) are past a gate ``level``
    or within the relative ``margin`` of it, on its bad side."""
    if low_bad:
        return values < level * (1.0 + margin)
    return values > level * (1.0 - margin)


def _gate_misses(
    pr: _Problem, x: NDArray[np.float64], gate: Mapping[str, float], margin: float, reach: float
) -> NDArray[np.bool_]:
    """(E,) the problem's solids past (or within ``margin`` of) the gate's levels, for each
    measure whose worst over the problem is within ``reach`` of its level (relative; for the
    dihedral angles, of the angle to 0 or 180 deg): where the worst is farther, the gate fails
    whatever the rest of the mesh gives up for it."""
    counts = np.diff(pr.elem_ptr)
    miss = np.zeros(len(counts), dtype=bool)

    def past(values: NDArray, level: float, low_bad: bool) -> NDArray[np.bool_]:
        if low_bad:
            in_reach = values.min(initial=np.inf) >= (1.0 - reach) * level
        else:
            in_reach = values.max(initial=-np.inf) <= level / (1.0 - reach)
        return _past_level(values, level, low_bad, margin) & in_reach

    solids = counts > 1
    if "jacobian" in gate and solids.any():
        j = _element_jacobians(pr, x)[: len(counts)]
        miss[solids] = past(j[solids], gate["jacobian"], True)
    tets = np.flatnonzero(counts == 1)
    if len(tets):
        c = pr.corners[pr.elem_ptr[tets]]
        m = tet_measures_only([x[c[:, j]].T for j in range(4)])
        bad = np.zeros(len(tets), dtype=bool)
        for name, (distance, low_bad) in _TET_GATE_MEASURES.items():
            if name in gate:
                bad |= past(distance(m[name]), distance(gate[name]), low_bad)
        miss[tets[bad]] = True
    return miss


def gate_shortfall_nodes(
    coords: NDArray[np.float64],
    blocks: Mapping[str, ElementBlock],
    gate: Mapping[str, float],
    initial: QualityResult,
    node_mask: NDArray[np.bool_],
    margin: float,
) -> NDArray[np.int64]:
    """Nodes of the solids with a node in ``node_mask`` that are past (or within ``margin`` of)
    one of the gate's levels on a measure the pose made worse than in the initial model.

    The second test leaves out an element no worse than it was (the model's worst element
    carried rigidly sits on the gate's level): only what the pose degraded is returned.

    Parameters
    ----------
    coords : (N, 3) ndarray
    blocks : mapping of str to ElementBlock
    gate : mapping of str to float
        The gate's levels (:attr:`QualityAims.gate`).
    initial : QualityResult
        Quality of the initial model (every row of each block).
    node_mask : (N,) ndarray of bool
        Only the solids with a node here are measured.
    margin : float
        Relative margin, as :attr:`QualityOptions.gate_margin` (of the distance from a flat
        tet for the tet measures, :data:`_TET_GATE_MEASURES`).

    Returns
    -------
    (M,) ndarray of int
        Sorted node indices (every corner node of those elements).
    """
    found = np.zeros(len(coords), dtype=bool)
    worse = 1e-9  # relative: the rounding of a rigid motion does not make an element worse
    for etype, block, conn, rows in _blocks_touching(blocks, node_mask):
        if etype not in SOLID_CORNER_TYPES or etype not in initial:
            continue
        q = compute_quality(coords, {etype: block}, rows={etype: rows})[etype]
        q0 = initial[etype]
        at = np.searchsorted(q0.rows, rows)
        measures = _TET_GATE_MEASURES if etype in TET_TYPES else _SOLID_GATE_MEASURES
        bad = np.zeros(len(rows), dtype=bool)
        for name, (distance, low_bad) in measures.items():
            field_name = _GATE_FIELDS.get(name, name)
            now, then = getattr(q, field_name), getattr(q0, field_name)
            if name not in gate or now is None or then is None:
                continue
            v, v0 = distance(now), distance(then[at])
            made_worse = v < v0 * (1.0 - worse) if low_bad else v > v0 * (1.0 + worse)
            bad |= _past_level(v, distance(gate[name]), low_bad, margin) & made_worse
        found[conn[rows[bad]]] = True
    return np.flatnonzero(found)


def _build_problem(
    blocks: Mapping[str, ElementBlock],
    n_nodes: int,
    free: NDArray[np.int64],
    aims: QualityAims,
    options: QualityOptions,
) -> _Problem:
    is_free = np.zeros(n_nodes, dtype=bool)
    is_free[free] = True
    corners, counts, jac_solid, quads, jac_quad, ref_volume = [], [], [], [], [], []
    collapse_solid, sine_solid, ratio_solid, index_solid = [], [], [], []
    offsets = _element_offsets(blocks)
    faces, f_aspect, f_warp, f_skew = [], [], [], []
    for etype, _block, conn, rows in _blocks_touching(blocks, is_free):

        def aim(metric: str, default: float, etype: str = etype, rows=rows) -> NDArray:
            values = getattr(aims, metric).get(etype)
            return np.full(len(rows), default) if values is None else np.asarray(values)[rows]

        jac = aim("jacobian", 0.0)  # a type without aims only has to stay positive
        if etype == "quad4":
            quads.append(conn[rows])
            jac_quad.append(jac)
        else:
            triples = np.array(CORNER_TRIPLES[etype], dtype=np.int64)
            corners.append(conn[rows][:, triples].reshape(-1, 4))
            counts.append(np.full(len(rows), len(triples)))
            jac_solid.append(jac)
            collapse_solid.append(aim("tet_collapse", 0.0))  # other solids: no collapse aim
            sine_solid.append(aim("tet_dihedral_sine", 0.0))
            ratio_solid.append(1.0 - aim("tet_vol_skew", 1.0))  # 0: no aim
            index_solid.append(offsets[etype] + rows)
            ref = aims.volume.get(etype)
            ref_volume.append(np.full(len(rows), np.nan) if ref is None else ref[rows])
        local = _FACES[etype]
        f = np.where(local >= 0, conn[rows][:, np.maximum(local, 0)], -1)  # (m, faces, 4)
        faces.append(f.reshape(-1, 4))
        per_face = local.shape[0]
        f_aspect.append(np.repeat(aim("aspect", np.inf), per_face))
        f_warp.append(np.repeat(aim("warpage", 180.0), per_face))
        f_skew.append(np.repeat(aim("skew", 90.0), per_face))

    def cat(parts: list, shape: tuple[int, ...] = (0,), dtype=np.float64) -> NDArray:
        return np.concatenate(parts) if parts else np.zeros(shape, dtype=dtype)

    corners_g = cat(corners, (0, 4), np.int64)
    quads_g = cat(quads, (0, 4), np.int64)
    faces_g = cat(faces, (0, 4), np.int64)
    used = np.concatenate([corners_g.ravel(), quads_g.ravel(), faces_g[faces_g >= 0]])
    nodes = sorted_unique(used)

    def local(idx: NDArray[np.int64]) -> NDArray[np.int64]:
        return np.where(idx >= 0, np.searchsorted(nodes, idx), -1).astype(np.int64)

    def log_aim(goal: NDArray[np.float64]) -> NDArray[np.float64]:
        # a goal of 0 or less asks only for positive corners: log 0 = -inf never binds
        with np.errstate(divide="ignore"):
            return np.log(np.clip(goal + options.margin, 0.0, 1.0) * (goal > 0))

    def log_ratio_aim(goal: NDArray[np.float64]) -> NDArray[np.float64]:
        # the ratio V / V_ideal spans decades (1e-4 on a fair-looking tet with a far
        # circumcentre): its margin is relative
        with np.errstate(divide="ignore"):
            return np.log(np.clip(goal * (1.0 + options.margin), 0.0, 1.0))

    jac_s, jac_q = cat(jac_solid), cat(jac_quad)
    collapse = cat(collapse_solid)
    ref = cat(ref_volume)
    limited = (ref > 0) & np.isfinite(aims.volume_change)
    band = np.where(limited, np.log1p(aims.volume_change) if limited.any() else 0.0, np.inf)
    # a face shared by two elements is measured once, against the stricter of their aims
    # (aspect, warpage and skew do not depend on the face's orientation)
    _, first, group = np.unique(
        np.sort(faces_g, axis=1).reshape(-1, 4), axis=0, return_index=True, return_inverse=True
    )
    group = group.ravel()

    def strictest(values: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.full(len(first), np.inf)
        np.minimum.at(out, group, values)
        return out

    faces_g = faces_g[first]
    aspect = np.maximum(strictest(cat(f_aspect)), 1.0)
    warpage = strictest(cat(f_warp))
    skew = strictest(cat(f_skew))
    return _Problem(
        nodes=nodes,
        free=np.searchsorted(nodes, np.intersect1d(free, nodes)),
        corners=local(corners_g),
        elem_ptr=np.concatenate([[0], np.cumsum(cat(counts, dtype=np.int64))]).astype(np.int64),
        log_aim=log_aim(jac_s),
        log_collapse_aim=log_aim(collapse),
        log_sine_aim=log_aim(cat(sine_solid)),
        log_ratio_aim=log_ratio_aim(cat(ratio_solid)),
        element_weight=np.ones(len(jac_s)),
        element_index=cat(index_solid, dtype=np.int64),
        collapse_aim=collapse,
        log_volume=np.log(np.where(limited, ref, 1.0)),
        volume_band=band,
        volume_weight=float(options.volume_weight),
        jacobian_aim=np.concatenate([jac_s, jac_q]),
        quads=local(quads_g),
        quad_log_aim=log_aim(jac_q),
        faces=local(faces_g),
        face_aims=face_aims(
            np.log(aspect),
            np.radians(np.clip(warpage, 0.0, 180.0)),
            np.radians(np.clip(skew, 0.0, 90.0)),
        ),
        weights=np.asarray(options.weights, dtype=np.float64),
    )


def _element_jacobians(pr: _Problem, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Corner Jacobian of the problem's solids, then its quads, at local coordinates ``x``."""
    c = pr.corners
    a, b, e = (x[c[:, j]] - x[c[:, 0]] for j in (1, 2, 3))
    d = np.einsum("ij,ij->i", np.cross(a, b), e)
    starts = pr.elem_ptr[:-1]
    out = []
    if len(starts):
        hi = np.maximum.reduceat(d, starts)
        with np.errstate(divide="ignore", invalid="ignore"):  # hi <= 0 is replaced just below
            out.append(np.minimum.reduceat(d, starts) / hi)
        out[-1][hi <= 0] = -1.0
    if len(pr.quads):
        p = x[pr.quads]
        n = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
        t = QUAD_TRIPLES
        w = np.cross(p[:, t[:, 1]] - p[:, t[:, 0]], p[:, t[:, 2]] - p[:, t[:, 0]])
        dq = np.einsum("qkj,qj->qk", w, n)
        hi = dq.max(axis=1)
        out.append(np.where(hi > 0, dq.min(axis=1) / np.where(hi > 0, hi, 1.0), -1.0))
    return np.concatenate(out) if out else np.zeros(0)


def _tet_collapses(pr: _Problem, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Tet collapse of the problem's tetrahedra (its one-corner solids) at local ``x``, in
    their order, with their aims (``pr.collapse_aim``) alongside."""
    tets = np.flatnonzero(np.diff(pr.elem_ptr) == 1)
    c = pr.corners[pr.elem_ptr[tets]]
    p = x[c]
    d = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    largest = np.zeros(len(tets))
    for i0, i1, i2 in TET_OPPOSITE:
        n = np.cross(p[:, i1] - p[:, i0], p[:, i2] - p[:, i0])
        largest = np.maximum(largest, np.einsum("ij,ij->i", n, n))
    with np.errstate(divide="ignore", invalid="ignore"):
        log_c = np.log(d) - 0.75 * np.log(largest) + LOG_COLLAPSE_SCALE
    return np.where(d > 0, np.exp(log_c), 0.0)


def corner_ratio_penalty_numpy(
    x: NDArray[np.float64],
    corners: NDArray[np.int64],
    elem_ptr: NDArray[np.int64],
    log_aim: NDArray[np.float64],
    log_collapse_aim: NDArray[np.float64],
    log_sine_aim: NDArray[np.float64],
    log_ratio_aim: NDArray[np.float64],
    element_weight: NDArray[np.float64],
    log_volume: NDArray[np.float64],
    volume_band: NDArray[np.float64],
    volume_weight: float,
    quads: NDArray[np.int64],
    quad_log_aim: NDArray[np.float64],
) -> tuple[float, NDArray[np.float64]]:
    """NumPy reference of the compiled corner penalty
    (:func:`kneegui.meshopt.quality_kernel.corner_ratio_penalty`).

    Returns ``(penalty, gradient (S, 3))``; ``(inf, zeros)`` when a corner is not positive.
    """
    grad = np.zeros_like(x)
    total = 0.0
    counts = np.diff(elem_ptr)
    for k in np.unique(counts):
        elems = np.flatnonzero(counts == k)
        c = corners[(elem_ptr[elems][:, None] + np.arange(k)).ravel()]
        a, b, e = (x[c[:, j]] - x[c[:, 0]] for j in (1, 2, 3))
        d = np.einsum("ij,ij->i", np.cross(a, b), e)
        if np.any(d <= 0):
            return np.inf, np.zeros_like(x)
        logs = np.log(d).reshape(-1, k)
        u = log_aim[elems][:, None, None] - logs[:, :, None] + logs[:, None, :]
        u[:, np.arange(k), np.arange(k)] = 0.0
        pos = np.maximum(u, 0.0)
        weight = element_weight[elems]  # (m,) each element's weight
        total += float(np.sum(weight[:, None, None] * pos * pos))
        s = (weight[:, None] * (-2.0 * pos.sum(axis=2) + 2.0 * pos.sum(axis=1))).ravel() / d
        mean = d.reshape(-1, k).mean(axis=1)
        change = np.log(mean) - log_volume[elems]
        excess = np.maximum(np.abs(change) - volume_band[elems], 0.0)
        total += volume_weight * float(np.sum(excess * excess))
        s = s + np.repeat(2.0 * volume_weight * excess * np.sign(change) / (k * mean), k)
        if k == 1:  # tetrahedra: the collapse at each node, h_i / sqrt(A_i)
            p = x[c]  # (m, 4, 3)
            faces = []
            for i0, i1, i2 in TET_OPPOSITE:
                u_, v_ = p[:, i1] - p[:, i0], p[:, i2] - p[:, i0]
                n = np.cross(u_, v_)
                nn = np.einsum("ij,ij->i", n, n)
                faces.append((i0, i1, i2, u_, v_, n, nn))
                log_c = np.log(d) - 0.75 * np.log(nn) + LOG_COLLAPSE_SCALE
                short = np.maximum(log_collapse_aim[elems] - log_c, 0.0)
                total += float(np.sum(weight * short * short))
                s = s - 2.0 * weight * short / d
                w = (3.0 * weight * short / nn)[:, None]
                gu, gv = w * np.cross(v_, n), w * np.cross(n, u_)
                for col, g in ((i1, gu), (i2, gv), (i0, -(gu + gv))):
                    np.add.at(grad, c[:, col], g)
            for ea, eb, fk, fl in TET_EDGES:  # the sine of the dihedral angle at each edge
                edge = p[:, eb] - p[:, ea]
                ll = np.einsum("ij,ij->i", edge, edge)
                log_sin = np.log(d) + 0.5 * np.log(ll / (faces[fk][6] * faces[fl][6]))
                short = np.maximum(log_sine_aim[elems] - log_sin, 0.0)
                total += float(np.sum(weight * short * short))
                s = s - 2.0 * weight * short / d
                np.add.at(grad, c[:, eb], -(2.0 * weight * short / ll)[:, None] * edge)
                np.add.at(grad, c[:, ea], (2.0 * weight * short / ll)[:, None] * edge)
                for f in (fk, fl):
                    i0, i1, i2, u_, v_, n, nn = faces[f]
                    w = (2.0 * weight * short / nn)[:, None]
                    gu, gv = w * np.cross(v_, n), w * np.cross(n, u_)
                    for col, g in ((i1, gu), (i2, gv), (i0, -(gu + gv))):
                        np.add.at(grad, c[:, col], g)
            # 1 - volumetric skew: V / V_ideal = 2.598 d^4 / |M|^3
            aa, bb, ee = (np.einsum("ij,ij->i", v, v) for v in (a, b, e))
            m = aa[:, None] * np.cross(b, e) + bb[:, None] * np.cross(e, a)
            m += ee[:, None] * np.cross(a, b)
            mm = np.einsum("ij,ij->i", m, m)
            log_ratio = LOG_RATIO_SCALE + 4.0 * np.log(d) - 1.5 * np.log(mm)
            short = np.maximum(log_ratio_aim[elems] - log_ratio, 0.0)
            total += float(np.sum(weight * short * short))
            s = s - 8.0 * weight * short / d
            w = (6.0 * weight * short / mm)[:, None]
            dot = lambda u_, v_: np.einsum("ij,ij->i", u_, v_)[:, None]  # noqa: E731
            g_a = w * (2 * dot(m, np.cross(b, e)) * a + bb[:, None] * np.cross(m, e)
                       + ee[:, None] * np.cross(b, m))  # fmt: skip
            g_b = w * (aa[:, None] * np.cross(e, m) + 2 * dot(m, np.cross(e, a)) * b
                       + ee[:, None] * np.cross(m, a))  # fmt: skip
            g_e = w * (aa[:, None] * np.cross(m, b) + bb[:, None] * np.cross(a, m)
                       + 2 * dot(m, np.cross(a, b)) * e)  # fmt: skip
            for col, g in ((1, g_a), (2, g_b), (3, g_e), (0, -(g_a + g_b + g_e))):
                np.add.at(grad, c[:, col], g)
        s = s[:, None]
        ga, gb, ge = s * np.cross(b, e), s * np.cross(e, a), s * np.cross(a, b)
        for col, g in ((1, ga), (2, gb), (3, ge), (0, -(ga + gb + ge))):
            np.add.at(grad, c[:, col], g)
    if len(quads):
        p = x[quads]
        pv, qv = p[:, 2] - p[:, 0], p[:, 3] - p[:, 1]
        n = np.cross(pv, qv)
        t = QUAD_TRIPLES
        u_, v_ = p[:, t[:, 1]] - p[:, t[:, 0]], p[:, t[:, 2]] - p[:, t[:, 0]]  # (Q, 4, 3)
        w = np.cross(u_, v_)
        d = np.einsum("qkj,qj->qk", w, n)
        if np.any(d <= 0):
            return np.inf, np.zeros_like(x)
        logs = np.log(d)
        u = quad_log_aim[:, None, None] - logs[:, :, None] + logs[:, None, :]
        u[:, np.arange(4), np.arange(4)] = 0.0
        pos = np.maximum(u, 0.0)
        total += float(np.sum(pos * pos))
        s = ((-2.0 * pos.sum(axis=2) + 2.0 * pos.sum(axis=1)) / d)[:, :, None]
        nn = np.broadcast_to(n[:, None, :], u_.shape)
        gu, gv = s * np.cross(v_, nn), s * np.cross(nn, u_)
        gp = (s * np.cross(np.broadcast_to(qv[:, None, :], w.shape), w)).sum(axis=1)
        gq = (s * np.cross(w, np.broadcast_to(pv[:, None, :], w.shape))).sum(axis=1)
        for k in range(4):
            np.add.at(grad, quads[:, t[k, 1]], gu[:, k])
            np.add.at(grad, quads[:, t[k, 2]], gv[:, k])
            np.add.at(grad, quads[:, t[k, 0]], -(gu[:, k] + gv[:, k]))
        for col, g in ((2, gp), (0, -gp), (3, gq), (1, -gq)):
            np.add.at(grad, quads[:, col], g)
    return total, grad


class _SplitPenalty:
    """The problem's penalty in fixed parts (:mod:`kneegui.meshopt.parallel`)."""

    def __init__(self, pr: _Problem) -> None:
        self.pr = pr
        self.e_cut = part_bounds(len(pr.elem_ptr) - 1)
        self.q_cut = part_bounds(len(pr.quads))
        self.f_cut = part_bounds(len(pr.faces))
        self.buffers = np.zeros((PARTS, len(pr.nodes), 3))

    def __call__(self, x: NDArray[np.float64], grad: NDArray[np.float64]) -> float:
        pr = self.pr
        totals = np.empty(PARTS)
        with PARALLEL_KERNEL_LOCK:
            penalty_in_parts(
                x,
                pr.corners,
                pr.elem_ptr,
                pr.log_aim,
                pr.log_collapse_aim,
                pr.log_sine_aim,
                pr.log_ratio_aim,
                pr.element_weight,
                pr.log_volume,
                pr.volume_band,
                pr.volume_weight,
                pr.quads,
                QUAD_TRIPLES,
                pr.quad_log_aim,
                pr.faces,
                pr.face_aims,
                pr.weights,
                self.e_cut,
                self.q_cut,
                self.f_cut,
                self.buffers,
                totals,
            )
        total = add_in_order(totals)
        if not np.isfinite(total):
            return np.inf
        np.sum(self.buffers, axis=0, out=grad)
        return total


def _penalty_of(pr: _Problem) -> Callable[[NDArray[np.float64], NDArray[np.float64]], float]:
    """``penalty(x, grad)`` of the problem: in fixed parts on threads when it is large."""
    if len(pr.elem_ptr) - 1 + len(pr.quads) >= PARALLEL_MIN_ELEMENTS:
        return _SplitPenalty(pr)
    return lambda x, grad: _penalty(pr, x, grad)


def _penalty(pr: _Problem, x: NDArray[np.float64], grad: NDArray[np.float64]) -> float:
    """Corner and face penalties at local coordinates ``x``; fills ``grad``."""
    value = corner_ratio_penalty(x, *pr.corner_args(), grad)
    if not np.isfinite(value):
        return np.inf
    return float(value) + float(face_shape_penalty(x, pr.faces, pr.face_aims, pr.weights, grad))


class _Objective:
    """Penalties + anchor + constraints over the free nodes' scaled coordinates ``v = x / h``."""

    def __init__(
        self,
        pr: _Problem,
        x: NDArray[np.float64],
        h: NDArray[np.float64],
        anchor: float,
        stiffness: float,
        start: NDArray[np.float64] | None = None,
        penalty: Callable[[NDArray[np.float64], NDArray[np.float64]], float] | None = None,
    ) -> None:
        self.pr, self.h, self.anchor, self.stiffness = pr, h, anchor, stiffness
        self.work = x.copy()
        self.start = (x[pr.free] if start is None else start).copy()
        self.grad = np.zeros_like(x)
        self.c_rows = np.zeros(0, dtype=np.int64)
        self.c_weights = np.zeros(0)
        self.c_partners = np.zeros(0, dtype=np.int64)
        self.c_partner_weights = np.zeros(0)
        self.c_normals, self.c_offsets = np.zeros((0, 3)), np.zeros(0)
        self.penalty = penalty or _penalty_of(pr)
        #: ``(log J floor, log collapse floor)``: a point where a solid falls below either is
        #: refused like an inverted corner (``None``: only the corners' signs count)
        self.floors: tuple[float, float] | None = None

    def set_constraints(
        self,
        rows: NDArray[np.int64],
        normals: NDArray[np.float64],
        offsets: NDArray[np.float64],
        weights: NDArray[np.float64] | None = None,
        partners: NDArray[np.int64] | None = None,
        partner_weights: NDArray[np.float64] | None = None,
    ) -> None:
        """Keep these free rows on the side ``normal . (w x_row + w' x_partner) >= offset``
        (``w`` 1 and no partner by default)."""
        self.c_rows = np.ascontiguousarray(rows, dtype=np.int64)
        k = len(self.c_rows)
        self.c_normals = np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3)
        self.c_offsets = np.ascontiguousarray(offsets, dtype=np.float64)
        self.c_weights = np.ascontiguousarray(np.ones(k) if weights is None else weights)
        self.c_partners = np.ascontiguousarray(
            np.full(k, -1, dtype=np.int64) if partners is None else partners, dtype=np.int64
        )
        self.c_partner_weights = np.ascontiguousarray(
            np.zeros(k) if partner_weights is None else partner_weights, dtype=np.float64
        )

    def __call__(self, v: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        pr, h = self.pr, self.h
        scatter_free(self.work, pr.free, v, h)
        if self.floors is not None and below_floor(
            self.work, pr.corners, pr.elem_ptr, *self.floors
        ):
            return np.inf, np.zeros_like(v)
        value = self.penalty(self.work, self.grad)
        if not np.isfinite(value):
            return np.inf, np.zeros_like(v)
        out = np.empty_like(v)
        value += anchor_and_constraints(
            v,
            h,
            self.start,
            pr.free,
            self.grad,
            self.anchor,
            self.c_rows,
            self.c_weights,
            self.c_partners,
            self.c_partner_weights,
            self.c_normals,
            self.c_offsets,
            self.stiffness,
            out,
        )
        return value, out


def _node_lengths(pr: _Problem, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """(F, 1) mean length of the face edges at each free node (its length scale)."""
    f = pr.faces
    nxt = np.where(np.roll(f, -1, axis=1) >= 0, np.roll(f, -1, axis=1), f[:, :1])
    valid = f >= 0
    length = np.linalg.norm(x[np.maximum(nxt, 0)] - x[np.maximum(f, 0)], axis=2)
    total = np.bincount(f[valid], length[valid], minlength=len(x))
    count = np.bincount(f[valid], minlength=len(x))
    h = total[pr.free] / np.maximum(count[pr.free], 1)
    fallback = float(h[h > 0].mean()) if np.any(h > 0) else 1.0
    return np.where(h > 0, h, fallback)[:, None]


def _no_constraints() -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0)


class _Stage:
    """The problem over one set of free nodes: its elements, the free nodes' length scales
    (from the start coordinates, or from ``lengths``' stage where it has them) and the map from
    global node ids to free rows."""

    def __init__(
        self,
        blocks: Mapping[str, ElementBlock],
        start: NDArray[np.float64],
        free: NDArray[np.int64],
        aims: QualityAims,
        options: QualityOptions,
        lengths: _Stage | None = None,
        check: Callable[[], None] = lambda: None,
    ) -> None:
        # ``check`` between the steps: each is seconds over a whole-body model's region
        self.pr = _build_problem(blocks, len(start), free, aims, options)
        check()
        self.start = start[self.pr.nodes[self.pr.free]]
        self.options = options
        global_free = self.pr.nodes[self.pr.free]
        if lengths is None:
            self.h = _node_lengths(self.pr, start[self.pr.nodes])
        else:  # the same scaling as the first stage: the rounds see one problem, narrowed
            self.h = lengths.h[lengths.row_of[global_free]]
        self.row_of = np.full(len(start), -1, dtype=np.int64)
        self.row_of[global_free] = np.arange(len(global_free))
        check()
        self.penalty = _penalty_of(self.pr)  # its buffers serve every round on this stage

    def objective(
        self,
        x: NDArray[np.float64],
        stiffness: float,
        constraints: tuple[NDArray, ...],
        coords: NDArray[np.float64] | None = None,
    ) -> _Objective:
        """The objective at local coordinates ``x`` against global ``constraints``
        (:data:`ConstraintCallback`'s arrays). A plane on the middle of two nodes of which
        only one is free here holds that one, the other's share (at the global ``coords``,
        where it stays) moved into the offset; planes without a free node are left out."""
        objective = _Objective(
            self.pr, x, self.h, self.options.anchor, stiffness, self.start, self.penalty
        )
        nodes, normals, offsets, partners = with_partners(constraints)
        rows = self.row_of[nodes]
        paired = partners >= 0
        if not paired.any():
            keep = rows >= 0
            objective.set_constraints(rows[keep], normals[keep], offsets[keep])
            return objective
        if coords is None:
            raise ValueError("planes on two nodes need the global coordinates")
        other = np.where(paired, self.row_of[np.where(paired, partners, 0)], -1)
        # the free one first
        swap = (rows < 0) & (other >= 0)
        rows, other = np.where(swap, other, rows), np.where(swap, rows, other)
        fixed_node = np.where(swap, nodes, partners)
        keep = rows >= 0
        weights = np.where(paired, 0.5, 1.0)
        partner_weights = np.where(paired & (other >= 0), 0.5, 0.0)
        offsets = offsets.copy()
        held = paired & (other < 0) & keep
        offsets[held] -= 0.5 * np.einsum("ij,ij->i", normals[held], coords[fixed_node[held]])
        objective.set_constraints(
            rows[keep],
            normals[keep],
            offsets[keep],
            weights[keep],
            np.where(partner_weights > 0, other, -1)[keep],
            partner_weights[keep],
        )
        return objective


#: How far (a fraction of it) a gate round may take the worst corner Jacobian or tet collapse
#: around the free nodes below where the gate rounds started before it is undone.
GATE_ROUND_LOSS = 0.1


def optimise_quality(
    coords: NDArray[np.float64],
    blocks: Mapping[str, ElementBlock],
    free_nodes: NDArray[np.int64],
    aims: QualityAims,
    *,
    constraints: ConstraintCallback | None = None,
    options: QualityOptions | None = None,
    progress: ProgressCallback | None = None,
    cancel: Callable[[], bool] | None = None,
) -> tuple[NDArray[np.float64], QualityOptimisationReport]:
    """Move ``free_nodes`` together so that the elements around them meet their aims.

    Parameters
    ----------
    coords : (N, 3) ndarray of float
        Node coordinates; every corner of the elements around the free nodes must be positive
        (an untangled mesh). Not modified.
    blocks : mapping of str to ElementBlock
        The model's elements (hex8, wedge6, pyramid5, tet4 solids and quad4 shells are used).
    free_nodes : (F,) ndarray of int
        Nodes that may move.
    aims : QualityAims
        Per element: the corner Jacobian to reach, the aspect, warpage and skew not to exceed
        (:func:`quality_aims`).
    constraints : callable, optional
        ``constraints(coords) -> (nodes, normals, offsets)``, re-evaluated before each round;
        each listed node is kept on the side ``normal . x >= offset`` by a quadratic penalty.
    options : QualityOptions, optional
    progress, cancel : callable, optional
        ``progress(fraction, message)``; ``cancel()`` returning True raises
        :class:`kneegui.errors.Cancelled` between rounds.

    Returns
    -------
    coords : (N, 3) ndarray
        New coordinates (only free nodes differ).
    report : QualityOptimisationReport

    Raises
    ------
    ValueError
        If an element around the free nodes is inverted (untangle it first).
    """
    opt = options or QualityOptions()
    report_progress = progress or (lambda fraction, message: None)
    should_cancel = cancel or (lambda: False)

    def check() -> None:
        # between a round's set-up steps too: each is a second or more on a whole-body
        # model's region (the 1.76M demo: 1.7-2.7 s between two questions before)
        if should_cancel():
            raise Cancelled("quality optimisation cancelled")

    t0 = time.perf_counter()
    start_all = np.array(coords, dtype=np.float64, copy=True)
    x_all = start_all.copy()
    free_nodes = sorted_unique(np.asarray(free_nodes, dtype=np.int64))
    check()
    whole = _Stage(blocks, start_all, free_nodes, aims, opt, check=check)
    pr0 = whole.pr
    if len(pr0.free) == 0:
        return x_all, QualityOptimisationReport(seconds=time.perf_counter() - t0)
    check()
    j_before = _element_jacobians(pr0, x_all[pr0.nodes])
    c_before = _tet_collapses(pr0, x_all[pr0.nodes])
    if np.any(j_before <= 0):
        raise ValueError("optimise_quality needs an untangled mesh: some elements are inverted")
    stage = whole
    boost = np.ones(sum(len(b) for t, b in blocks.items() if t in SOLID_CORNER_TYPES))

    def escalate() -> int:
        """Weigh the elements now past the gate's levels more heavily; how many there are."""
        if not aims.gate:
            return 0
        miss = _gate_misses(pr0, x_all[pr0.nodes], aims.gate, opt.gate_margin, opt.gate_reach)
        index = pr0.element_index[miss]
        boost[index] = np.minimum(boost[index] * opt.gate_boost, opt.gate_boost_limit)
        return int(np.count_nonzero(miss))

    iterations = evaluations = rounds = 0
    active_sizes: list[int] = []
    stiffness = opt.constraint_stiffness
    fresh = _no_constraints()

    def refresh_constraints() -> None:
        nonlocal fresh
        if constraints is not None:
            fresh = with_partners(constraints(x_all))

    is_free = np.zeros(len(x_all), dtype=bool)
    is_free[free_nodes] = True

    def gaps() -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """The constrained nodes this stage moves and how far each is on the right side of its
        plane. A node it holds (of an element the untangling left inverted, or beyond the
        region) stays where its plane finds it whatever the rounds do, so it neither seeds a
        round nor keeps the settling going (the 177k demo at 90 deg ran the round over the
        whole stage, 64,315 nodes and 5.4 s, for contour nodes it held past their planes)."""
        nodes, gap = constraint_gaps(fresh, x_all)
        movable = is_free[nodes]
        return nodes[movable], gap[movable]

    def narrowed(current: _Stage, settling: bool = False) -> _Stage:
        """The stage over the nodes still around a shortfall or a violated constraint (the
        rest already meets its aims and stays put), when that is markedly fewer nodes; when
        ``settling``, around the violated constraints alone (the rounds are over, only the
        constraints are left to settle)."""
        if opt.active_shrink <= 0.0:
            return current
        nodes, gap = gaps()
        seeds = nodes[gap < -opt.constraint_tolerance]
        active = shortfall_region(
            x_all,
            blocks,
            aims,
            free_nodes,
            opt.active_rings,
            seeds,
            misses=not settling,
            shape_aims=False,
            cancel=should_cancel,
        )
        if len(active) == 0 or len(active) > opt.active_shrink * len(current.pr.free):
            return current
        check()  # the region and the stage: 0.7-0.8 s each on the 1.76M demo's
        return _Stage(blocks, start_all, active, aims, opt, lengths=whole, check=check)

    def run_round(
        current: _Stage, floors: tuple[float, float] | None = None
    ) -> tuple[float, float]:
        """One L-BFGS run on ``current`` against the fresh constraints (no solid below
        ``floors``, :class:`_Objective`); the objective before and after."""
        nonlocal iterations, evaluations, rounds
        np.copyto(current.pr.element_weight, boost[current.pr.element_index])
        x = x_all[current.pr.nodes]
        objective = current.objective(x, stiffness, fresh, x_all)
        objective.floors = floors
        v0 = (x[current.pr.free] / current.h).ravel()
        check()
        before = objective(v0)[0]
        monitor = round_monitor(
            should_cancel,
            report_progress,
            # settling alone (``rounds=0``, the relaxation's settling of tissue left in a bone)
            # has no rounds to count against
            lambda done: min(1.0, (rounds + done) / max(opt.rounds, 1)),
            "optimising element quality",
            "quality optimisation cancelled",
        )
        result = minimize_lbfgs(objective, v0, opt.iterations_per_round, each_iteration=monitor)
        x_all[current.pr.nodes[current.pr.free]] = result.x.reshape(-1, 3) * current.h
        rounds += 1
        iterations += int(result.nit)
        evaluations += int(result.nfev)
        active_sizes.append(len(current.pr.free))
        return float(before), float(result.fun)

    def deepest_violation() -> float:
        return float(max(0.0, -gaps()[1].min(initial=0.0)))

    def worst_solids() -> tuple[float, float]:
        """The worst corner Jacobian and tet collapse around the free nodes now."""
        x = x_all[pr0.nodes]
        return (
            float(_element_jacobians(pr0, x).min(initial=1.0)),
            float(_tet_collapses(pr0, x).min(initial=1.0)),
        )

    previous = np.inf
    for rnd in range(opt.rounds):
        check()
        refresh_constraints()
        if rnd:
            check()
            escalate()
            check()
            stage = narrowed(stage)
        before, after = run_round(stage)
        report_progress((rnd + 1) / opt.rounds, "optimising element quality")
        # against the last round's end, not this round's start: refitted planes add to the
        # start what the round then takes off again
        if after <= 1e-12 or min(before, previous) - after <= opt.tolerance * after:
            # what is left past a plane is the settling's, on the nodes around it alone
            break
        previous = after

    def gate_rounds() -> int:
        """Rounds on the elements past the gate's levels alone, weighed up each time (at
        most ``gate_rounds``); how many ran and were kept. A round that leaves the worst
        corner Jacobian or tet collapse more than :data:`GATE_ROUND_LOSS` below where these
        rounds started is undone and ends them: weighing up the elements past the gate (and
        the fresh planes each round) can press another flatter than any of them was (the
        coarse tet demo at 120 deg: the worst collapse from 0.042 to 0.014 in one round)."""
        nonlocal stage
        lowest = [(1.0 - GATE_ROUND_LOSS) * w for w in worst_solids()]
        for count in range(opt.gate_rounds):
            if should_cancel():
                raise Cancelled("quality optimisation cancelled")
            if escalate() == 0:
                return count
            check()
            refresh_constraints()
            check()
            stage = narrowed(stage)
            kept = x_all.copy()
            run_round(stage)
            if any(w < f for w, f in zip(worst_solids(), lowest, strict=True)):
                x_all[:] = kept
                return count
        return opt.gate_rounds

    # the rounds ended on their objective, but an element may still be past the gate's levels
    # (or a last round pushed one there)
    gate_rounds()

    def floors() -> tuple[float, float]:
        """Logs of ``settling_floor`` times the worst corner Jacobian and tet collapse around
        the free nodes now."""
        worst = worst_solids()
        if opt.settling_floors is not None:
            # at the worst itself, the start would sit on its own floor: measured here as a
            # ratio and in the line search as a difference of logs, it passes or not on the
            # last bit, and a start below its floor moves nothing
            return tuple(
                float(np.log(min(f, w))) - FLOOR_ROUNDING_MARGIN
                for f, w in zip(opt.settling_floors, worst, strict=True)
            )
        return tuple(float(np.log(opt.settling_floor * w)) for w in worst)

    def settle(floor: tuple[float, float]) -> float:
        """Rounds against fresh planes, four times stiffer each, until every node is within
        the tolerance, no solid taken below ``floor``; the deepest violation left."""
        nonlocal stiffness, stage
        for count in range(opt.settling_rounds + 1):
            if should_cancel():
                raise Cancelled("quality optimisation cancelled")
            refresh_constraints()
            depth = deepest_violation()
            if depth <= opt.constraint_tolerance or count == opt.settling_rounds:
                return depth
            stiffness *= 4.0
            check()
            stage = narrowed(stage, settling=True)
            run_round(stage, floor)
        raise AssertionError("unreachable")

    if constraints is not None:
        # The planes of the last round were set before that round moved the nodes (some by
        # several millimetres): a node can end past a bone surface its planes did not describe.
        # Settle against fresh planes, stiffer each time, so the result never hinges on where
        # the round count ran out. Stiffer planes must not flatten elements for a node they
        # cannot bring back (the coarse tet demo at 120 deg: a skin node in the crease held
        # 1.3 mm past its contour plane through twelve rounds while 33 tets went flat, collapse
        # 1e-9): no settling step may take a solid below half the worst at the rounds' end.
        floor = floors()
        depth = settle(floor)
        if depth > opt.constraint_tolerance and stage is not whole:
            # A node pressed into a bone by the tissue around it cannot come out while only
            # its two element layers move (the hex leg built at 20 deg, at 60 deg: a node
            # held 0.95 mm inside the tibia through six settling rounds): once more over the
            # whole stage, then settle again; kept only if that brought the node out further.
            before = x_all.copy()
            stage = whole
            run_round(stage, floor)
            if settle(floor) >= depth:
                x_all[:] = before
        # The settling's floors keep the Jacobian and the collapse, not the tets' shape: its
        # stiffer planes can push an element past a gate level the rounds had met (the coarse
        # mixed demo at 90 deg: a tet's aspect from 13.07 to 13.54 against the initial worst
        # 13.46). Gate rounds again, at the settled stiffness, narrowed from the whole stage
        # (the settling's stage holds only the nodes around its planes), then settle what they
        # moved.
        stage = whole
        if gate_rounds():
            settle(floor)
    j_after = _element_jacobians(pr0, x_all[pr0.nodes])
    c_after = _tet_collapses(pr0, x_all[pr0.nodes])
    c_aim = pr0.collapse_aim[np.diff(pr0.elem_ptr) == 1]
    moved = x_all[pr0.nodes[pr0.free]] - start_all[pr0.nodes[pr0.free]]
    return x_all, QualityOptimisationReport(
        free_nodes=len(pr0.free),
        elements=len(j_before),
        below_aim_before=int(np.sum(j_before < pr0.jacobian_aim)),
        below_aim_after=int(np.sum(j_after < pr0.jacobian_aim)),
        worst_before=float(j_before.min(initial=np.inf)),
        worst_after=float(j_after.min(initial=np.inf)),
        collapse_below_aim_before=int(np.sum(c_before < c_aim)),
        collapse_below_aim_after=int(np.sum(c_after < c_aim)),
        collapse_worst_before=float(c_before.min()) if len(c_before) else float("nan"),
        collapse_worst_after=float(c_after.min()) if len(c_after) else float("nan"),
        rounds=rounds,
        iterations=iterations,
        evaluations=evaluations,
        max_displacement=float(np.linalg.norm(moved, axis=1).max(initial=0.0)),
        seconds=time.perf_counter() - t0,
        active_nodes=active_sizes,
    )
