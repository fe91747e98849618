"""Vectorised quality kernels, one per element type (QUALITY.md is the specification).

Every kernel takes the element's node positions as a list of ``(3, m)`` arrays (one per node,
component-major so that each arithmetic step is one contiguous numpy operation over ``m``
elements) and returns a dict of ``(m,)`` arrays:

``jacobian_corner``, ``jacobian_gauss``
    Ratio of determinants ``min_p d_p / max_p d_p`` over the sample points (corners or Gauss
    points), ``-1`` when ``max_p d_p <= 0``. Linear simplices (tet, tri) have a constant
    determinant: ``1`` if positive, else ``-1``.
``aspect``
    Worst face's longest / shortest edge (``inf`` for a zero-length edge).
``warpage``
    Worst quad face's fold angle in degrees (0-180); triangles score 0.
``skew``
    Worst face's skew in degrees (0-90).
``volume``
    Signed volume (solids, model units cubed) or area (shells, always >= 0).

The kernels compare cosines / squared lengths across faces and take a single ``arccos`` /
``arcsin`` / ``sqrt`` of the worst one per element; that is what makes a million hexes cheap.

This module is also the one implementation of the corner determinants (from
:data:`kneegui.topology.CORNER_TRIPLES`): :func:`corner_vectors`,
:func:`corner_determinants_cm` (component-major, as the kernels use it),
:func:`corner_determinants` / :func:`corner_jacobian` (node-major ``(..., k, 3)`` arrays) and
:func:`scaled_corner_determinants`. The smoother, the quality optimiser, the relaxation and the
demo's repair call them; the compiled penalty in :mod:`kneegui.meshopt.quality_kernel` has its
NumPy reference in :mod:`kneegui.meshopt.quality_optimiser`, tested against it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from kneegui.topology import (
    CORNER_NODES,
    CORNER_TRIPLES,
    ELEMENT_EDGES,
    NODES_PER_ELEMENT,
    hex_faces_parametric,
)

Vec = NDArray[np.float64]  # (3, m) vectors, component-major
Arr = NDArray[np.float64]  # (m,)

#: Gauss abscissa of the 2-point rule.
GAUSS_2 = 1.0 / np.sqrt(3.0)


# ---------------------------------------------------------------------- vector helpers
def _cross(a: Vec, b: Vec) -> Vec:
    out = np.empty_like(a)
    np.subtract(a[1] * b[2], a[2] * b[1], out=out[0])
    np.subtract(a[2] * b[0], a[0] * b[2], out=out[1])
    np.subtract(a[0] * b[1], a[1] * b[0], out=out[2])
    return out


def _dot(a: Vec, b: Vec) -> Arr:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _sq(a: Vec) -> Arr:
    return a[0] * a[0] + a[1] * a[1] + a[2] * a[2]


def _triple(a: Vec, b: Vec, c: Vec) -> Arr:
    """``(a x b) . c``, the determinant of the matrix with columns a, b, c."""
    return (
        c[0] * (a[1] * b[2] - a[2] * b[1])
        + c[1] * (a[2] * b[0] - a[0] * b[2])
        + c[2] * (a[0] * b[1] - a[1] * b[0])
    )


def _cos_between(a: Vec, b: Vec) -> Arr:
    """Cosine of the angle between a and b; 1 where either is zero (no angle defined)."""
    den = np.sqrt(_sq(a) * _sq(b))
    out = _dot(a, b)
    out /= den  # 0/0 -> nan where a vector is zero (the caller runs under errstate)
    out[den == 0.0] = 1.0
    return out


# ---------------------------------------------------------------------- corner determinants
#: :data:`kneegui.topology.CORNER_TRIPLES` as index arrays, for the node-major gathers.
_TRIPLE_ARRAYS: dict[str, NDArray[np.int64]] = {
    etype: np.array(table, dtype=np.int64) for etype, table in CORNER_TRIPLES.items()
}


def corner_vectors(
    p: Sequence[Vec], etype: str, normal: Vec | None = None
) -> list[tuple[Vec, Vec, Vec]]:
    """The three edge vectors ``(a, b, c)`` of every corner (:data:`CORNER_TRIPLES` order).

    Parameters
    ----------
    p : sequence of (3, ...) ndarray of float
        Node positions, one component-major array per node (any trailing shape).
    etype : str
        A type of :data:`kneegui.topology.CORNER_TRIPLES`.
    normal : (3, ...) ndarray of float, optional
        Quad shells only: the normal that is each corner's third vector; default the quad's
        own mean normal ``(p2 - p0) x (p3 - p1)``.
    """
    if etype == "quad4" and normal is None:
        normal = _cross(p[2] - p[0], p[3] - p[1])
    out = []
    for i, a, b, c in CORNER_TRIPLES[etype]:
        vc = normal if c < 0 else p[c] - p[i]
        out.append((p[a] - p[i], p[b] - p[i], vc))
    return out


def corner_determinants_cm(p: Sequence[Vec], etype: str, normal: Vec | None = None) -> list[Arr]:
    """Corner determinants ``det(a, b, c)`` of :func:`corner_vectors`, one array per corner.

    This is the one implementation of the corner Jacobian's determinants; the quality
    kernels, the smoother, the quality optimiser's volumes and the demo's repair use it (the
    compiled penalty in :mod:`kneegui.meshopt.quality_kernel` is tested against it).
    """
    return [_triple(a, b, c) for a, b, c in corner_vectors(p, etype, normal)]


def scaled_corner_determinants(p: Sequence[Vec], etype: str) -> tuple[list[Arr], list[Arr]]:
    """Corner determinants and the same scaled by their edge lengths, one array per corner.

    The scaled value ``det / (|a| |b| |c|)`` lies in [-1, 1] (-1 where an edge has zero
    length); it varies continuously through inversion, where the ratio of determinants jumps.
    """
    dets, scaled = [], []
    for a, b, c in corner_vectors(p, etype):
        d = _triple(a, b, c)
        norm = np.sqrt(_sq(a) * _sq(b) * _sq(c))
        ratio = np.full(d.shape, -1.0)
        np.divide(d, norm, out=ratio, where=norm > 0)
        dets.append(d)
        scaled.append(ratio)
    return dets, scaled


def corner_determinants(
    points: NDArray[np.float64], etype: str, normal: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """Corner determinants of elements given node-major: ``(..., k, 3)`` in, ``(..., T)`` out.

    The same corners and edge vectors as :func:`corner_vectors`, laid out node-major for the
    callers that gather element points (smoother, relaxation, optimiser volumes, demo repair);
    the triple product is summed by ``einsum``, which rounds differently from the kernels'
    component-major :func:`corner_determinants_cm` (agreement to 1e-15 relative is tested).
    The relaxation's and the optimiser's iterations amplify such last-bit differences, so
    each caller keeps the layout it was tuned and measured with.

    Parameters
    ----------
    points : (..., k, 3) ndarray of float
        Node positions (corner nodes in the model's order).
    etype : str
        A type of :data:`kneegui.topology.CORNER_TRIPLES`.
    normal : (..., 3) ndarray of float, optional
        Quad shells: the normal to use instead of each quad's own.
    """
    pts = np.asarray(points, dtype=np.float64)
    t = _TRIPLE_ARRAYS[etype]
    base = pts[..., t[:, 0], :]
    a = pts[..., t[:, 1], :] - base
    b = pts[..., t[:, 2], :] - base
    if etype == "quad4":
        if normal is None:
            normal = np.cross(pts[..., 2, :] - pts[..., 0, :], pts[..., 3, :] - pts[..., 1, :])
        c = np.broadcast_to(np.asarray(normal, dtype=np.float64)[..., None, :], a.shape)
    else:
        c = pts[..., t[:, 3], :] - base
    return np.einsum("...tk,...tk->...t", np.cross(a, b), c)


def ratio_of_determinants(dets: Sequence[Arr] | NDArray[np.float64]) -> Arr:
    """``min/max`` of the sample determinants, ``-1`` where the largest is not positive.

    ``dets`` is a sequence of equally shaped arrays (one per sample point) or an array whose
    *first* axis runs over the sample points.
    """
    lo = dets[0].copy()
    hi = dets[0].copy()
    for d in dets[1:]:
        np.minimum(lo, d, out=lo)
        np.maximum(hi, d, out=hi)
    positive = hi > 0.0
    out = np.full_like(lo, -1.0)
    np.divide(lo, hi, out=out, where=positive)
    return out


def corner_jacobian(points: NDArray[np.float64], etype: str) -> NDArray[np.float64]:
    """Corner Jacobian ratio of elements given node-major ``(..., k, 3)``: shape ``(...)``."""
    return ratio_of_determinants(np.moveaxis(corner_determinants(points, etype), -1, 0))


# ---------------------------------------------------------------------- face accumulators
#: The worst-face measures of :class:`_FaceAccumulator`.
FACE_METRICS: tuple[str, ...] = ("aspect", "warpage", "skew")


class _FaceAccumulator:
    """Running worst-face values: squared aspect, min warp cosine, max skew sine (those of
    ``want`` alone: each is worked out by the same operations whether the others are or not)."""

    def __init__(self, m: int, want: Sequence[str] = FACE_METRICS):
        self.want = frozenset(want)
        self.aspect_sq = np.ones(m)
        self.warp_cos = np.ones(m)
        self.skew_sin = np.zeros(m)

    def add_quad(self, p: Sequence[Vec], edge_sq: Sequence[Arr]) -> None:
        """Quad face p0..p3 with squared edge lengths (01, 12, 23, 30)."""
        if "aspect" in self.want:
            hi = np.maximum(np.maximum(edge_sq[0], edge_sq[1]), np.maximum(edge_sq[2], edge_sq[3]))
            lo = np.minimum(np.minimum(edge_sq[0], edge_sq[1]), np.minimum(edge_sq[2], edge_sq[3]))
            self._add_aspect(hi, lo)
        if not self.want & {"warpage", "skew"}:
            return
        e0, e1, e2, e3 = p[1] - p[0], p[2] - p[1], p[3] - p[2], p[0] - p[3]
        if "warpage" in self.want:
            # n012 = e0 x e1, n013 = e3 x e0; n012 + n023 == n013 + n123 == (p2 - p0) x (p3 - p1)
            area2 = _cross(e0 + e1, e1 + e2)
            n012 = _cross(e0, e1)
            n013 = _cross(e3, e0)
            c1 = _cos_between(n012, area2 - n012)
            c2 = _cos_between(n013, area2 - n013)
            np.minimum(self.warp_cos, np.minimum(c1, c2), out=self.warp_cos)
        if "skew" in self.want:
            # principal axes (mid-side to mid-side) X1 = m12 - m30, X2 = m23 - m01 (x2)
            np.maximum(self.skew_sin, np.abs(_cos_between(e0 - e2, e1 - e3)), out=self.skew_sin)

    def add_tri(self, edge_sq: Sequence[Arr]) -> None:
        """Triangle face with squared edge lengths (01, 12, 20)."""
        a, b, c = edge_sq  # a = |p1-p0|^2, b = |p2-p1|^2, c = |p0-p2|^2
        if "aspect" in self.want:
            hi = np.maximum(np.maximum(a, b), c)
            lo = np.minimum(np.minimum(a, b), c)
            self._add_aspect(hi, lo)
        if "skew" not in self.want:
            return  # (a triangle's warpage is 0)
        # At vertex i: median m_i to the opposite mid-side versus the line joining the other two
        # mid-sides (parallel to the opposite edge e_i). With squared side lengths:
        # m_i . e_i = (difference of the adjacent sides' squares) / 2,
        # |m_i|^2 = (2 (adjacent squares) - opposite square) / 4.
        best = np.zeros_like(a)
        for opp, s1, s2 in ((b, a, c), (c, a, b), (a, b, c)):
            num = np.abs(s1 - s2)
            den = np.sqrt(np.maximum(2.0 * (s1 + s2) - opp, 0.0) * opp)
            cos = np.zeros_like(num)
            np.divide(num, den, out=cos, where=den > 0.0)
            np.maximum(best, cos, out=best)
        np.maximum(self.skew_sin, np.minimum(best, 1.0), out=self.skew_sin)

    def _add_aspect(self, hi: Arr, lo: Arr) -> None:
        # a face edge of ~1e-160 (a damaged deck) overflows the ratio to inf: its aspect is
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            ratio = hi / lo
        ratio[lo <= 0.0] = np.inf
        np.maximum(self.aspect_sq, ratio, out=self.aspect_sq)

    def finish(self) -> dict[str, Arr]:
        out = {}
        if "aspect" in self.want:
            out["aspect"] = np.sqrt(self.aspect_sq)
        if "warpage" in self.want:
            out["warpage"] = np.degrees(np.arccos(np.clip(self.warp_cos, -1.0, 1.0)))
        if "skew" in self.want:
            out["skew"] = np.degrees(np.arcsin(np.clip(self.skew_sin, 0.0, 1.0)))
        return out


def _selection(want: Sequence[str] | None) -> tuple[tuple[str, ...], bool]:
    """The face measures a kernel asked for ``want`` works out, and whether its Gauss
    determinants and volume (one computation) are among them. ``None``: everything."""
    if want is None:
        return FACE_METRICS, True
    return (
        tuple(k for k in FACE_METRICS if k in want),
        bool({"jacobian_gauss", "volume"} & set(want)),
    )


def _result(
    acc: _FaceAccumulator, corner: Arr, gauss: Arr | None, volume: Arr | None
) -> dict[str, Arr]:
    """A kernel's output: the face metrics with the two Jacobians and the volume (those
    worked out: ``None`` is left out)."""
    out = acc.finish()
    out["jacobian_corner"] = corner
    if gauss is not None:
        out["jacobian_gauss"] = gauss
    if volume is not None:
        out["volume"] = volume
    return out


# ---------------------------------------------------------------------- solids
#: Hex faces as parametric node cycles (:func:`kneegui.topology.hex_faces_parametric`): the
#: face metrics are unsigned, and these cycles fix their rounding.
HEX_FACES = hex_faces_parametric()


def hex8_quality(p: Sequence[Vec], want: Sequence[str] | None = None) -> dict[str, Arr]:
    """Metrics of trilinear hexahedra (nodes 0-3 bottom, 4-7 top).

    ``want``: the metrics to work out besides the corner Jacobian (default all of them); each
    comes out bit-identical whatever else is asked for, and the others are left out.
    """
    m = p[0].shape[1]
    faces, volumes = _selection(want)
    # edges along the parametric directions xi (0->1), eta (0->3), zeta (0->4)
    ex = (p[1] - p[0], p[2] - p[3], p[5] - p[4], p[6] - p[7])  # at (eta, zeta) = --, +-, -+, ++
    ey = (p[3] - p[0], p[2] - p[1], p[7] - p[4], p[6] - p[5])  # at (xi, zeta) = --, +-, -+, ++
    ez = (p[4] - p[0], p[5] - p[1], p[7] - p[3], p[6] - p[2])  # at (xi, eta) = --, +-, -+, ++
    corner = corner_determinants_cm(p, "hex8")
    gauss = volume = None
    if volumes:
        gauss = _hex_gauss_determinants(ex, ey, ez)
        volume = sum(gauss[1:], gauss[0]) * 0.125
    acc = _FaceAccumulator(m, faces)
    if faces:
        # faces (any orientation; metrics are unsigned)
        sq: dict[frozenset[int], Arr | None] = {}
        for edges, pairs in (
            (ex, ((0, 1), (3, 2), (4, 5), (7, 6))),
            (ey, ((0, 3), (1, 2), (4, 7), (5, 6))),
            (ez, ((0, 4), (1, 5), (3, 7), (2, 6))),
        ):
            for vec, (i, j) in zip(edges, pairs, strict=True):
                sq[frozenset((i, j))] = _sq(vec) if "aspect" in faces else None
        for face in HEX_FACES:
            edge_sq = [sq[frozenset((face[i], face[(i + 1) % 4]))] for i in range(4)]
            acc.add_quad([p[i] for i in face], edge_sq)
    return _result(
        acc,
        ratio_of_determinants(corner),
        None if gauss is None else ratio_of_determinants(gauss),
        volume,
    )


def _hex_gauss_determinants(ex: Sequence[Vec], ey: Sequence[Vec], ez: Sequence[Vec]) -> list[Arr]:
    """Determinants at the 2 x 2 x 2 Gauss points from each direction's four edges."""
    # Gauss points: bilinear interpolation of each direction's four edges at +-g
    g = GAUSS_2

    def interp(e: Sequence[Vec]) -> list[Vec]:
        # e[0..3] at (s, t) = (-,-), (+,-), (-,+), (+,+); returns values at (s, t) = (-g|+g)^2
        out = []
        for t in (-g, g):
            lo = 0.5 * ((1 - t) * e[0] + (1 + t) * e[2])  # s = -1 line, at t
            hi = 0.5 * ((1 - t) * e[1] + (1 + t) * e[3])  # s = +1 line, at t
            mid = 0.5 * (lo + hi)
            half = (0.5 * g) * (hi - lo)
            out.append(mid - half)  # s = -g
            out.append(mid + half)  # s = +g
        return out  # order (s, t): (-,-), (+,-), (-,+), (+,+)

    gx = interp(ex)  # indexed by (eta, zeta)
    gy = interp(ey)  # indexed by (xi, zeta)
    gz = interp(ez)  # indexed by (xi, eta)
    gauss = []
    for zi in (0, 1):
        for yi in (0, 1):
            for xi in (0, 1):
                gauss.append(_triple(gx[yi + 2 * zi], gy[xi + 2 * zi], gz[xi + 2 * yi]))
    return gauss


