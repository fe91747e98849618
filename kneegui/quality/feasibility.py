"""Whether an element with some nodes held in place can still be made valid by moving the others.

A corner's determinant (the signed volume of the tetrahedron of a corner and its three
neighbours, :data:`~kneegui.topology.CORNER_TRIPLES`) is affine in each of its nodes, so for
one free node the corners in which it is the only free node are half-spaces it must lie in.
:func:`could_be_valid` looks for a proof that no position of the free nodes makes every corner
positive; it is used by the pre-flight check (elements locked between two bones beyond some
flexion, :mod:`kneegui.reposition.preflight`) and by the relaxation, which leaves the corners of
an element proven locked at a pose out of its energy (:mod:`kneegui.reposition.relax`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from kneegui.topology import CORNER_TRIPLES


def corner_determinant_gradients(
    corners: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Determinants ``(...)`` of corner tetrahedra ``(..., 4, 3)`` (the corner node first, then
    its three neighbours) and their gradients ``(..., 4, 3)`` with respect to each of the four
    nodes: a determinant is affine in each node, ``d + g . (x - x_0)`` in that node alone."""
    e1, e2, e3 = (corners[..., s, :] - corners[..., 0, :] for s in (1, 2, 3))
    grads = np.stack([np.cross(e2, e3), np.cross(e3, e1), np.cross(e1, e2)], axis=-2)
    det = np.einsum("...i,...i->...", e1, grads[..., 0, :])
    return det, np.concatenate([-grads.sum(axis=-2, keepdims=True), grads], axis=-2)


def could_be_valid(
    posed: NDArray[np.float64], free: NDArray[np.bool_], etype: str, tolerance: float = 0.0
) -> NDArray[np.bool_]:
    """Whether elements with some nodes fixed at ``posed`` (L, k, 3) could still be valid
    wherever their ``free`` (L, k) nodes go: False only with a proof that they cannot.

    A corner's determinant is the signed volume of the tetrahedron of the corner and its three
    neighbours, affine in each of its nodes. Proofs: (a) a corner with no free node whose
    determinant is not positive; (b) for one free node, the corners in which it is the only
    free node ask it to lie strictly on the positive side of the planes through their other
    (fixed) nodes; when there are four such corners with independent normals ``g_c``
    (determinant ``d_c + g_c . (x - x_0)``), they admit no position exactly when the one
    combination ``sum l_c g_c = 0`` has every ``l_c >= 0`` and ``sum l_c d_c <= 0`` (Farkas'
    lemma; the sum is the same for every ``x_0``). Corners with two free nodes are left out,
    so a False is a proof and a True only means no proof was found. Fully fixed elements get
    the plain corner test.

    ``tolerance`` > 0 asks each proof to hold by that margin, relative to the element's largest
    corner determinant (a corner determinant at most ``-tolerance`` times it; every ``l_c`` at
    least ``tolerance`` times the largest and ``sum l_c d_c`` at most ``-tolerance`` times
    the largest determinant times ``sum l_c``): a decision that rounding cannot flip (a corner
    flat in the deck, moved rigidly, has a determinant of either sign at the last bits). It
    proves less, never more.
    """
    table = np.array(CORNER_TRIPLES[etype])
    if (table < 0).any():  # a shell's corners are not volumes: no proof
        return np.ones(len(posed), dtype=bool)
    det, grads = corner_determinant_gradients(posed[:, table])  # (L, C), (L, C, 4, 3)
    n_free = free[:, table].sum(axis=-1)  # (L, C)
    margin = tolerance * np.abs(det).max(axis=1)  # (L,)
    ok = ~((n_free == 0) & (det <= -margin[:, None])).any(axis=1)
    for node in range(posed.shape[1]):
        where = np.argwhere(table == node)  # (corner, slot) pairs holding the node
        if len(where) != 4:
            continue  # fewer than four half-spaces in 3-D always meet; more: not proven here
        cs, slots = where[:, 0], where[:, 1]
        use = free[:, node] & (n_free[:, cs] == 1).all(axis=1) & ok
        if not use.any():
            continue
        g = grads[use][:, cs, slots]  # (u, 4, 3): one normal per corner
        u, sv, _ = np.linalg.svd(g, full_matrices=True)
        independent = sv[:, 2] > 1e-9 * sv[:, 0]
        lam = u[:, :, 3]  # spans the null space of g^T when the normals are independent
        lam = lam * np.where(lam.sum(axis=1) < 0.0, -1.0, 1.0)[:, None]
        proof = independent & (lam >= tolerance * lam.max(axis=1, keepdims=True)).all(axis=1)
        proof &= np.einsum("uc,uc->u", lam, det[use][:, cs]) <= -margin[use] * lam.sum(axis=1)
        ok[np.flatnonzero(use)[proof]] = False
    return ok
