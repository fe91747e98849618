"""Local mesh repair of the demo leg: move free flesh nodes until every element meets the bounds.

The structured grid places every node by formula. At coarse resolutions a few cells (flesh at
the corners of the O-grid, in front of the joint line) come out just below the quality bounds
(``resources/quality_thresholds.csv``: corner Jacobian, aspect ratio, warpage). This module fixes
them without touching the anatomy: only nodes that are free (all their elements are flesh: not on
a bone, ligament, meniscus, the skin or a cut; the caller decides, see
:func:`kneegui.demo.grid.free_flesh_nodes`) move, and only those around failing elements. Cells
that are not elements but must keep their shape (the joint cavity) can be given as *guards*: no
move turns one inside out.

The method is a deterministic node-by-node pattern search (Gauss-Seidel order). Each node tries a
few trial positions (steps along x, y, z and the diagonals, and towards the centroid of its edge
neighbours) and keeps the one that most lowers the *worst score* of its incident elements::

    score = max((J_t - J) / J_t, (A - A_t) / A_t, (W - W_t) / W_t)

(``J`` corner Jacobian, ``A`` aspect ratio, ``W`` warpage in degrees; the targets ``_t`` are the
fail limits with a small margin, :data:`TARGET_MARGIN`). An element meets the targets when its score
is <= 0. Since a node only moves when the worst score of its own elements goes down, the worst
score of the repaired patch never goes up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kneegui.quality.kernels import HEX_FACES, corner_jacobian
from kneegui.topology import ELEMENT_EDGES

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

_CHUNK = 8192  # elements per vectorised evaluation

#: Relative margin the repair aims at beyond the fail limits (J >= 1.08 * 0.3, A <= 10 / 1.03,
#: W <= 30 / 1.03), so that the written deck (rounded coordinates) still passes.
TARGET_MARGIN = (1.08, 1.03, 1.03)

#: Unit trial directions: the 6 axis directions and the 8 cube diagonals.
_DIRECTIONS = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    + [[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)],
    dtype=np.float64,
)
_DIRECTIONS /= np.linalg.norm(_DIRECTIONS, axis=1)[:, None]
#: Nodes whose incident elements all score below this are left alone in a sweep.
ACTIVE_SCORE = -0.03
#: The repair stops when the patch's worst score improved by less than 1e-4 in this many sweeps.
STALL_SWEEPS = 8


@dataclass(frozen=True)
class QualityTargets:
    """Limits an element must meet: corner Jacobian >= ``jacobian``, aspect <= ``aspect``,
    warpage <= ``warpage`` (degrees)."""

    jacobian: float
    aspect: float
    warpage: float

    @classmethod
    def from_thresholds(cls, margin: tuple[float, float, float] = TARGET_MARGIN) -> QualityTargets:
        """The default fail limits (``resources/quality_thresholds.csv``, role ``*``), tightened
        by ``margin`` (factors on the Jacobian, aspect and warpage limits)."""
        from kneegui.quality.thresholds import default_thresholds

        limits = default_thresholds().for_role(None)
        return cls(
            jacobian=limits["jacobian"].fail * margin[0],
            aspect=limits["aspect"].fail / margin[1],
            warpage=limits["warpage"].fail / margin[2],
        )


def element_scores(
    coords: FloatArray, hexes: IntArray, quads: IntArray, targets: QualityTargets
) -> tuple[FloatArray, FloatArray]:
    """Score (see the module docstring; <= 0 meets the targets) of every hex and quad.

    Parameters
    ----------
    coords : (N, 3) ndarray of float
        Node positions (mm).
    hexes : (m, 8) ndarray of int
        Hexahedra (node indices, LS-DYNA order).
    quads : (q, 4) ndarray of int
        Quad shells (node indices).
    targets : QualityTargets

    Returns
    -------
    (m,) ndarray, (q,) ndarray
    """
    return (
        _scores(_hex_metrics, coords, hexes, targets),
        _scores(_quad_metrics, coords, quads, targets),
    )


def _scores(measure, coords, conn, targets: QualityTargets) -> FloatArray:
    out = np.empty(len(conn))
    for start in range(0, len(conn), _CHUNK):
        block = conn[start : start + _CHUNK]
        with np.errstate(invalid="ignore", divide="ignore"):
            out[start : start + len(block)] = _score_of(measure(coords[block]), targets)
    return out


def _score_of(q: dict, targets: QualityTargets) -> FloatArray:
    score = np.maximum.reduce(
        [
            (targets.jacobian - q["jacobian_corner"]) / targets.jacobian,
            (q["aspect"] - targets.aspect) / targets.aspect,
            (q["warpage"] - targets.warpage) / targets.warpage,
        ]
    )
    return np.where(np.isfinite(score), score, np.inf)


def repair_quality(
    coords: FloatArray,
    hexes: IntArray,
    quads: IntArray,
    movable: BoolArray,
    targets: QualityTargets,
    guards: IntArray | None = None,
    grow: int = 2,
    max_sweeps: int = 60,
) -> FloatArray:
    """Move free nodes around the elements that miss the targets until they meet them.

    Parameters
    ----------
    coords : (N, 3) ndarray of float
        Node positions (mm); not modified.
    hexes : (m, 8) ndarray of int
        Hexahedra (node indices, LS-DYNA order).
    quads : (q, 4) ndarray of int
        Quad shells (node indices); they are measured too, so shells on moved nodes stay good.
    movable : (N,) ndarray of bool
        Nodes that may move (free flesh nodes).
    targets : QualityTargets
        What every element should meet.
    guards : (g, 8) ndarray of int, optional
        Hexahedral cells that are not elements (the joint cavity) but must not turn inside out:
        a move that would invert one of them is not made, so free nodes on the cavity's wall
        cannot cross it.
    grow : int
        The patch is the movable nodes of the failing elements plus ``grow`` layers of movable
        neighbours (node-to-node through shared elements).
    max_sweeps : int
        Gauss-Seidel sweeps over the patch at most.

    Returns
    -------
    (N, 3) ndarray of float
        New positions; equal to ``coords`` if every element already meets the targets or no
        failing element has a movable node. Whether the targets are met in the end is for the
        caller to check (:func:`element_scores`).
    """
    out = np.array(coords, dtype=np.float64, copy=True)
    hex_score, quad_score = element_scores(out, hexes, quads, targets)
    bad_nodes = np.zeros(len(out), dtype=bool)
    bad_nodes[hexes[hex_score > 0].ravel()] = True
    bad_nodes[quads[quad_score > 0].ravel()] = True
    patch = bad_nodes & movable
    if not patch.any():
        return out
    for _ in range(grow):
        touching = np.any(patch[hexes], axis=1)
        grown = np.zeros_like(patch)
        grown[hexes[touching].ravel()] = True
        patch |= grown & movable
    nodes = np.flatnonzero(patch)
    hex_of, quad_of = _incidence(nodes, hexes, len(out)), _incidence(nodes, quads, len(out))
    guards = np.zeros((0, 8), dtype=np.int64) if guards is None else guards
    guard_of = _incidence(nodes, guards, len(out))
    neighbours = _edge_neighbours(nodes, hexes, len(out))
    patch_hexes = np.unique(np.concatenate(hex_of))
    patch_quads = np.unique(np.concatenate(quad_of)) if len(quads) else np.zeros(0, np.int64)
    # initial step: a fifth of the shortest incident edge
    step = np.array([0.2 * _shortest_edge(out, hexes[hex_of[a]]) for a in range(len(nodes))])
    history: list[float] = []
    for _ in range(max_sweeps):
        hex_score, quad_score = element_scores(out, hexes[patch_hexes], quads[patch_quads], targets)
        worst = max(hex_score.max(initial=-np.inf), quad_score.max(initial=-np.inf))
        history.append(worst)
        if worst <= 0.0 or (
            len(history) > STALL_SWEEPS and history[-STALL_SWEEPS - 1] - worst < 1e-4
        ):
            break
        score = np.full(len(hexes), -np.inf)
        score[patch_hexes] = hex_score
        qscore = np.full(len(quads), -np.inf)
        qscore[patch_quads] = quad_score
        for a, node in enumerate(nodes):
            local = max(
                score[hex_of[a]].max(initial=-np.inf), qscore[quad_of[a]].max(initial=-np.inf)
            )
            if local < ACTIVE_SCORE:
                continue  # every element around this node is comfortably good
            h, q = hexes[hex_of[a]], quads[quad_of[a]]
            current = out[node]
            centroid = out[neighbours[a]].mean(axis=0)
            trials = np.vstack(
                [current, current + step[a] * _DIRECTIONS, 0.5 * (current + centroid), centroid]
            )
            trial_worst = _trial_scores(out, node, trials, h, q, targets)
            trial_worst[_inverts(out, node, trials, guards[guard_of[a]])] = np.inf
            best = int(np.argmin(trial_worst))
            if best > 0 and trial_worst[best] < trial_worst[0] - 1e-9:
                out[node] = trials[best]
            else:
                step[a] *= 0.5
    return out


def _trial_scores(coords, node, trials, hexes, quads, targets) -> FloatArray:
    """Worst score of the elements around ``node`` for each trial position ``(t, 3)``."""
    worst = np.full(len(trials), -np.inf)
    for measure, conn in ((_hex_metrics, hexes), (_quad_metrics, quads)):
        if len(conn) == 0:
            continue
        xyz = np.broadcast_to(coords[conn], (len(trials), *conn.shape, 3)).copy()  # (t, e, k, 3)
        xyz[:, conn == node] = trials[:, None, :]
        with np.errstate(invalid="ignore", divide="ignore"):
            score = _score_of(measure(xyz), targets)
        worst = np.maximum(worst, score.max(axis=1))
    return worst


def _inverts(coords, node, trials, guards) -> BoolArray:
    """Trials that turn a guard cell inside out (corner Jacobian <= 0) that was not before."""
    if len(guards) == 0:
        return np.zeros(len(trials), dtype=bool)
    xyz = np.broadcast_to(coords[guards], (len(trials), *guards.shape, 3)).copy()
    xyz[:, guards == node] = trials[:, None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        jac = _hex_metrics(xyz)["jacobian_corner"]  # (t, g)
    was_valid = jac[0] > 0
    return np.any(was_valid[None, :] & ~(jac > 0), axis=1)


#: Hex faces as the quality kernels' parametric cycles (unsigned metrics).
_FACES = np.array(HEX_FACES)


def _face_metrics(p: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Aspect (longest / shortest edge) and warpage (degrees) of quads ``(..., 4, 3)``."""
    edges = np.linalg.norm(np.roll(p, -1, axis=-2) - p, axis=-1)
    aspect = edges.max(axis=-1) / edges.min(axis=-1)
    p0, p1, p2, p3 = (p[..., i, :] for i in range(4))
    warp = np.maximum(
        _angle(np.cross(p1 - p0, p2 - p0), np.cross(p2 - p0, p3 - p0)),
        _angle(np.cross(p1 - p0, p3 - p0), np.cross(p2 - p1, p3 - p1)),
    )
    return aspect, warp