#: 3-point triangle rule (r, s), weight 1/6 each.
_TRI_POINTS = ((1.0 / 6.0, 1.0 / 6.0), (2.0 / 3.0, 1.0 / 6.0), (1.0 / 6.0, 2.0 / 3.0))


def wedge6_quality(p: Sequence[Vec], want: Sequence[str] | None = None) -> dict[str, Arr]:
    """Metrics of linear wedges (triangle 0,1,2 below 3,4,5; edges i -> i+3); ``want`` as
    for :func:`hex8_quality`."""
    m = p[0].shape[1]
    faces, volumes = _selection(want)
    b1, b2 = p[1] - p[0], p[2] - p[0]
    t1, t2 = p[4] - p[3], p[5] - p[3]
    v = (p[3] - p[0], p[4] - p[1], p[5] - p[2])
    corner = corner_determinants_cm(p, "wedge6")
    gauss: list[Arr] | None = None
    volume = None
    if volumes:
        gauss = []
        volume = np.zeros(m)
        for z in (-GAUSS_2, GAUSS_2):
            wb, wt = 0.5 * (1 - z), 0.5 * (1 + z)
            n = _cross(wb * b1 + wt * t1, wb * b2 + wt * t2)
            for r, s in _TRI_POINTS:
                xz = 0.5 * ((1 - r - s) * v[0] + r * v[1] + s * v[2])
                d = _dot(n, xz)
                gauss.append(d)
                volume += d / 6.0
    acc = _FaceAccumulator(m, faces)
    if faces:
        sq01, sq12, sq20 = _sq(b1), _sq(p[2] - p[1]), _sq(b2)
        sq34, sq45, sq53 = _sq(t1), _sq(p[5] - p[4]), _sq(t2)
        sq03, sq14, sq25 = _sq(v[0]), _sq(v[1]), _sq(v[2])
        acc.add_tri((sq01, sq12, sq20))
        acc.add_tri((sq34, sq45, sq53))
        acc.add_quad([p[0], p[1], p[4], p[3]], (sq01, sq14, sq34, sq03))
        acc.add_quad([p[1], p[2], p[5], p[4]], (sq12, sq25, sq45, sq14))
        acc.add_quad([p[2], p[0], p[3], p[5]], (sq20, sq03, sq53, sq25))
    return _result(
        acc,
        ratio_of_determinants(corner),
        None if gauss is None else ratio_of_determinants(gauss),
        volume,
    )


