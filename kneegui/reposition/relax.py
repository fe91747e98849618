"""Elastic relaxation: untangle and even out the soft tissue of a pose, with bone contact.

The rigid blend moves every soft-tissue node by a mix of the bones' motions. That is cheap and
smooth, but it cannot make the tissue behind a deeply flexed knee bulge, nor keep it out of a
condyle that is not a circle about the F-E axis, so some elements fold. This stage starts from the
blended pose and minimises a distortion energy over the soft-tissue nodes near the joint, with the
bones (and the tissue attached to them) held where the kinematics put them:

- every solid element is cut into corner tetrahedra (the three edges through each corner, the same
  corners as the corner Jacobian of QUALITY.md); for each, ``J`` maps the corner's initial edges to
  its current edges, and the energy is the foldover-free distortion of Garanzha et al. (2021),
  *Foldover-free maps in 50 lines of code*, ACM Trans. Graph. 40(4)::

      f(J) = (1 - theta) |J|^2 / chi(det J)^(2/3) + theta (det J^2 + 1) / chi(det J)
      chi(D) = (D + sqrt(eps^2 + D^2)) / 2

  every corner weighted the same (or by its initial volume). The first term penalises change of
  shape, the second change of volume; both are smallest at the initial shape (``J`` a rotation).
  As ``eps`` -> 0 the energy becomes a barrier that no corner can cross into inversion; the
  schedule of ``eps`` from the paper untangles corners that the blend inverted. Minimised with
  L-BFGS (:func:`minimize_lbfgs`) on Jacobi-scaled variables.
- shells lying on solid faces (skin, capsule, tendon) add tetrahedra to a virtual apex inside the
  solid and a barrier on their own corner determinants, so they cannot fold or turn into darts.
- bone contact: a soft-tissue node near a bone is kept on the outside of the bone's tangent plane at
  its closest surface point (a penalty whose force stops growing 1 mm deep), with the planes
  recomputed from the bone surfaces between the solver's rounds, so tissue slides along a condyle
  instead of entering it.
- polish: the energy evens out the distortion on average; the worst elements it leaves are then
  lifted by the quality-guarded smoother
  (:func:`kneegui.meshopt.smooth_mesh`) on the same free nodes, with a guard that lets no node
  go deeper into a bone than it is or than the contact allows.

Element count, node ids and connectivity never change; only the free nodes move.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from kneegui.errors import Cancelled, GeometryError
from kneegui.geometry.transforms import RigidTransform
from kneegui.meshopt.lbfgs import minimize_lbfgs
from kneegui.meshopt.quality_optimiser import (
    QualityAims,
    QualityOptimisationReport,
    QualityOptions,
    optimise_quality,
    shortfall_region,
)
from kneegui.meshopt.smoother import SmoothingReport, corner_determinants, smooth_mesh
from kneegui.model import CORNER_TRIPLES, SOLID_TYPES, ElementBlock
from kneegui.reposition.contact import BoneSurfaceDistance
from kneegui.reposition.skin_contours import ContourOrder, SkinContours

ProgressCallback = Callable[[float, str], None]

#: Where the virtual apex of a shell's tetrahedra sits, from the shell's centroid (0) to the
#: centroid of the solid it covers (1).
APEX_DEPTH = 0.3

try:  # the compiled kernel (Numba); the NumPy reference is used where Numba is missing
    from kneegui.meshopt.foldover_kernel import foldover_free_energy as _kernel
except ImportError:  # pragma: no cover - numba is a dependency
    _kernel = None


def corner_tetrahedra(
    blocks: Mapping[str, ElementBlock], masks: Mapping[str, NDArray[np.bool_]] | None = None
) -> NDArray[np.int64]:
    """(C, 4) node indices of the corner tetrahedra of the solid elements.

    Parameters
    ----------
    blocks : mapping of element type to ElementBlock
    masks : mapping of element type to (m,) bool, optional
        Which elements of each block to take (default: all).
    """
    out = [np.zeros((0, 4), dtype=np.int64)]
    for etype in SOLID_TYPES:
        table = CORNER_TRIPLES[etype]  # the corners of the corner Jacobian
        block = blocks.get(etype)
        if block is None or len(block.conn) == 0:
            continue
        conn = block.conn if masks is None else block.conn[masks[etype]]
        out.append(conn[:, np.array(table)].reshape(-1, 4).astype(np.int64))
    return np.concatenate(out)


def shell_face_tetrahedra(
    blocks: Mapping[str, ElementBlock],
    shell_masks: Mapping[str, NDArray[np.bool_]],
    solid_masks: Mapping[str, NDArray[np.bool_]],
    n_nodes: int,
) -> tuple[NDArray[np.int64], sp.csr_matrix]:
    """Tetrahedra that keep shells lying on solid faces from folding.

    For every selected shell that is a face of a selected solid, each triangle of the shell
    (both diagonals of a quad) and an apex inside the solid make a tetrahedron; the apex lies
    :data:`APEX_DEPTH` of the way from the shell's centroid to the solid's. The apexes are
    *virtual nodes* numbered from ``n_nodes`` on; the returned matrix gives their positions as
    linear combinations of the real nodes.

    Returns
    -------
    tets : (T, 4) ndarray of int
        Node indices; index ``n_nodes + k`` is virtual node ``k``.
    virtual : (V, n_nodes) sparse matrix
        ``virtual @ coords`` are the virtual nodes' coordinates.
    """
    from kneegui.model import SOLID_FACES

    # every face of the selected solids as a sorted, -1 padded 4-tuple, with its owner
    keys, owners, owner_types = [], [], []
    solid_types = [e for e in SOLID_FACES if e in blocks and e in solid_masks]
    for t_index, etype in enumerate(solid_types):
        block = blocks[etype]
        rows = np.flatnonzero(solid_masks[etype])
        for face in SOLID_FACES[etype]:
            k = np.full((len(rows), 4), -1, dtype=np.int64)
            k[:, : len(face)] = np.sort(block.conn[np.ix_(rows, list(face))], axis=1)
            keys.append(np.sort(k, axis=1))
            owners.append(rows)
            owner_types.append(np.full(len(rows), t_index))
    shell_keys, shell_conn = [], []
    for etype, mask in shell_masks.items():
        block = blocks.get(etype)
        if block is None:
            continue
        conn = block.conn[mask]
        k = np.full((len(conn), 4), -1, dtype=np.int64)
        k[:, : conn.shape[1]] = conn
        shell_keys.append(np.sort(k, axis=1))
        padded = np.full((len(conn), 4), -1, dtype=np.int64)
        padded[:, : conn.shape[1]] = conn
        shell_conn.append(padded)
    empty = (np.zeros((0, 4), dtype=np.int64), sp.csr_matrix((0, n_nodes)))
    if not keys or not shell_keys:
        return empty
    face_keys = np.concatenate(keys)
    face_owner = np.concatenate(owners)
    face_type = np.concatenate(owner_types)
    s_keys = np.concatenate(shell_keys)
    s_conn = np.concatenate(shell_conn)
    if len(s_keys) == 0:  # shell roles present but without shells (e.g. no skin part)
        return empty
    # match shells to solid faces by their sorted node tuples
    both = np.concatenate([face_keys, s_keys])
    _, inverse = np.unique(both, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    face_id, shell_id = inverse[: len(face_keys)], inverse[len(face_keys) :]
    order = np.argsort(face_id, kind="stable")
    sorted_ids = face_id[order]
    lo = np.searchsorted(sorted_ids, shell_id, side="left")
    hi = np.searchsorted(sorted_ids, shell_id, side="right")
    counts = hi - lo
    shell_rows = np.repeat(np.arange(len(s_keys)), counts)
    face_rows = order[np.concatenate([np.arange(a, b) for a, b in zip(lo, hi, strict=True)])]
    if len(face_rows) == 0:
        return empty
    # one virtual apex per (shell, owning solid): a point inside the solid close to the shell,
    # so that the tetrahedra also see a shell that twists or turns into a dart
    conn = s_conn[shell_rows]
    quad = conn[:, 3] >= 0
    n_pairs = len(face_rows)
    v_rows, v_cols, v_vals = [], [], []
    for t_index, etype in enumerate(solid_types):
        mine = np.flatnonzero(face_type[face_rows] == t_index)
        if len(mine) == 0:
            continue
        solid = blocks[etype].conn[face_owner[face_rows[mine]]]
        solid = solid[:, :4] if etype == "tet10" else solid
        v_rows.append(np.repeat(mine, solid.shape[1]))
        v_cols.append(solid.ravel())
        v_vals.append(np.full(solid.size, APEX_DEPTH / solid.shape[1]))
    for is_quad, width in ((True, 4), (False, 3)):
        mine = np.flatnonzero(quad == is_quad)
        v_rows.append(np.repeat(mine, width))
        v_cols.append(conn[mine, :width].ravel())
        v_vals.append(np.full(len(mine) * width, (1.0 - APEX_DEPTH) / width))
    virtual = sp.csr_matrix(
        (np.concatenate(v_vals), (np.concatenate(v_rows), np.concatenate(v_cols))),
        shape=(n_pairs, n_nodes),
    )
    apex = n_nodes + np.arange(n_pairs)
    tets = [np.column_stack([conn[~quad, 0], conn[~quad, 1], conn[~quad, 2], apex[~quad]])]
    q, qa = conn[quad], apex[quad]
    for a, b, c in ((0, 1, 2), (0, 2, 3), (1, 2, 3), (1, 3, 0)):
        tets.append(np.column_stack([q[:, a], q[:, b], q[:, c], qa]))
    return np.concatenate(tets).astype(np.int64), virtual


def _edges(x: NDArray[np.float64], tets: NDArray[np.int64]) -> NDArray[np.float64]:
    """(C, 3, 3) edge matrices: column k is x[tets[:, k+1]] - x[tets[:, 0]]."""
    base = x[tets[:, 0]]
    return np.stack([x[tets[:, k]] - base for k in (1, 2, 3)], axis=2)


def _chi(det: NDArray[np.float64], eps: float) -> tuple[NDArray, NDArray]:
    """Garanzha's regularised determinant ``(D + sqrt(eps^2 + D^2)) / 2`` and its derivative,
    in a form that does not cancel to zero for very negative ``D``."""
    root = np.sqrt(eps * eps + det * det)
    with np.errstate(divide="ignore", invalid="ignore"):
        chi = np.where(det >= 0, 0.5 * (det + root), 0.5 * eps * eps / (root - det))
    return np.maximum(chi, 1e-300), 0.5 * (1.0 + det / root)


@dataclass(frozen=True)
class RelaxOptions:
    """Parameters of the elastic relaxation.

    Attributes
    ----------
    volume_weight : float
        ``theta``: weight of the volume term against the shape term (0..1).
    uniform_weights : bool
        Every corner counts the same (the mesh quality view: a small element matters as much as
        a large one); otherwise corners are weighted by their initial volume (the elastic view).
    shell_weight : float
        Weight of a quad shell corner's barrier against a solid corner's energy.
    seed_volume_ratio, seed_shape : float
        A corner whose volume ratio ``det J`` is below ``seed_volume_ratio`` (or above its
        inverse) or whose shape distortion is above ``seed_shape`` seeds the relaxed region.
    rings : int
        How many mesh edges the region grows from its seeds.
    max_rounds : int
        Rounds of (update eps and contact planes, then L-BFGS).
    iterations_per_round : int
        L-BFGS iterations per round.
    eps_decrease : float
        Smallest relative decrease of ``eps`` per round (Garanzha's ``sigma`` floor, 0.1 in the
        paper; larger untangles in fewer rounds).
    tolerance : float
        Relative energy decrease below which the rounds stop (once nothing is inverted).
    contact_stiffness, untangling_contact_stiffness : float
        Penalty stiffness of the bone contact, relative to the elastic stiffness of a node:
        final, and while elements are still inverted. A stiff contact during untangling
        crushes the tissue pinched between two bones; once nothing is inverted the barrier
        keeps every element valid and the stiffness is raised 4x per round to the final one.
    contact_force_depth : float
        Depth (model units) beyond which the contact force stops growing.
    contact_band : float
        Nodes closer to a bone than this (model units) get a contact plane.
    contact_clearance : float
        Distance from the bone surface the contact holds nodes at (model units).
    optimise_quality : bool
        After the energy has untangled the region, bring its elements within their quality
        aims with :func:`kneegui.meshopt.quality_optimiser.optimise_quality` (all four
        metrics, all nodes together, the bone contact as constraints; needs the element
        blocks and aims, see :class:`ElasticRelaxation`).
    quality : QualityOptions
        Parameters of that optimisation.
    volume_change : float or None
        In that optimisation, every soft solid element aims to keep its volume within
        ``1 + volume_change`` times its initial volume, either way (None: no limit). Without
        it the optimiser may shrink an element whose proportions stay good: the demo's PCL
        elements at 90 deg ended at 0.1 % of their volume, and the largest growth was 725 %.
        Tighter aims trade volume against the bone contact: on the default demo, 0.1 brings
        the 95th percentile of the soft solids' change at 90 deg from 46 to 12 % at the same
        worst Jacobian, but at 120 deg it pushed a node 0.5 mm into a bone and crushed an
        element to 0.3 % of its volume, the compressed flesh having nowhere else to go; with
        a 3x stiffer contact no node entered a bone but an element grew by 202 % (0.5: 119 %)
        and the worst Jacobian fell to 0.136 (0.5: 0.151). Measured, not kept (see
        docs/repositioning.md, known limits).
    contour_margin : float or None
        In that optimisation, every skin contour keeps at least this far (model units) beyond
        the plane of its neighbour nearer the joint, so that no contour crosses another (needs
        the contours, see :class:`ElasticRelaxation`); None lets them cross, which gives the
        crease behind a deeply flexed knee more room.
    polish : bool
        Then lift the worst elements with the quality-guarded smoother (needs the element
        blocks, see :class:`ElasticRelaxation`). Off by default since the quality
        optimisation: on the default demo it changed no worst Jacobian from 0 to 90 deg, added
        0.007 at 120 deg, warped 89 more faces beyond 30 deg there, and moved skin nodes
        across the contour planes.
    restarts : int
        How many times the rounds start again when corners are still inverted after
        ``max_rounds``: the nodes of those corners go back to their posed positions and the
        barrier is softened to ``restart_eps`` (the schedule can drive ``eps`` to its floor
        while nodes pressed onto one point keep a corner at zero volume). The last restart
        also frees those nodes from the bone contact.
    restart_eps : float
        ``eps`` a restart begins with.
    slide_skin : bool or None
        Skin nodes move only in the tangent plane of the pose being relaxed (the sliding nodes
        given to :class:`ElasticRelaxation`; ``None`` slides them there too).
        :class:`kneegui.reposition.Repositioner` resolves ``None`` by method: it slides
        the skin for the ``blend`` method, whose skin is the mapped surface, and frees it for
        ``paper`` and ``hybrid``, whose contour-placed skin can fold and must be free to
        unfold (the default demo at 60 deg with ``paper``: 80 elements left inverted with a
        sliding skin, none with a free one).
    """

    volume_weight: float = 0.5
    uniform_weights: bool = True
    shell_weight: float = 1.0
    seed_volume_ratio: float = 0.3
    seed_shape: float = 2.0
    rings: int = 2
    max_rounds: int = 20
    iterations_per_round: int = 150
    eps_decrease: float = 0.65
    tolerance: float = 1e-4
    contact_stiffness: float = 50.0
    untangling_contact_stiffness: float = 3.0
    contact_band: float = 3.0
    contact_force_depth: float = 1.0
    contact_clearance: float = 0.2
    optimise_quality: bool = True
    quality: QualityOptions = field(
        default_factory=lambda: QualityOptions(
            rounds=15, iterations_per_round=150, constraint_stiffness=100.0, volume_weight=3.0
        )
    )
    volume_change: float | None = 0.5
    contour_margin: float | None = 0.5
    polish: bool = False
    restarts: int = 2
    restart_eps: float = 0.05
    slide_skin: bool | None = None


@dataclass
class RelaxReport:
    """What the relaxation did."""

    free_nodes: int = 0
    corners: int = 0
    rounds: int = 0
    restarts: int = 0
    contact_released: int = 0
    iterations: int = 0
    evaluations: int = 0
    min_det_before: float = float("nan")
    min_det_after: float = float("nan")
    inverted_corners_before: int = 0
    inverted_corners_after: int = 0
    contact_nodes: int = 0
    deepest_penetration: float = 0.0
    seconds: float = 0.0
    history: list[dict[str, float]] = field(default_factory=list)
    quality: QualityOptimisationReport | None = None  # what the quality optimisation did
    polish: SmoothingReport | None = None  # what the polish did (the smoother's own report)

    def to_dict(self) -> dict[str, object]:
        """JSON-ready summary."""
        out = dict(self.__dict__)
        out.pop("history")
        out["quality"] = None if self.quality is None else self.quality.to_dict()
        out["polish"] = None if self.polish is None else self.polish.to_dict()
        return out


def _cross3(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise cross products of (M, 3) arrays (np.cross costs more on short arrays)."""
    return _cross_t(a.T, b.T).T


