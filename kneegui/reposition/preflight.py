"""The pre-flight check: what limits a pose, found before posing.

Three findings, all from the model, the setup and the bones' rigid motions (no soft-tissue
mapping is run):

*Locked elements*
    Elements whose every node is tied rigidly to a segment (femur, tibia with fibula, patella,
    or ``fixed``: the nodes :func:`~kneegui.reposition.repositioner.classify_nodes` gives a
    segment, which the repositioner moves with that segment's rigid transform and nothing else
    ever moves), with nodes on two segments that move relative to each other over the flexion
    range: a flesh element in the joint gap with nodes on both femur and tibia, a tendon element
    between patella and tibia. No stage of the export may move any of their nodes, so their shape
    at a flexion is fixed by the kinematics alone. For each, the flexion range over which it stays
    valid: its corner Jacobian (the quality gate's measure,
    :func:`kneegui.quality.kernels.corner_jacobian`) is evaluated under the bones' rigid motions
    of :meth:`Repositioner.bone_pose` at every ``step_deg`` over the supported range, from the
    initial flexion outwards; the first sampled angle on each side where it is not positive is
    refined by bisection to :data:`REFINE_STEPS` halvings of the step. Elements with free nodes
    whose bone nodes span two such segments are locked beyond the first flexion at which those
    bone nodes alone are proven to leave the free nodes no valid position
    (:func:`~kneegui.quality.feasibility.could_be_valid`).
*Coincident node pairs*
    Distinct nodes of elements at the same place (a sliding interface made of contact
    definitions, as at the demo's joint): count, and the parts on either side.
*The movable region*
    The nodes the repositioner may move (every soft-tissue node not tied to a segment), by part,
    and the elements with at least one of them.

:func:`preflight_of` runs it once per repositioner (cached); ``kneegui check``, the pose report
and the GUI show its figures, and :meth:`Preflight.split_inverted` splits a pose's inverted
elements into locked and movable ones (docs/preflight.md).
"""

from __future__ import annotations

import math
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from kneegui.errors import raise_if_cancelled
from kneegui.kinematics.posing import BonePose
from kneegui.model import Model
from kneegui.quality.feasibility import could_be_valid
from kneegui.quality.kernels import corner_jacobian
from kneegui.quality.metrics import QualityResult
from kneegui.reposition.repositioner import NodeGroups, Repositioner
from kneegui.setup.kinematic_tables import SUPPORTED_FLEXION_DEG
from kneegui.topology import CORNER_TRIPLES, sorted_unique

#: The rigid segments in label order; label ``len(RIGID_SEGMENTS)`` is a movable node.
RIGID_SEGMENTS: tuple[str, ...] = ("femur", "tibia", "patella", "fixed")
MOVABLE = len(RIGID_SEGMENTS)
#: Element types that can invert (those with corner determinants; lines and triangles cannot).
CHECKED_TYPES: tuple[str, ...] = tuple(CORNER_TRIPLES)
#: Default sampling step of the flexion range (degrees), from the initial flexion outwards: on
#: the repositioner's patellar-lift grid, whose every solved lift (about 15 ms each on the demo)
#: the poses then reuse; the crossings are refined by bisection.
SAMPLE_STEP_DEG = 2.0
#: Bisection halvings of a sampled bracket: the crossing is found to ``step / 2**REFINE_STEPS``.
REFINE_STEPS = 6
#: Two nodes closer than this fraction of the model's bounding-box diagonal are coincident.
COINCIDENT_TOLERANCE = 1e-7
#: Two segments whose transforms differ by less than this fraction of the diagonal, at every
#: corner of the bounding box and every sampled angle, do not move relative to each other.
RELATIVE_MOTION_TOLERANCE = 1e-9
#: Elements per vectorised chunk of the angle sampling (bounds the temporaries to ~10 MB).
_CHUNK = 4096

BonePoseFunction = Callable[[float], BonePose]