def pyramid5_quality(p: Sequence[Vec], want: Sequence[str] | None = None) -> dict[str, Arr]:
    """Metrics of pyramids (quad base 0-3 counter-clockwise seen from apex 4); ``want`` as for
    :func:`hex8_quality`.

    The collapsed-hex map of a pyramid is singular at the apex, so both Jacobians are the ratio
    of the four base-corner determinants ``det(p[i+1]-p[i], p[i-1]-p[i], p[4]-p[i])`` (1 for a
    right pyramid on a rectangle or parallelogram). Volume: ``(p2-p0)x(p3-p1) . (apex - base
    centroid) / 6``, exact for a planar base.
    """
    m = p[0].shape[1]
    faces, volumes = _selection(want)
    base = p[:4]
    jac = ratio_of_determinants(corner_determinants_cm(p, "pyramid5"))
    volume = None
    if volumes:
        centroid = 0.25 * (base[0] + base[1] + base[2] + base[3])
        volume = _dot(_cross(base[2] - base[0], base[3] - base[1]), p[4] - centroid) / 6.0
    acc = _FaceAccumulator(m, faces)
    if faces:
        e = [base[(i + 1) % 4] - base[i] for i in range(4)]  # e[i] = edge i -> i+1
        sq_base = [_sq(ei) for ei in e]
        sq_side = [_sq(p[4] - base[i]) for i in range(4)]
        acc.add_quad(list(base), sq_base)
        for i in range(4):
            acc.add_tri((sq_base[i], sq_side[(i + 1) % 4], sq_side[i]))
    return _result(acc, jac, None if volume is None else jac.copy(), volume)


