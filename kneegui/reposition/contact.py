"""Bone contact: soft tissue slides on the bones but never enters them (penetration fixing).

The rigid blend rotates tissue about the F-E axis; where a bone's surface is not a circle about
that axis, tissue lying on it would be carried into the bone. Candidates are the soft-tissue nodes
within ``reach`` of a bone surface in the initial pose. For a pose, each candidate is expressed in
each bone's initial frame, its closest point on that bone's surface is found exactly (among the
triangles around the nearest surface node), and if it is closer to the surface than it was at rest
(up to ``clearance``) it is pushed out along the surface normal. The pushes are then extended
smoothly into the other soft-tissue nodes by a Laplace solve (factorised once), so the tissue
behind a pushed node moves with it instead of being crushed: the paper's "local stretching".

A node carried deep into a bone is not sent to the nearest surface point: from 10 mm inside a
tibial condyle the nearest point may be on the plateau for one node and on the posterior wall for
its neighbour, which tears the element between them. It goes back along the straight way to its
rest place relative to that bone (outside it at rest) and stops where that way leaves the bone.

:class:`BoneDepthGuard` keeps the smoother from pushing tissue into a bone.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numba import njit
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from kneegui.errors import raise_if_cancelled
from kneegui.geometry.transforms import RigidTransform
from kneegui.reposition.rigid_blend import DIRECT_SOLVE_MAX, block_cg
from kneegui.reposition.triangle_grid import TriangleGrid
from kneegui.topology import sorted_unique

#: Points per chunk of a threaded :meth:`BoneSurfaceDistance.query`.
QUERY_CHUNK = 2048
#: Chunks between two questions to a :meth:`BoneSurfaceDistance.query`'s ``cancel``.
QUERY_WAVE = 64


def _incident(triangles: NDArray[np.int64], nodes: NDArray[np.int64]) -> NDArray[np.int64]:
    pos = np.full(int(triangles.max()) + 1, -1, dtype=np.int64)
    pos[nodes] = np.arange(len(nodes))
    owner = np.repeat(np.arange(len(triangles)), 3)
    node = pos[triangles.reshape(-1)]
    order = np.argsort(node, kind="stable")
    node, owner = node[order], owner[order]
    counts = np.bincount(node, minlength=len(nodes))
    width = int(counts.max())
    table = np.full((len(nodes), width), -1, dtype=np.int64)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(len(node)) - start[node]
    table[node, rank] = owner
    return table


@njit(cache=True, nogil=True, error_model="numpy")
def _closest_on_triangles(p, tri, q):  # pragma: no cover - compiled
    for m in range(p.shape[0]):
        ab = np.empty(3)
        ac = np.empty(3)
        d1 = d2 = d3 = d4 = d5 = d6 = 0.0
        for k in range(3):  # the row sums in NumPy's order: 0 + x + y + z
            ab[k] = tri[m, 1, k] - tri[m, 0, k]
            ac[k] = tri[m, 2, k] - tri[m, 0, k]
            ap = p[m, k] - tri[m, 0, k]
            bp = p[m, k] - tri[m, 1, k]
            cp = p[m, k] - tri[m, 2, k]
            d1 += ab[k] * ap
            d2 += ac[k] * ap
            d3 += ab[k] * bp
            d4 += ac[k] * bp
            d5 += ab[k] * cp
            d6 += ac[k] * cp
        va = d3 * d6 - d5 * d4
        vb = d5 * d2 - d1 * d6
        vc = d1 * d4 - d3 * d2
        # the last region that holds wins, as the NumPy reference's chain of np.where
        if d6 >= 0 and d5 <= d6:
            for k in range(3):
                q[m, k] = tri[m, 2, k]
        elif d3 >= 0 and d4 <= d3:
            for k in range(3):
                q[m, k] = tri[m, 1, k]
        elif d1 <= 0 and d2 <= 0:
            for k in range(3):
                q[m, k] = tri[m, 0, k]
        elif va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
            t = _unit_clip((d4 - d3) / ((d4 - d3) + (d5 - d6)))
            for k in range(3):
                q[m, k] = tri[m, 1, k] + t * (tri[m, 2, k] - tri[m, 1, k])
        elif vb <= 0 and d2 >= 0 and d6 <= 0:
            t = _unit_clip(d2 / (d2 - d6))
            for k in range(3):
                q[m, k] = tri[m, 0, k] + t * ac[k]
        elif vc <= 0 and d1 >= 0 and d3 <= 0:
            t = _unit_clip(d1 / (d1 - d3))
            for k in range(3):
                q[m, k] = tri[m, 0, k] + t * ab[k]
        else:
            total = va + vb + vc
            if total == 0:
                total = 1.0
            v = vb / total
            w = vc / total
            for k in range(3):
                q[m, k] = tri[m, 0, k] + v * ab[k] + w * ac[k]


@njit(cache=True, nogil=True)
def _unit_clip(t):  # pragma: no cover - compiled
    """``np.clip(np.nan_to_num(t), 0, 1)``."""
    if t != t:
        return 0.0
    return min(max(t, 0.0), 1.0)


def closest_on_triangles(p: NDArray[np.float64], tri: NDArray[np.float64]) -> NDArray[np.float64]:
    """Closest points (M, 3) on triangles (M, 3, 3) to points (M, 3) (Ericson 5.1.5).

    Compiled; :func:`closest_on_triangles_numpy` is the reference it gives the same bits as
    (tested).
    """
    q = np.empty((len(p), 3))
    _closest_on_triangles(
        np.ascontiguousarray(p, dtype=np.float64), np.ascontiguousarray(tri, dtype=np.float64), q
    )
    return q


def closest_on_triangles_numpy(p, tri):
    """Closest points (M, 3) on triangles (M, 3, 3) to points (M, 3) (Ericson 5.1.5)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = p - b
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = p - c
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    s = va + vb + vc
    s = np.where(s == 0, 1.0, s)
    q = a + (vb / s)[:, None] * ab + (vc / s)[:, None] * ac
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = np.clip(np.nan_to_num(d1 / (d1 - d3)), 0, 1)
        t_ac = np.clip(np.nan_to_num(d2 / (d2 - d6)), 0, 1)
        t_bc = np.clip(np.nan_to_num((d4 - d3) / ((d4 - d3) + (d5 - d6))), 0, 1)
    q = np.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[:, None], a + t_ab[:, None] * ab, q)
    q = np.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[:, None], a + t_ac[:, None] * ac, q)
    q = np.where(
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[:, None], b + t_bc[:, None] * (c - b), q
    )
    q = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, q)
    q = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, q)
    q = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, q)
    return q


