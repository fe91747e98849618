"""Compiled energy and gradient of the elastic relaxation (one fused loop over the corners).

The NumPy version, :meth:`kneegui.meshopt.foldover.FoldoverEnergy.energy_numpy`, is the
reference; this is the same arithmetic, corner by corner, compiled with Numba so that a solver
iteration costs a few milliseconds instead of tens (tests check the two agree). Every 3 x 3
matrix lives in scalars (Numba keeps them in registers; small arrays it allocates on the heap
once per call and reads through memory), which made the loop about twice as fast.
"""

from __future__ import annotations

import math

from numba import njit, prange

from kneegui.meshopt.quality_kernel import _cross_grad, _diagonal_cross_grad, _normal


@njit(cache=True, nogil=True, inline="always")
def _regularised(det, eps):  # pragma: no cover - compiled
    """Garanzha's regularised determinant ``chi`` and ``d chi / d det``, as
    :func:`kneegui.meshopt.foldover.regularised_det` for one value."""
    root = math.sqrt(eps * eps + det * det)
    if det >= 0.0:
        chi = 0.5 * (det + root)
    else:
        chi = 0.5 * eps * eps / (root - det)
    if chi < 1e-300:
        chi = 1e-300
    return chi, 0.5 * (1.0 + det / root)


@njit(cache=True, nogil=True)
def foldover_free_energy(
    xa, tets, g, w, rows, theta, eps, grad, det_out, corner_theta
):  # pragma: no cover - compiled
    """Energy of Garanzha et al. (2021) summed over corners; fills ``grad`` (S, 3) and
    ``det_out`` (C,).

    ``xa`` (S, 3) coordinates, ``tets`` (C, 4) local node indices (corner first); corner ``c``'s
    inverse rest edge matrix (J = E @ G) is ``g[rows[c]]`` and its weight ``w[rows[c]]``: the
    rows of arrays shared with the whole relaxation, which a region's energy does not copy.
    ``corner_theta`` (C,) gives each corner its own volume weight instead of ``theta`` (empty:
    ``theta`` for every corner).
    """
    grad[:, :] = 0.0
    total = 0.0
    own_theta = corner_theta.shape[0] > 0
    for c in range(tets.shape[0]):
        a0 = tets[c, 0]
        a1 = tets[c, 1]
        a2 = tets[c, 2]
        a3 = tets[c, 3]
        x0 = xa[a0, 0]
        y0 = xa[a0, 1]
        z0 = xa[a0, 2]
        # edge matrix E: row = coordinate, column = edge
        e00 = xa[a1, 0] - x0
        e10 = xa[a1, 1] - y0
        e20 = xa[a1, 2] - z0
        e01 = xa[a2, 0] - x0
        e11 = xa[a2, 1] - y0
        e21 = xa[a2, 2] - z0
        e02 = xa[a3, 0] - x0
        e12 = xa[a3, 1] - y0
        e22 = xa[a3, 2] - z0
        r = rows[c]
        g00 = g[r, 0, 0]
        g01 = g[r, 0, 1]
        g02 = g[r, 0, 2]
        g10 = g[r, 1, 0]
        g11 = g[r, 1, 1]
        g12 = g[r, 1, 2]
        g20 = g[r, 2, 0]
        g21 = g[r, 2, 1]
        g22 = g[r, 2, 2]
        # J = E @ G
        j00 = e00 * g00 + e01 * g10 + e02 * g20
        j01 = e00 * g01 + e01 * g11 + e02 * g21
        j02 = e00 * g02 + e01 * g12 + e02 * g22
        j10 = e10 * g00 + e11 * g10 + e12 * g20
        j11 = e10 * g01 + e11 * g11 + e12 * g21
        j12 = e10 * g02 + e11 * g12 + e12 * g22
        j20 = e20 * g00 + e21 * g10 + e22 * g20
        j21 = e20 * g01 + e21 * g11 + e22 * g21
        j22 = e20 * g02 + e21 * g12 + e22 * g22
        # cofactor columns: c1 x c2, c2 x c0, c0 x c1
        f00 = j11 * j22 - j21 * j12
        f10 = j21 * j02 - j01 * j22
        f20 = j01 * j12 - j11 * j02
        f01 = j12 * j20 - j22 * j10
        f11 = j22 * j00 - j02 * j20
        f21 = j02 * j10 - j12 * j00
        f02 = j10 * j21 - j20 * j11
        f12 = j20 * j01 - j00 * j21
        f22 = j00 * j11 - j10 * j01
        det = j00 * f00 + j10 * f10 + j20 * f20
        det_out[c] = det
        chi, dchi = _regularised(det, eps)
        frob = (
            j00 * j00
            + j01 * j01
            + j02 * j02
            + j10 * j10
            + j11 * j11
            + j12 * j12
            + j20 * j20
            + j21 * j21
            + j22 * j22
        )
        chi23 = chi ** (2.0 / 3.0)
        shape = frob / chi23
        volume = (det * det + 1.0) / chi
        wc = w[r]
        if own_theta:
            theta = corner_theta[c]
        total += wc * ((1.0 - theta) * shape + theta * volume)
        d_cof = wc * (
            (1.0 - theta) * (-2.0 / 3.0) * shape * dchi / chi
            + theta * (2.0 * det / chi - volume * dchi / chi)
        )
        d_frob = wc * (1.0 - theta) * 2.0 / chi23
        d00 = d_frob * j00 + d_cof * f00
        d01 = d_frob * j01 + d_cof * f01
        d02 = d_frob * j02 + d_cof * f02
        d10 = d_frob * j10 + d_cof * f10
        d11 = d_frob * j11 + d_cof * f11
        d12 = d_frob * j12 + d_cof * f12
        d20 = d_frob * j20 + d_cof * f20
        d21 = d_frob * j21 + d_cof * f21
        d22 = d_frob * j22 + d_cof * f22
        # dE = dJ @ G^T: edge j, coordinate i
        h00 = d00 * g00 + d01 * g01 + d02 * g02
        h10 = d10 * g00 + d11 * g01 + d12 * g02
        h20 = d20 * g00 + d21 * g01 + d22 * g02
        h01 = d00 * g10 + d01 * g11 + d02 * g12
        h11 = d10 * g10 + d11 * g11 + d12 * g12
        h21 = d20 * g10 + d21 * g11 + d22 * g12
        h02 = d00 * g20 + d01 * g21 + d02 * g22
        h12 = d10 * g20 + d11 * g21 + d12 * g22
        h22 = d20 * g20 + d21 * g21 + d22 * g22
        grad[a1, 0] += h00
        grad[a1, 1] += h10
        grad[a1, 2] += h20
        grad[a2, 0] += h01
        grad[a2, 1] += h11
        grad[a2, 2] += h21
        grad[a3, 0] += h02
        grad[a3, 1] += h12
        grad[a3, 2] += h22
        grad[a0, 0] -= h00 + h01 + h02
        grad[a0, 1] -= h10 + h11 + h12
        grad[a0, 2] -= h20 + h21 + h22
    return total