#: h / sqrt(A) of the regular tetrahedron (height over the square root of the opposite face's
#: area): sqrt(2/3) / sqrt(sqrt(3)/4) = 1.2408. HyperMesh's help rounds it to 1.24, OptiStruct's
#: CTETRA check prints 1.2408; the exact value makes the regular tet's collapse exactly 1.
TET_COLLAPSE_NORM = float(np.sqrt(2.0 / 3.0) / np.sqrt(np.sqrt(3.0) / 4.0))
#: Altitude normalisation of the tet aspect ratio: the regular tet's longest edge / shortest
#: altitude is sqrt(3/2), so ``tet_aspect`` = L_max / (h_min sqrt(3/2)) is 1 for it.
TET_ASPECT_NORM = float(np.sqrt(1.5))
#: The tetrahedral shape measures every tet kernel adds (definitions in docs/quality.md).
TET_METRICS: tuple[str, ...] = (
    "tet_collapse",
    "dihedral_min",
    "dihedral_max",
    "vol_skew",
    "tet_aspect",
)
#: The mid-side-node measures of a 10-node tet (OptiStruct's "hoe" offsets of a 3-node edge).
TET10_METRICS: tuple[str, ...] = ("midside_normal", "midside_tangent")
#: (corner, corner, mid-side node) of each edge of a 10-node tet, read off
#: :data:`kneegui.topology.ELEMENT_EDGES` (which lists each edge as corner-mid, mid-corner).
TET10_MIDSIDE: tuple[tuple[int, int, int], ...] = tuple(
    (a, d, b)
    for (a, b), (c, d) in zip(
        ELEMENT_EDGES["tet10"][0::2], ELEMENT_EDGES["tet10"][1::2], strict=True
    )
    if b == c
)


