"""Compiled penalties of the quality optimiser (fused loops over elements and faces).

:func:`kneegui.meshopt.quality_optimiser.corner_ratio_penalty_numpy` is the reference; this
is the same arithmetic, element by element, compiled with Numba (tests check the two agree).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from kneegui.quality.kernels import TET_COLLAPSE_NORM

#: ``log (V / V_ideal) = LOG_RATIO_SCALE + 4 log d - 3 log |M|`` for a tet's six-volume ``d`` and
#: ``M = |a|^2 (b x e) + |b|^2 (e x a) + |e|^2 (a x b)`` (``2 d`` times the circumcentre seen from
#: the corner node), ``V_ideal`` the regular tet inscribed in the circumsphere
LOG_RATIO_SCALE = math.log(1.5 * math.sqrt(3.0))
#: ``log collapse = log d - 0.75 log |n|^2 + LOG_COLLAPSE_SCALE`` for a tet's six-volume ``d``
#: and the doubled area vector ``n`` of a face (``h / sqrt(A) = sqrt(2) d / |n|^1.5``).
LOG_COLLAPSE_SCALE = 0.5 * math.log(2.0) - math.log(TET_COLLAPSE_NORM)
#: The face opposite each corner of a tet (its other three corners).
TET_OPPOSITE = np.array([(1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2)], dtype=np.int64)
#: A tetrahedron's six edges ``(a, b)`` and the two faces (by opposite node, as
#: :data:`TET_OPPOSITE`) that meet along each: those opposite the other two nodes.
TET_EDGES = np.array(
    [(0, 1, 2, 3), (0, 2, 1, 3), (0, 3, 1, 2), (1, 2, 0, 3), (1, 3, 0, 2), (2, 3, 0, 1)],
    dtype=np.int64,
)


@njit(cache=True, nogil=True)
def corner_ratio_penalty(  # pragma: no cover - compiled
    x,
    corners,
    elem_ptr,
    log_aim,
    log_collapse_aim,
    log_sine_aim,
    log_ratio_aim,
    element_weight,
    log_volume,
    volume_band,
    volume_weight,
    quads,
    quad_triples,
    quad_log_aim,
    grad,
):
    """Sum over elements of ``max(0, log aim - log d_i + log d_j)^2`` over corner pairs, plus
    ``volume_weight * max(0, |log(v / v0)| - band)^2`` for the element's volume ``v`` (the mean
    of its corner determinants; ``log_volume`` = ``log v0`` (E,), ``volume_band`` (E,), ``inf``
    for none).

    ``x`` (S, 3) coordinates; ``corners`` (C, 4) local node indices (corner node, then the
    three edge ends) of the solids, grouped by element through ``elem_ptr`` (E + 1,);
    ``log_aim`` (E,); ``log_collapse_aim`` (E,) the log of the tet collapse each tetrahedron
    (an element of one corner) should reach, ``-inf`` for none: its penalty is
    ``sum_i max(0, log aim - log c_i)^2`` over the four nodes' ``c_i = h_i / sqrt(A_i)``
    (normalised as :data:`~kneegui.quality.kernels.TET_COLLAPSE_NORM`), so a sliver with fair
    faces, which no face aspect sees, costs; ``log_sine_aim`` (E,) the log of the sine every
    dihedral angle of a tetrahedron should keep (``-inf`` for none): its penalty is
    ``sum_edges max(0, log aim - log sin)^2`` with ``sin = d L / (|n_k| |n_l|)`` at the edge
    of length ``L`` between the faces of normals ``n_k``, ``n_l`` (a sharp and a flat
    dihedral angle both have a small sine: a cap, whose collapse can be fair, costs too);
    ``log_ratio_aim`` (E,) the log of the ratio ``V / V_ideal`` (1 - the volumetric skew:
    ``V_ideal`` the regular tet in the circumsphere) to reach, ``-inf`` for none, penalised as
    ``max(0, log aim - log ratio)^2``; ``element_weight`` (E,) weighs each element's corner
    and tet terms (not its volume term);
    ``quads`` (Q, 4) shell nodes whose corner determinants use the quad's own diagonal normal,
    ``quad_triples`` (4, 3) their corners, ``quad_log_aim`` (Q,). Fills ``grad`` (S, 3).
    Returns ``inf`` (and a meaningless gradient) when a corner determinant is not positive:
    the solver treats that as a rejected step.
    """
    grad[:, :] = 0.0
    total = 0.0
    dets = np.empty(8)
    logs = np.empty(8)
    g_log = np.empty(8)
    normals = np.empty((4, 3))
    nns = np.empty(4)
    for e in range(elem_ptr.shape[0] - 1):
        p0 = elem_ptr[e]
        k = elem_ptr[e + 1] - p0
        lo = math.inf
        hi = 0.0
        for i in range(k):
            c = corners[p0 + i]
            ax, ay, az, bx, by, bz, ex, ey, ez = _corner_vectors(x, c)
            d = ex * (ay * bz - az * by) + ey * (az * bx - ax * bz) + ez * (ax * by - ay * bx)
            if not d > 0.0:
                return math.inf
            dets[i] = d
            g_log[i] = 0.0
            lo = min(lo, d)
            hi = max(hi, d)
        aim = log_aim[e]
        tet_weight = element_weight[e]
        # the logarithms only where a term may be active: a pair of corners only when the
        # largest over the smallest determinant comes within a relative 1e-9 of 1 / aim (far
        # beyond the logs' rounding, so every element skipped adds exactly nothing, as before)
        pairs = k > 1 and aim > -math.inf and hi > lo * math.exp(-aim) * (1.0 - 1e-9)
        tet_terms = k == 1 and (
            log_collapse_aim[e] > -math.inf
            or log_sine_aim[e] > -math.inf
            or log_ratio_aim[e] > -math.inf
        )
        if pairs or tet_terms:
            for i in range(k):
                logs[i] = math.log(dets[i])
        if pairs:
            for i in range(k):
                for j in range(k):
                    u = aim - logs[i] + logs[j]
                    if i != j and u > 0.0:
                        total += tet_weight * u * u
                        g_log[i] -= 2.0 * tet_weight * u
                        g_log[j] += 2.0 * tet_weight * u
        if k == 1 and (log_collapse_aim[e] > -math.inf or log_sine_aim[e] > -math.inf):
            c = corners[p0]
            for f in range(4):
                i0 = c[TET_OPPOSITE[f, 0]]
                i1 = c[TET_OPPOSITE[f, 1]]
                i2 = c[TET_OPPOSITE[f, 2]]
                nx, ny, nz = _normal(x, i0, i1, i2)
                nn = nx * nx + ny * ny + nz * nz
                normals[f, 0] = nx
                normals[f, 1] = ny
                normals[f, 2] = nz
                nns[f] = nn
                u = log_collapse_aim[e] - (logs[0] - 0.75 * math.log(nn) + LOG_COLLAPSE_SCALE)
                if u > 0.0:
                    total += tet_weight * u * u
                    g_log[0] -= 2.0 * tet_weight * u
                    # d log|n| = n . dn / |n|^2, and log c falls by 1.5 log|n|
                    _cross_grad(x, grad, i0, i1, i2, nx, ny, nz, 3.0 * tet_weight * u / nn)
            if log_sine_aim[e] > -math.inf:
                for m in range(6):
                    a = c[TET_EDGES[m, 0]]
                    b = c[TET_EDGES[m, 1]]
                    lx = x[b, 0] - x[a, 0]
                    ly = x[b, 1] - x[a, 1]
                    lz = x[b, 2] - x[a, 2]
                    ll = lx * lx + ly * ly + lz * lz
                    fk = TET_EDGES[m, 2]
                    fl = TET_EDGES[m, 3]
                    # log sin = log d + log L - log|n_k| - log|n_l|
                    u = log_sine_aim[e] - (logs[0] + 0.5 * math.log(ll / (nns[fk] * nns[fl])))
                    if u > 0.0:
                        w = 2.0 * tet_weight * u
                        total += tet_weight * u * u
                        g_log[0] -= w
                        s_l = w / ll  # d(u^2)/d b = -2u (b - a) / L^2
                        grad[b, 0] -= s_l * lx
                        grad[b, 1] -= s_l * ly
                        grad[b, 2] -= s_l * lz
                        grad[a, 0] += s_l * lx
                        grad[a, 1] += s_l * ly
                        grad[a, 2] += s_l * lz
                        for f in (fk, fl):
                            # d(u^2) = 2u d log|n_f| = 2u n . dn / |n|^2
                            _cross_grad(
                                x,
                                grad,
                                c[TET_OPPOSITE[f, 0]],
                                c[TET_OPPOSITE[f, 1]],
                                c[TET_OPPOSITE[f, 2]],
                                normals[f, 0],
                                normals[f, 1],
                                normals[f, 2],
                                w / nns[f],
                            )
        if k == 1 and log_ratio_aim[e] > -math.inf:
            ax, ay, az, bx, by, bz, ex, ey, ez = _corner_vectors(x, corners[p0])
            aa = ax * ax + ay * ay + az * az
            bb = bx * bx + by * by + bz * bz
            ee = ex * ex + ey * ey + ez * ez
            bex, bey, bez = by * ez - bz * ey, bz * ex - bx * ez, bx * ey - by * ex
            eax, eay, eaz = ey * az - ez * ay, ez * ax - ex * az, ex * ay - ey * ax
            abx, aby, abz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            mx = aa * bex + bb * eax + ee * abx
            my = aa * bey + bb * eay + ee * aby
            mz = aa * bez + bb * eaz + ee * abz
            mm = mx * mx + my * my + mz * mz
            u = log_ratio_aim[e] - (LOG_RATIO_SCALE + 4.0 * logs[0] - 1.5 * math.log(mm))
            if u > 0.0:
                total += tet_weight * u * u
                g_log[0] -= 8.0 * tet_weight * u
                s = 6.0 * tet_weight * u / mm  # d(u^2) = ... + 6u M . dM / |M|^2
                m_be = mx * bex + my * bey + mz * bez
                m_ea = mx * eax + my * eay + mz * eaz
                m_ab = mx * abx + my * aby + mz * abz
                # dM . M over a: 2 (M . b x e) a + |b|^2 (M x e) + |e|^2 (b x M)
                gax = s * (2.0 * m_be * ax + bb * (my * ez - mz * ey) + ee * (by * mz - bz * my))
                gay = s * (2.0 * m_be * ay + bb * (mz * ex - mx * ez) + ee * (bz * mx - bx * mz))
                gaz = s * (2.0 * m_be * az + bb * (mx * ey - my * ex) + ee * (bx * my - by * mx))
                # over b: |a|^2 (e x M) + 2 (M . e x a) b + |e|^2 (M x a)
                gbx = s * (aa * (ey * mz - ez * my) + 2.0 * m_ea * bx + ee * (my * az - mz * ay))
                gby = s * (aa * (ez * mx - ex * mz) + 2.0 * m_ea * by + ee * (mz * ax - mx * az))
                gbz = s * (aa * (ex * my - ey * mx) + 2.0 * m_ea * bz + ee * (mx * ay - my * ax))
                # over e: |a|^2 (M x b) + |b|^2 (a x M) + 2 (M . a x b) e
                gex = s * (aa * (my * bz - mz * by) + bb * (ay * mz - az * my) + 2.0 * m_ab * ex)
                gey = s * (aa * (mz * bx - mx * bz) + bb * (az * mx - ax * mz) + 2.0 * m_ab * ey)
                gez = s * (aa * (mx * by - my * bx) + bb * (ax * my - ay * mx) + 2.0 * m_ab * ez)
                c = corners[p0]
                _add_corner_gradient(grad, c, gax, gay, gaz, gbx, gby, gbz, gex, gey, gez)
        g_volume = 0.0
        if volume_band[e] < math.inf:
            mean = 0.0
            for i in range(k):
                mean += dets[i]
            mean /= k
            change = math.log(mean) - log_volume[e]
            excess = abs(change) - volume_band[e]
            if excess > 0.0:
                total += volume_weight * excess * excess
                # d/d d_i of log(mean) = 1 / (k mean)
                sign = 1.0 if change > 0.0 else -1.0
                g_volume = 2.0 * volume_weight * excess * sign / (k * mean)
        for i in range(k):
            if g_log[i] == 0.0 and g_volume == 0.0:
                continue
            s = g_log[i] / dets[i] + g_volume
            c = corners[p0 + i]
            ax, ay, az, bx, by, bz, ex, ey, ez = _corner_vectors(x, c)
            # d = (a x b) . e: dd/da = b x e, dd/db = e x a, dd/de = a x b
            gax = s * (by * ez - bz * ey)
            gay = s * (bz * ex - bx * ez)
            gaz = s * (bx * ey - by * ex)
            gbx = s * (ey * az - ez * ay)
            gby = s * (ez * ax - ex * az)
            gbz = s * (ex * ay - ey * ax)
            gex = s * (ay * bz - az * by)
            gey = s * (az * bx - ax * bz)
            gez = s * (ax * by - ay * bx)
            _add_corner_gradient(grad, c, gax, gay, gaz, gbx, gby, gbz, gex, gey, gez)
    for q in range(quads.shape[0]):
        n0 = quads[q, 0]
        n1 = quads[q, 1]
        n2 = quads[q, 2]
        n3 = quads[q, 3]
        px = x[n2, 0] - x[n0, 0]
        py = x[n2, 1] - x[n0, 1]
        pz = x[n2, 2] - x[n0, 2]
        qx = x[n3, 0] - x[n1, 0]
        qy = x[n3, 1] - x[n1, 1]
        qz = x[n3, 2] - x[n1, 2]
        nx = py * qz - pz * qy
        ny = pz * qx - px * qz
        nz = px * qy - py * qx
        for i in range(4):
            c = quads[q, quad_triples[i, 0]]
            wx, wy, wz = _normal(x, c, quads[q, quad_triples[i, 1]], quads[q, quad_triples[i, 2]])
            d = nx * wx + ny * wy + nz * wz
            if not d > 0.0:
                return math.inf
            dets[i] = d
            logs[i] = math.log(d)
            g_log[i] = 0.0
        aim = quad_log_aim[q]
        for i in range(4):
            for j in range(4):
                u = aim - logs[i] + logs[j]
                if i != j and u > 0.0:
                    total += u * u
                    g_log[i] -= 2.0 * u
                    g_log[j] += 2.0 * u
        for i in range(4):
            if g_log[i] == 0.0:
                continue
            s = g_log[i] / dets[i]
            c = quads[q, quad_triples[i, 0]]
            a = quads[q, quad_triples[i, 1]]
            b = quads[q, quad_triples[i, 2]]
            # d = w . n with w = (x_a - x_c) x (x_b - x_c) and n = p x q: the corner's
            # vectors as in _cross_grad, and dd/dp = q x w, dd/dq = w x p
            _cross_grad(x, grad, c, a, b, nx, ny, nz, s)
            wx, wy, wz = _normal(x, c, a, b)
            _diagonal_cross_grad(x, grad, n0, n1, n2, n3, px, py, pz, qx, qy, qz, wx, wy, wz, s)
    return total


@njit(cache=True, nogil=True, inline="always")
def _add_corner_gradient(
    grad, c, gax, gay, gaz, gbx, gby, gbz, gex, gey, gez
):  # pragma: no cover - compiled
    """Add a corner's gradient over its edge vectors ``a, b, e`` (``x[c[j]] - x[c[0]]``) to
    its four nodes: each edge end gets its own, the corner node minus their sum."""
    grad[c[1], 0] += gax
    grad[c[1], 1] += gay
    grad[c[1], 2] += gaz
    grad[c[2], 0] += gbx
    grad[c[2], 1] += gby
    grad[c[2], 2] += gbz
    grad[c[3], 0] += gex
    grad[c[3], 1] += gey
    grad[c[3], 2] += gez
    grad[c[0], 0] -= gax + gbx + gex
    grad[c[0], 1] -= gay + gby + gey
    grad[c[0], 2] -= gaz + gbz + gez


@njit(cache=True, nogil=True, inline="always")
def _corner_vectors(x, c):  # pragma: no cover - compiled
    """The corner's edge vectors ``a, b, e`` (``x[c[j]] - x[c[0]]``, j = 1, 2, 3) as 9 floats:
    :data:`kneegui.topology.CORNER_TRIPLES` as in :func:`kneegui.quality.kernels.corner_vectors`."""
    ax = x[c[1], 0] - x[c[0], 0]
    ay = x[c[1], 1] - x[c[0], 1]
    az = x[c[1], 2] - x[c[0], 2]
    bx = x[c[2], 0] - x[c[0], 0]
    by = x[c[2], 1] - x[c[0], 1]
    bz = x[c[2], 2] - x[c[0], 2]
    ex = x[c[3], 0] - x[c[0], 0]
    ey = x[c[3], 1] - x[c[0], 1]
    ez = x[c[3], 2] - x[c[0], 2]
    return ax, ay, az, bx, by, bz, ex, ey, ez


@njit(cache=True, nogil=True, inline="always")
def _cross_grad(x, grad, base, iu, iv, gx, gy, gz, s):  # pragma: no cover - compiled
    """Add ``s * d(G . n)/dx`` for ``n = (x[iu] - x[base]) x (x[iv] - x[base])``."""
    ux = x[iu, 0] - x[base, 0]
    uy = x[iu, 1] - x[base, 1]
    uz = x[iu, 2] - x[base, 2]
    vx = x[iv, 0] - x[base, 0]
    vy = x[iv, 1] - x[base, 1]
    vz = x[iv, 2] - x[base, 2]
    # d(G . (u x v))/du = v x G, /dv = G x u
    aux = s * (vy * gz - vz * gy)
    auy = s * (vz * gx - vx * gz)
    auz = s * (vx * gy - vy * gx)
    avx = s * (gy * uz - gz * uy)
    avy = s * (gz * ux - gx * uz)
    avz = s * (gx * uy - gy * ux)
    grad[iu, 0] += aux
    grad[iu, 1] += auy
    grad[iu, 2] += auz
    grad[iv, 0] += avx
    grad[iv, 1] += avy
    grad[iv, 2] += avz
    grad[base, 0] -= aux + avx
    grad[base, 1] -= auy + avy
    grad[base, 2] -= auz + avz


@njit(cache=True, nogil=True, inline="always")
def _diagonal_cross_grad(
    x, grad, q0, q1, q2, q3, px, py, pz, qx, qy, qz, wx, wy, wz, s
):  # pragma: no cover - compiled
    """Add ``s * d(w . n)/dx`` for a quad's diagonal normal ``n = p x q`` with
    ``p = x[q2] - x[q0]``, ``q = x[q3] - x[q1]`` (given), ``w`` held fixed."""
    # d(w . (p x q))/dp = q x w, /dq = w x p
    gpx = s * (qy * wz - qz * wy)
    gpy = s * (qz * wx - qx * wz)
    gpz = s * (qx * wy - qy * wx)
    gqx = s * (wy * pz - wz * py)
    gqy = s * (wz * px - wx * pz)
    gqz = s * (wx * py - wy * px)
    grad[q2, 0] += gpx
    grad[q2, 1] += gpy
    grad[q2, 2] += gpz
    grad[q0, 0] -= gpx
    grad[q0, 1] -= gpy
    grad[q0, 2] -= gpz
    grad[q3, 0] += gqx
    grad[q3, 1] += gqy
    grad[q3, 2] += gqz
    grad[q1, 0] -= gqx
    grad[q1, 1] -= gqy
    grad[q1, 2] -= gqz


@njit(cache=True, nogil=True, inline="always")
def _normal(x, base, iu, iv):  # pragma: no cover - compiled
    ux = x[iu, 0] - x[base, 0]
    uy = x[iu, 1] - x[base, 1]
    uz = x[iu, 2] - x[base, 2]
    vx = x[iv, 0] - x[base, 0]
    vy = x[iv, 1] - x[base, 1]
    vz = x[iv, 2] - x[base, 2]
    return uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx


@njit(cache=True, nogil=True, inline="always")
def _angle_gradients(ax, ay, az, bx, by, bz):  # pragma: no cover - compiled
    """Angle theta in [0, pi] between vectors a and b, and d theta / d a, d theta / d b.

    ``theta = atan2(|a^ x b^|, a^ . b^)``; its gradient ``-(b^ - cos a^) / (sin |a|)`` stays
    finite as the vectors turn parallel or opposite (where the cosine's own gradient
    vanishes: a face folded flat would otherwise feel no pull). Returns zeros for a zero
    vector or an angle of exactly 0 or pi.
    """
    la = math.sqrt(ax * ax + ay * ay + az * az)
    lb = math.sqrt(bx * bx + by * by + bz * bz)
    if la == 0.0 or lb == 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    c = (ax * bx + ay * by + az * bz) / (la * lb)
    cx = (ay * bz - az * by) / (la * lb)
    cy = (az * bx - ax * bz) / (la * lb)
    cz = (ax * by - ay * bx) / (la * lb)
    sn = math.sqrt(cx * cx + cy * cy + cz * cz)
    theta = math.atan2(sn, c)
    if sn < 1e-12:
        return theta, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    ka = -1.0 / (sn * la)
    kb = -1.0 / (sn * lb)
    return (
        theta,
        ka * (bx / lb - c * ax / la),
        ka * (by / lb - c * ay / la),
        ka * (bz / lb - c * az / la),
        kb * (ax / la - c * bx / lb),
        kb * (ay / la - c * by / lb),
        kb * (az / la - c * bz / lb),
    )


@njit(cache=True, nogil=True, inline="always")
def _fold_penalty(x, grad, a0, a1, a2, b0, b1, b2, aim, cos_aim, weight):  # pragma: no cover
    """``weight * max(0, theta - aim)^2``, theta the angle (radians) between the normals of
    triangles (a0, a1, a2) and (b0, b1, b2) (base first); adds its gradient, returns the
    penalty."""
    ax, ay, az = _normal(x, a0, a1, a2)
    bx, by, bz = _normal(x, b0, b1, b2)
    # cheap test first: most faces are flatter than their aim
    norms = math.sqrt((ax * ax + ay * ay + az * az) * (bx * bx + by * by + bz * bz))
    if norms == 0.0 or ax * bx + ay * by + az * bz >= cos_aim * norms:
        return 0.0
    theta, gax, gay, gaz, gbx, gby, gbz = _angle_gradients(ax, ay, az, bx, by, bz)
    excess = theta - aim
    if excess <= 0.0:
        return 0.0
    s = 2.0 * weight * excess
    _cross_grad(x, grad, a0, a1, a2, gax, gay, gaz, s)
    _cross_grad(x, grad, b0, b1, b2, gbx, gby, gbz, s)
    return weight * excess * excess


def face_aims(log_aspect_aim: np.ndarray, warp_aim: np.ndarray, skew_aim: np.ndarray) -> np.ndarray:
    """(F, 6) per-face aims of :func:`face_shape_penalty`: the log aspect aim, the squared
    edge-length ratio it allows, the warpage aim (radians) and its cosine, the skew aim
    (radians) and its sine. Worked out once per problem: the cosine and sine per face and
    evaluation were half of the kernel's time."""
    return np.ascontiguousarray(
        np.column_stack(
            [
                log_aspect_aim,
                np.exp(2.0 * log_aspect_aim),
                warp_aim,
                np.cos(warp_aim),
                skew_aim,
                np.sin(skew_aim),
            ]
        ),
        dtype=np.float64,
    )