def _quad_energy(
    x: NDArray[np.float64],
    quads: NDArray[np.int64],
    rest: NDArray[np.float64],
    weight: float,
    eps: float,
) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """Barrier on the quads' corner determinants relative to rest: ``(r^2 + 1) / chi(r)``.

    Returns the energy, the gradient per quad node (Q, 4, 3) and the ratios r (4Q,).
    """
    p = [x[quads[:, i]] for i in range(4)]
    u, v = p[2] - p[0], p[3] - p[1]
    n = _cross3(u, v)
    grad = np.zeros((len(quads), 4, 3))
    total = 0.0
    ratios = []
    for i in range(4):
        a = p[(i + 1) % 4] - p[i]
        b = p[(i + 3) % 4] - p[i]
        w = _cross3(a, b)
        r = np.einsum("ij,ij->i", w, n) / rest[:, i]
        chi, dchi = _chi(r, eps)
        total += weight * float(np.sum((r * r + 1.0) / chi))
        dr = (weight * (2.0 * r / chi - (r * r + 1.0) * dchi / (chi * chi)) / rest[:, i])[:, None]
        ga = _cross3(b, n) * dr  # d/da of (a x b) . n
        gb = _cross3(n, a) * dr
        gu = _cross3(v, w) * dr  # d/du of (u x v) . w
        gv = _cross3(w, u) * dr
        grad[:, (i + 1) % 4] += ga
        grad[:, (i + 3) % 4] += gb
        grad[:, i] -= ga + gb
        grad[:, 2] += gu
        grad[:, 0] -= gu
        grad[:, 3] += gv
        grad[:, 1] -= gv
        ratios.append(r)
    return total, grad, np.concatenate(ratios)