def _tet_face_normals(p: Sequence[Vec], a: Vec, b: Vec, c: Vec) -> tuple[Vec, Vec, Vec, Vec]:
    """Outward area vectors (twice the face area) of the faces opposite nodes 0..3 (they sum
    to 0); ``a, b, c`` are the edges from node 0."""
    n0 = _cross(p[2] - p[1], p[3] - p[1])
    n2 = _cross(a, c)
    n3 = _cross(b, a)
    n1 = n0 + n2
    n1 += n3
    np.negative(n1, out=n1)
    return n0, n1, n2, n3


def _tet_collapse(six_volume: Arr, area_sq: Sequence[Arr]) -> tuple[Arr, Arr]:
    """HyperMesh's tet collapse from six times the volume and the faces' squared area vectors
    (h_i / sqrt(A_i) = sqrt(2) 6V / |n_i|^1.5 is smallest at the largest face), and the
    largest face's |n|."""
    largest_sq = np.maximum(np.maximum(area_sq[0], area_sq[1]), np.maximum(area_sq[2], area_sq[3]))
    largest = np.sqrt(largest_sq)
    collapse = np.zeros_like(six_volume)
    np.divide(
        (np.sqrt(2.0) / TET_COLLAPSE_NORM) * six_volume,
        largest * np.sqrt(largest),
        out=collapse,
        where=largest > 0.0,
    )
    return collapse, largest


