"""Exact closest points on a triangulated surface, through a uniform grid of its triangles.

:class:`~kneegui.reposition.contact.BoneSurfaceDistance` measures most points against the fan of
triangles around the nearest surface node, which is cheap but not always the closest triangle
(among long, thin triangles, or where a segment's surface is several closed ones). The points
that must be exact are measured here: every triangle is listed in the grid cells its bounding
box overlaps, and each point searches the cells in rings of growing distance until no cell
farther out can hold a nearer triangle. The search is compiled, one point at a time (the
caller's threads share the points out); each point's result is worked out on its own, so it
does not depend on the thread count, and it is the same arithmetic as the NumPy path of
:meth:`~kneegui.reposition.contact.BoneSurfaceDistance._closest` (tested to the bit).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

#: The grid has at most this many cells per triangle (the cell size grows to keep to it).
CELLS_PER_TRIANGLE = 4
#: Relative and absolute slack within which two distances count as the same (a tie: the
#: pseudo-normal sums the normals of every tied triangle), as in ``BoneSurfaceDistance``.
TIE_RELATIVE, TIE_ABSOLUTE = 1e-9, 1e-12
#: Triangles within reach one point keeps as candidates for the ties (when full, those out of
#: reach of the best so far are dropped first).
MAX_CANDIDATES = 256


class TriangleGrid:
    """Triangles ``tri_xyz`` (T, 3, 3) in a uniform grid of cells about the size of a
    triangle's bounding box (at most :data:`CELLS_PER_TRIANGLE` cells per triangle).

    Parameters
    ----------
    tri_xyz : (T, 3, 3) ndarray
    normal : (T, 3) ndarray
        Unit normals of the triangles.
    corner_angle : (T, 3) ndarray
        Each triangle's angle at each corner (the pseudo-normal's weights at a vertex).
    longest_edge : float
        The longest edge of any triangle (the scale of "at a vertex").
    """

    def __init__(
        self,
        tri_xyz: NDArray[np.float64],
        normal: NDArray[np.float64],
        corner_angle: NDArray[np.float64],
        longest_edge: float,
    ) -> None:
        self.tri_xyz = np.ascontiguousarray(tri_xyz, dtype=np.float64)
        self.normal = np.ascontiguousarray(normal, dtype=np.float64)
        self.corner_angle = np.ascontiguousarray(corner_angle, dtype=np.float64)
        self.vertex_tolerance = 1e-9 * max(longest_edge, 1e-300)
        t_lo, t_hi = self.tri_xyz.min(axis=1), self.tri_xyz.max(axis=1)
        self.boxes = np.ascontiguousarray(np.concatenate([t_lo, t_hi], axis=1))
        self.lo = t_lo.min(axis=0)
        span = np.maximum(t_hi.max(axis=0) - self.lo, 1e-12)
        typical = float(np.median((t_hi - t_lo).max(axis=1))) if len(t_lo) else 1.0
        # no more cells than CELLS_PER_TRIANGLE per triangle: a flat, elongated surface would
        # otherwise ask for a grid of mostly empty cells
        volume_cell = float(np.prod(span)) / max(CELLS_PER_TRIANGLE * len(t_lo), 1)
        self.cell = max(typical, volume_cell ** (1.0 / 3.0), 1e-12)
        self.dims = np.maximum(np.ceil(span / self.cell).astype(np.int64), 1)
        first = _cell_of(t_lo, self.lo, self.cell, self.dims)
        last = _cell_of(t_hi, self.lo, self.cell, self.dims)
        self.start, self.items = _fill_grid(first, last, self.dims)

    def closest(
        self, p: NDArray[np.float64], bound: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Distance (M,), closest point (M, 3) and unit pseudo-normal (M, 3) of each point
        ``p`` (M, 3) on the surface, given an upper bound (M,) of each distance (the search
        stops there; a point with no triangle within it gets ``inf``)."""
        p = np.ascontiguousarray(p, dtype=np.float64)
        best = np.empty(len(p))
        point = np.empty((len(p), 3))
        normal = np.empty((len(p), 3))
        _grid_closest(
            p,
            np.ascontiguousarray(bound, dtype=np.float64),
            self.tri_xyz,
            self.boxes,
            self.normal,
            self.corner_angle,
            self.vertex_tolerance,
            self.lo,
            self.cell,
            self.dims,
            self.start,
            self.items,
            best,
            point,
            normal,
        )
        return best, point, normal


def _cell_of(
    x: NDArray[np.float64], lo: NDArray[np.float64], cell: float, dims: NDArray[np.int64]
) -> NDArray[np.int64]:
    return np.clip(np.floor((x - lo) / cell).astype(np.int64), 0, dims - 1)