@njit(cache=True, nogil=True, parallel=True)
def foldover_energy_in_parts(
    xa, tets, g, w, rows, theta, eps, cut, buffers, det, totals, corner_theta
):  # pragma: no cover - compiled
    """:func:`foldover_free_energy` over the fixed parts ``cut`` (:mod:`kneegui.meshopt.parallel`)
    in parallel: part ``k`` fills ``buffers[k]`` (S, 3) with its gradient and ``totals[k]`` with
    its energy; ``det`` as for the whole."""
    for k in prange(len(cut) - 1):
        a = cut[k]
        b = cut[k + 1]
        own = corner_theta[a:b] if corner_theta.shape[0] > 0 else corner_theta
        totals[k] = foldover_free_energy(
            xa, tets[a:b], g, w, rows[a:b], theta, eps, buffers[k], det[a:b], own
        )


@njit(cache=True, nogil=True)
def quad_barrier_energy(x, quads, rest, weight, eps, grad, ratios):  # pragma: no cover - compiled
    """:func:`kneegui.meshopt.foldover.quad_barrier`, compiled: the barrier
    ``(r^2 + 1) / chi(r)`` on each quad corner's determinant ratio ``r`` to rest.

    ``x`` (S, 3), ``quads`` (Q, 4) local node indices, ``rest`` (Q, 4) rest determinants. Adds
    the gradient into ``grad`` (S, 3); fills ``ratios`` (4Q,), corner ``i`` of quad ``q`` at
    ``i * Q + q``. Returns the energy.
    """
    n_quads = quads.shape[0]
    total = 0.0
    for q in range(n_quads):
        q0, q1, q2, q3 = quads[q, 0], quads[q, 1], quads[q, 2], quads[q, 3]
        # n = u x v over the diagonals u = x_2 - x_0, v = x_3 - x_1
        ux = x[q2, 0] - x[q0, 0]
        uy = x[q2, 1] - x[q0, 1]
        uz = x[q2, 2] - x[q0, 2]
        vx = x[q3, 0] - x[q1, 0]
        vy = x[q3, 1] - x[q1, 1]
        vz = x[q3, 2] - x[q1, 2]
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
        for i in range(4):
            n_i, n_1, n_3 = quads[q, i], quads[q, (i + 1) % 4], quads[q, (i + 3) % 4]
            # w = (x_1 - x_i) x (x_3 - x_i), the corner's own normal
            wx, wy, wz = _normal(x, n_i, n_1, n_3)
            r = (wx * nx + wy * ny + wz * nz) / rest[q, i]
            ratios[i * n_quads + q] = r
            chi, dchi = _regularised(r, eps)
            total += weight * (r * r + 1.0) / chi
            dr = weight * (2.0 * r / chi - (r * r + 1.0) * dchi / (chi * chi)) / rest[q, i]
            # d(w . n) through w, then through n = u x v: d/du = v x w, d/dv = w x u
            _cross_grad(x, grad, n_i, n_1, n_3, nx, ny, nz, dr)
            _diagonal_cross_grad(x, grad, q0, q1, q2, q3, ux, uy, uz, vx, vy, vz, wx, wy, wz, dr)
    return total