@njit(cache=True, nogil=True)
def face_shape_penalty(x, faces, aims, weights, grad):  # pragma: no cover - compiled
    """Penalties on quad faces (F, 4) and triangle faces (F, 4 with -1 last) whose aspect
    ratio, warpage or skew exceed their aims (QUALITY.md definitions); adds to ``grad``.

    ``aims`` (F, 6) from :func:`face_aims`; ``weights`` = (aspect, warpage, skew). Aspect:
    ``max(0, log(l_i / l_j) - log aim)^2`` over the face's edge pairs; warpage:
    ``max(0, theta - aim)^2`` for the angle between the triangle normals of both diagonal
    splits; skew: ``max(0, |theta - pi/2| - aim)^2`` for the angle between the mid-side lines.
    Each term is first tested cheaply (squared lengths, cosines, against limits worked out
    once in :func:`face_aims`): the logarithms, angles and gradients are only worked out for
    the faces that miss an aim.
    """
    total = 0.0
    sq = np.empty(4)
    g_log = np.empty(4)
    w_aspect, w_warp, w_skew = weights[0], weights[1], weights[2]
    for f in range(faces.shape[0]):
        k = 4 if faces[f, 3] >= 0 else 3
        lo = math.inf
        hi = 0.0
        for i in range(k):
            a = faces[f, i]
            b = faces[f, (i + 1) % k]
            dx = x[b, 0] - x[a, 0]
            dy = x[b, 1] - x[a, 1]
            dz = x[b, 2] - x[a, 2]
            sq[i] = dx * dx + dy * dy + dz * dz
            if not sq[i] > 0.0:
                return math.inf
            lo = min(lo, sq[i])
            hi = max(hi, sq[i])
        aim = aims[f, 0]
        if w_aspect > 0.0 and hi > aims[f, 1] * lo:
            for i in range(k):
                g_log[i] = 0.0
            for i in range(k):
                for j in range(k):
                    u = 0.5 * (math.log(sq[i]) - math.log(sq[j])) - aim
                    if i != j and u > 0.0:
                        total += w_aspect * u * u
                        g_log[i] += 2.0 * w_aspect * u
                        g_log[j] -= 2.0 * w_aspect * u
            for i in range(k):
                if g_log[i] == 0.0:
                    continue
                a = faces[f, i]
                b = faces[f, (i + 1) % k]
                dx = x[b, 0] - x[a, 0]
                dy = x[b, 1] - x[a, 1]
                dz = x[b, 2] - x[a, 2]
                s = g_log[i] / sq[i]  # d(0.5 log sq) = d sq / (2 sq)
                grad[b, 0] += s * dx
                grad[b, 1] += s * dy
                grad[b, 2] += s * dz
                grad[a, 0] -= s * dx
                grad[a, 1] -= s * dy
                grad[a, 2] -= s * dz
        if k == 3:
            continue
        p0 = faces[f, 0]
        p1 = faces[f, 1]
        p2 = faces[f, 2]
        p3 = faces[f, 3]
        if w_warp > 0.0:
            # split along 0-2: (0, 1, 2) and (0, 2, 3); along 1-3: (0, 1, 3) and (1, 2, 3)
            aim = aims[f, 2]
            cos_aim = aims[f, 3]
            total += _fold_penalty(x, grad, p0, p1, p2, p0, p2, p3, aim, cos_aim, w_warp)
            total += _fold_penalty(x, grad, p0, p1, p3, p1, p2, p3, aim, cos_aim, w_warp)
        if w_skew > 0.0:
            # X1 = (p1 - p0) - (p3 - p2), X2 = (p2 - p1) - (p0 - p3)
            ax = x[p1, 0] - x[p0, 0] - x[p3, 0] + x[p2, 0]
            ay = x[p1, 1] - x[p0, 1] - x[p3, 1] + x[p2, 1]
            az = x[p1, 2] - x[p0, 2] - x[p3, 2] + x[p2, 2]
            bx = x[p2, 0] - x[p1, 0] - x[p0, 0] + x[p3, 0]
            by = x[p2, 1] - x[p1, 1] - x[p0, 1] + x[p3, 1]
            bz = x[p2, 2] - x[p1, 2] - x[p0, 2] + x[p3, 2]
            # cheap test first: |cos| of the angle between the lines against sin(aim)
            norms = math.sqrt((ax * ax + ay * ay + az * az) * (bx * bx + by * by + bz * bz))
            if norms == 0.0 or abs(ax * bx + ay * by + az * bz) <= aims[f, 5] * norms:
                continue
            theta, gax, gay, gaz, gbx, gby, gbz = _angle_gradients(ax, ay, az, bx, by, bz)
            half = 0.5 * math.pi
            excess = abs(theta - half) - aims[f, 4]
            if excess <= 0.0:
                continue
            total += w_skew * excess * excess
            s = 2.0 * w_skew * excess * (1.0 if theta > half else -1.0)
            gax *= s
            gay *= s
            gaz *= s
            gbx *= s
            gby *= s
            gbz *= s
            # dX1: +p1 +p2 -p0 -p3; dX2: +p2 +p3 -p1 -p0
            grad[p1, 0] += gax - gbx
            grad[p1, 1] += gay - gby
            grad[p1, 2] += gaz - gbz
            grad[p2, 0] += gax + gbx
            grad[p2, 1] += gay + gby
            grad[p2, 2] += gaz + gbz
            grad[p0, 0] -= gax + gbx
            grad[p0, 1] -= gay + gby
            grad[p0, 2] -= gaz + gbz
            grad[p3, 0] += gbx - gax
            grad[p3, 1] += gby - gay
            grad[p3, 2] += gbz - gaz
    return total