def tet_collapse_only(p: Sequence[Vec]) -> Arr:
    """The tet collapse alone, bit-identical to the ``tet_collapse`` of :func:`tet4_quality`
    (the same operations on the same arrays), for a tet-collapse heat-map redrawn with every
    slider pose: about a sixth of the full kernel's cost. Component-major corner positions."""
    a, b, c = p[1] - p[0], p[2] - p[0], p[3] - p[0]
    six_volume = _triple(a, b, c)
    normals = _tet_face_normals(p, a, b, c)
    return _tet_collapse(six_volume, [_sq(n) for n in normals])[0]


def tet_shape_measures(p: Sequence[Vec], six_volume: Arr, edge_sq: Sequence[Arr]) -> dict[str, Arr]:
    """The crash pre-processors' tetrahedron measures (docs/quality.md), vectorised.

    Parameters
    ----------
    p : sequence of four (3, m) ndarray of float
        Corner positions (triangle 0,1,2 counter-clockwise seen from 3 for a positive tet).
    six_volume : (m,) ndarray of float
        Six times the signed volume, ``(p1 - p0) x (p2 - p0) . (p3 - p0)``.
    edge_sq : sequence of six (m,) ndarray of float
        Squared lengths of the six edges (any order).

    Returns
    -------
    dict of str to (m,) ndarray of float
        ``tet_collapse``: min over the nodes of h_i / sqrt(A_i) / :data:`TET_COLLAPSE_NORM`
        (1 regular, 0 flat, the sign of the volume); ``dihedral_min`` / ``dihedral_max``:
        the smallest and largest of the six interior dihedral angles (degrees; a face of zero
        area gives 0 / 180); ``vol_skew``: 1 - V / V_ideal with V_ideal the regular tet
        inscribed in the circumsphere (0 regular, 1 flat, > 1 inverted); ``tet_aspect``: longest
        edge / (shortest altitude x sqrt(3/2)) (1 regular, ``inf`` flat).
    """
    a, b, c = p[1] - p[0], p[2] - p[0], p[3] - p[0]
    normals = _tet_face_normals(p, a, b, c)
    _, n1, n2, n3 = normals
    area_sq = [_sq(n) for n in normals]
    smallest_sq = np.minimum(np.minimum(area_sq[0], area_sq[1]), np.minimum(area_sq[2], area_sq[3]))
    collapse, largest = _tet_collapse(six_volume, area_sq)
    # interior dihedral angle along the edge two faces share: cos = -(n_a . n_b) / |n_a| |n_b|
    inv = [np.zeros_like(six_volume) for _ in normals]
    for k in range(4):
        np.divide(1.0, np.sqrt(area_sq[k]), out=inv[k], where=area_sq[k] > 0.0)
    cos_hi = np.full_like(six_volume, -1.0)
    cos_lo = np.full_like(six_volume, 1.0)
    for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)):
        cos = _dot(normals[i], normals[j])
        cos *= inv[i]
        cos *= inv[j]
        np.negative(cos, out=cos)
        np.maximum(cos_hi, cos, out=cos_hi)
        np.minimum(cos_lo, cos, out=cos_lo)
    flat_face = smallest_sq <= 0.0
    np.copyto(cos_hi, 1.0, where=flat_face)
    np.copyto(cos_lo, -1.0, where=flat_face)
    # circumsphere: centre - p0 = (|a|^2 (b x c) + |b|^2 (c x a) + |c|^2 (a x b)) / (2 * 6V),
    # with b x c = -n1, c x a = -n2, a x b = -n3; V / V_ideal = (3 sqrt(3) / 2) 6V |6V|^3 / |num|^3
    num = _sq(a) * n1
    num += _sq(b) * n2
    num += _sq(c) * n3
    num_sq = _sq(num)
    num_cubed = num_sq * np.sqrt(num_sq)
    abs_volume = np.abs(six_volume)
    ratio = np.zeros_like(six_volume)
    np.divide(
        (1.5 * np.sqrt(3.0)) * six_volume * abs_volume * abs_volume * abs_volume,
        num_cubed,
        out=ratio,
        where=num_cubed > 0.0,
    )
    longest_sq = edge_sq[0]
    for s in edge_sq[1:]:
        longest_sq = np.maximum(longest_sq, s)
    tet_aspect = np.full_like(six_volume, np.inf)
    np.divide(
        np.sqrt(longest_sq) * largest,
        abs_volume * TET_ASPECT_NORM,
        out=tet_aspect,
        where=abs_volume > 0.0,
    )
    return {
        "tet_collapse": collapse,
        "dihedral_min": np.degrees(np.arccos(np.clip(cos_hi, -1.0, 1.0))),
        "dihedral_max": np.degrees(np.arccos(np.clip(cos_lo, -1.0, 1.0))),
        "vol_skew": 1.0 - ratio,
        "tet_aspect": tet_aspect,
    }


