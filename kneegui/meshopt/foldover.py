"""The foldover-free energy: untangling a mesh region by minimising a distortion barrier.

Every solid element is cut into corner tetrahedra (the three edges through each corner, the same
corners as the corner Jacobian of QUALITY.md); for each, ``J`` maps the corner's initial edges to
its current edges, and the energy is the foldover-free distortion of Garanzha et al. (2021),
*Foldover-free maps in 50 lines of code*, ACM Trans. Graph. 40(4)::

    f(J) = (1 - theta) |J|^2 / chi(det J)^(2/3) + theta (det J^2 + 1) / chi(det J)
    chi(D) = (D + sqrt(eps^2 + D^2)) / 2

every corner weighted the same (or by its initial volume). The first term penalises change of
shape, the second change of volume; both are smallest at the initial shape (``J`` a rotation).
As ``eps`` -> 0 the energy becomes a barrier that no corner can cross into inversion; the
schedule of ``eps`` from the paper (:func:`next_eps`) untangles inverted corners. Minimised with
L-BFGS (:func:`kneegui.meshopt.lbfgs.minimize_lbfgs`) on Jacobi-scaled variables
(:func:`penalised_objective`), with half-space constraints (e.g. bone contact) as a penalty and
sliding nodes held in their tangent planes. Shells lying on solid faces add tetrahedra to a
virtual apex inside the solid and a barrier on their own corner determinants
(:func:`quad_barrier`), so they cannot fold or turn into darts.

The compiled kernel (:mod:`kneegui.meshopt.foldover_kernel`, Numba, a dependency) computes the
energy; :meth:`FoldoverEnergy.energy_numpy` is the NumPy reference it is tested against.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from kneegui.errors import raise_if_cancelled
from kneegui.meshopt.foldover_kernel import (
    add_at_rows,
    foldover_energy_in_parts,
    foldover_free_energy,
    gather_rows,
    quad_barrier_energy,
    scatter_scaled,
)
from kneegui.meshopt.parallel import (
    PARALLEL_KERNEL_LOCK,
    PARALLEL_MIN_ELEMENTS,
    PARTS,
    add_in_order,
    part_bounds,
)
from kneegui.meshopt.quality_optimiser import QualityOptimisationReport
from kneegui.quality.kernels import corner_determinants
from kneegui.topology import sorted_unique


def edge_matrices(x: NDArray[np.float64], tets: NDArray[np.int64]) -> NDArray[np.float64]:
    """(C, 3, 3) edge matrices: column k is x[tets[:, k+1]] - x[tets[:, 0]]."""
    base = x[tets[:, 0]]
    return np.stack([x[tets[:, k]] - base for k in (1, 2, 3)], axis=2)


def regularised_det(det: NDArray[np.float64], eps: float) -> tuple[NDArray, NDArray]:
    """Garanzha's regularised determinant ``(D + sqrt(eps^2 + D^2)) / 2`` and its derivative,
    in a form that does not cancel to zero for very negative ``D``."""
    root = np.sqrt(eps * eps + det * det)
    with np.errstate(divide="ignore", invalid="ignore"):
        chi = np.where(det >= 0, 0.5 * (det + root), 0.5 * eps * eps / (root - det))
    return np.maximum(chi, 1e-300), 0.5 * (1.0 + det / root)


@dataclass(frozen=True)
class RelaxOptions:
    """Parameters of the foldover-free energy's stage (the untangling) and its region.

    Attributes
    ----------
    volume_weight : float
        ``theta``: weight of the volume term against the shape term (0..1).
    healthy_volume_weight : float
    healthy_det : (float, float)
        Opt-in (0, the default: every corner weighs volume by ``volume_weight``). A corner
        whose ``det J`` is above ``healthy_det[1]`` when a round starts weighs volume by
        ``healthy_volume_weight`` in that round, one below ``healthy_det[0]`` by
        ``volume_weight``, one between by a weight linear in its ``det J`` (a ramp, not a
        step: a ``det J`` a rounding apart must not change a corner's class). At ``theta`` =
        0.5 the energy is a compressible material whose rounds trade volume for shape; the
        healthy tissue stiff in volume keeps it while the crushed and inverted corners stay
        soft enough to come free. Not the default: at 0.95 it left the 1M demo at 90 deg with
        18 elements inverted instead of 30 and a p95 volume change of 57.6 % instead of 64.5 %,
        but the 1.7M-node demo with 52 instead of 32 and 45 soft-tissue nodes up to 1.16 mm
        in a bone instead of 1 (docs/repositioning.md, relaxation).
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
        keeps every element valid and the next round runs at the final stiffness. (Raised 4x
        per round instead, the 20k demo at 90 deg spent three rounds of its seven, 450 of 1,050
        iterations, on the way up, for the same worst Jacobian.)
    contact_force_depth : float
        Depth (model units) beyond which the contact force stops growing.
    contact_band : float
        Nodes closer to a bone than this (model units) get a contact plane.
    contact_clearance : float
        Distance from the bone surface the contact holds nodes at (model units).
    penetration_tolerance : float
        A contact node deeper than this (model units) inside a bone seeds the relaxed region.
    restarts : int
        How many times the rounds start again when corners are still inverted after
        ``max_rounds``: the nodes of those corners go back to their posed positions and the
        barrier is softened to ``restart_eps`` (the schedule can drive ``eps`` to its floor
        while nodes pressed onto one point keep a corner at zero volume). The last restart
        also frees those nodes from the bone contact. Every restart lets the sliding skin
        nodes among them off their tangent planes.
    restart_eps : float
        ``eps`` a restart begins with.
    restart_rings : int
        A restart moves only the free nodes within this many mesh edges of the stuck ones,
        the rest of the region keeping what the passes before reached (0: the whole region
        again).
    focus_rings : int
        After a round that left corners inverted, the next round moves only the free nodes
        within this many mesh edges of them (of the attempt's region), the rest keeping what
        it reached; a round that untangles them hands the next one back the attempt's whole
        region, so the contact stiffens everywhere (0: every round moves the attempt's whole
        region). 10 rather than 6: with 6 the coarse leg built at 20 deg, posed to 120 deg,
        kept 7 movable elements inverted instead of 5 (10: 1), and the leg built at 0 deg a
        soft-tissue node 0.5 mm inside a bone at 120 deg (docs/repositioning.md).
    stall_rounds : int
        An attempt whose rounds have not lowered its fewest inverted corners for this many
        rounds in a row ends there (restarts, or stops after the last). When corners are still
        inverted at the end, the relaxation keeps the round that left the fewest (of any
        attempt).
    slow_eps_decrease : float
        When the rounds and restarts leave corners inverted, a last pass starts the nodes within
        ``slow_rings`` mesh edges of them again from the pose, with ``eps`` falling more slowly
        (this floor of the relative decrease per round instead of ``eps_decrease``), and its
        result is kept if it leaves fewer corners inverted (0: no such pass). With the fast
        schedule the barrier stiffens before a fold deep in pinched tissue is undone (the leg
        built at 20 deg, posed to 120 deg, kept 5 corners at ``det J`` about ``-eps`` round
        after round); over the whole region, the slow schedule costs rounds everywhere (the
        20k demo at 120 deg: 12 rounds instead of 7) and ran out of them at 177k.
    slow_rings : int
        Mesh edges around the inverted corners' nodes that the slow pass moves.
    slow_pass_nodes : int
        The slow pass runs only when it would move at most this many nodes (its cost is its
        nodes times its rounds, and it starts them again from the pose): on the coarse and
        177k demos it moved 1,367-2,253 nodes and was kept in two of four measured cells (the
        leg built at 20 deg and the welded joint at 120 deg); on the 1M demo at 90 deg it moved
        15,259 nodes through 55 rounds, about 35 s of the export, and was not kept in either
        measured run (docs/repositioning.md). Left out, the pose is the first pass's to the
        bit.
    slide_skin : bool or None
        Skin nodes move only in the tangent plane of the pose being relaxed (the sliding nodes
        given to :class:`ElasticRelaxation`; ``None`` slides them there too).
        :class:`kneegui.reposition.Repositioner` resolves ``None`` by method: it slides
        the skin for ``blend``, whose skin is the mapped surface, and frees it for ``paper``,
        whose contour-placed skin can fold and must be free to unfold (docs/repositioning.md).
    skin_outward : bool
        A sliding skin node may also leave its tangent plane outwards, never inwards: a
        one-sided plane on it (stiff as the bone contact) instead of the projection onto the
        plane. The flesh pressed together behind a flexed knee pushes the skin out instead of
        being crushed under it or pressed into a bone (the 1M demo at 90 deg: 1 soft-tissue
        node past the tolerance in a bone instead of 114; docs/repositioning.md).
    """

    volume_weight: float = 0.5
    healthy_volume_weight: float = 0.0
    healthy_det: tuple[float, float] = (0.25, 0.75)
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
    penetration_tolerance: float = 1e-3
    restarts: int = 2
    restart_eps: float = 0.05
    restart_rings: int = 4
    focus_rings: int = 10
    stall_rounds: int = 4
    slow_eps_decrease: float = 0.3
    slow_rings: int = 10
    slow_pass_nodes: int = 8000
    slide_skin: bool | None = None
    skin_outward: bool = True

    def __post_init__(self) -> None:
        if not 0 <= self.volume_weight <= 1 or not 0 <= self.healthy_volume_weight <= 1:
            raise ValueError(
                "RelaxOptions.volume_weight and healthy_volume_weight must be in [0, 1], not"
                f" {self.volume_weight} and {self.healthy_volume_weight}"
            )
        if (
            self.max_rounds < 1
            or self.iterations_per_round < 1
            or self.restarts < 0
            or self.stall_rounds < 1
            or self.restart_rings < 0
            or self.focus_rings < 0
        ):
            raise ValueError(
                "RelaxOptions needs max_rounds >= 1, iterations_per_round >= 1, restarts >= 0,"
                " restart_rings >= 0, focus_rings >= 0 and stall_rounds >= 1"
            )
        if not 0 <= self.healthy_det[0] < self.healthy_det[1]:
            raise ValueError(
                "RelaxOptions.healthy_det must be two det J 0 <= low < high, not"
                f" {self.healthy_det}"
            )
        if not 0 < self.eps_decrease < 1:
            raise ValueError(
                f"RelaxOptions.eps_decrease must be in (0, 1), not {self.eps_decrease}"
            )
        if not 0 <= self.slow_eps_decrease < 1 or self.slow_rings < 1:
            raise ValueError(
                "RelaxOptions needs slow_eps_decrease in [0, 1) (0: no slow pass) and"
                f" slow_rings >= 1, not {self.slow_eps_decrease} and {self.slow_rings}"
            )
        if self.slow_pass_nodes < 1:
            raise ValueError(
                f"RelaxOptions.slow_pass_nodes must be >= 1, not {self.slow_pass_nodes}"
            )

    def scaled(self, length: float) -> RelaxOptions:
        """These options with every length (model units) multiplied by ``length``: the same
        relaxation of a model drawn ``length`` times larger (or in other units)."""
        return replace(
            self,
            contact_band=self.contact_band * length,
            contact_force_depth=self.contact_force_depth * length,
            contact_clearance=self.contact_clearance * length,
            penetration_tolerance=self.penetration_tolerance * length,
        )


@dataclass
class RelaxReport:
    """What the relaxation did."""

    free_nodes: int = 0
    corners: int = 0
    rounds: int = 0
    restarts: int = 0
    contact_released: int = 0
    sliding_released: int = 0  # sliding skin nodes a restart let off their tangent planes
    kept_attempt: int = -1  # attempt (0: before any restart) of the round kept; -1: the last
    iterations: int = 0
    evaluations: int = 0
    min_det_before: float = float("nan")
    min_det_after: float = float("nan")
    inverted_corners_before: int = 0
    inverted_corners_after: int = 0
    #: corners left out as those of elements the bones leave no valid shape (welded tissue)
    locked_corners: int = 0
    contact_nodes: int = 0
    deepest_penetration: float = 0.0
    seconds: float = 0.0
    region_seconds: float = 0.0  # finding the degraded region (part of ``seconds``)
    history: list[dict[str, float]] = field(default_factory=list)
    quality: QualityOptimisationReport | None = None  # what the quality optimisation did
    #: the slow pass around what stayed inverted (``RelaxOptions.slow_eps_decrease``), when
    #: corners stayed inverted: its nodes, whether it ran (not beyond
    #: ``RelaxOptions.slow_pass_nodes``), its rounds, the inverted corners before and after it,
    #: and whether it was kept
    slow_pass: dict[str, float | int | bool] | None = None

    def to_dict(self) -> dict[str, object]:
        """JSON-ready summary."""
        out = dict(self.__dict__)
        out.pop("history")
        out["quality"] = None if self.quality is None else self.quality.to_dict()
        return out


def _cross3(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise cross products of (M, 3) arrays (np.cross costs more on short arrays)."""
    return _cross_t(a.T, b.T).T


def quad_barrier(
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
        chi, dchi = regularised_det(r, eps)
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


#: ``corner_theta`` of an energy whose corners all weigh volume by its ``theta``.
_EVERY_CORNER_THETA = np.zeros(0)

#: Corners whose preconditioner terms :class:`FoldoverEnergy` works out at a time.
_DIAGONAL_BLOCK = 1 << 16


class FoldoverEnergy:
    """The foldover-free energy of the corner tetrahedra touching a set of free nodes, in local
    numbering: the real nodes they use (and the virtual nodes need) first, then the virtual
    nodes.

    Parameters
    ----------
    tets : (C, 4) ndarray of int
        The corner tetrahedra (global numbering; ``n_nodes + k`` is virtual node ``k``).
    inv_rest : (R, 3, 3) ndarray
        Inverse rest edge matrices (``J = E @ G``): corner ``c``'s is ``inv_rest[rows[c]]``.
    weight : (R,) ndarray
        Weights: corner ``c``'s is ``weight[rows[c]]``.
    virtual : (V, N) sparse matrix
        The virtual nodes as combinations of the real ones.
    quads : (Q, 4) ndarray of int
        Shells whose corner determinants get a barrier (global numbering).
    rest : (N, 3) ndarray
        Rest coordinates (the quads' reference determinants).
    free : (F,) ndarray of int
        The free nodes (global numbering).
    volume_weight, shell_weight : float
        ``theta`` and the shells' barrier weight (:class:`RelaxOptions`).
    rows : (C,) ndarray of int, optional
        Each corner's row of ``inv_rest`` and ``weight`` (default: ``c``). The relaxation
        passes its own arrays and the rows of the region's corners: a whole-body region has
        millions of corners, and each round's energy would otherwise copy 80 bytes of each.
    cancel : callable, optional
        Asked between the build's steps; True raises :class:`kneegui.errors.Cancelled`.
    """

    def __init__(
        self,
        tets: NDArray[np.int64],
        inv_rest: NDArray[np.float64],
        weight: NDArray[np.float64],
        virtual: sp.csr_matrix,
        quads: NDArray[np.int64],
        rest: NDArray[np.float64],
        free: NDArray[np.int64],
        volume_weight: float,
        shell_weight: float,
        rows: NDArray[np.int64] | None = None,
        cancel: Callable[[], bool] | None = None,
    ):
        def check() -> None:
            # a whole-body region's energy takes seconds to build (the 1M demo: 2.1 s)
            raise_if_cancelled(cancel, "relaxation cancelled while its energy was built")

        n = virtual.shape[1]
        is_virtual = tets >= n
        used_virtual = sorted_unique(tets[is_virtual]) - n
        v_sub = virtual[used_virtual]
        self.nodes = np.union1d(np.union1d(sorted_unique(tets[~is_virtual]), v_sub.indices), quads)
        check()
        m = len(self.nodes)
        self.quads = np.searchsorted(self.nodes, quads).reshape(-1, 4)
        self.quad_rest = corner_determinants(rest[quads.reshape(-1, 4)], "quad4")
        self.quad_weight = shell_weight
        q_flat = self.quads.ravel()
        self.quad_scatter = sp.csr_matrix(
            (np.ones(len(q_flat)), (q_flat, np.arange(len(q_flat)))), shape=(m, len(q_flat))
        )
        self.virtual = v_sub[:, self.nodes].tocsr() if len(used_virtual) else None
        self.virtual_t = None if self.virtual is None else self.virtual.T.tocsr()
        local = np.empty(tets.shape, dtype=np.int32 if m + len(used_virtual) < 2**31 else np.int64)
        local[~is_virtual] = np.searchsorted(self.nodes, tets[~is_virtual])
        local[is_virtual] = m + np.searchsorted(used_virtual, tets[is_virtual] - n)
        self.tets = local
        self.m = m
        check()
        # the shared (R, ...) arrays, not copied; corner c's rows of them: self.rows[c] (the
        # per-corner copies are the properties g_rows and weight)
        self.inv_rest = np.ascontiguousarray(inv_rest, dtype=np.float64)
        self.weights = np.ascontiguousarray(weight, dtype=np.float64)
        index = np.int32 if len(self.inv_rest) < 2**31 else np.int64  # half the bytes to read
        self.rows = (
            np.arange(len(tets), dtype=index)
            if rows is None
            else np.ascontiguousarray(rows, dtype=index)
        )
        self.theta = volume_weight
        self.free = np.searchsorted(self.nodes, free)  # local indices of the free nodes
        self._size = m + len(used_virtual)
        # diagonal of the shape term's Hessian at rest, per node: a preconditioner (summed
        # term by term, in the order of the edge-major sums, a block of corners at a time: no
        # copy of every corner's matrix)
        size, c = self._size, len(self.tets)
        end_sq, base_sq = np.empty((3, c)), np.empty(c)
        for lo in range(0, c, _DIAGONAL_BLOCK):
            check()
            g = self.inv_rest[self.rows[lo : lo + _DIAGONAL_BLOCK]]
            end_sq[:, lo : lo + len(g)] = (g[:, :, 0] ** 2 + g[:, :, 1] ** 2 + g[:, :, 2] ** 2).T
            col = g[:, 0] + g[:, 1] + g[:, 2]  # the three edges' rows summed
            base_sq[lo : lo + len(g)] = col[:, 0] ** 2 + col[:, 1] ** 2 + col[:, 2] ** 2
        ends = self.tets[:, 1:].T.ravel()  # edge j of corner c at j * C + c
        check()
        weight = self.weight
        diag = np.zeros(size)
        np.add.at(diag, ends, np.tile(weight, 3) * end_sq.ravel())
        np.add.at(diag, self.tets[:, 0], weight * base_sq)
        if self.virtual_t is not None:
            diag = diag[:m] + self.virtual_t.multiply(self.virtual_t) @ diag[m:]
        self.diagonal = diag[:m]
        self._buffers: NDArray[np.float64] | None = None
        self._cut = part_bounds(len(self.tets))

    @property
    def g_rows(self) -> NDArray[np.float64]:
        """(C, 3, 3) each corner's inverse rest edge matrix (a copy, for the NumPy reference
        and the tests; the compiled kernel reads the shared rows)."""
        return self.inv_rest[self.rows]

    @property
    def weight(self) -> NDArray[np.float64]:
        """(C,) each corner's weight (a copy)."""
        return self.weights[self.rows]

    @property
    def g(self) -> NDArray[np.float64]:
        """(3 edges, 3, C) the inverse rest edge matrices, edge-major (the NumPy reference's
        layout); made when asked for, since the compiled kernel reads the shared rows and a
        whole-body model's region has millions of corners."""
        return np.ascontiguousarray(np.transpose(self.g_rows, (1, 2, 0)))

    @property
    def scatter(self) -> sp.csr_matrix:
        """(nodes, 3 C) the gradient scatter of the NumPy reference: edge gradients
        (3 edges x C, 3) to nodes as one sparse product; made when asked for."""
        c, size = len(self.tets), self._size
        cols = np.arange(3 * c)
        ends = self.tets[:, 1:].T.ravel()  # column j * C + corner
        plus = sp.csr_matrix((np.ones(3 * c), (ends, cols)), shape=(size, 3 * c))
        base = np.tile(self.tets[:, 0], 3)
        minus = sp.csr_matrix((np.ones(3 * c), (base, cols)), shape=(size, 3 * c))
        return (plus - minus).tocsr()

    def augment(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Local real coordinates (m, 3) followed by the virtual nodes' coordinates."""
        return x if self.virtual is None else np.vstack([x, self.virtual @ x])

    def energy(
        self,
        x: NDArray[np.float64],
        eps: float,
        corner_theta: NDArray[np.float64] | None = None,
    ) -> tuple[float, NDArray, NDArray]:
        """Energy, gradient (m, 3) and per-corner det J at local coordinates ``x`` (m, 3);
        ``corner_theta`` (one per corner) replaces the volume weight ``theta`` corner by
        corner."""
        xa = np.ascontiguousarray(self.augment(x))
        grad = np.empty_like(xa)
        det = np.empty(len(self.tets))
        own = self._corner_theta(corner_theta)
        if len(self.tets) < PARALLEL_MIN_ELEMENTS:
            energy = foldover_free_energy(xa, *self._corners, eps, grad, det, own)
        else:
            energy = self._energy_in_parts(xa, eps, grad, det, own)
        if self.virtual_t is not None:
            grad = grad[: self.m] + self.virtual_t @ grad[self.m :]
        if len(self.quads) == 0:
            return float(energy), grad, det
        ratios = np.empty(4 * len(self.quads))
        energy += quad_barrier_energy(
            np.ascontiguousarray(x), self.quads, self.quad_rest, self.quad_weight, eps, grad, ratios
        )
        return float(energy), grad, np.concatenate([det, ratios])

    @property
    def _corners(self) -> tuple:
        """The kernels' corner arguments: tets, inverse rest matrices, weights, their rows and
        ``theta``."""
        return self.tets, self.inv_rest, self.weights, self.rows, self.theta

    def _corner_theta(self, corner_theta: NDArray[np.float64] | None) -> NDArray[np.float64]:
        """``corner_theta`` as the kernel takes it (empty: ``theta`` everywhere), checked."""
        if corner_theta is None:
            return _EVERY_CORNER_THETA
        if len(corner_theta) != len(self.tets):
            raise ValueError(
                f"corner_theta has {len(corner_theta)} values for {len(self.tets)} corners"
            )
        return np.ascontiguousarray(corner_theta, dtype=np.float64)

    def _energy_in_parts(self, xa, eps, grad, det, corner_theta) -> float:
        """The compiled energy over fixed parts of the corners, each into its own gradient
        buffer, added in order (:mod:`kneegui.meshopt.parallel`)."""
        if self._buffers is None or self._buffers.shape[1:] != xa.shape:
            self._buffers = np.empty((PARTS, *xa.shape))
        totals = np.empty(PARTS)
        with PARALLEL_KERNEL_LOCK:
            foldover_energy_in_parts(
                xa, *self._corners, eps, self._cut, self._buffers, det, totals, corner_theta
            )
        np.sum(self._buffers, axis=0, out=grad)
        return add_in_order(totals)

    def _add_shells(self, x, eps, energy, grad, det):
        if len(self.quads) == 0:
            return energy, grad, det
        e_q, g_q, r_q = quad_barrier(x, self.quads, self.quad_rest, self.quad_weight, eps)
        grad = grad + self.quad_scatter @ g_q.reshape(-1, 3)
        return energy + e_q, grad, np.concatenate([det, r_q])

    def energy_numpy(
        self,
        x: NDArray[np.float64],
        eps: float,
        corner_theta: NDArray[np.float64] | None = None,
    ) -> tuple[float, NDArray, NDArray]:
        """:meth:`energy` in NumPy (the reference the compiled kernel is tested against).

        Laid out as (component, corner) arrays so that every step is an elementwise operation
        on long vectors.
        """
        theta = self.theta if corner_theta is None else self._corner_theta(corner_theta)
        g, t = self.g, self.tets
        xt = self.augment(x).T
        base = xt[:, t[:, 0]]
        edges = np.stack([xt[:, t[:, k]] - base for k in (1, 2, 3)])  # (3 edges, 3 coords, C)
        jac = sum(edges[j][:, None, :] * g[j][None, :, :] for j in range(3))  # (3, 3, C)
        c0, c1, c2 = jac[:, 0], jac[:, 1], jac[:, 2]
        cof = np.stack([_cross_t(c1, c2), _cross_t(c2, c0), _cross_t(c0, c1)], axis=1)
        det = np.sum(c0 * cof[:, 0], axis=0)
        chi, dchi = regularised_det(det, eps)
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


def penalised_objective(
    energy: FoldoverEnergy,
    start: NDArray[np.float64],
    scale: NDArray[np.float64],
    eps: float,
    planes: tuple[NDArray, NDArray, NDArray, NDArray],
    force_depth: float,
    sliding: tuple[NDArray[np.int64], NDArray[np.float64]],
    corner_theta: NDArray[np.float64] | None = None,
) -> Callable[[NDArray[np.float64]], tuple[float, NDArray]]:
    """The energy over the scaled free variables, with half-space penalties.

    Parameters
    ----------
    energy : FoldoverEnergy
    start : (m, 3) ndarray
        Local coordinates; the free rows are replaced by the variables.
    scale : (F, 1) ndarray
        Variable scaling of the free nodes (Jacobi preconditioning).
    eps : float
        The barrier's regularisation.
    planes : (local nodes, normals, offsets, stiffness)
        Penalties ``k/2 gap^2`` on ``gap = n . x - offset < 0``, quadratic up to
        ``force_depth`` deep and linear beyond (Huber): a node pinched between two planes is
        pushed with a bounded force, so the barrier, not the penalty, has the last word.
    sliding : (rows of the free nodes, unit normals)
        Free nodes moving only in their tangent planes (the gradient's normal part is removed,
        so L-BFGS stays in those planes).
    corner_theta : (C,) ndarray, optional
        Each corner's volume weight instead of the energy's ``theta``
        (:meth:`FoldoverEnergy.energy`).
    """
    work = start.copy()
    c_local, c_normals, c_offsets, c_k = planes
    c_local = np.ascontiguousarray(c_local, dtype=np.int64)
    slide_rows, slide_normals = sliding
    sub_free = np.ascontiguousarray(energy.free, dtype=np.int64)
    scale = np.ascontiguousarray(scale, dtype=np.float64)
    g_free = np.empty((len(sub_free), 3))

    # the scatter, gather and contact forces in compiled loops: NumPy's fancy indexing and
    # np.add.at cost about 2 ms per evaluation at 177k (10 %); the same operations in the same
    # order, so the same bits
    def fun(flat: NDArray[np.float64]) -> tuple[float, NDArray]:
        scatter_scaled(work, sub_free, np.ascontiguousarray(flat), scale)
        value, grad, _ = energy.energy(work, eps, corner_theta)
        if len(c_local):
            gap = np.einsum("ij,ij->i", c_normals, work[c_local]) - c_offsets
            short = np.minimum(gap, 0.0)
            clipped = np.maximum(short, -force_depth)
            value += float(
                np.sum(c_k * (0.5 * clipped * clipped + force_depth * (clipped - short)))
            )
            add_at_rows(grad, c_local, (c_k * clipped)[:, None] * c_normals)
        gather_rows(grad, sub_free, g_free)
        if len(slide_rows):
            along = np.einsum("ij,ij->i", g_free[slide_rows], slide_normals)
            g_free[slide_rows] -= along[:, None] * slide_normals
        return value, (g_free * scale).ravel()

    return fun


def next_eps(eps: float, before: float, after: float, d_min: float, sigma_floor: float) -> float:
    """Garanzha et al. 2021: shrink ``eps`` as fast as the energy's decrease in the last round
    (``before`` -> ``after``) allows, given the smallest corner ``det J`` ``d_min``; the
    relative decrease per round is at least ``sigma_floor``."""
    sigma = max(1.0 - after / before, sigma_floor) if before > 0 else 1.0
    chi_min = 0.5 * (d_min + np.sqrt(eps * eps + d_min * d_min))
    mu = (1.0 - sigma) * chi_min
    return max(float(2.0 * np.sqrt(mu * (mu - d_min))) if d_min < mu else 0.0, 1e-9)
