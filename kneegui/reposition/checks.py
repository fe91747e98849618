"""Geometric checks of a pose: tissue inside the skin and outside the bones.

Inside-ness is decided by ray casting: a ray from the point crosses a closed surface an odd number
of times if and only if the point is inside. The skin of a limb model is a tube open at its cut
ends; a ray along the medial-lateral direction (perpendicular to the limb) still crosses it an odd
number of times from inside.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from kneegui.model import Model
from kneegui.topology import boundary_faces


def surface_triangles(model: Model, part_ids: Iterable[int], shells: bool = True) -> NDArray:
    """(T, 3) node-index triangles of the outer surface of the given parts' solids (faces used
    once, outward), plus their shells when ``shells`` is true."""
    wanted = sorted(set(int(p) for p in part_ids))
    quads, tris = boundary_faces(model.blocks, wanted)
    quad_list, tri_list = [quads], [tris]
    if shells:
        for etype, group in (("quad4", quad_list), ("tri3", tri_list)):
            block = model.blocks.get(etype)
            if block is not None:
                group.append(block.conn[np.isin(block.part_ids, wanted)])
    quads, tris = np.concatenate(quad_list), np.concatenate(tri_list)
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]], tris]).astype(np.int64)


#: The rays' direction is perturbed by this so that they do not graze edges.
RAY_PERTURBATION = np.array([1.3e-4, -2.7e-4, 3.1e-4])


def crossings_along_ray(
    points: NDArray[np.float64],
    triangles: NDArray[np.float64],
    direction: NDArray[np.float64],
    chunk: int = 256,
) -> NDArray[np.int64]:
    """How many triangles the ray ``point + t * direction`` (t > 0) crosses, per point.

    The points and triangles are first binned on a grid across the ray (a ray can only cross
    a triangle whose shadow along it covers the point), so each point is tested against the
    triangles of its bin only: the same counts as testing every triangle, in a fraction of
    the time on a bone surface of thousands of triangles.

    Parameters
    ----------
    points : (P, 3) ndarray
    triangles : (T, 3, 3) ndarray
        Triangle vertex coordinates.
    direction : (3,) ndarray
        Ray direction (perturbed slightly inside so rays do not graze edges).
    """
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d) + RAY_PERTURBATION
    out = np.zeros(len(points), dtype=np.int64)
    if len(points) == 0 or len(triangles) == 0:
        return out
    # two axes across the ray, and each triangle's shadow's box on them (with a margin)
    across = np.linalg.svd(d[None, :])[2][1:]
    flat_tris = triangles @ across.T  # (T, 3, 2)
    flat_points = points @ across.T
    lo, hi = flat_tris.min(axis=1), flat_tris.max(axis=1)
    margin = 1e-9 * max(float(np.abs(flat_tris).max()), 1.0)
    lo, hi = lo - margin, hi + margin
    size = max(float(np.median(hi - lo)), margin)
    origin = lo.min(axis=0)
    cells = np.maximum(np.ceil((hi.max(axis=0) - origin) / size).astype(np.int64), 1)
    first = np.clip(((lo - origin) // size).astype(np.int64), 0, cells - 1)
    last = np.clip(((hi - origin) // size).astype(np.int64), 0, cells - 1)
    # each triangle listed in every cell its box covers
    span = last - first + 1
    count = span[:, 0] * span[:, 1]
    tri = np.repeat(np.arange(len(triangles)), count)
    k = np.arange(len(tri)) - np.repeat(np.cumsum(count) - count, count)
    cx = first[tri, 0] + k // span[tri, 1]
    cy = first[tri, 1] + k % span[tri, 1]
    tri_cell = cx * cells[1] + cy
    order = np.argsort(tri_cell, kind="stable")
    tri, tri_cell = tri[order], tri_cell[order]
    pc = np.floor((flat_points - origin) / size).astype(np.int64)
    inside_grid = np.all((pc >= 0) & (pc < cells), axis=1)
    point_cell = np.where(inside_grid, pc[:, 0] * cells[1] + pc[:, 1], -1)
    bounds = np.searchsorted(tri_cell, np.arange(cells[0] * cells[1] + 1))
    for cell in np.unique(point_cell[point_cell >= 0]):
        which = tri[bounds[cell] : bounds[cell + 1]]
        if len(which) == 0:
            continue
        rows = np.flatnonzero(point_cell == cell)
        out[rows] = _count_crossings(points[rows], triangles[which], d, chunk)
    return out


def _count_crossings(
    points: NDArray[np.float64], triangles: NDArray[np.float64], d: NDArray[np.float64], chunk: int
) -> NDArray[np.int64]:
    """Möller-Trumbore over every (point, triangle) pair: crossings of ``p + t d``, t > 0."""
    v0 = triangles[:, 0]
    e1 = triangles[:, 1] - v0
    e2 = triangles[:, 2] - v0
    h = np.cross(d, e2)
    a = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(a) > 1e-12
    v0, e1, e2, h, a = v0[ok], e1[ok], e2[ok], h[ok], a[ok]
    inv = 1.0 / a
    out = np.zeros(len(points), dtype=np.int64)
    for lo in range(0, len(points), chunk):
        p = points[lo : lo + chunk]
        s = p[:, None, :] - v0[None, :, :]
        u = np.einsum("ptj,tj->pt", s, h) * inv
        q = np.cross(s, e1[None, :, :])
        v = (q @ d) * inv
        t = np.einsum("ptj,tj->pt", q, e2) * inv
        hit = (u >= 0) & (u <= 1) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
        out[lo : lo + chunk] = hit.sum(axis=1)
    return out


def inside_closed_surface(
    points: NDArray[np.float64],
    coords: NDArray[np.float64],
    triangles: NDArray[np.int64],
    direction: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """Which points lie inside the surface made of ``triangles`` (node indices into ``coords``)."""
    if len(triangles) == 0:
        return np.zeros(len(points), dtype=bool)
    return crossings_along_ray(points, coords[triangles], direction) % 2 == 1


def distance_to_triangles(
    points: NDArray[np.float64], triangles: NDArray[np.float64], chunk: int = 64
) -> NDArray[np.float64]:
    """Exact distance (P,) from each point to the nearest of the triangles (T, 3, 3).

    Closest point on a triangle by its Voronoi regions (Ericson, *Real-Time Collision
    Detection*, 5.1.5), vectorised over point chunks x all triangles.
    """
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    ab, ac = b - a, c - a
    out = np.empty(len(points))
    for lo in range(0, len(points), chunk):
        p = points[lo : lo + chunk, None, :]
        ap = p - a
        d1, d2 = (ap * ab).sum(-1), (ap * ac).sum(-1)
        bp = p - b
        d3, d4 = (bp * ab).sum(-1), (bp * ac).sum(-1)
        cp = p - c
        d5, d6 = (cp * ab).sum(-1), (cp * ac).sum(-1)
        va = d3 * d6 - d5 * d4
        vb = d5 * d2 - d1 * d6
        vc = d1 * d4 - d3 * d2
        denom = np.where(va + vb + vc == 0, 1.0, va + vb + vc)
        v = vb / denom
        w = vc / denom
        closest = a + v[..., None] * ab + w[..., None] * ac  # inside the face
        with np.errstate(divide="ignore", invalid="ignore"):
            # edge regions
            t_ab = np.clip(d1 / np.where(d1 - d3 == 0, 1, d1 - d3), 0, 1)
            t_ac = np.clip(d2 / np.where(d2 - d6 == 0, 1, d2 - d6), 0, 1)
            t_bc = np.clip(
                (d4 - d3) / np.where((d4 - d3) + (d5 - d6) == 0, 1, (d4 - d3) + (d5 - d6)), 0, 1
            )
        on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        on_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        closest = np.where(on_ab[..., None], a + t_ab[..., None] * ab, closest)
        closest = np.where(on_ac[..., None], a + t_ac[..., None] * ac, closest)
        closest = np.where(on_bc[..., None], b + t_bc[..., None] * (c - b), closest)
        # vertex regions
        closest = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, closest)
        closest = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, closest)
        closest = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, closest)
        out[lo : lo + chunk] = np.sqrt(((p - closest) ** 2).sum(-1)).min(axis=1)
    return out


def penetrating(
    points: NDArray[np.float64],
    coords: NDArray[np.float64],
    triangles: NDArray[np.int64],
    direction: NDArray[np.float64],
    tolerance: float,
) -> NDArray[np.bool_]:
    """Points inside the closed surface by more than ``tolerance`` (a point on the surface, as
    at a sliding interface with coincident nodes, does not count)."""
    inside = inside_closed_surface(points, coords, triangles, direction)
    if inside.any():
        depth = distance_to_triangles(points[inside], coords[triangles])
        inside[np.flatnonzero(inside)[depth <= tolerance]] = False
    return inside
