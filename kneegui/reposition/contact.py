"""Bone contact: soft tissue slides on the bones but never enters them (penetration fixing).

The rigid blend rotates tissue about the F-E axis; where a bone's surface is not a circle about
that axis, tissue lying on it would be carried into the bone. Candidates are the soft-tissue nodes
within ``reach`` of a bone surface in the initial pose. For a pose, each candidate is expressed in
each bone's initial frame, its closest point on that bone's surface is found exactly (among the
triangles around the nearest surface node), and if it is closer to the surface than it was at rest
(up to ``clearance``) it is pushed out along the surface normal. The pushes are then extended
smoothly into the other soft-tissue nodes by a Laplace solve (factorised once), so the tissue
behind a pushed node moves with it instead of being crushed: the paper's "local stretching".
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from kneegui.geometry.transforms import RigidTransform


@dataclass
class _Surface:
    segment: str
    tri_xyz: NDArray[np.float64]  # (T, 3, 3) initial pose, outward-oriented
    tri_normal: NDArray[np.float64]  # (T, 3) unit outward normals
    node_xyz: NDArray[np.float64]  # (S, 3) surface nodes
    node_tris: NDArray[np.int64]  # (S, K) incident triangles, -1 padded
    tree: cKDTree
    floor: NDArray[np.float64]  # (C,) clearance each candidate keeps from this bone


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


def closest_on_triangles(p, tri):
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


class BoneContact:
    """Precomputed contact of soft tissue with the bones.

    Parameters
    ----------
    coords : (N, 3) ndarray
        Initial coordinates.
    bone_triangles : mapping of segment name to (T, 3) ndarray of int
        Outward-oriented outer surface triangles of each rigid segment.
    soft : (S,) ndarray of int
        Soft-tissue nodes that move by mapping.
    edges : (E, 2) ndarray of int
        Soft-tissue mesh edges (for the smooth extension of the pushes).
    reach : float
        Soft nodes closer than this to a bone at rest are kept out of it.
    clearance : float
        The largest rest clearance a candidate is held to (closer than this is allowed only if
        it was closer at rest).
    """

    def __init__(self, coords, bone_triangles, soft, edges, reach: float, clearance: float):
        self.reach = reach
        soft = np.asarray(soft, dtype=np.int64)
        raw = []
        near = np.zeros(len(soft), dtype=bool)
        for segment, tris in bone_triangles.items():
            if len(tris) == 0:
                continue
            nodes = np.unique(tris)
            tree = cKDTree(coords[nodes])
            d, _ = tree.query(coords[soft], distance_upper_bound=reach)
            near |= np.isfinite(d)
            txyz = coords[tris]
            n = np.cross(txyz[:, 1] - txyz[:, 0], txyz[:, 2] - txyz[:, 0])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
            raw.append((segment, txyz, n, coords[nodes], _incident(tris, nodes), tree))
        self.candidates = soft[near]
        self.surfaces: list[_Surface] = []
        for segment, txyz, n, nxyz, table, tree in raw:
            depth, _, close = self._signed_distance(
                coords[self.candidates], txyz, n, nxyz, table, tree
            )
            floor = np.where(close & (depth >= 0), np.minimum(depth, clearance), -np.inf)
            self.surfaces.append(_Surface(segment, txyz, n, nxyz, table, tree, floor))
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
            self._solve = spla.splu(lap.tocsc()).solve
            self._coupling = sp.csr_matrix(
                (np.concatenate(cval), (np.concatenate(crow), np.concatenate(ccol))),
                shape=(len(free), len(self.candidates)),
            )

    def _signed_distance(self, p, txyz, tn, nxyz, table, tree):
        """Signed distance to the surface (+ outside), closest point, and "near a bone"."""
        dist, k = tree.query(p)
        tris = table[k]  # (M, K) triangles around the nearest surface node
        m, width = tris.shape
        d_all = np.full((m, width), np.inf)
        q_all = np.zeros((m, width, 3))
        for j in range(width):
            t = tris[:, j]
            ok = t >= 0
            if ok.any():
                q_all[ok, j] = closest_on_triangles(p[ok], txyz[t[ok]])
                d_all[ok, j] = np.linalg.norm(p[ok] - q_all[ok, j], axis=1)
        j_best = np.argmin(d_all, axis=1)
        rows = np.arange(m)
        best = d_all[rows, j_best]
        point = q_all[rows, j_best]
        # sign from the pseudo-normal: the mean normal of every triangle as close as the best
        # (at a shared edge or vertex one face's normal alone can give the wrong side)
        tie = d_all <= best[:, None] * (1 + 1e-9) + 1e-12
        normals = np.where((tie & (tris >= 0))[..., None], tn[np.maximum(tris, 0)], 0.0).sum(1)
        side = np.einsum("ij,ij->i", p - point, normals)
        sign = np.where(side < 0, -1.0, 1.0)
        return sign * best, point, dist < self.reach

    def resolve(
        self, positions: NDArray[np.float64], transforms: Mapping[str, RigidTransform]
    ) -> int:
        """Push candidates that came closer to a bone than allowed back out, spread the push
        smoothly into the free soft tissue; in place. Returns the number of nodes pushed."""
        if len(self.candidates) == 0:
            return 0
        p = positions[self.candidates]
        push = np.zeros_like(p)
        for srf in self.surfaces:
            t = transforms[srf.segment]
            local = t.inverse().apply(p + push)
            depth, q, close = self._signed_distance(
                local, srf.tri_xyz, srf.tri_normal, srf.node_xyz, srf.node_tris, srf.tree
            )
            bad = close & (depth < srf.floor)
            if bad.any():
                direction = local[bad] - q[bad]
                norm = np.linalg.norm(direction, axis=1, keepdims=True)
                # behind the surface the closest-point direction points inwards: flip it
                direction = np.where(norm > 1e-12, direction / np.maximum(norm, 1e-300), 0.0)
                direction *= np.sign(depth[bad])[:, None]
                target = q[bad] + srf.floor[bad][:, None] * direction
                push[bad] += t.apply_vector(target - local[bad])
        moved = np.flatnonzero(np.linalg.norm(push, axis=1) > 0)
        if len(moved) == 0:
            return 0
        positions[self.candidates] = p + push
        if len(self.free):
            positions[self.free] += self._solve(self._coupling @ push)
        return len(moved)