@dataclass(frozen=True)
class LockedElements:
    """Elements tied rigidly to segments that move relative to each other.

    Attributes
    ----------
    etype : (L,) ndarray of str
    rows : (L,) ndarray of int
        Rows of their blocks.
    ids, part_ids : (L,) ndarray of int
    segments : tuple of tuple of str
        The segments each element's nodes are tied to.
    inverts_below_deg, inverts_above_deg : (L,) ndarray of float
        The first flexion below / above the initial one at which the element inverts (within
        the resolution), NaN when it stays valid to the end of the checked range.
    inverted_at_rest : (L,) ndarray of bool
        Already inverted in the initial model (its limits are then NaN).
    free_nodes : (L,) ndarray of int
        Nodes the repositioner may move: 0 for an element tied wholly to bones; more for one
        whose tied nodes alone leave it no valid shape beyond its limits
        (:func:`~kneegui.quality.feasibility.could_be_valid`).
    """

    etype: NDArray[np.str_]
    rows: NDArray[np.int64]
    ids: NDArray[np.int64]
    part_ids: NDArray[np.int64]
    segments: tuple[tuple[str, ...], ...]
    inverts_below_deg: NDArray[np.float64]
    inverts_above_deg: NDArray[np.float64]
    inverted_at_rest: NDArray[np.bool_]
    free_nodes: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class Preflight:
    """What limits the pose of one model and setup (:func:`run_preflight`).

    Attributes
    ----------
    initial_flexion_deg : float
    flexion_range_deg : (float, float)
        The checked range (the supported one unless asked otherwise).
    sample_step_deg, resolution_deg : float
        Sampling step and the resolution of the refined limits.
    locked : LockedElements
    coincident_pairs : (P, 2) ndarray of int
        Node indices of coincident pairs (first < second).
    coincident_joins : list of dict
        The pairs grouped by the parts on either side: ``parts_a``, ``parts_b``,
        ``segment_a``, ``segment_b`` (``"movable"`` or a rigid segment), ``pairs``.
    coincident_tolerance : float
        Model units.
    movable_nodes : int
    movable_nodes_by_part, movable_elements_by_part : dict of int to int
    movable_elements : int
        Elements with at least one movable node.
    movable_rows : dict of str to (m,) ndarray of bool
        Per block, the elements with a movable node.
    node_ids : (N,) ndarray of int
        The model's node ids (to name the pairs).
    part_titles : dict of int to str
    seconds : float
    """

    initial_flexion_deg: float
    flexion_range_deg: tuple[float, float]
    sample_step_deg: float
    resolution_deg: float
    locked: LockedElements
    coincident_pairs: NDArray[np.int64]
    coincident_joins: list[dict[str, Any]]
    coincident_tolerance: float
    movable_nodes: int
    movable_nodes_by_part: dict[int, int]
    movable_elements: int
    movable_elements_by_part: dict[int, int]
    movable_rows: dict[str, NDArray[np.bool_]] = field(repr=False)
    node_ids: NDArray[np.int64] = field(repr=False)
    part_titles: dict[int, str] = field(repr=False)
    seconds: float = 0.0

    @cached_property
    def _locked_keys(self) -> dict[tuple[str, int], int]:
        """(element type, block row) -> position in :attr:`locked`."""
        return {
            (str(t), int(r)): k
            for k, (t, r) in enumerate(zip(self.locked.etype, self.locked.rows, strict=True))
        }

    # ---------------------------------------------------------------------- figures
    def valid_range_deg(self) -> tuple[float, float]:
        """The flexion range over which every locked element stays valid (the checked range
        when none inverts; the initial flexion on a side where one is inverted at rest)."""
        lo, hi = self.flexion_range_deg
        locked = self.locked
        if np.any(locked.inverted_at_rest):
            lo = hi = self.initial_flexion_deg
        below = locked.inverts_below_deg[np.isfinite(locked.inverts_below_deg)]
        above = locked.inverts_above_deg[np.isfinite(locked.inverts_above_deg)]
        if len(below):
            lo = max(lo, float(below.max()))
        if len(above):
            hi = min(hi, float(above.min()))
        return lo, hi

    def locked_rows(self) -> dict[str, NDArray[np.int64]]:
        """Block rows of the locked elements, by element type."""
        return {t: self.locked.rows[self.locked.etype == t] for t in np.unique(self.locked.etype)}

    def locked_limits(self, k: int) -> str:
        """Where one locked element inverts, as text: ``"inverts at 58.5 deg (flexing)"``,
        ``"inverts at -3.2 and 58.5 deg"``, ``"valid over the whole range"`` or
        ``"inverted at rest"``."""
        locked = self.locked
        if locked.inverted_at_rest[k]:
            return "inverted at rest"
        below, above = locked.inverts_below_deg[k], locked.inverts_above_deg[k]
        if np.isfinite(below) and np.isfinite(above):
            return f"inverts at {below:.1f} and {above:.1f} deg"
        if np.isfinite(above):
            return f"inverts at {above:.1f} deg (flexing)"
        if np.isfinite(below):
            return f"inverts at {below:.1f} deg (extending)"
        return "valid over the whole range"

    def kind_of(self, etype: str, row: int) -> str:
        """What can move one element: ``"locked between segments"``, ``"movable"`` (it has a
        node the repositioner may move) or ``"rigid with one segment"``, as
        :meth:`split_inverted` counts them."""
        if (etype, int(row)) in self._locked_keys:
            return "locked between segments"
        rows = self.movable_rows.get(etype)
        return "movable" if rows is not None and rows[int(row)] else "rigid with one segment"

    def split_inverted(self, model: Model, quality: QualityResult) -> dict[str, Any]:
        """A pose's inverted elements split into locked, movable (with a node the repositioner
        may move) and other (tied rigidly to one segment, so inverted at rest already).

        Parameters
        ----------
        model : Model
            The model checked (its blocks name the elements).
        quality : QualityResult
            A pose's quality (:func:`kneegui.quality.compute_quality`).

        Returns
        -------
        dict
            ``total``, ``locked``, ``movable``, ``other`` (counts) and ``locked_ids``,
            ``movable_ids``, ``other_ids`` (sorted element ids).
        """
        ids: dict[str, list[NDArray[np.int64]]] = {"locked": [], "movable": [], "other": []}
        for etype in quality:
            q = quality[etype]
            rows = q.rows[q.inverted]
            if not len(rows):
                continue
            block = model.blocks[etype]
            locked = np.array([(etype, int(r)) in self._locked_keys for r in rows], dtype=bool)
            movable = self.movable_rows[etype][rows]
            ids["locked"].append(block.ids[rows[locked]])
            ids["movable"].append(block.ids[rows[movable & ~locked]])
            ids["other"].append(block.ids[rows[~movable & ~locked]])
        out: dict[str, Any] = {}
        for key, chunks in ids.items():
            found = np.sort(np.concatenate(chunks)) if chunks else np.zeros(0, dtype=np.int64)
            out[key] = len(found)
            out[f"{key}_ids"] = found.tolist()
        out["total"] = out["locked"] + out["movable"] + out["other"]
        return out

    # ---------------------------------------------------------------------- output
    def to_dict(self, pair_ids: bool = True) -> dict[str, Any]:
        """Every figure, with the full lists (JSON-ready: NaN limits are None); ``pair_ids``
        False leaves out the node ids of the coincident pairs (the pose report's choice:
        tens of thousands on a large model, and the same for every pose)."""
        locked = self.locked
        lo, hi = self.valid_range_deg()

        def limit(x: float) -> float | None:
            return None if not np.isfinite(x) else float(x)

        by_part: dict[str, int] = {}
        for pid in locked.part_ids.tolist():
            by_part[str(pid)] = by_part.get(str(pid), 0) + 1
        return {
            "initial_flexion_deg": float(self.initial_flexion_deg),
            "flexion_range_deg": [float(v) for v in self.flexion_range_deg],
            "sample_step_deg": float(self.sample_step_deg),
            "resolution_deg": float(self.resolution_deg),
            "locked": {
                "count": len(locked),
                "by_part": dict(sorted(by_part.items())),
                "valid_range_deg": [float(lo), float(hi)],
                "inverted_at_rest": int(np.count_nonzero(locked.inverted_at_rest)),
                "elements": [
                    {
                        "id": int(locked.ids[k]),
                        "type": str(locked.etype[k]),
                        "part": int(locked.part_ids[k]),
                        "segments": list(locked.segments[k]),
                        "inverts_below_deg": limit(locked.inverts_below_deg[k]),
                        "inverts_above_deg": limit(locked.inverts_above_deg[k]),
                        "inverted_at_rest": bool(locked.inverted_at_rest[k]),
                        "free_nodes": int(locked.free_nodes[k]),
                    }
                    for k in range(len(locked))
                ],
            },
            "coincident_pairs": {
                "count": len(self.coincident_pairs),
                "tolerance": float(self.coincident_tolerance),
                "joins": self.coincident_joins,
                **({"node_ids": self.node_ids[self.coincident_pairs].tolist()} if pair_ids else {}),
            },
            "movable": {
                "nodes": int(self.movable_nodes),
                "nodes_by_part": {str(k): v for k, v in self.movable_nodes_by_part.items()},
                "elements": int(self.movable_elements),
                "elements_by_part": {str(k): v for k, v in self.movable_elements_by_part.items()},
            },
            "part_titles": {str(k): v for k, v in self.part_titles.items()},
            "seconds": float(self.seconds),
        }

    def coincident_by_segment(self) -> dict[tuple[str, str], tuple[int, set[int], set[int]]]:
        """The coincident pairs by the segments on either side (``"movable"`` for a node the
        repositioner may move): pair count and the parts on each side, most pairs first."""
        out: dict[tuple[str, str], tuple[int, set[int], set[int]]] = {}
        for join in self.coincident_joins:
            key = (join["segment_a"], join["segment_b"])
            n, a, b = out.get(key, (0, set(), set()))
            out[key] = (n + join["pairs"], a | set(join["parts_a"]), b | set(join["parts_b"]))
        return dict(sorted(out.items(), key=lambda kv: -kv[1][0]))

    def summary_lines(self, max_rows: int = 20) -> list[str]:
        """The human summary of ``kneegui check``: counts, the locked-element table capped at
        ``max_rows`` rows ("and N more"), the flexion limits."""

        def part(pid: int) -> str:
            title = self.part_titles.get(pid, "")
            return f"{pid} {title}".strip()

        lo, hi = self.flexion_range_deg
        locked = self.locked
        lines = [
            f"initial flexion {self.initial_flexion_deg:.1f} deg; checked {lo:g} to {hi:g} deg "
            f"every {self.sample_step_deg:g} deg (limits to {self.resolution_deg:.2g} deg) "
            f"in {self.seconds:.2f} s",
            f"movable region: {self.movable_nodes} node(s) the repositioner may move, "
            f"{self.movable_elements} element(s) with at least one of them",
        ]
        for pid, n in sorted(self.movable_nodes_by_part.items()):
            elements = self.movable_elements_by_part.get(pid, 0)
            lines.append(f"  {part(pid)}: {n} node(s), {elements} element(s)")
        lines.append(f"coincident node pairs (sliding interfaces): {len(self.coincident_pairs)}")
        for (seg_a, seg_b), (n, parts_a, parts_b) in self.coincident_by_segment().items():
            a = ", ".join(part(p) for p in sorted(parts_a))
            b = ", ".join(part(p) for p in sorted(parts_b))
            lines.append(f"  {n} pair(s) {seg_a} | {seg_b}: {a} | {b}")
        if not len(locked):
            lines.append(
                "locked elements: none (every element has a movable node or moves with one segment)"
            )
            return lines
        vlo, vhi = self.valid_range_deg()
        lines.append(
            f"locked elements: {len(locked)} (every node tied to bones that move relative to "
            f"each other, or too few free nodes to save it beyond its limit: "
            f"{int(np.count_nonzero(locked.free_nodes))}); all valid from {vlo:.1f} to "
            f"{vhi:.1f} deg"
        )
        order = np.lexsort((locked.ids, -_narrowness(self)))
        lines.append(f"  {'id':>10}  {'type':<8} {'segments':<16} {'flexion limit':<30} part")
        for k in order[:max_rows].tolist():
            lines.append(
                f"  {int(locked.ids[k]):>10}  {locked.etype[k]!s:<8} "
                f"{'+'.join(locked.segments[k]):<16} {self.locked_limits(k):<30} "
                f"{part(int(locked.part_ids[k]))}"
            )
        if len(locked) > max_rows:
            lines.append(f"  and {len(locked) - max_rows} more (--json lists them all)")
        return lines


