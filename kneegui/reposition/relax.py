"""As-rigid-as-possible relaxation of the soft tissue (Sorkine & Alexa 2007, volumetric form).

Starting from a pose (the rigid blend), free nodes are moved to minimise
``sum_e sum_(i,j in edges(e)) |(p_i - p_j) - R_e (x_i - x_j)|^2`` with bone and fixed nodes held:
each element wants to be a rotated copy of its initial shape. Where the blend squeezes tissue
(behind a bending knee), the relaxation pushes it out instead, as flesh bulges. Alternates a local
step (best rotation per element, by SVD) and a global step (one sparse solve, factorised once).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from kneegui.model import ElementBlock
from kneegui.reposition.rigid_blend import ELEMENT_EDGES


class ArapRelaxer:
    """Precomputed ARAP system of the selected elements.

    Parameters
    ----------
    coords : (N, 3) ndarray
        Initial (rest) coordinates.
    blocks : mapping of str to ElementBlock
        Element blocks.
    element_masks : mapping of str to (M,) bool
        Elements taking part (the soft tissue).
    free : (F,) ndarray of int
        Nodes that may move; every other node of the selected elements is held.
    """

    def __init__(
        self,
        coords: NDArray[np.float64],
        blocks: Mapping[str, ElementBlock],
        element_masks: Mapping[str, NDArray[np.bool_]],
        free: NDArray[np.int64],
    ) -> None:
        n = len(coords)
        a_list, b_list, owner_list = [], [], []
        n_elem = 0
        for etype, block in blocks.items():
            mask = element_masks.get(etype)
            if mask is None or not mask.any() or etype not in ELEMENT_EDGES:
                continue
            conn = block.conn[mask]
            for i, j in ELEMENT_EDGES[etype]:
                a_list.append(conn[:, i])
                b_list.append(conn[:, j])
                owner_list.append(n_elem + np.arange(len(conn)))
            n_elem += len(conn)
        self.n_elements = n_elem
        if n_elem == 0:
            self.free = np.zeros(0, dtype=np.int64)
            return
        a = np.concatenate(a_list)
        b = np.concatenate(b_list)
        owner = np.concatenate(owner_list)
        keep = a != b
        a, b, owner = a[keep], b[keep], owner[keep]
        self.a, self.b, self.owner = a, b, owner
        self.rest = coords[a] - coords[b]  # (K, 3) rest edge vectors
        k = len(a)
        # incidence: +1 at a, -1 at b, per element-edge
        self.incidence = sp.csr_matrix(
            (
                np.concatenate([np.ones(k), -np.ones(k)]),
                (np.concatenate([a, b]), np.concatenate([np.arange(k), np.arange(k)])),
            ),
            shape=(n, k),
        )
        lap = (self.incidence @ self.incidence.T).tocsr()
        self.free = np.asarray(free, dtype=np.int64)
        is_free = np.zeros(n, dtype=bool)
        is_free[self.free] = True
        self.held = np.flatnonzero(~is_free)
        self.l_ff = lap[self.free][:, self.free].tocsc()
        self.l_fh = lap[self.free][:, self.held].tocsr()
        self._solve = spla.splu(self.l_ff).solve if len(self.free) else None
        # element-edge -> element summation matrix for the covariance
        self.gather = sp.csr_matrix((np.ones(k), (owner, np.arange(k))), shape=(n_elem, k))

    def relax(self, positions: NDArray[np.float64], iterations: int = 10) -> NDArray[np.float64]:
        """Relaxed copy of ``positions`` (N, 3); held nodes are returned unchanged."""
        p = np.array(positions, dtype=np.float64, copy=True)
        if self.n_elements == 0 or len(self.free) == 0 or iterations <= 0:
            return p
        rhs_held = self.l_fh @ p[self.held]
        for _ in range(iterations):
            cur = p[self.a] - p[self.b]
            # covariance per element: sum over its edges of rest (x) current
            outer = self.rest[:, :, None] * cur[:, None, :]  # (K, 3, 3)
            cov = (self.gather @ outer.reshape(len(cur), 9)).reshape(-1, 3, 3)
            u, _, vt = np.linalg.svd(cov)
            rot = np.einsum("eji,ekj->eik", vt, u)  # R = V U^T
            bad = np.linalg.det(rot) < 0
            if bad.any():
                vt_fixed = vt[bad].copy()
                vt_fixed[:, 2, :] *= -1
                rot[bad] = np.einsum("eji,ekj->eik", vt_fixed, u[bad])
            target = np.einsum("kij,kj->ki", rot[self.owner], self.rest)
            rhs = (self.incidence @ target)[self.free] - rhs_held
            p[self.free] = self._solve(rhs)
        return p