def _tet_volume_and_edges(p: Sequence[Vec]) -> tuple[Arr, tuple[Arr, ...]]:
    """Six times the signed volume and the squared edge lengths (01, 02, 03, 12, 13, 23)."""
    e01, e02, e03 = p[1] - p[0], p[2] - p[0], p[3] - p[0]
    six_volume = _triple(e01, e02, e03)
    edge_sq = (_sq(e01), _sq(e02), _sq(e03), _sq(p[2] - p[1]), _sq(p[3] - p[1]), _sq(p[3] - p[2]))
    return six_volume, edge_sq


def tet4_quality(p: Sequence[Vec], want: Sequence[str] | None = None) -> dict[str, Arr]:
    """Metrics of linear tetrahedra (triangle 0,1,2 counter-clockwise seen from apex 3);
    ``want`` as for :func:`hex8_quality` (any of :data:`TET_METRICS` brings all of them).

    The determinant is constant: both Jacobians are 1 for a positive volume, else -1. The
    tetrahedral measures of :func:`tet_shape_measures` are added.
    """
    m = p[0].shape[1]
    faces, _ = _selection(want)
    six_volume, edge_sq = _tet_volume_and_edges(p)
    s01, s02, s03, s12, s13, s23 = edge_sq
    volume = six_volume / 6.0
    jac = np.where(volume > 0.0, 1.0, -1.0)
    acc = _FaceAccumulator(m, faces)
    if faces:
        acc.add_tri((s01, s12, s02))
        acc.add_tri((s01, s13, s03))
        acc.add_tri((s12, s23, s13))
        acc.add_tri((s02, s23, s03))
    out = _result(acc, jac, jac.copy(), volume)
    if want is None or set(TET_METRICS) & set(want):
        out.update(tet_shape_measures(p, six_volume, edge_sq))
    return out


def tet_measures_only(p: Sequence[Vec]) -> dict[str, Arr]:
    """The tetrahedral shape measures (:data:`TET_METRICS`) alone, bit-identical to those of
    :func:`tet4_quality` (the same operations on the same arrays), without the faces' aspect,
    warpage and skew: for a heat-map of a dihedral angle or the volumetric skew redrawn with
    every slider pose. Component-major corner positions."""
    return tet_shape_measures(p, *_tet_volume_and_edges(p))


def midside_offsets(p: Sequence[Vec]) -> dict[str, Arr]:
    """Mid-side-node offsets of 10-node tets, OptiStruct's "hoe" offsets of a 3-node edge.

    For each edge (i, j) with mid-side node k, ``d = x_k - (x_i + x_j) / 2`` splits into a part
    along the edge and a part normal to it. ``midside_normal`` = max over the edges of
    |normal part| / |x_j - x_i| (OptiStruct "hoe normal offset"); ``midside_tangent`` = max of
    |part along the edge| / |x_j - x_i| ("hoe tangent offset": 0.25 is the quarter point,
    where the quadratic map's Jacobian vanishes at the corner). ``inf`` for a zero-length edge.
    """
    normal = np.zeros(p[0].shape[1])
    tangent = np.zeros_like(normal)
    for i, j, k in TET10_MIDSIDE:
        e = p[j] - p[i]
        d = p[k] - 0.5 * (p[i] + p[j])
        length_sq = _sq(e)
        along = _dot(d, e)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.abs(along) / length_sq
            nrm = np.sqrt(np.maximum(_sq(d) - along * along / length_sq, 0.0) / length_sq)
        t[length_sq <= 0.0] = np.inf
        nrm[length_sq <= 0.0] = np.inf
        np.maximum(tangent, t, out=tangent)
        np.maximum(normal, nrm, out=normal)
    return {"midside_normal": normal, "midside_tangent": tangent}


def tet10_quality(p: Sequence[Vec], want: Sequence[str] | None = None) -> dict[str, Arr]:
    """Metrics of 10-node tetrahedra: every tet4 metric of the corner tetrahedron (nodes 0-3)
    and the mid-side-node offsets of :func:`midside_offsets` (nodes 4-9); ``want`` as for
    :func:`tet4_quality` (either offset brings both)."""
    out = tet4_quality(p[:4], want)
    if want is None or set(TET10_METRICS) & set(want):
        out.update(midside_offsets(p))
    return out