def _narrowness(pre: Preflight) -> NDArray[np.float64]:
    """Sort key: elements that invert nearest the initial flexion first."""
    locked = pre.locked
    init = pre.initial_flexion_deg
    span = np.full(len(locked), np.inf)
    for limits in (locked.inverts_below_deg, locked.inverts_above_deg):
        d = np.abs(limits - init)
        span = np.where(np.isfinite(d), np.minimum(span, d), span)
    span[locked.inverted_at_rest] = 0.0
    return -span


# -------------------------------------------------------------------------- the check
def node_segments(n_nodes: int, groups: NodeGroups) -> NDArray[np.int8]:
    """Per node: the index in :data:`RIGID_SEGMENTS` of the segment it is tied to, or
    :data:`MOVABLE`. Nodes of no group stay where they are: ``fixed``."""
    labels = np.full(n_nodes, RIGID_SEGMENTS.index("fixed"), dtype=np.int8)
    labels[groups.soft] = MOVABLE
    for k, name in enumerate(RIGID_SEGMENTS):
        labels[groups.segment[name]] = k
    return labels


def movable_element_mask(model: Model, labels: NDArray[np.int8]) -> dict[str, NDArray[np.bool_]]:
    """Per block, which elements have at least one movable node (:func:`node_segments`)."""
    return {
        etype: (labels[block.conn] == MOVABLE).any(axis=1) for etype, block in model.blocks.items()
    }