@njit(cache=True, nogil=True, parallel=True)
def penalty_in_parts(  # pragma: no cover - compiled
    x,
    corners,
    elem_ptr,
    log_aim,
    log_collapse_aim,
    log_sine_aim,
    log_ratio_aim,
    element_weight,
    log_volume,
    volume_band,
    volume_weight,
    quads,
    quad_triples,
    quad_log_aim,
    faces,
    aims,
    weights,
    e_cut,
    q_cut,
    f_cut,
    buffers,
    totals,
):
    """:func:`corner_ratio_penalty` plus :func:`face_shape_penalty` over fixed parts of the
    elements, quads and faces (``e_cut``, ``q_cut``, ``f_cut``: :mod:`kneegui.meshopt.parallel`)
    in parallel: part ``k`` fills ``buffers[k]`` with its gradient and ``totals[k]`` with its
    penalty (``inf`` where a corner is not positive)."""
    for k in prange(len(e_cut) - 1):
        e0, e1 = e_cut[k], e_cut[k + 1]
        c0, c1 = elem_ptr[e0], elem_ptr[e1]
        q0, q1 = q_cut[k], q_cut[k + 1]
        f0, f1 = f_cut[k], f_cut[k + 1]
        value = corner_ratio_penalty(  # zeroes the buffer first
            x,
            corners[c0:c1],
            elem_ptr[e0 : e1 + 1] - c0,
            log_aim[e0:e1],
            log_collapse_aim[e0:e1],
            log_sine_aim[e0:e1],
            log_ratio_aim[e0:e1],
            element_weight[e0:e1],
            log_volume[e0:e1],
            volume_band[e0:e1],
            volume_weight,
            quads[q0:q1],
            quad_triples,
            quad_log_aim[q0:q1],
            buffers[k],
        )
        if not np.isfinite(value):
            totals[k] = np.inf
        else:
            totals[k] = value + face_shape_penalty(
                x, faces[f0:f1], aims[f0:f1], weights, buffers[k]
            )