# ---------------------------------------------------------------------- shells
def quad4_quality(p: Sequence[Vec], want: Sequence[str] | None = None) -> dict[str, Arr]:
    """Metrics of bilinear quad shells; ``want`` as for :func:`hex8_quality` (the area, cheap,
    always comes along).

    Determinants ``d = (x_xi x x_eta) . n`` with ``n = (p2 - p0) x (p3 - p1)`` (the element's
    mean normal; its length does not change the ratio). Area = ``|n| / 2``.
    """
    m = p[0].shape[1]
    faces, _ = _selection(want)
    n = _cross(p[2] - p[0], p[3] - p[1])
    e = [p[(i + 1) % 4] - p[i] for i in range(4)]  # e[i] = edge i -> i+1
    corner = corner_determinants_cm(p, "quad4", n)
    gauss = None
    if want is None or "jacobian_gauss" in want:
        # x_xi along edges 0->1 (eta=-1) and 3->2 (eta=+1); x_eta along 0->3 (xi=-1), 1->2 (xi=+1)
        ex_lo, ex_hi = e[0], -e[2]
        ey_lo, ey_hi = -e[3], e[1]
        gauss = []
        for eta in (-GAUSS_2, GAUSS_2):
            x_xi = 0.5 * ((1 - eta) * ex_lo + (1 + eta) * ex_hi)
            for xi in (-GAUSS_2, GAUSS_2):
                x_eta = 0.5 * ((1 - xi) * ey_lo + (1 + xi) * ey_hi)
                gauss.append(_dot(_cross(x_xi, x_eta), n))
    acc = _FaceAccumulator(m, faces)
    if faces:
        acc.add_quad(list(p), [_sq(ei) for ei in e])
    return _result(
        acc,
        ratio_of_determinants(corner),
        None if gauss is None else ratio_of_determinants(gauss),
        0.5 * np.sqrt(_sq(n)),
    )


def tri3_quality(p: Sequence[Vec], want: Sequence[str] | None = None) -> dict[str, Arr]:
    """Metrics of linear triangle shells: Jacobian 1 (or -1 for zero area), area >= 0;
    ``want`` as for :func:`hex8_quality`."""
    m = p[0].shape[1]
    faces, _ = _selection(want)
    e01, e02 = p[1] - p[0], p[2] - p[0]
    area = 0.5 * np.sqrt(_sq(_cross(e01, e02)))
    jac = np.where(area > 0.0, 1.0, -1.0)
    acc = _FaceAccumulator(m, faces)
    if faces:
        acc.add_tri((_sq(e01), _sq(p[2] - p[1]), _sq(e02)))
    return _result(acc, jac, jac.copy(), area)


def corner_jacobian_only(p: Sequence[Vec], etype: str) -> Arr:
    """The corner Jacobian alone, bit-identical to the ``jacobian_corner`` of the type's kernel.

    The same operations on the same arrays as the kernels above, without the faces, Gauss
    points and volume they also work out: what a heat-map of the Jacobian needs per frame.
    Component-major ``p`` as for the kernels (corner nodes only).
    """
    if etype in ("hex8", "wedge6", "pyramid5"):
        return ratio_of_determinants(corner_determinants_cm(p, etype))
    if etype == "quad4":
        n = _cross(p[2] - p[0], p[3] - p[1])
        return ratio_of_determinants(corner_determinants_cm(p, "quad4", n))
    if etype in ("tet4", "tet10"):
        six_volume = _triple(p[1] - p[0], p[2] - p[0], p[3] - p[0])
        return np.where(six_volume / 6.0 > 0.0, 1.0, -1.0)
    if etype == "tri3":
        area = 0.5 * np.sqrt(_sq(_cross(p[1] - p[0], p[2] - p[0])))
        return np.where(area > 0.0, 1.0, -1.0)
    raise ValueError(f"no corner Jacobian for element type {etype!r}")


#: Kernel and the node columns it reads, per element type: the corner nodes, except for the
#: 10-node tet, whose mid-side nodes the mid-side offsets read (its shape measures use the
#: corner tetrahedron).
_KERNEL_COLUMNS = {**CORNER_NODES, "tet10": NODES_PER_ELEMENT["tet10"]}
KERNELS: dict[str, tuple[Callable[[Sequence[Vec]], dict[str, Arr]], tuple[int, ...]]] = {
    etype: (kernel, tuple(range(_KERNEL_COLUMNS[etype])))
    for etype, kernel in (
        ("hex8", hex8_quality),
        ("wedge6", wedge6_quality),
        ("pyramid5", pyramid5_quality),
        ("tet4", tet4_quality),
        ("tet10", tet10_quality),
        ("quad4", quad4_quality),
        ("tri3", tri3_quality),
    )
}
#: Measures a kernel returns beyond the common ones (``jacobian_corner`` ... ``volume``).
KERNEL_EXTRA_METRICS: dict[str, tuple[str, ...]] = {
    "tet4": TET_METRICS,
    "tet10": TET_METRICS + TET10_METRICS,
}