def _angle(a: FloatArray, b: FloatArray) -> FloatArray:
    return np.degrees(
        np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("...i,...i", a, b))
    )


def _hex_metrics(p: FloatArray) -> dict[str, FloatArray]:
    """Corner Jacobian, aspect and warpage of hexes ``(..., 8, 3)``."""
    aspect, warp = _face_metrics(p[..., _FACES, :])
    return {
        "jacobian_corner": corner_jacobian(p, "hex8"),
        "aspect": aspect.max(axis=-1),
        "warpage": warp.max(axis=-1),
    }


def _quad_metrics(p: FloatArray) -> dict[str, FloatArray]:
    """Corner Jacobian, aspect and warpage of quads ``(..., 4, 3)``."""
    aspect, warp = _face_metrics(p)
    return {"jacobian_corner": corner_jacobian(p, "quad4"), "aspect": aspect, "warpage": warp}


def _incidence(nodes: IntArray, conn: IntArray, n: int) -> list[IntArray]:
    """Rows of ``conn`` that use each of ``nodes``."""
    position = np.full(n, -1, dtype=np.int64)
    position[nodes] = np.arange(len(nodes))
    rows, cols = np.nonzero(position[conn] >= 0)
    owner = position[conn[rows, cols]]
    order = np.lexsort((rows, owner))
    rows, owner = rows[order], owner[order]
    bounds = np.searchsorted(owner, np.arange(len(nodes) + 1))
    return [np.unique(rows[bounds[i] : bounds[i + 1]]) for i in range(len(nodes))]


_HEX_EDGES = ELEMENT_EDGES["hex8"]


def _edge_neighbours(nodes: IntArray, hexes: IntArray, n: int) -> list[IntArray]:
    """Nodes sharing a hex edge with each of ``nodes``."""
    pairs = np.concatenate([hexes[:, [a, b]] for a, b in _HEX_EDGES])
    pairs = np.concatenate([pairs, pairs[:, ::-1]])
    position = np.full(n, -1, dtype=np.int64)
    position[nodes] = np.arange(len(nodes))
    sel = position[pairs[:, 0]] >= 0
    owner, other = position[pairs[sel, 0]], pairs[sel, 1]
    order = np.lexsort((other, owner))
    owner, other = owner[order], other[order]
    bounds = np.searchsorted(owner, np.arange(len(nodes) + 1))
    return [np.unique(other[bounds[i] : bounds[i + 1]]) for i in range(len(nodes))]


def _shortest_edge(coords: FloatArray, hexes: IntArray) -> float:
    a = np.concatenate([hexes[:, i] for i, _ in _HEX_EDGES])
    b = np.concatenate([hexes[:, j] for _, j in _HEX_EDGES])
    return float(np.linalg.norm(coords[a] - coords[b], axis=1).min())