@njit(cache=True, nogil=True)
def below_floor(  # pragma: no cover - compiled
    x, corners, elem_ptr, log_jacobian_floor, log_collapse_floor
):
    """True when a solid has a corner that is not positive, a corner Jacobian ``min d / max d``
    (elements of several corners) below ``exp(log_jacobian_floor)``, or a tetrahedron (one
    corner) a collapse below ``exp(log_collapse_floor)``; the arguments as
    :func:`corner_ratio_penalty`'s."""
    for e in range(elem_ptr.shape[0] - 1):
        p0 = elem_ptr[e]
        k = elem_ptr[e + 1] - p0
        lo = math.inf
        hi = -math.inf
        for i in range(k):
            ax, ay, az, bx, by, bz, ex, ey, ez = _corner_vectors(x, corners[p0 + i])
            d = ex * (ay * bz - az * by) + ey * (az * bx - ax * bz) + ez * (ax * by - ay * bx)
            if not d > 0.0:
                return True
            log_d = math.log(d)
            lo = min(lo, log_d)
            hi = max(hi, log_d)
        if k > 1:
            if lo - hi < log_jacobian_floor:
                return True
        elif log_collapse_floor > -math.inf:
            c = corners[p0]
            for f in range(4):
                nx, ny, nz = _normal(
                    x, c[TET_OPPOSITE[f, 0]], c[TET_OPPOSITE[f, 1]], c[TET_OPPOSITE[f, 2]]
                )
                nn = nx * nx + ny * ny + nz * nz
                if lo - 0.75 * math.log(nn) + LOG_COLLAPSE_SCALE < log_collapse_floor:
                    return True
    return False