class BoneSurfaceDistance:
    """Signed distance from points to a rigid bone's surface, evaluated in the bone's rest frame.

    Parameters
    ----------
    tri_xyz : (T, 3, 3) ndarray
        Outward-oriented surface triangles at rest.
    exact_within : float
        Points that may lie closer to the surface than this (model units), and every point
        inside, get the exact distance; farther ones the distance to the triangles around the
        nearest surface node, which is at least the exact one (:meth:`query`).
    """

    def __init__(self, tri_xyz: NDArray[np.float64], exact_within: float = 0.0) -> None:
        self.tri_xyz = tri_xyz
        flat = tri_xyz.reshape(-1, 3)
        nodes_xyz, inverse = np.unique(flat, axis=0, return_inverse=True)
        tris = inverse.reshape(-1, 3)
        normal = np.cross(tri_xyz[:, 1] - tri_xyz[:, 0], tri_xyz[:, 2] - tri_xyz[:, 0])
        self.normal = normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        self.node_xyz = nodes_xyz
        self.node_tris = _incident(tris, np.arange(len(nodes_xyz)))
        self.tree = cKDTree(nodes_xyz)
        self.lower, self.upper = nodes_xyz.min(axis=0), nodes_xyz.max(axis=0)
        edge = np.linalg.norm(tri_xyz - np.roll(tri_xyz, 1, axis=1), axis=2)  # (T, 3)
        self.longest_edge = float(edge.max(initial=0.0))
        # every point of a triangle lies within (longest edge) / sqrt 3 of one of its corners
        self.corner_reach = self.longest_edge / np.sqrt(3.0)
        # a point whose nearest surface node is farther than this is at least exact_within
        # from the surface (its closest point lies within corner_reach of a node)
        self.exact_reach = float(exact_within) + self.corner_reach
        # each triangle's angle at each corner: the weights of the pseudo-normal at a vertex
        u = np.roll(tri_xyz, -1, axis=1) - tri_xyz
        v = np.roll(tri_xyz, 1, axis=1) - tri_xyz
        self.corner_angle = np.arctan2(
            np.linalg.norm(np.cross(u, v), axis=2), np.einsum("tij,tij->ti", u, v)
        )
        self.grid = TriangleGrid(tri_xyz, self.normal, self.corner_angle, self.longest_edge)

    def in_box(self, p: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which points (M, 3), in the rest frame, lie in the surface's bounding box: those
        outside it are outside the (closed) bone."""
        return np.all((p >= self.lower) & (p <= self.upper), axis=1)

    def query(
        self,
        p: NDArray[np.float64],
        threads: int | None = None,
        cancel: Callable[[], bool] | None = None,
    ) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """For points (M, 3) in the rest frame: signed distance (M,) (+ outside), closest surface
        point (M, 3), unit outward (pseudo-)normal there (M, 3), and the distance to the nearest
        surface node (M,).

        The closest point is exact among the triangles around the nearest surface node; the
        sign comes from the mean normal of every triangle as close as the best (at a shared edge
        or vertex one face's normal alone can give the wrong side). Many points are split into
        chunks of :data:`QUERY_CHUNK` measured on ``threads`` threads (default: every core, at
        most 8); each point's result is worked out on its own, so it does not depend on the
        thread count. With ``cancel``, it is asked before every :data:`QUERY_WAVE` chunks (a
        whole-body model's contact nodes: seconds per bone); True raises
        :class:`~kneegui.errors.Cancelled`.
        """
        p = np.asarray(p, dtype=np.float64)
        threads = threads or min(os.cpu_count() or 1, 8)
        if len(p) < 2 * QUERY_CHUNK or (threads == 1 and cancel is None):
            return self._query(p)
        starts = list(range(0, len(p), QUERY_CHUNK))
        parts = []
        with ThreadPoolExecutor(threads) as pool:
            for wave in range(0, len(starts), QUERY_WAVE):
                raise_if_cancelled(cancel, "cancelled while measuring the distance to a bone")
                parts += pool.map(
                    lambda s: self._query(p[s : s + QUERY_CHUNK]),
                    starts[wave : wave + QUERY_WAVE],
                )
        return tuple(np.concatenate(column) for column in zip(*parts, strict=True))

    def _query(self, p: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        node_distance, k = self.tree.query(p)
        tris = self.node_tris[k]
        ok = tris >= 0
        rows = np.broadcast_to(np.arange(len(p))[:, None], tris.shape)[ok]
        best, point, normals = self._closest(p, rows, tris[ok])
        # The fan of the nearest surface node does not always hold the closest triangle, and
        # the wrong triangle can give the wrong distance and the wrong side: a node 14 mm
        # behind the tibia was reported 14 mm inside it (the relaxation's contact would have
        # pushed it to the wrong surface), and among long, thin triangles (the coarse demo's
        # tibia has edges of 18 mm) a node 0.07 mm from the surface was measured 4.2 mm away,
        # beyond the contact's band, and the quality optimisation then pushed it 1 mm into the
        # bone. (Nor is a closest point inside the fan enough: a segment's surface may be
        # several closed ones, the tibia's and the fibula's.) So every point the fan puts
        # inside, and every point that may lie within exact_within of the surface, is measured
        # exactly (:class:`TriangleGrid`); a farther point is at least exact_within away, and the
        # fan's distance is at least the exact one.
        side = np.einsum("ij,ij->i", p - point, normals)
        exact = np.flatnonzero((side < 0) | (node_distance < self.exact_reach))
        if len(exact):
            best[exact], point[exact], normals[exact] = self.grid.closest(p[exact], best[exact])
        side = np.einsum("ij,ij->i", p - point, normals)
        sign = np.where(side < 0, -1.0, 1.0)
        return sign * best, point, normals, node_distance

    def certain(self, depth: NDArray[np.float64], node_distance: NDArray[np.float64]) -> NDArray:
        """A lower bound of the exact signed distance of points :meth:`query` measured as
        ``depth`` with nearest-node distance ``node_distance``: the depth itself where it is
        exact, else the distance to the nearest node less the farthest a triangle's point lies
        from its nearest corner."""
        estimated = (depth > 0) & (node_distance >= self.exact_reach)
        return np.where(estimated, np.minimum(depth, node_distance - self.corner_reach), depth)

    def _closest(
        self, p: NDArray[np.float64], rows: NDArray[np.int64], tris: NDArray[np.int64]
    ) -> tuple[NDArray, NDArray, NDArray]:
        """Distance, closest point and pseudo-normal of each point ``p`` (M, 3) among its
        candidate triangles: the pairs ``(rows[i], tris[i])``, sorted by row, each at most
        once, every row at least once.

        The pseudo-normal (Baerentzen & Aanaes 2005) sums the normals of every candidate as
        close as the best at the same closest point, each weighted by its angle there when
        that is one of its corners: with the exact closest point its side is the point's side,
        where a plain mean of the faces around a saddle-shaped vertex can point the wrong way.
        """
        if len(p) == 0:
            return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))
        corners = self.tri_xyz[tris]
        q = closest_on_triangles(p[rows], corners)
        d = np.linalg.norm(p[rows] - q, axis=1)
        # rows come grouped and in order (row-major pairs): a reduction per group
        starts = np.concatenate([[0], np.flatnonzero(np.diff(rows)) + 1])
        best = np.minimum.reduceat(d, starts)
        hit = np.flatnonzero(d == best[rows])
        first = hit[np.concatenate([[True], rows[hit][1:] != rows[hit][:-1]])]
        point = q[first]
        # the triangles as close as the best at the same closest point (at a shared edge or
        # vertex); a point as far from two faces apart (inside a thin plate) takes the first
        same = np.linalg.norm(q - point[rows], axis=1) <= 1e-9 * max(self.longest_edge, 1e-300)
        tie = np.flatnonzero((d <= best[rows] * (1 + 1e-9) + 1e-12) & same)
        at_corner = np.linalg.norm(corners[tie] - q[tie, None, :], axis=2)  # (ties, 3)
        j = np.argmin(at_corner, axis=1)
        on_vertex = at_corner[np.arange(len(tie)), j] <= 1e-9 * max(self.longest_edge, 1e-300)
        weight = np.where(on_vertex, self.corner_angle[tris[tie], j], np.pi)
        normals = np.zeros((len(p), 3))
        for c in range(3):
            normals[:, c] = np.bincount(
                rows[tie], weight * self.normal[tris[tie], c], minlength=len(p)
            )
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
        return best, point, normals


class DistanceMemo:
    """Signed distances to one bone surface already measured at some points of its rest
    frame, so that a point provably farther outside than a threshold is not measured again.

    The signed distance changes by at most as much as the point moves (it is 1-Lipschitz), so
    a point measured ``d`` outside and moved by ``m`` since is still at least ``d - m``
    outside. The solvers ask for the planes of thousands of nodes before every round, while
    most of them lie centimetres from every bone but the nearest (on the 20k demo at 90 deg a
    call took 0.1 s, a fifth of the export's time, nearly all of it for nodes that get no
    plane). A skipped point is one the full query would also have put beyond the threshold,
    so the planes are the same.

    Parameters
    ----------
    surface : BoneSurfaceDistance
    where : (K, 3) ndarray
        Points (rest frame) whose distance is known.
    depth, node_distance : (K,) ndarray
        Their signed distances and nearest-node distances, as :meth:`BoneSurfaceDistance.query`
        gave them.
    """

    def __init__(
        self,
        surface: BoneSurfaceDistance,
        where: NDArray[np.float64],
        depth: NDArray[np.float64],
        node_distance: NDArray[np.float64],
    ) -> None:
        self.surface = surface
        self.where = np.array(where, dtype=np.float64, copy=True)
        self.depth = surface.certain(np.asarray(depth, dtype=np.float64), node_distance)

    def query(
        self,
        rows: NDArray[np.int64],
        p: NDArray[np.float64],
        beyond: float,
        cancel: Callable[[], bool] | None = None,
    ) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Points ``p`` (M, 3) in the rest frame, memo slots ``rows`` (M,): signed distance,
        closest point and normal as :meth:`BoneSurfaceDistance.query` where measured; where
        not, a lower bound of the distance above ``beyond`` and NaN point and normal. The
        fourth output marks the measured points (their slots are updated). ``cancel`` is passed
        to the measure (asked between its waves of points)."""
        moved = np.linalg.norm(p - self.where[rows], axis=1)
        depth = self.depth[rows] - moved
        measured = ~(depth > beyond)
        point = np.full_like(p, np.nan)
        normal = np.full_like(p, np.nan)
        if measured.any():
            d, q, n, node_distance = self.surface.query(p[measured], cancel=cancel)
            depth[measured], point[measured], normal[measured] = d, q, n
            self.where[rows[measured]] = p[measured]
            # a far point's measured distance may be more than the exact one: the bound the
            # next queries rest on must not be
            self.depth[rows[measured]] = self.surface.certain(d, node_distance)
        return depth, point, normal, measured


@dataclass
class _Surface:
    segment: str
    distance: BoneSurfaceDistance
    floor: NDArray[np.float64]  # (C,) clearance each candidate keeps from this bone
    rows: NDArray[np.int64]  # the candidates with a finite floor (the others never touch it)


class BoneContact:
    """Precomputed contact of soft tissue with the bones.

    Parameters
    ----------
    coords : (N, 3) ndarray
        Initial coordinates.
    bone_surfaces : mapping of segment name to BoneSurfaceDistance
        Rest surface of each rigid segment (shared with the relaxation and the overlap check).
    soft : (S,) ndarray of int
        Soft-tissue nodes that move by mapping.
    edges : (E, 2) ndarray of int
        Soft-tissue mesh edges (for the smooth extension of the pushes).
    reach : float
        Soft nodes closer than this to a bone at rest are kept out of it.
    clearance : float
        The largest rest clearance a candidate is held to (closer than this is allowed only if
        it was closer at rest).
    ray_depth : (float, float), optional
        Depths (model units) between which the place a pushed node leaves the bone changes from
        the nearest surface point to the point where the segment from the node back to its rest
        place (in that bone's frame) leaves the bone. Default: always the nearest point.
    cancel : callable, optional
        Asked between the set-up's steps; True raises :class:`kneegui.errors.Cancelled`.
    """

    def __init__(
        self,
        coords,
        bone_surfaces,
        soft,
        edges,
        reach: float,
        clearance: float,
        ray_depth: tuple[float, float] | None = None,
        cancel: Callable[[], bool] | None = None,
    ):
        self.reach = reach
        self.ray_depth = ray_depth
        self.rest = np.asarray(coords, dtype=np.float64)
        soft = np.asarray(soft, dtype=np.int64)
        near = np.zeros(len(soft), dtype=bool)
        distances = []
        for segment, distance in bone_surfaces.items():
            raise_if_cancelled(cancel, "bone contact set-up cancelled")
            # every soft node of a whole-body model: seconds per bone on one thread
            d, _ = distance.tree.query(coords[soft], distance_upper_bound=reach, workers=-1)
            found = np.isfinite(d)
            near |= found
            distances.append((segment, distance, found))
        self.candidates = soft[near]
        self.surfaces: list[_Surface] = []
        for segment, distance, found in distances:
            raise_if_cancelled(cancel, "bone contact set-up cancelled")
            # a candidate with no surface node of this bone within reach keeps no clearance from
            # it: measured only where one is (each point is measured on its own, so the values
            # are those of measuring every candidate)
            rows = np.flatnonzero(found[near])
            depth, _, _, node_distance = distance.query(coords[self.candidates[rows]])
            close = node_distance < reach
            floor = np.full(len(self.candidates), -np.inf)
            floor[rows] = np.where(close & (depth >= 0), np.minimum(depth, clearance), -np.inf)
            kept = np.flatnonzero(np.isfinite(floor))
            self.surfaces.append(_Surface(segment, distance, floor, kept))
        raise_if_cancelled(cancel, "bone contact set-up cancelled")
        # Laplacian extension: candidates and non-soft nodes are held, the other soft nodes free
        free = soft[~near]
        n_all = len(coords)
        pos = np.full(n_all, -1, dtype=np.int64)
        pos[free] = np.arange(len(free))
        cpos = np.full(n_all, -1, dtype=np.int64)
        cpos[self.candidates] = np.arange(len(self.candidates))
        a, b = edges[:, 0], edges[:, 1]
        length2 = np.maximum(np.sum((coords[a] - coords[b]) ** 2, axis=1), 1e-12)
        w = 1.0 / length2
        rows, cols, vals, crow, ccol, cval = [], [], [], [], [], []
        deg = np.zeros(len(free))
        for u, v in ((a, b), (b, a)):
            fu = pos[u] >= 0
            np.add.at(deg, pos[u[fu]], w[fu])
            both = fu & (pos[v] >= 0)
            rows.append(pos[u[both]]), cols.append(pos[v[both]]), vals.append(-w[both])
            to_c = fu & (cpos[v] >= 0)
            crow.append(pos[u[to_c]]), ccol.append(cpos[v[to_c]]), cval.append(w[to_c])
        self.free = free
        if len(free):
            lap = sp.csr_matrix(
                (
                    np.concatenate([*vals, deg + 1e-9 * max(deg.mean(), 1e-30)]),
                    (
                        np.concatenate([*rows, np.arange(len(free))]),
                        np.concatenate([*cols, np.arange(len(free))]),
                    ),
                ),
                shape=(len(free), len(free)),
            )
            if len(free) <= DIRECT_SOLVE_MAX:
                lu = spla.splu(lap.tocsc())

                def direct(rhs: NDArray[np.float64], cancel=None) -> NDArray[np.float64]:
                    return lu.solve(rhs)  # one call of a fraction of a second: nothing to ask

                self._solve = direct
            else:
                # a whole-body model's soft tissue: an LU grows super-linearly (time and memory);
                # the pushes are local, so solve only around them
                self._solve = LocalLaplaceSolve(lap)
            self._coupling = sp.csr_matrix(
                (np.concatenate(cval), (np.concatenate(crow), np.concatenate(ccol))),
                shape=(len(free), len(self.candidates)),
            )

    def _ray_target(self, srf, local, rows, depth, nearest):
        """Deep nodes go back towards their rest place along the way they came, where they
        leave the bone (their neighbours then leave it at neighbouring places); shallow ones
        to the nearest surface point; blended between the two depths of ``ray_depth``."""
        lo, hi = self.ray_depth
        rest = self.rest[self.candidates[rows]]
        floor = srf.floor[rows]
        a, b = np.zeros(len(rows)), np.ones(len(rows))
        for _ in range(14):
            mid = 0.5 * (a + b)
            d = srf.distance.query(local + mid[:, None] * (rest - local))[0]
            out = d >= floor
            b = np.where(out, mid, b)
            a = np.where(out, a, mid)
        ray = local + b[:, None] * (rest - local)
        s = np.clip((-depth - lo) / max(hi - lo, 1e-12), 0.0, 1.0)[:, None]
        return (1.0 - s) * nearest + s * ray

    def resolve(
        self,
        positions: NDArray[np.float64],
        transforms: Mapping[str, RigidTransform],
        cancel: Callable[[], bool] | None = None,
    ) -> int:
        """Push candidates that came closer to a bone than allowed back out, spread the push
        smoothly into the free soft tissue; in place. Returns the number of nodes pushed.
        ``cancel()`` is asked before and during each bone's measure (True raises
        :class:`kneegui.errors.Cancelled`, nothing moved) and during the spreading's solve on
        a whole-body model (``positions`` then partly moved)."""
        if len(self.candidates) == 0:
            return 0
        p = positions[self.candidates]
        push = np.zeros_like(p)
        for srf in self.surfaces:
            raise_if_cancelled(cancel, "export cancelled while pushing tissue out of the bones")
            if len(srf.rows) == 0:
                continue
            t = transforms[srf.segment]
            # every candidate transformed together, as before (a matrix product over another
            # number of rows may round differently); only those with a floor for this bone can
            # be pushed out of it, so only they are measured
            local = t.inverse().apply(p + push)
            depth = np.full(len(p), np.inf)
            q = np.zeros_like(p)
            measured, q[srf.rows], _, node_distance = srf.distance.query(
                local[srf.rows], cancel=cancel
            )
            depth[srf.rows] = measured
            bad = np.zeros(len(p), dtype=bool)
            bad[srf.rows] = (node_distance < self.reach) & (measured < srf.floor[srf.rows])
            if bad.any():
                direction = local[bad] - q[bad]
                norm = np.linalg.norm(direction, axis=1, keepdims=True)
                # behind the surface the closest-point direction points inwards: flip it
                direction = np.where(norm > 1e-12, direction / np.maximum(norm, 1e-300), 0.0)
                direction *= np.sign(depth[bad])[:, None]
                target = q[bad] + srf.floor[bad][:, None] * direction
                if self.ray_depth is not None:
                    target = self._ray_target(
                        srf, local[bad], np.flatnonzero(bad), depth[bad], target
                    )
                push[bad] += t.apply_vector(target - local[bad])
        moved = np.flatnonzero(np.linalg.norm(push, axis=1) > 0)
        if len(moved) == 0:
            return 0
        positions[self.candidates] = p + push
        if len(self.free):
            positions[self.free] += self._solve(self._coupling @ push, cancel)
        return len(moved)


class LocalLaplaceSolve:
    """``solve(rhs)`` for a sparse Laplacian whose right-hand side is non-zero near a few nodes
    (the pushes of the bone contact): conjugate gradients on the nodes within ``hops`` mesh
    edges of them, zero beyond, with ``hops`` doubled until the solution at the edge of that
    region is below ``tolerance`` times its largest value (or the region is everything).

    The soft tissue lies between the bones (held) and the skin, so a push fades within a few
    tissue thicknesses: the knee's pushes never reach the rest of a whole-body model, and its
    nodes are not read.

    Parameters
    ----------
    matrix : (n, n) sparse matrix
        Symmetric positive definite, with the mesh's adjacency as its pattern.
    hops : int
        Initial reach of the region (mesh edges).
    tolerance : float
        Relative size of the solution allowed at the region's edge.
    """

    def __init__(self, matrix: sp.spmatrix, hops: int = 16, tolerance: float = 1e-7) -> None:
        self.matrix = sp.csr_matrix(matrix)
        self.inv_diag = 1.0 / self.matrix.diagonal()
        self.hops = hops
        self.tolerance = tolerance
        self.last_region = 0  # nodes the last solve worked on

    def _grow(self, mask: NDArray[np.bool_], frontier: NDArray[np.int64], hops: int) -> None:
        ptr, idx = self.matrix.indptr, self.matrix.indices
        for _ in range(hops):
            if len(frontier) == 0:
                return
            counts = ptr[frontier + 1] - ptr[frontier]
            starts = np.repeat(ptr[frontier] - np.cumsum(counts) + counts, counts)
            nbrs = idx[starts + np.arange(int(counts.sum()))]
            nbrs = sorted_unique(nbrs[~mask[nbrs]])
            mask[nbrs] = True
            frontier = nbrs

    def __call__(
        self, rhs: NDArray[np.float64], cancel: Callable[[], bool] | None = None
    ) -> NDArray[np.float64]:
        """The solution (n, k) of ``matrix @ x = rhs`` (``cancel`` as for :func:`block_cg`)."""
        n = self.matrix.shape[0]
        rhs = np.asarray(rhs, dtype=np.float64).reshape(n, -1)
        out = np.zeros_like(rhs)
        seeds = np.flatnonzero(np.any(rhs != 0, axis=1))
        if len(seeds) == 0:
            return out
        hops = self.hops
        while True:
            mask = np.zeros(n, dtype=bool)
            mask[seeds] = True
            self._grow(mask, seeds, hops)
            region = np.flatnonzero(mask)
            sub = self.matrix[region][:, region]
            x = block_cg(
                sub,
                rhs[region],
                np.zeros((len(region), rhs.shape[1])),
                self.inv_diag[region],
                rtol=1e-10,
                cancel=cancel,
            )
            if len(region) == n:
                break
            # the region's edge: nodes with a neighbour outside it
            outside = (~mask).astype(np.float64)
            edge = (self.matrix[region] @ outside) != 0
            if np.abs(x[edge]).max(initial=0.0) <= self.tolerance * np.abs(x).max(initial=0.0):
                break
            hops *= 2
        out[region] = x
        self.last_region = len(region)
        return out


class BoneDepthGuard:
    """Position guard for the smoother: no soft-tissue node goes deeper into a bone than it is.

    A node outside every bone in the pose being smoothed must stay outside; a node already inside
    one (the pose put it there) may not go deeper. Used as ``position_guard`` of
    :func:`kneegui.meshopt.smooth_mesh`: the smoother then only keeps moves that respect it, so
    smoothing can no longer buy a better Jacobian by pushing tissue into a bone.

    Parameters
    ----------
    surfaces : mapping of segment name to BoneSurfaceDistance
        Rest surface of each rigid segment.
    transforms : mapping of segment name to RigidTransform
        The bones' pose (segments without a transform are ignored).
    start_coords : (N, 3) ndarray
        All node coordinates of the pose before smoothing.
    """

    def __init__(
        self,
        surfaces: Mapping[str, BoneSurfaceDistance],
        transforms: Mapping[str, RigidTransform],
        start_coords: NDArray[np.float64],
    ) -> None:
        self.segments = [name for name in surfaces if name in transforms]
        self._bones = [(surfaces[name], transforms[name].inverse()) for name in self.segments]
        self.start = np.array(start_coords, dtype=np.float64, copy=True)
        # each node's smallest signed distance to a bone at the start, measured on first use
        self._start_depth = np.full((len(self.start), len(self._bones)), np.nan)

    def depths(self, nodes: NDArray[np.int64], coords: NDArray[np.float64]) -> NDArray:
        """Signed distances (len(nodes), bones) of ``coords`` (one row per node)."""
        out = np.empty((len(nodes), len(self._bones)))
        for j, (surface, to_rest) in enumerate(self._bones):
            out[:, j] = surface.query(to_rest.apply(coords))[0]
        return out

    def start_depth(self, nodes: NDArray[np.int64]) -> NDArray[np.float64]:
        """(len(nodes), bones) signed distances of the nodes at the start (+ outside)."""
        nodes = np.asarray(nodes, dtype=np.int64)
        todo = sorted_unique(nodes[np.isnan(self._start_depth[nodes, 0])]) if self._bones else []
        if len(todo):
            self._start_depth[todo] = self.depths(todo, self.start[todo])
        return self._start_depth[nodes]

    def __call__(self, nodes: NDArray[np.int64], coords: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which of ``nodes`` may sit where ``coords`` (all nodes, trial positions) puts them."""
        nodes = np.asarray(nodes, dtype=np.int64)
        ok = np.ones(len(nodes), dtype=bool)
        if not self._bones or len(nodes) == 0:
            return ok
        start = self.start_depth(nodes)
        # a distance changes no faster than the point moves: a node that moved less than its
        # clearance from every bone is still outside (no query needed)
        moved = np.linalg.norm(coords[nodes] - self.start[nodes], axis=1)
        check = np.flatnonzero(moved >= start.min(axis=1))
        if len(check):
            now = self.depths(nodes[check], coords[nodes[check]])
            ok[check] = (now >= np.minimum(start[check], 0.0) - 1e-9).all(axis=1)
        return ok