@njit(cache=True, nogil=True)
def scatter_scaled(work, rows, flat, scale):  # pragma: no cover - compiled
    """``work[rows] = flat.reshape(-1, 3) * scale`` (``scale`` (F, 1)) without the temporaries
    of NumPy's fancy indexing: the same products, so the same bits."""
    for i in range(rows.shape[0]):
        r = rows[i]
        s = scale[i, 0]
        work[r, 0] = flat[3 * i] * s
        work[r, 1] = flat[3 * i + 1] * s
        work[r, 2] = flat[3 * i + 2] * s


@njit(cache=True, nogil=True)
def gather_rows(grad, rows, out):  # pragma: no cover - compiled
    """``out[:] = grad[rows]`` (out (F, 3))."""
    for i in range(rows.shape[0]):
        r = rows[i]
        out[i, 0] = grad[r, 0]
        out[i, 1] = grad[r, 1]
        out[i, 2] = grad[r, 2]


@njit(cache=True, nogil=True)
def add_at_rows(grad, rows, values):  # pragma: no cover - compiled
    """``np.add.at(grad, rows, values)``: each row added in turn, in the order given (as
    ``np.add.at`` adds repeated rows), so the same bits."""
    for i in range(rows.shape[0]):
        r = rows[i]
        grad[r, 0] += values[i, 0]
        grad[r, 1] += values[i, 1]
        grad[r, 2] += values[i, 2]