def _segment_transforms(pose: BonePose) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(4, 3, 3) rotations and (4, 3) translations in :data:`RIGID_SEGMENTS` order."""
    rot = np.tile(np.eye(3), (len(RIGID_SEGMENTS), 1, 1))
    trans = np.zeros((len(RIGID_SEGMENTS), 3))
    for k, name in enumerate(RIGID_SEGMENTS):
        tr = pose.transforms.get(name)
        if tr is not None:
            rot[k] = tr.rotation
            trans[k] = tr.translation
    return rot, trans


def _sample_angles(initial: float, lo: float, hi: float, step: float) -> NDArray[np.float64]:
    """The angles ``initial + k step`` inside [lo, hi], with lo and hi added at the ends."""
    k_lo = math.ceil((lo - initial) / step - 1e-9)
    k_hi = math.floor((hi - initial) / step + 1e-9)
    grid = initial + step * np.arange(k_lo, k_hi + 1)
    grid = grid[(grid >= lo) & (grid <= hi)]
    if not len(grid) or grid[0] - lo > 1e-9:
        grid = np.concatenate([[lo], grid])
    if hi - grid[-1] > 1e-9:
        grid = np.concatenate([grid, [hi]])
    return grid


def _moving_pair_table(
    rot: NDArray[np.float64], trans: NDArray[np.float64], box: NDArray[np.float64], tol: float
) -> NDArray[np.bool_]:
    """For every bit mask of rigid segments (16 of them), whether two of its segments move
    relative to each other at some sampled angle: their transforms differ at a corner of the
    model's bounding box (two rigid motions that agree on four non-coplanar points agree)."""
    corners = np.array(
        [[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    )
    # (S, segments, corners, 3)
    moved = np.einsum("sgij,cj->sgci", rot, corners) + trans[:, :, None, :]
    n = len(RIGID_SEGMENTS)
    moving = np.zeros((n, n), dtype=bool)
    for a in range(n):
        for b in range(a + 1, n):
            gap = np.linalg.norm(moved[:, a] - moved[:, b], axis=-1).max()
            moving[a, b] = moving[b, a] = gap > tol
    table = np.zeros(1 << n, dtype=bool)
    for mask in range(1 << n):
        members = [g for g in range(n) if mask >> g & 1]
        table[mask] = any(moving[a, b] for a in members for b in members if a < b)
    return table


def _valid(
    points: NDArray[np.float64],
    labels: NDArray[np.int8],
    rot: NDArray[np.float64],
    trans: NDArray[np.float64],
    etype: str,
) -> NDArray[np.bool_]:
    """Whether elements whose tied nodes move rigidly can be valid: ``points`` (L, k, 3) at
    rest, ``labels`` (L, k) their segments (:data:`MOVABLE`: a free node, left where it is),
    ``rot`` (L, 4, 3, 3) and ``trans`` (L, 4, 3) one pose per element. Fully tied elements:
    a positive corner Jacobian; others: no proof that their free nodes cannot restore it
    (:func:`~kneegui.quality.feasibility.could_be_valid`). Returns (L,)."""
    idx = np.arange(len(points))[:, None]
    rot = np.concatenate([rot, np.broadcast_to(np.eye(3), (len(rot), 1, 3, 3))], axis=1)
    trans = np.concatenate([trans, np.zeros((len(trans), 1, 3))], axis=1)
    r = rot[idx, labels]  # (L, k, 3, 3)
    t = trans[idx, labels]
    posed = np.einsum("lkij,lkj->lki", r, points) + t
    free = labels == MOVABLE
    out = np.empty(len(points), dtype=bool)
    tied = ~free.any(axis=1)
    out[tied] = corner_jacobian(posed[tied], etype) > 0.0
    out[~tied] = could_be_valid(posed[~tied], free[~tied], etype)
    return out


def _limits(
    points: NDArray[np.float64],
    labels: NDArray[np.int8],
    etype: str,
    angles: NDArray[np.float64],
    i0: int,
    poses: Callable[[float], tuple[NDArray[np.float64], NDArray[np.float64]]],
    refine_steps: int,
    check: Callable[[], None] = lambda: None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """First inverting flexion below and above ``angles[i0]`` of each element (NaN: none);
    ``check()`` before each sampled angle."""
    n = len(points)
    at_rest = ~_valid(
        points,
        labels,
        np.broadcast_to(np.eye(3), (n, len(RIGID_SEGMENTS), 3, 3)),
        np.zeros((n, len(RIGID_SEGMENTS), 3)),
        etype,
    )
    valid = np.empty((len(angles), n), dtype=bool)
    transforms = [poses(float(a)) for a in angles]
    for s, (rot, trans) in enumerate(transforms):
        check()
        if s == i0:
            valid[s] = ~at_rest
            continue
        for start in range(0, n, _CHUNK):
            sl = slice(start, start + _CHUNK)
            m = len(points[sl])
            valid[s, sl] = _valid(
                points[sl],
                labels[sl],
                np.broadcast_to(rot, (m, *rot.shape)),
                np.broadcast_to(trans, (m, *trans.shape)),
                etype,
            )
    below = np.full(n, np.nan)
    above = np.full(n, np.nan)
    for direction, out in ((1, above), (-1, below)):
        order = np.arange(i0 + direction, len(angles) if direction > 0 else -1, direction)
        if not len(order):
            continue
        bad = ~valid[order]  # (steps, n), from the initial flexion outwards
        hit = bad.any(axis=0) & ~at_rest
        first = np.argmax(bad, axis=0)
        els = np.flatnonzero(hit)
        if not len(els):
            continue
        good_angle = angles[order[first[els]] - direction]
        bad_angle = angles[order[first[els]]]
        good_angle, bad_angle = _bisect(
            points[els], labels[els], etype, good_angle, bad_angle, poses, refine_steps
        )
        out[els] = bad_angle
    return below, above, at_rest


def _bisect(
    points: NDArray[np.float64],
    labels: NDArray[np.int8],
    etype: str,
    good: NDArray[np.float64],
    bad: NDArray[np.float64],
    poses: Callable[[float], tuple[NDArray[np.float64], NDArray[np.float64]]],
    steps: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Halve each element's bracket ``[good, bad]`` ``steps`` times; vectorised over the
    elements, one bone pose per distinct midpoint."""
    good, bad = good.copy(), bad.copy()
    for _ in range(steps):
        mid = 0.5 * (good + bad)
        unique, inverse = np.unique(mid, return_inverse=True)
        solved = [poses(float(a)) for a in unique]
        rot = np.stack([s[0] for s in solved])[inverse]
        trans = np.stack([s[1] for s in solved])[inverse]
        ok = _valid(points, labels, rot, trans, etype)
        good = np.where(ok, mid, good)
        bad = np.where(ok, bad, mid)
    return good, bad


def _incidence(
    model: Model, nodes_mask: NDArray[np.bool_]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Unique (node, part) pairs of elements using the flagged nodes, sorted by node."""
    parts = model.part_ids()
    keys = []
    for block in model.blocks.values():
        if not len(block):
            continue
        rows, cols = np.nonzero(nodes_mask[block.conn])
        if len(rows):
            # one int64 key per pair: a 1-D unique is many times faster than a row-wise one
            part_index = np.searchsorted(parts, block.part_ids[rows])
            keys.append(block.conn[rows, cols] * len(parts) + part_index)
    if not keys:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    found = sorted_unique(np.concatenate(keys))
    return found // len(parts), parts[found % len(parts)]


def _coincident(
    model: Model,
    labels: NDArray[np.int8],
    tolerance: float,
    check: Callable[[], None] = lambda: None,
) -> tuple[NDArray[np.int64], list[dict[str, Any]]]:
    used = np.zeros(model.n_nodes, dtype=bool)
    for block in model.blocks.values():
        used[block.conn.reshape(-1)] = True
    used_idx = np.flatnonzero(used)
    if len(used_idx) < 2:
        return np.zeros((0, 2), dtype=np.int64), []
    tree = cKDTree(model.coords[used_idx])
    check()
    pairs = tree.query_pairs(tolerance, output_type="ndarray")
    check()
    pairs = np.sort(used_idx[pairs.astype(np.int64)], axis=1) if len(pairs) else pairs
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))] if len(pairs) else pairs
    if not len(pairs):
        return pairs, []
    flagged = np.zeros(model.n_nodes, dtype=bool)
    flagged[pairs.reshape(-1)] = True
    nodes, parts = _incidence(model, flagged)
    parts_of: dict[int, tuple[int, ...]] = {}
    for node, pid in zip(nodes.tolist(), parts.tolist(), strict=True):
        parts_of[node] = (*parts_of.get(node, ()), pid)
    names = (*RIGID_SEGMENTS, "movable")
    groups: dict[tuple, int] = {}
    for a, b in pairs.tolist():
        side_a = (parts_of.get(a, ()), names[labels[a]])
        side_b = (parts_of.get(b, ()), names[labels[b]])
        key = tuple(sorted((side_a, side_b)))
        groups[key] = groups.get(key, 0) + 1
    joins = [
        {
            "parts_a": list(a[0]),
            "segment_a": a[1],
            "parts_b": list(b[0]),
            "segment_b": b[1],
            "pairs": n,
        }
        for (a, b), n in sorted(groups.items(), key=lambda kv: (-kv[1], kv[0]))
    ]
    return pairs, joins


def run_preflight(
    model: Model,
    groups: NodeGroups,
    bone_pose: BonePoseFunction,
    initial_flexion_deg: float,
    *,
    flexion_range_deg: tuple[float, float] = SUPPORTED_FLEXION_DEG,
    step_deg: float = SAMPLE_STEP_DEG,
    refine_steps: int = REFINE_STEPS,
    cancel: Callable[[], bool] | None = None,
) -> Preflight:
    """Find the locked elements, coincident node pairs and movable region of a model.

    Parameters
    ----------
    model : Model
        The model in its initial pose.
    groups : NodeGroups
        How the repositioner moves each node (:func:`classify_nodes`).
    bone_pose : callable
        ``bone_pose(flexion_deg) -> BonePose``: the bones' rigid motions as the repositioner
        poses them (:meth:`Repositioner.bone_pose`, the patellar seating included).
    initial_flexion_deg : float
        The model's measured flexion.
    flexion_range_deg : (float, float)
        Range to check (default: the supported one).
    step_deg : float
        Sampling step (degrees) from the initial flexion outwards.
    refine_steps : int
        Bisection halvings of the bracket of each crossing.
    cancel : callable, optional
        Asked between the check's steps and element types (a whole-body model: seconds in
        all); True raises :class:`~kneegui.errors.Cancelled`.

    Returns
    -------
    Preflight
    """

    def check() -> None:
        raise_if_cancelled(cancel, "pre-flight check cancelled")

    t0 = time.perf_counter()
    lo, hi = (float(v) for v in flexion_range_deg)
    initial = float(initial_flexion_deg)
    labels = node_segments(model.n_nodes, groups)
    angles = _sample_angles(initial, lo, hi, step_deg)
    i0 = int(np.argmin(np.abs(angles - initial)))
    if abs(angles[i0] - initial) > 1e-9:  # the initial flexion lies outside the range
        angles = np.sort(np.concatenate([angles, [initial]]))
        i0 = int(np.argmin(np.abs(angles - initial)))
    cache: dict[float, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}

    def poses(angle: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        if angle not in cache:
            cache[angle] = (
                _segment_transforms(bone_pose(angle))
                if abs(angle - initial) > 1e-12
                else (
                    np.tile(np.eye(3), (len(RIGID_SEGMENTS), 1, 1)),
                    np.zeros((len(RIGID_SEGMENTS), 3)),
                )
            )
        return cache[angle]

    box = model.bounding_box()
    diagonal = float(np.linalg.norm(box[1] - box[0])) or 1.0
    bits = (np.uint8(1) << np.arange(MOVABLE + 1, dtype=np.uint8)).astype(np.uint8)
    several = np.array([bin(m).count("1") >= 2 for m in range(1 << MOVABLE)])
    candidates: dict[str, tuple[NDArray[np.int64], NDArray[np.uint8]]] = {}
    for etype in CHECKED_TYPES:
        block = model.blocks.get(etype)
        if block is None or not len(block):
            continue
        check()
        # the segments of each element's tied nodes; its free nodes, if any, may still be
        # unable to save it (:func:`~kneegui.quality.feasibility.could_be_valid`)
        mask = np.bitwise_or.reduce(bits[labels[block.conn]], axis=1) & ~bits[MOVABLE]
        tied_rows = np.flatnonzero(several[mask])
        if len(tied_rows):
            candidates[etype] = (tied_rows, mask[tied_rows])
    if candidates:  # the bones' motions are sampled only when some element spans two segments
        sampled = [poses(float(a)) for a in angles]
        rot = np.stack([s[0] for s in sampled])
        trans = np.stack([s[1] for s in sampled])
        moving_table = _moving_pair_table(rot, trans, box, RELATIVE_MOTION_TOLERANCE * diagonal)

    keys = ("etype", "rows", "below", "above", "rest", "mask", "free")
    chunks: dict[str, list] = {k: [] for k in keys}
    for etype, (tied_rows, tied_mask) in candidates.items():
        check()
        keep = moving_table[tied_mask]
        locked_rows, mask = tied_rows[keep], tied_mask[keep]
        if not len(locked_rows):
            continue
        conn = model.blocks[etype].conn[locked_rows]
        below, above, rest = _limits(
            model.coords[conn], labels[conn], etype, angles, i0, poses, refine_steps, check
        )
        free = (labels[conn] == MOVABLE).sum(axis=1)
        # an element with a free node is locked only where it is proven unable to stay valid
        keep = (free == 0) | rest | np.isfinite(below) | np.isfinite(above)
        locked_rows, mask, below, above, rest, free = (
            a[keep] for a in (locked_rows, mask, below, above, rest, free)
        )
        chunks["etype"].append(np.full(len(locked_rows), etype))
        chunks["rows"].append(locked_rows)
        chunks["below"].append(below)
        chunks["above"].append(above)
        chunks["rest"].append(rest)
        chunks["mask"].append(mask)
        chunks["free"].append(free)

    def cat(key: str, dtype) -> NDArray:
        return np.concatenate(chunks[key]) if chunks[key] else np.zeros(0, dtype=dtype)

    etypes = cat("etype", "<U8")
    rows = cat("rows", np.int64)
    ids = np.array(
        [model.blocks[t].ids[r] for t, r in zip(etypes.tolist(), rows.tolist(), strict=True)],
        dtype=np.int64,
    )
    pids = np.array(
        [model.blocks[t].part_ids[r] for t, r in zip(etypes.tolist(), rows.tolist(), strict=True)],
        dtype=np.int64,
    )
    masks = cat("mask", np.uint8)
    segments = tuple(
        tuple(name for g, name in enumerate(RIGID_SEGMENTS) if int(m) >> g & 1)
        for m in masks.tolist()
    )
    locked = LockedElements(
        etype=etypes,
        rows=rows,
        ids=ids,
        part_ids=pids,
        segments=segments,
        inverts_below_deg=cat("below", np.float64),
        inverts_above_deg=cat("above", np.float64),
        inverted_at_rest=cat("rest", bool),
        free_nodes=cat("free", np.int64),
    )

    tolerance = COINCIDENT_TOLERANCE * diagonal
    check()
    pairs, joins = _coincident(model, labels, tolerance, check)

    movable_nodes = labels == MOVABLE
    check()
    nodes, parts = _incidence(model, movable_nodes)
    check()
    part_list, counts = np.unique(parts, return_counts=True)
    nodes_by_part = dict(zip(part_list.tolist(), counts.tolist(), strict=True))
    elements_by_part: dict[int, int] = {}
    n_movable_elements = 0
    movable_rows = movable_element_mask(model, labels)
    for etype, has in movable_rows.items():
        block = model.blocks[etype]
        n_movable_elements += int(np.count_nonzero(has))
        p, c = np.unique(block.part_ids[has], return_counts=True)
        for pid, n in zip(p.tolist(), c.tolist(), strict=True):
            elements_by_part[pid] = elements_by_part.get(pid, 0) + n
    titles = {int(pid): part.title for pid, part in model.parts.items()}
    return Preflight(
        initial_flexion_deg=initial,
        flexion_range_deg=(lo, hi),
        sample_step_deg=float(step_deg),
        resolution_deg=float(step_deg) / 2**refine_steps,
        locked=locked,
        coincident_pairs=pairs,
        coincident_joins=joins,
        coincident_tolerance=float(tolerance),
        movable_nodes=int(np.count_nonzero(movable_nodes[sorted_unique(nodes)]))
        if len(nodes)
        else 0,
        movable_nodes_by_part=nodes_by_part,
        movable_elements=n_movable_elements,
        movable_elements_by_part=dict(sorted(elements_by_part.items())),
        movable_rows=movable_rows,
        node_ids=model.node_ids,
        part_titles=titles,
        seconds=time.perf_counter() - t0,
    )


_CACHE: weakref.WeakKeyDictionary[Repositioner, Preflight] = weakref.WeakKeyDictionary()


def preflight_of(repositioner: Repositioner, cancel: Callable[[], bool] | None = None) -> Preflight:
    """The pre-flight check of a repositioner's model and setup, run once and kept while the
    repositioner lives (the pose report of every angle and the GUI share it); ``cancel`` as
    for :func:`run_preflight` (a cancelled check is not kept)."""
    found = _CACHE.get(repositioner)
    if found is None:
        found = run_preflight(
            repositioner.model,
            repositioner.groups,
            repositioner.bone_pose,
            repositioner.initial_flexion,
            cancel=cancel,
        )
        _CACHE[repositioner] = found
    return found