class _Subproblem:
    """The corner tetrahedra touching a set of free nodes, in local numbering: the real nodes
    they use (and the virtual nodes need) first, then the virtual nodes."""

    def __init__(self, relax: ElasticRelaxation, rows: NDArray[np.int64], free: NDArray[np.int64]):
        n = relax.n_nodes
        tets = relax.tets[rows]
        is_virtual = tets >= n
        used_virtual = np.unique(tets[is_virtual]) - n
        v_sub = relax.virtual[used_virtual]
        quads = relax.quads[relax.is_free_quad(free)]
        self.nodes = np.union1d(np.union1d(np.unique(tets[~is_virtual]), v_sub.indices), quads)
        m = len(self.nodes)
        self.quads = np.searchsorted(self.nodes, quads).reshape(-1, 4)
        self.quad_rest = corner_determinants(relax.rest[quads.reshape(-1, 4)], "quad4")
        self.quad_weight = relax.options.shell_weight
        q_flat = self.quads.ravel()
        self.quad_scatter = sp.csr_matrix(
            (np.ones(len(q_flat)), (q_flat, np.arange(len(q_flat)))), shape=(m, len(q_flat))
        )
        self.virtual = v_sub[:, self.nodes].tocsr() if len(used_virtual) else None
        self.virtual_t = None if self.virtual is None else self.virtual.T.tocsr()
        local = np.empty_like(tets)
        local[~is_virtual] = np.searchsorted(self.nodes, tets[~is_virtual])
        local[is_virtual] = m + np.searchsorted(used_virtual, tets[is_virtual] - n)
        self.tets = local
        self.m = m
        g = relax.inv_rest[rows]  # J = E @ G
        self.g_rows = np.ascontiguousarray(g)  # (C, 3, 3) for the compiled kernel
        self.g = np.ascontiguousarray(np.transpose(g, (1, 2, 0)))  # (3 edges, 3, C)
        self.weight = relax.weight[rows]
        self.theta = relax.options.volume_weight
        self.free = np.searchsorted(self.nodes, free)  # local indices of the free nodes
        # gradient scatter: d_edges (3 edges x C, 3) -> nodes, as one sparse product
        c, size = len(self.tets), m + len(used_virtual)
        cols = np.arange(3 * c)
        ends = self.tets[:, 1:].T.ravel()  # column j * C + corner
        plus = sp.csr_matrix((np.ones(3 * c), (ends, cols)), shape=(size, 3 * c))
        base = np.tile(self.tets[:, 0], 3)
        minus = sp.csr_matrix((np.ones(3 * c), (base, cols)), shape=(size, 3 * c))
        self.scatter = (plus - minus).tocsr()
        # diagonal of the shape term's Hessian at rest, per node: a preconditioner
        end_sq = np.einsum("jkc,jkc->jc", self.g, self.g)
        base_sq = np.sum(self.g.sum(axis=0) ** 2, axis=0)
        diag = np.zeros(size)
        np.add.at(diag, ends, np.tile(self.weight, 3) * end_sq.ravel())
        np.add.at(diag, self.tets[:, 0], self.weight * base_sq)
        if self.virtual_t is not None:
            diag = diag[:m] + self.virtual_t.multiply(self.virtual_t) @ diag[m:]
        self.diagonal = diag[:m]

    def augment(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Local real coordinates (m, 3) followed by the virtual nodes' coordinates."""
        return x if self.virtual is None else np.vstack([x, self.virtual @ x])

    def energy(self, x: NDArray[np.float64], eps: float) -> tuple[float, NDArray, NDArray]:
        """Energy, gradient (m, 3) and per-corner det J at local coordinates ``x`` (m, 3)."""
        if _kernel is None:
            return self.energy_numpy(x, eps)
        xa = np.ascontiguousarray(self.augment(x))
        grad = np.empty_like(xa)
        det = np.empty(len(self.tets))
        energy = _kernel(xa, self.tets, self.g_rows, self.weight, self.theta, eps, grad, det)
        if self.virtual_t is not None:
            grad = grad[: self.m] + self.virtual_t @ grad[self.m :]
        return self._add_shells(x, eps, float(energy), grad, det)

    def _add_shells(self, x, eps, energy, grad, det):
        if len(self.quads) == 0:
            return energy, grad, det
        e_q, g_q, r_q = _quad_energy(x, self.quads, self.quad_rest, self.quad_weight, eps)
        grad = grad + self.quad_scatter @ g_q.reshape(-1, 3)
        return energy + e_q, grad, np.concatenate([det, r_q])

    def energy_numpy(self, x: NDArray[np.float64], eps: float) -> tuple[float, NDArray, NDArray]:
        """:meth:`energy` in NumPy (the reference the compiled kernel is tested against).

        Laid out as (component, corner) arrays so that every step is an elementwise operation
        on long vectors.
        """
        theta, g, t = self.theta, self.g, self.tets
        xt = self.augment(x).T
        base = xt[:, t[:, 0]]
        edges = np.stack([xt[:, t[:, k]] - base for k in (1, 2, 3)])  # (3 edges, 3 coords, C)
        jac = sum(edges[j][:, None, :] * g[j][None, :, :] for j in range(3))  # (3, 3, C)
        c0, c1, c2 = jac[:, 0], jac[:, 1], jac[:, 2]
        cof = np.stack([_cross_t(c1, c2), _cross_t(c2, c0), _cross_t(c0, c1)], axis=1)
        det = np.sum(c0 * cof[:, 0], axis=0)
        chi, dchi = _chi(det, eps)
        frob = np.sum(jac * jac, axis=(0, 1))
        chi23 = chi ** (2.0 / 3.0)
        shape = frob / chi23
        volume = (det * det + 1.0) / chi
        w = self.weight
        energy = float(np.einsum("i,i->", w, (1.0 - theta) * shape + theta * volume))
        d_cof = w * (
            (1.0 - theta) * (-2.0 / 3.0) * shape * dchi / chi
            + theta * (2.0 * det / chi - volume * dchi / chi)
        )
        d_jac = (w * (1.0 - theta) * 2.0 / chi23) * jac + d_cof * cof
        # dE[j, i] = sum_k dJ[i, k] G[j, k]
        d_edges = np.einsum("ikc,jkc->jci", d_jac, g).reshape(-1, 3)
        grad = self.scatter @ d_edges
        if self.virtual_t is not None:
            grad = grad[: self.m] + self.virtual_t @ grad[self.m :]
        return self._add_shells(x, eps, energy, grad, det)


def _cross_t(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cross products of (3, C) column-vector arrays."""
    return np.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


class ElasticRelaxation:
    """Precomputed relaxation of a model's soft tissue (see the module docstring).

    Only the tissue around what the pose degraded is relaxed: corners that are inverted, flat
    or distorted (and nodes that entered a bone) seed a region that grows ``rings`` mesh edges;
    its free nodes move, everything else stays as posed.

    Parameters
    ----------
    rest_coords : (N, 3) ndarray
        Initial coordinates (the reference shapes).
    tets : (C, 4) ndarray of int
        Corner tetrahedra of the soft-tissue solids (:func:`corner_tetrahedra`).
    free : (F,) ndarray of int
        Nodes the relaxation may move; every other node stays where the pose put it.
    bones : mapping of segment name to BoneSurfaceDistance or (T, 3, 3) ndarray, optional
        Rest-pose outer surface of each rigid segment (or its triangles), for contact.
    contact_nodes : (K,) ndarray of int, optional
        Free nodes that are kept out of the bones (default: every free node).
    options : RelaxOptions, optional
    virtual : (V, N) sparse matrix, optional
        Virtual nodes ``N + k`` used by ``tets`` (:func:`shell_face_tetrahedra`).
    attached : (A,) ndarray of int, optional
        Nodes that move with a bone; tissue next to them may go as deep into a bone as they do.
    quads : (Q, 4) ndarray of int, optional
        Quad shells whose corner determinants are kept positive (skin, capsule, tendon).
    sliding : (L,) ndarray of int, optional
        Free nodes on the outer surface (the skin) that only slide in their surface's tangent
        plane of the pose being relaxed (``options.slide_skin``): the mapping's smooth crease
        behind a flexed knee keeps its shape instead of being pulled into a fold.
    region_radius : float
        Besides ``options.rings`` mesh edges, the relaxed region takes every free node within
        this distance (model units) of a seed: a fold needs room in millimetres, not in
        elements, to unfold.
    blocks : mapping of str to ElementBlock, optional
        The model's element blocks, for the polish (``options.polish``); without them there is
        none.
    goals : mapping of str to (m,) ndarray, optional
        Per element of ``blocks``, the corner Jacobian the polish aims at
        (:func:`kneegui.meshopt.smoothing_pipeline.smoothing_goals`; default 0.6 everywhere).
    aims : QualityAims, optional
        Per element of ``blocks``, the quality the optimisation aims at
        (:func:`kneegui.meshopt.quality_optimiser.quality_aims`); without them there is no
        quality optimisation.
    skin_contours : SkinContours, optional
        The skin's contours, kept in order by the quality optimisation
        (``options.contour_margin``).
    """

    def __init__(
        self,
        rest_coords: NDArray[np.float64],
        tets: NDArray[np.int64],
        free: NDArray[np.int64],
        bones: Mapping[str, BoneSurfaceDistance | NDArray[np.float64]] | None = None,
        contact_nodes: NDArray[np.int64] | None = None,
        options: RelaxOptions | None = None,
        virtual: sp.csr_matrix | None = None,
        attached: NDArray[np.int64] | None = None,
        quads: NDArray[np.int64] | None = None,
        region_radius: float = 0.0,
        sliding: NDArray[np.int64] | None = None,
        blocks: Mapping[str, ElementBlock] | None = None,
        goals: Mapping[str, NDArray[np.float64]] | None = None,
        aims: QualityAims | None = None,
        skin_contours: SkinContours | None = None,
    ) -> None:
        self.options = options or RelaxOptions()
        self.blocks = blocks
        self.goals = goals
        self.aims = aims
        self.contour_order = (
            ContourOrder(skin_contours, rest_coords, self.options.contour_margin)
            if skin_contours is not None and self.options.contour_margin is not None
            else None
        )
        n = len(rest_coords)
        self.rest = np.asarray(rest_coords, dtype=np.float64)
        self.region_radius = float(region_radius)
        self.virtual = sp.csr_matrix((0, n)) if virtual is None else sp.csr_matrix(virtual)
        n_aug = n + self.virtual.shape[0]
        free = np.unique(np.asarray(free, dtype=np.int64))
        is_free = np.zeros(n_aug, dtype=bool)
        is_free[free] = True
        tets = np.asarray(tets, dtype=np.int64)
        tets = tets[is_free[tets].any(axis=1)]
        e0 = _edges(self.augment(rest_coords), tets)
        det0 = np.linalg.det(e0)
        usable = np.abs(det0) > 1e-12 * np.maximum(np.abs(e0).max(axis=(1, 2)) ** 3, 1e-300)
        self.tets = tets[usable]
        self.inv_rest = np.linalg.inv(e0[usable])  # G: J = E @ G
        self.weight = (
            np.ones(int(usable.sum()))
            if self.options.uniform_weights
            else np.abs(det0[usable]) / 6.0
        )
        # free nodes that are not in any tetrahedron have no energy: leave them alone
        in_tet = np.zeros(n_aug, dtype=bool)
        in_tet[self.tets.ravel()] = True
        self.free = free[in_tet[free]]
        self.is_free = np.zeros(n, dtype=bool)
        self.is_free[self.free] = True
        self.n_nodes = n
        # node adjacency along the corner edges (real nodes), for growing the relaxed region
        a = np.repeat(self.tets[:, 0], 3)
        b = self.tets[:, 1:].ravel()
        real = b < n
        adj = sp.csr_matrix((np.ones(int(real.sum())), (a[real], b[real])), shape=(n, n))
        self._adjacency = ((adj + adj.T) > 0).astype(np.int8).tocsr()
        # corner rows by (real) node, to pick the corners touching a set of nodes
        flat = self.tets.ravel()
        owner = np.repeat(np.arange(len(self.tets)), 4)
        real = flat < n
        self._node_rows = sp.csr_matrix(
            (np.ones(int(real.sum())), (flat[real], owner[real])), shape=(n, len(self.tets))
        )
        self.bones = {
            name: tri if isinstance(tri, BoneSurfaceDistance) else BoneSurfaceDistance(tri)
            for name, tri in (bones or {}).items()
            if isinstance(tri, BoneSurfaceDistance) or len(tri)
        }
        if contact_nodes is None:
            contact_nodes = self.free
        contact_nodes = np.asarray(contact_nodes, dtype=np.int64)
        keep = self.is_free[contact_nodes]
        self.contact_nodes = contact_nodes[keep]
        # each contact node keeps at least its rest clearance from each bone, up to
        # contact_clearance (tissue lying on a bone at rest may stay on it)
        self._rest_floor: dict[str, NDArray[np.float64]] = {}
        for name, surface in self.bones.items():
            depth = surface.query(self.rest[self.contact_nodes])[0]
            self._rest_floor[name] = np.clip(depth, 0.0, self.options.contact_clearance)
        quads = np.zeros((0, 4), dtype=np.int64) if quads is None else np.asarray(quads)
        if len(quads):
            rest_det = corner_determinants(self.rest[quads], "quad4")
            quads = quads[(rest_det > 0).all(axis=1) & self.is_free[quads].any(axis=1)]
        self.quads = quads.astype(np.int64)
        sliding = np.zeros(0, dtype=np.int64) if sliding is None else np.asarray(sliding)
        self.sliding = np.intersect1d(sliding.astype(np.int64), self.free)
        # tissue next to an attachment may go as deep into another bone as the attachment
        # itself (a patella pressed into the trochlea): holding it out would tear the elements
        # between the attachment and the contact plane
        self._attached_nb: sp.csr_matrix | None = None
        if attached is not None and len(attached):
            attached = np.unique(np.asarray(attached, dtype=np.int64))
            nb = self._adjacency[self.contact_nodes][:, attached].tocsr()
            used = np.unique(nb.indices)
            self._attached_nodes = attached[used]
            self._attached_nb = sp.csr_matrix(
                (np.ones(nb.nnz), np.searchsorted(used, nb.indices), nb.indptr),
                shape=(len(self.contact_nodes), len(used)),
            )

    def is_free_quad(self, free: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Which of :attr:`quads` have a node among ``free``."""
        mask = np.zeros(self.n_nodes, dtype=bool)
        mask[free] = True
        return mask[self.quads].any(axis=1)

    def augment(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Coordinates of the real nodes followed by those of the virtual nodes."""
        return np.vstack([x, self.virtual @ x]) if self.virtual.shape[0] else x

    # ------------------------------------------------------------------ region
    def corner_distortion(self, x: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
        """Per corner: det J and the shape distortion ``|J|^2 / (3 det J^(2/3))`` (1 = similar)."""
        jac = _edges(self.augment(x), self.tets) @ self.inv_rest
        det = np.linalg.det(jac)
        frob = np.einsum("cij,cij->c", jac, jac)
        with np.errstate(invalid="ignore", divide="ignore"):
            shape = np.where(det > 0, frob / (3.0 * np.cbrt(det) ** 2), np.inf)
        return det, shape

    def degraded_region(
        self, x: NDArray[np.float64], extra_seeds: NDArray[np.int64] | None = None
    ) -> NDArray[np.int64]:
        """Free nodes within ``rings`` edges or ``region_radius`` of a degraded corner (or of
        ``extra_seeds``)."""
        opt = self.options
        det, shape = self.corner_distortion(x)
        bad = (det < opt.seed_volume_ratio) | (det > 1.0 / opt.seed_volume_ratio)
        bad |= shape > opt.seed_shape
        seed = np.zeros(self.n_nodes, dtype=bool)
        nodes = self.tets[bad].ravel()
        seed[nodes[nodes < self.n_nodes]] = True
        if extra_seeds is not None:
            seed[extra_seeds] = True
        region = seed.astype(np.int8)
        for _ in range(opt.rings):
            region = region + self._adjacency @ region
            region = (region > 0).astype(np.int8)
        region = region > 0
        if self.region_radius > 0 and seed.any():
            from scipy.spatial import cKDTree

            dist, _ = cKDTree(x[seed]).query(x[self.free], distance_upper_bound=self.region_radius)
            region[self.free[np.isfinite(dist)]] = True
        return np.flatnonzero(region & self.is_free)

    # ------------------------------------------------------------------ contact
    def _contact_planes(
        self,
        x: NDArray[np.float64],
        nodes: NDArray[np.int64],
        transforms: Mapping[str, RigidTransform],
    ) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Constraints ``n . x_node >= offset`` for the given nodes near a bone, and each
        node's smallest margin ``depth - allowed depth`` over the bones (< 0: too deep)."""
        clearance, band = self.options.contact_clearance, self.options.contact_band
        out_nodes, normals, offsets = [], [], []
        nearest = np.full(len(nodes), np.inf)
        p = x[nodes]
        nb = None
        if self._attached_nb is not None:
            nb = self._attached_nb[np.searchsorted(self.contact_nodes, nodes)].tocsr()
        for name, surface in self.bones.items():
            tr = transforms.get(name)
            if tr is None:
                continue
            local = tr.inverse().apply(p)
            depth, point, normal, _ = surface.query(local)
            slot = np.searchsorted(self.contact_nodes, nodes)
            floor = self._rest_floor[name][slot].copy()
            if nb is not None and nb.nnz:
                att = tr.inverse().apply(x[self._attached_nodes])
                att_depth = np.minimum(surface.query(att)[0], clearance)
                rows = np.repeat(np.arange(len(nodes)), np.diff(nb.indptr))
                np.minimum.at(floor, rows, att_depth[nb.indices])
            nearest = np.minimum(nearest, depth - floor)
            near = depth < band
            if not near.any():
                continue
            n_world = tr.apply_vector(normal[near])
            p_world = tr.apply(point[near])
            out_nodes.append(np.flatnonzero(near))
            normals.append(n_world)
            offsets.append(np.einsum("ij,ij->i", n_world, p_world) + floor[near])
        if not out_nodes:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0), nearest
        return (
            np.concatenate(out_nodes),
            np.concatenate(normals),
            np.concatenate(offsets),
            nearest,
        )

    # ------------------------------------------------------------------ solve
    def relax(
        self,
        coords: NDArray[np.float64],
        transforms: Mapping[str, RigidTransform] | None = None,
        progress: ProgressCallback | None = None,
        cancel: Callable[[], bool] | None = None,
    ) -> tuple[NDArray[np.float64], RelaxReport]:
        """Relax a pose.

        Parameters
        ----------
        coords : (N, 3) ndarray
            The pose to start from (not modified).
        transforms : mapping of segment name to RigidTransform, optional
            The bones' motions in this pose (needed for contact).
        progress, cancel : callable, optional

        Returns
        -------
        coords : (N, 3) ndarray
            Relaxed coordinates (a new array).
        report : RelaxReport
        """
        opt = self.options
        report_progress = progress or (lambda fraction, message: None)
        should_cancel = cancel or (lambda: False)
        t0 = time.perf_counter()
        x = np.array(coords, dtype=np.float64, copy=True)
        report = RelaxReport()
        if len(self.free) == 0 or len(self.tets) == 0:
            return x, report
        use_contact = bool(self.bones) and transforms is not None
        penetrating = None
        if use_contact:
            _, _, _, depth = self._contact_planes(x, self.contact_nodes, transforms)
            report.deepest_penetration = float(max(0.0, -depth.min()))
            penetrating = self.contact_nodes[depth < -1e-3]
        free = self.degraded_region(x, penetrating)
        report.free_nodes = len(free)
        optimise_next = opt.optimise_quality and self.blocks is not None and self.aims is not None
        d_min = np.inf  # nothing tangled
        if len(free):
            x, d_min = self._minimise_energy(
                x,
                free,
                transforms,
                use_contact,
                optimise_next,
                report,
                report_progress,
                should_cancel,
            )
        if optimise_next and d_min > 0:
            x = self._optimise_quality(
                x,
                transforms if use_contact else None,
                report,
                lambda fraction, message: report_progress(0.8 + 0.1 * fraction, message),
                cancel,
            )
        if opt.polish and self.blocks is not None and len(free):
            x = self._polish(
                x,
                free,
                transforms if use_contact else None,
                report,
                lambda fraction, message: report_progress(0.9 + 0.1 * fraction, message),
                cancel,
            )
        report.seconds = time.perf_counter() - t0
        return x, report

    def _minimise_energy(
        self,
        x: NDArray[np.float64],
        free: NDArray[np.int64],
        transforms: Mapping[str, RigidTransform] | None,
        use_contact: bool,
        optimise_next: bool,
        report: RelaxReport,
        report_progress: ProgressCallback,
        should_cancel: Callable[[], bool],
    ) -> tuple[NDArray[np.float64], float]:
        """The energy's rounds (and restarts) over the region ``free``, ending as soon as
        nothing is inverted when the quality optimisation follows (``optimise_next``); fills
        ``report``. Returns the new coordinates and the smallest corner det J."""
        opt = self.options
        rows = np.unique(self._node_rows[free].indices)
        sub = _Subproblem(self, rows, free)
        xl = x[sub.nodes]
        xl_start = xl.copy()
        _, _, det = sub.energy(xl, 1e-3)
        report.corners = len(sub.tets)
        report.min_det_before = float(det.min())
        report.inverted_corners_before = int(np.sum(det <= 0))
        d_min = report.min_det_before
        eps = float(np.sqrt(1e-12 + 0.04 * min(d_min, 0.0) ** 2)) if d_min <= 0 else 1e-9
        eps = max(eps, 1e-9)
        contact_global = self.contact_nodes[np.isin(self.contact_nodes, free)]
        # variables scaled by the diagonal of the Hessian at rest (Jacobi preconditioning):
        # elements of very different sizes otherwise make L-BFGS crawl
        scale = 1.0 / np.sqrt(np.maximum(sub.diagonal[sub.free], 1e-300))[:, None]
        stiffness = opt.untangling_contact_stiffness
        c_local = np.zeros(0, dtype=np.int64)
        c_normals, c_offsets, c_k = np.zeros((0, 3)), np.zeros(0), np.zeros(0)
        sub_free = sub.free
        slide_rows, slide_normals = self._sliding_rows(x, sub)
        released = np.zeros(0, dtype=np.int64)

        def objective(
            eps: float,
            c_local: NDArray,
            c_normals: NDArray,
            c_offsets: NDArray,
            c_k: NDArray,
        ) -> Callable[[NDArray[np.float64]], tuple[float, NDArray]]:
            """The energy over the scaled free variables, with these contact planes."""
            work = xl.copy()

            def fun(flat: NDArray[np.float64]) -> tuple[float, NDArray]:
                work[sub_free] = flat.reshape(-1, 3) * scale
                energy, grad, _ = sub.energy(work, eps)
                if len(c_local):
                    gap = np.einsum("ij,ij->i", c_normals, work[c_local]) - c_offsets
                    # quadratic up to contact_force_depth deep, linear beyond (Huber): a node
                    # pinched between two bones is pushed with a bounded force, so the
                    # barrier, not the contact, has the last word
                    short = np.minimum(gap, 0.0)
                    limit = opt.contact_force_depth
                    clipped = np.maximum(short, -limit)
                    energy += float(
                        np.sum(c_k * (0.5 * clipped * clipped + limit * (clipped - short)))
                    )
                    np.add.at(grad, c_local, (c_k * clipped)[:, None] * c_normals)
                g_free = grad[sub_free]
                if len(slide_rows):  # tangential only: L-BFGS then stays in those planes
                    along = np.einsum("ij,ij->i", g_free[slide_rows], slide_normals)
                    g_free[slide_rows] -= along[:, None] * slide_normals
                return energy, (g_free * scale).ravel()

            return fun

        for attempt in range(1 + opt.restarts):
            if attempt:
                if d_min > 0:
                    break
                # the schedule drove eps to its floor with corners still inverted (typically
                # nodes pressed onto one point while the barrier was soft): put those nodes
                # back where the pose had them and start again from a soft barrier
                stuck = self._stuck_nodes(sub, det)
                xl[stuck] = xl_start[stuck]
                if attempt == opt.restarts:
                    # last chance: where bone contact presses the tissue flat (tissue pinched
                    # between femur and tibia at deep flexion) a valid element matters more
                    # than a node slightly inside a bone, which the pose report counts
                    released = np.union1d(released, sub.nodes[stuck])
                    contact_global = np.setdiff1d(contact_global, released)
                    report.contact_released = len(released)
                eps = opt.restart_eps
                stiffness = opt.untangling_contact_stiffness
                report.restarts += 1
            rnd_untangled = False
            for rnd in range(opt.max_rounds):
                if should_cancel():
                    raise Cancelled("relaxation cancelled")
                if use_contact and len(contact_global):
                    x[sub.nodes] = xl
                    which, c_normals, c_offsets, _ = self._contact_planes(
                        x, contact_global, transforms
                    )
                    c_global = contact_global[which]
                    c_local = np.searchsorted(sub.nodes, c_global)
                    c_k = stiffness * sub.diagonal[c_local]
                    report.contact_nodes = len(np.unique(c_global))
                fun = objective(eps, c_local, c_normals, c_offsets, c_k)
                start = (xl[sub_free] / scale).ravel()
                before = fun(start)[0]
                result = minimize_lbfgs(fun, start, opt.iterations_per_round)
                xl[sub_free] = result.x.reshape(-1, 3) * scale
                _, _, det = sub.energy(xl, eps)
                report.rounds += 1
                report.iterations += int(result.nit)
                report.evaluations += int(result.nfev)
                d_min = float(det.min())
                after = float(result.fun)
                report.history.append({"eps": eps, "energy": after, "min_det": d_min})
                report_progress(0.8 * min(1.0, (rnd + 1) / opt.max_rounds), "relaxing soft tissue")
                decrease = (before - after) / max(abs(before), 1e-300)
                # Garanzha et al. 2021: shrink eps as fast as the energy decrease allows
                sigma = max(1.0 - after / before, opt.eps_decrease) if before > 0 else 1.0
                chi_min = 0.5 * (d_min + np.sqrt(eps * eps + d_min * d_min))
                mu = (1.0 - sigma) * chi_min
                eps = max(float(2.0 * np.sqrt(mu * (mu - d_min))) if d_min < mu else 0.0, 1e-9)
                stiff_enough = stiffness >= opt.contact_stiffness or not len(c_local)
                if d_min > 0 and stiff_enough and (decrease < opt.tolerance or rnd_untangled):
                    break
                if d_min > 0 and optimise_next:
                    break  # untangled: the quality optimisation takes it from here
                rnd_untangled = d_min > 0 and eps <= 1e-9
                if d_min > 0:
                    stiffness = min(4.0 * stiffness, opt.contact_stiffness)
        x[sub.nodes] = xl
        report.min_det_after = d_min
        report.inverted_corners_after = int(np.sum(det <= 0))
        return x, d_min

    @staticmethod
    def _stuck_nodes(sub: _Subproblem, det: NDArray[np.float64]) -> NDArray[np.int64]:
        """Local indices of the free nodes of the inverted corners and quads.

        Nodes pressed onto one point while the barrier was soft make ``det J`` and its gradient
        zero, and the shape term holds them there; the pose had them apart.
        """
        c = len(sub.tets)
        corner_nodes = sub.tets[det[:c] <= 0].ravel()  # may name virtual nodes (>= m)
        quad_nodes = sub.quads[np.flatnonzero(det[c:] <= 0) % max(len(sub.quads), 1)].ravel()
        bad = np.concatenate([corner_nodes, quad_nodes])
        bad = np.unique(bad[bad < sub.m])
        is_free = np.zeros(sub.m, dtype=bool)
        is_free[sub.free] = True
        return bad[is_free[bad]]

    def _sliding_rows(
        self, x: NDArray[np.float64], sub: _Subproblem
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Rows of ``sub.free`` that slide, and their unit surface normals at ``x`` (area-weighted
        over the quads around each node)."""
        if self.options.slide_skin is False or len(self.sliding) == 0 or len(self.quads) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        free_global = sub.nodes[sub.free]
        rows = np.flatnonzero(np.isin(free_global, self.sliding))
        if len(rows) == 0:
            return rows, np.zeros((0, 3))
        p = x[self.quads]
        normal = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])  # twice the area, outward
        acc = np.zeros((self.n_nodes, 3))
        for k in range(4):
            np.add.at(acc, self.quads[:, k], normal)
        n = acc[free_global[rows]]
        length = np.linalg.norm(n, axis=1)
        ok = length > 0
        return rows[ok], n[ok] / length[ok, None]

    def _optimise_quality(
        self,
        x: NDArray[np.float64],
        transforms: Mapping[str, RigidTransform] | None,
        report: RelaxReport,
        progress: ProgressCallback,
        cancel: Callable[[], bool] | None,
    ) -> NDArray[np.float64]:
        """Bring the elements around the relaxable nodes within their quality aims, every node
        moving together, bones kept out by their contact planes, skin contours in order
        (``options.contour_margin``). The skin is free here: held
        in its tangent planes, the folded crease behind a knee flexed to 120 deg kept 142
        elements warped beyond 30 deg and a worst Jacobian of 0.11 (free: 80 and 0.19)."""
        assert self.blocks is not None and self.aims is not None
        order = self.contour_order
        crossing = None if order is None else order.crossing(x)
        free = shortfall_region(
            x, self.blocks, self.aims, self.free, self.options.rings, seeds=crossing
        )
        if len(free) == 0:
            return x
        contact = self.contact_nodes[np.isin(self.contact_nodes, free)]
        use_contact = transforms is not None and len(contact) > 0

        def constraints(coords: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
            parts = []
            if use_contact:
                which, normals, offsets, _ = self._contact_planes(coords, contact, transforms)
                parts.append((contact[which], normals, offsets))
            if order is not None:
                parts.append(order.constraints(coords))
            if not parts:
                return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0)
            return tuple(np.concatenate(p) for p in zip(*parts, strict=True))

        try:
            x, report.quality = optimise_quality(
                x,
                self.blocks,
                free,
                self.aims,
                constraints=constraints,
                options=self.options.quality,
                progress=progress,
                cancel=cancel,
            )
        except ValueError:  # an element stayed inverted or flat: the input has one (issue #22)
            raise GeometryError(
                "the relaxation cannot untangle the soft tissue it moves: an element there is "
                "inverted or flat (coincident nodes or a collapsed element in the deck? "
                "'kneegui quality' lists them)"
            ) from None
        return x

    def _polish(
        self,
        x: NDArray[np.float64],
        free: NDArray[np.int64],
        transforms: Mapping[str, RigidTransform] | None,
        report: RelaxReport,
        progress: ProgressCallback,
        cancel: Callable[[], bool] | None,
    ) -> NDArray[np.float64]:
        """Lift the worst elements around ``free`` with the quality-guarded smoother."""
        guard = None
        if transforms is not None:
            contact = self.contact_nodes[np.isin(self.contact_nodes, free)]
            start = self._contact_planes(x, contact, transforms)[3] if len(contact) else None
            start_xyz = x[contact]

            def guard(nodes: NDArray[np.int64], coords: NDArray[np.float64]) -> NDArray[np.bool_]:
                # no node goes deeper into a bone than it is, or than the contact allows
                ok = np.ones(len(nodes), dtype=bool)
                if start is None:
                    return ok
                slot = np.minimum(np.searchsorted(contact, nodes), len(contact) - 1)
                hit = np.flatnonzero(contact[slot] == nodes)
                # a distance moves no faster than the point: a node that moved less than its
                # margin at the start is still outside (no query needed)
                moved = np.linalg.norm(coords[nodes[hit]] - start_xyz[slot[hit]], axis=1)
                hit = hit[moved >= start[slot[hit]]]
                if len(hit):
                    margin = self._contact_planes(coords, nodes[hit], transforms)[3]
                    ok[hit] = margin >= np.minimum(start[slot[hit]], 0.0) - 1e-9
                return ok

        goals = self.goals if self.goals is not None else 0.6
        slide = self.options.slide_skin is not False
        sliding = self.sliding[np.isin(self.sliding, free)] if slide else None
        x, report.polish = smooth_mesh(
            x,
            self.blocks,
            free if sliding is None else np.setdiff1d(free, sliding),
            sliding_nodes=sliding,
            target=goals,
            position_guard=guard,
            progress=progress,
            cancel=cancel,
        )
        return x