@njit(cache=True, nogil=True)
def scatter_free(work, free, v, h):  # pragma: no cover - compiled
    """``work[free[r]] = v[3 r : 3 r + 3] * h[r]`` (the scaled variables back to coordinates)."""
    for r in range(free.shape[0]):
        for j in range(3):
            work[free[r], j] = v[3 * r + j] * h[r, 0]


@njit(cache=True, nogil=True)
def anchor_and_constraints(  # pragma: no cover - compiled
    v,
    h,
    start,
    free,
    grad,
    anchor,
    c_rows,
    c_weights,
    c_partners,
    c_partner_weights,
    c_normals,
    c_offsets,
    stiffness,
    out,
):
    """The optimiser's objective beyond the penalties, over the free nodes' scaled variables
    ``v`` (``x = v h``): ``anchor * |(x - start) / h|^2`` plus ``stiffness * min(0, gap)^2``
    per constraint row, ``gap = n . (w x_r + w' x_p) - offset`` for its free row ``r`` with
    weight ``w`` and, where ``c_partners`` is not -1, a second free row ``p`` with weight
    ``w'`` (a plane on a point between two nodes: an edge's middle); writes the whole gradient
    with respect to ``v`` (the penalties' ``grad`` at the free nodes included) into ``out``,
    returns the added value. Sums run in index order."""
    total = 0.0
    for r in range(free.shape[0]):
        hr = h[r, 0]
        for j in range(3):
            dx = (v[3 * r + j] * hr - start[r, j]) / hr
            total += anchor * dx * dx
            out[3 * r + j] = grad[free[r], j] + 2.0 * anchor * dx / hr
    for k in range(c_rows.shape[0]):
        r = c_rows[k]
        p = c_partners[k]
        w = c_weights[k]
        gap = -c_offsets[k]
        for j in range(3):
            gap += c_normals[k, j] * v[3 * r + j] * h[r, 0] * w
        if p >= 0:
            for j in range(3):
                gap += c_normals[k, j] * v[3 * p + j] * h[p, 0] * c_partner_weights[k]
        if gap < 0.0:
            total += stiffness * gap * gap
            for j in range(3):
                out[3 * r + j] += 2.0 * stiffness * gap * w * c_normals[k, j]
            if p >= 0:
                for j in range(3):
                    out[3 * p + j] += 2.0 * stiffness * gap * c_partner_weights[k] * c_normals[k, j]
    for r in range(free.shape[0]):
        for j in range(3):
            out[3 * r + j] *= h[r, 0]
    return total