def _fill_grid(
    first: NDArray[np.int64], last: NDArray[np.int64], dims: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """CSR lists of the triangles whose bounding box overlaps each cell (in triangle order).
    NumPy, not compiled: loading a compiled function from the cache costs more than this
    takes for a bone's triangles."""
    size = last - first + 1  # (T, 3) cells along each axis
    count = size.prod(axis=1)
    owner = np.repeat(np.arange(len(first)), count)
    rank = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    nj, nk = size[owner, 1], size[owner, 2]
    i = first[owner, 0] + rank // (nj * nk)
    j = first[owner, 1] + (rank // nk) % nj
    k = first[owner, 2] + rank % nk
    cell = (i * dims[1] + j) * dims[2] + k
    order = np.argsort(cell, kind="stable")
    start = np.zeros(int(np.prod(dims)) + 1, dtype=np.int64)
    np.cumsum(np.bincount(cell, minlength=int(np.prod(dims))), out=start[1:])
    return start, owner[order]


@njit(cache=True, nogil=True, inline="always")
def _unit_clip(t):  # pragma: no cover - compiled
    if t != t:
        return 0.0
    return min(max(t, 0.0), 1.0)


@njit(cache=True, nogil=True, inline="always")
def _box_gap(px, py, pz, x0, y0, z0, x1, y1, z1):  # pragma: no cover - compiled
    """Distance from a point to an axis-aligned box (0 inside)."""
    dx = max(x0 - px, 0.0, px - x1)
    dy = max(y0 - py, 0.0, py - y1)
    dz = max(z0 - pz, 0.0, pz - z1)
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True, nogil=True, error_model="numpy")
def _closest_on_triangle(px, py, pz, tri, t):  # pragma: no cover - compiled
    """The closest point of triangle ``t`` to ``(px, py, pz)``: the arithmetic of
    :func:`kneegui.reposition.contact.closest_on_triangles`, for one pair (a degenerate
    triangle's 0 / 0 is NaN, clipped to 0, as there)."""
    ax, ay, az = tri[t, 0, 0], tri[t, 0, 1], tri[t, 0, 2]
    bx, by, bz = tri[t, 1, 0], tri[t, 1, 1], tri[t, 1, 2]
    cx, cy, cz = tri[t, 2, 0], tri[t, 2, 1], tri[t, 2, 2]
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d1 = 0.0 + abx * apx + aby * apy + abz * apz
    d2 = 0.0 + acx * apx + acy * apy + acz * apz
    d3 = 0.0 + abx * bpx + aby * bpy + abz * bpz
    d4 = 0.0 + acx * bpx + acy * bpy + acz * bpz
    d5 = 0.0 + abx * cpx + aby * cpy + abz * cpz
    d6 = 0.0 + acx * cpx + acy * cpy + acz * cpz
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    if d6 >= 0 and d5 <= d6:
        return cx, cy, cz
    if d3 >= 0 and d4 <= d3:
        return bx, by, bz
    if d1 <= 0 and d2 <= 0:
        return ax, ay, az
    if va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
        s = _unit_clip((d4 - d3) / ((d4 - d3) + (d5 - d6)))
        return bx + s * (cx - bx), by + s * (cy - by), bz + s * (cz - bz)
    if vb <= 0 and d2 >= 0 and d6 <= 0:
        s = _unit_clip(d2 / (d2 - d6))
        return ax + s * acx, ay + s * acy, az + s * acz
    if vc <= 0 and d1 >= 0 and d3 <= 0:
        s = _unit_clip(d1 / (d1 - d3))
        return ax + s * abx, ay + s * aby, az + s * abz
    total = va + vb + vc
    if total == 0:
        total = 1.0
    v = vb / total
    w = vc / total
    return ax + v * abx + w * acx, ay + v * aby + w * acy, az + v * abz + w * acz


@njit(cache=True, nogil=True, error_model="numpy")
def _grid_closest(
    p,
    bound,
    tri,
    boxes,
    tri_normal,
    corner_angle,
    vertex_tolerance,
    lo,
    cell,
    dims,
    start,
    items,
    best_out,
    point_out,
    normal_out,
):  # pragma: no cover - compiled
    """:meth:`TriangleGrid.closest`: for each point, the cells in Chebyshev rings around its
    (clamped) cell until the next ring lies farther than the best distance found (a cell ``R``
    rings out is at least ``R - 1`` cells away). Every triangle measured within the slack of
    the best so far is kept as a candidate: the best only shrinks, so the ties of the final
    best (as near, at the same closest point) are among them."""
    cand_t = np.empty(MAX_CANDIDATES, dtype=np.int64)
    cand_q = np.empty((MAX_CANDIDATES, 3))
    cand_d = np.empty(MAX_CANDIDATES)
    for m in range(p.shape[0]):
        px, py, pz = p[m, 0], p[m, 1], p[m, 2]
        ci = min(max(math.floor((px - lo[0]) / cell), 0), dims[0] - 1)
        cj = min(max(math.floor((py - lo[1]) / cell), 0), dims[1] - 1)
        ck = min(max(math.floor((pz - lo[2]) / cell), 0), dims[2] - 1)
        cutoff = bound[m] * (1.0 + TIE_RELATIVE) + TIE_ABSOLUTE
        widest = max(dims[0], max(dims[1], dims[2]))
        best = math.inf
        best_t = -1
        qx = qy = qz = math.nan
        n_cand = 0
        reach = cutoff
        for r in range(widest + 1):
            # a tie may be up to the tie slack farther than the best
            if r >= 1 and (r - 1) * cell > reach:
                break
            for i in range(max(ci - r, 0), min(ci + r, dims[0] - 1) + 1):
                for j in range(max(cj - r, 0), min(cj + r, dims[1] - 1) + 1):
                    inner = abs(i - ci) < r and abs(j - cj) < r
                    k = max(ck - r, 0)
                    while k <= min(ck + r, dims[2] - 1):
                        if inner and abs(k - ck) < r:
                            k = ck + r  # only the ring's two faces along k
                            continue
                        c = (i * dims[1] + j) * dims[2] + k
                        x0, y0, z0 = lo[0] + i * cell, lo[1] + j * cell, lo[2] + k * cell
                        if (
                            _box_gap(px, py, pz, x0, y0, z0, x0 + cell, y0 + cell, z0 + cell)
                            > reach
                        ):
                            k += 1
                            continue
                        for s in range(start[c], start[c + 1]):
                            t = items[s]
                            b = boxes[t]
                            if _box_gap(px, py, pz, b[0], b[1], b[2], b[3], b[4], b[5]) > reach:
                                continue
                            x, y, z = _closest_on_triangle(px, py, pz, tri, t)
                            dx, dy, dz = px - x, py - y, pz - z
                            d = math.sqrt(dx * dx + dy * dy + dz * dz)
                            if d > reach:
                                continue
                            if d < best or (d == best and t < best_t):
                                best, best_t = d, t
                                qx, qy, qz = x, y, z
                                reach = min(best * (1.0 + TIE_RELATIVE) + TIE_ABSOLUTE, cutoff)
                            if n_cand == MAX_CANDIDATES:  # drop those now out of reach
                                kept = 0
                                for u in range(n_cand):
                                    if cand_d[u] <= reach:
                                        cand_t[kept], cand_d[kept] = cand_t[u], cand_d[u]
                                        cand_q[kept] = cand_q[u]
                                        kept += 1
                                n_cand = kept
                            if n_cand < MAX_CANDIDATES:
                                cand_t[n_cand], cand_d[n_cand] = t, d
                                cand_q[n_cand, 0], cand_q[n_cand, 1] = x, y
                                cand_q[n_cand, 2] = z
                                n_cand += 1
                        k += 1
        best_out[m] = best
        point_out[m, 0], point_out[m, 1], point_out[m, 2] = qx, qy, qz
        # the ties, each triangle once, their normals summed in triangle order
        limit = best * (1.0 + TIE_RELATIVE) + TIE_ABSOLUTE
        ties = np.empty(n_cand, dtype=np.int64)
        weights = np.empty(n_cand)
        n_ties = 0
        for u in range(n_cand):
            t = cand_t[u]
            if cand_d[u] > limit:
                continue
            x, y, z = cand_q[u, 0], cand_q[u, 1], cand_q[u, 2]
            # at the same closest point (a shared edge or vertex) only
            sx, sy, sz = x - qx, y - qy, z - qz
            if math.sqrt(sx * sx + sy * sy + sz * sz) > vertex_tolerance:
                continue
            seen = False
            for v in range(n_ties):
                if ties[v] == t:
                    seen = True
                    break
            if seen:  # listed in several cells
                continue
            # at a corner: that corner's angle, else pi (as _closest)
            nearest, at = math.inf, 0
            for v in range(3):
                ex = tri[t, v, 0] - x
                ey = tri[t, v, 1] - y
                ez = tri[t, v, 2] - z
                e = math.sqrt(ex * ex + ey * ey + ez * ez)
                if e < nearest:
                    nearest, at = e, v
            ties[n_ties] = t
            weights[n_ties] = corner_angle[t, at] if nearest <= vertex_tolerance else math.pi
            n_ties += 1
        order = np.argsort(ties[:n_ties])
        nx = ny = nz = 0.0
        for u in range(n_ties):
            t = ties[order[u]]
            w = weights[order[u]]
            nx += w * tri_normal[t, 0]
            ny += w * tri_normal[t, 1]
            nz += w * tri_normal[t, 2]
        length = max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-300)
        normal_out[m, 0], normal_out[m, 1], normal_out[m, 2] = nx / length, ny / length, nz / length
