"""Compiled element measures of the smoother: corner Jacobian, worst scaled corner, edge ratio
and warpage cosine of each element in one pass over its nodes.

:func:`kneegui.meshopt.smoother.corner_quality`, :func:`~kneegui.meshopt.smoother.edge_ratio` and
:func:`~kneegui.meshopt.smoother.warp_cosine` are the NumPy reference: the same arithmetic in
the same order, so the values are the same bits (tested). The smoother measures the elements
around every group of nodes it tries to move, hundreds of times per export; in NumPy each call
gathered the elements' points and made some sixty temporary arrays (6.8 s of the 177k demo's
12.8 s smoothing at 90 degrees).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from kneegui.meshopt.parallel import PARALLEL_KERNEL_LOCK, PARALLEL_MIN_ELEMENTS
from kneegui.topology import CORNER_TRIPLES, ELEMENT_EDGES, SOLID_FACES


def _quad_faces(etype: str) -> NDArray[np.int64]:
    if etype == "quad4":
        return np.array([(0, 1, 2, 3)], dtype=np.int64)
    faces = [f for f in SOLID_FACES.get(etype, ()) if len(f) == 4]
    return np.array(faces, dtype=np.int64).reshape(-1, 4)


#: The quadrilateral faces (F, 4) of each element type whose warpage the smoother measures
#: (F = 0: none); :func:`kneegui.meshopt.smoother.warp_cosine` reads the same table.
QUAD_FACES: dict[str, NDArray[np.int64]] = {etype: _quad_faces(etype) for etype in CORNER_TRIPLES}

#: Per element type: corner triples (T, 4) (a negative last entry: the quad's normal), edges
#: (E, 2) and quadrilateral faces (F, 4).
TYPE_TABLES: dict[str, tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]] = {
    etype: (
        np.array(triples, dtype=np.int64),
        np.array(ELEMENT_EDGES[etype], dtype=np.int64),
        QUAD_FACES[etype],
    )
    for etype, triples in CORNER_TRIPLES.items()
}


@njit(cache=True, nogil=True)
def _measure(coords, nodes, triples, edges, faces):  # pragma: no cover - compiled
    """(corner Jacobian, worst scaled corner, edge ratio, warpage cosine) of one element."""
    # the quad's own mean normal (p2 - p0) x (p3 - p1), the third vector of its corners
    n0 = n1 = n2 = 0.0
    if triples[0, 3] < 0:
        u0 = coords[nodes[2], 0] - coords[nodes[0], 0]
        u1 = coords[nodes[2], 1] - coords[nodes[0], 1]
        u2 = coords[nodes[2], 2] - coords[nodes[0], 2]
        v0 = coords[nodes[3], 0] - coords[nodes[1], 0]
        v1 = coords[nodes[3], 1] - coords[nodes[1], 1]
        v2 = coords[nodes[3], 2] - coords[nodes[1], 2]
        n0 = u1 * v2 - u2 * v1
        n1 = u2 * v0 - u0 * v2
        n2 = u0 * v1 - u1 * v0
    lo = 0.0
    hi = 0.0
    scaled = 0.0
    for t in range(triples.shape[0]):
        i = nodes[triples[t, 0]]
        a = nodes[triples[t, 1]]
        b = nodes[triples[t, 2]]
        a0 = coords[a, 0] - coords[i, 0]
        a1 = coords[a, 1] - coords[i, 1]
        a2 = coords[a, 2] - coords[i, 2]
        b0 = coords[b, 0] - coords[i, 0]
        b1 = coords[b, 1] - coords[i, 1]
        b2 = coords[b, 2] - coords[i, 2]
        if triples[t, 3] < 0:
            c0 = n0
            c1 = n1
            c2 = n2
        else:
            c = nodes[triples[t, 3]]
            c0 = coords[c, 0] - coords[i, 0]
            c1 = coords[c, 1] - coords[i, 1]
            c2 = coords[c, 2] - coords[i, 2]
        det = c0 * (a1 * b2 - a2 * b1) + c1 * (a2 * b0 - a0 * b2) + c2 * (a0 * b1 - a1 * b0)
        sq_a = a0 * a0 + a1 * a1 + a2 * a2
        sq_b = b0 * b0 + b1 * b1 + b2 * b2
        sq_c = c0 * c0 + c1 * c1 + c2 * c2
        norm = math.sqrt(sq_a * sq_b * sq_c)
        ratio = det / norm if norm > 0.0 else -1.0
        if t == 0:
            lo = det
            hi = det
            scaled = ratio
        else:
            lo = min(lo, det)
            hi = max(hi, det)
            scaled = min(scaled, ratio)
    jacobian = lo / hi if hi > 0.0 else -1.0
    longest = 0.0
    shortest = 0.0
    for e in range(edges.shape[0]):
        p = nodes[edges[e, 0]]
        q = nodes[edges[e, 1]]
        d0 = coords[q, 0] - coords[p, 0]
        d1 = coords[q, 1] - coords[p, 1]
        d2 = coords[q, 2] - coords[p, 2]
        sq = d0 * d0 + d1 * d1 + d2 * d2
        if e == 0:
            longest = sq
            shortest = sq
        else:
            longest = max(longest, sq)
            shortest = min(shortest, sq)
    aspect = math.sqrt(longest / shortest) if shortest > 0.0 else math.inf
    warp = 1.0
    for f in range(faces.shape[0]):
        q0 = nodes[faces[f, 0]]
        q1 = nodes[faces[f, 1]]
        q2 = nodes[faces[f, 2]]
        q3 = nodes[faces[f, 3]]
        x0 = coords[q1, 0] - coords[q0, 0]  # d01
        x1 = coords[q1, 1] - coords[q0, 1]
        x2 = coords[q1, 2] - coords[q0, 2]
        y0 = coords[q2, 0] - coords[q0, 0]  # d02
        y1 = coords[q2, 1] - coords[q0, 1]
        y2 = coords[q2, 2] - coords[q0, 2]
        z0 = coords[q3, 0] - coords[q0, 0]  # d03
        z1 = coords[q3, 1] - coords[q0, 1]
        z2 = coords[q3, 2] - coords[q0, 2]
        w0 = coords[q3, 0] - coords[q1, 0]  # p3 - p1
        w1 = coords[q3, 1] - coords[q1, 1]
        w2 = coords[q3, 2] - coords[q1, 2]
        area0 = y1 * w2 - y2 * w1
        area1 = y2 * w0 - y0 * w2
        area2 = y0 * w1 - y1 * w0
        for split in range(2):
            if split == 0:  # n012 = d01 x d02
                s0 = x1 * y2 - x2 * y1
                s1 = x2 * y0 - x0 * y2
                s2 = x0 * y1 - x1 * y0
            else:  # n013 = d01 x d03
                s0 = x1 * z2 - x2 * z1
                s1 = x2 * z0 - x0 * z2
                s2 = x0 * z1 - x1 * z0
            r0 = area0 - s0
            r1 = area1 - s1
            r2 = area2 - s2
            den = math.sqrt((s0 * s0 + s1 * s1 + s2 * s2) * (r0 * r0 + r1 * r1 + r2 * r2))
            cosine = (s0 * r0 + s1 * r1 + s2 * r2) / den if den > 0.0 else 1.0
            warp = min(warp, cosine)
    return jacobian, scaled, aspect, warp


@njit(cache=True, nogil=True)
def _measure_row(coords, conn, rows, k, triples, edges, faces, out):  # pragma: no cover
    out[0, k], out[1, k], out[2, k], out[3, k] = _measure(
        coords, conn[rows[k]], triples, edges, faces
    )


@njit(cache=True, nogil=True)
def _measure_serial(coords, conn, rows, triples, edges, faces, out):  # pragma: no cover
    for k in range(rows.shape[0]):
        _measure_row(coords, conn, rows, k, triples, edges, faces, out)


@njit(cache=True, nogil=True, parallel=True)
def _measure_parallel(coords, conn, rows, triples, edges, faces, out):  # pragma: no cover
    for k in prange(rows.shape[0]):
        _measure_row(coords, conn, rows, k, triples, edges, faces, out)


def element_measures(
    coords: NDArray[np.float64], conn: NDArray[np.int64], rows: NDArray[np.int64], etype: str
) -> NDArray[np.float64]:
    """Corner Jacobian, worst scaled corner, edge ratio and warpage cosine of elements.

    Parameters
    ----------
    coords : (N, 3) ndarray of float
        Node coordinates.
    conn : (E, k) ndarray of int
        Connectivity (indices into ``coords``) of elements of type ``etype``; only the nodes
        the measures use are read.
    rows : (m,) ndarray of int
        The rows of ``conn`` to measure.
    etype : str
        A type of :data:`kneegui.topology.CORNER_TRIPLES`.

    Returns
    -------
    (4, m) ndarray of float
        The four measures of :func:`kneegui.meshopt.smoother.corner_quality` (two),
        :func:`~kneegui.meshopt.smoother.edge_ratio` and
        :func:`~kneegui.meshopt.smoother.warp_cosine`, the same bits; each element is measured
        on its own, so the thread count cannot change them.
    """
    triples, edges, faces = TYPE_TABLES[etype]
    coords = np.ascontiguousarray(coords, dtype=np.float64)
    conn = np.ascontiguousarray(conn, dtype=np.int64)
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    out = np.empty((4, len(rows)))
    if len(rows) >= PARALLEL_MIN_ELEMENTS:
        with PARALLEL_KERNEL_LOCK:
            _measure_parallel(coords, conn, rows, triples, edges, faces, out)
    else:
        _measure_serial(coords, conn, rows, triples, edges, faces, out)
    return out


@njit(cache=True, nogil=True)
def _greedy_colours(ptr, nbrs, order):  # pragma: no cover - compiled
    colour = np.full(len(ptr) - 1, -1, dtype=np.int64)
    taken = np.zeros(1, dtype=np.bool_)
    for node in order:
        lo, hi = ptr[node], ptr[node + 1]
        if hi - lo + 1 > taken.shape[0]:
            taken = np.zeros(hi - lo + 1, dtype=np.bool_)
        for k in range(lo, hi):
            c = colour[nbrs[k]]
            if 0 <= c < taken.shape[0]:
                taken[c] = True
        c = 0
        while taken[c]:
            c += 1
        colour[node] = c
        for k in range(lo, hi):
            c = colour[nbrs[k]]
            if 0 <= c < taken.shape[0]:
                taken[c] = False
    return colour


def greedy_colours(
    ptr: NDArray[np.int64], nbrs: NDArray[np.int64], priority: NDArray[np.int64]
) -> NDArray[np.int64]:
    """Colours of a graph's nodes, neighbours never sharing one: each node in decreasing
    ``priority`` takes the smallest colour its neighbours coloured before it do not use.

    This is the colouring the Jones-Plassmann rounds reach (a node is coloured in the round
    after all its higher-priority neighbours, and takes the smallest colour they leave), one
    node at a time instead of a round of array operations per colour.

    Parameters
    ----------
    ptr, nbrs : ndarray of int
        The graph in CSR form: the neighbours of node ``i`` are ``nbrs[ptr[i]:ptr[i + 1]]``.
    priority : (n,) ndarray of int
        Distinct priorities (a permutation of ``range(n)``).
    """
    order = np.argsort(-np.asarray(priority, dtype=np.int64), kind="stable")
    return _greedy_colours(
        np.ascontiguousarray(ptr, dtype=np.int64), np.ascontiguousarray(nbrs, dtype=np.int64), order
    )
