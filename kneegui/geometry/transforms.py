"""Rigid transforms: rotation about an arbitrary axis, composition, best-fit (Kabsch)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kneegui.errors import GeometryError


def unit(vector: ArrayLike, what: str = "vector") -> NDArray[np.float64]:
    """``vector / |vector|``; raises :class:`GeometryError` for a zero or non-finite vector."""
    v = np.asarray(vector, dtype=np.float64)
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n == 0.0:
        raise GeometryError(f"{what} has zero or non-finite length")
    return v / n


def rotation_matrix(axis: ArrayLike, angle_deg: float) -> NDArray[np.float64]:
    """Rotation matrix (3, 3) by ``angle_deg`` about ``axis`` (right-hand rule, Rodrigues)."""
    k = unit(axis, "rotation axis")
    a = np.radians(angle_deg)
    c, s = np.cos(a), np.sin(a)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return c * np.eye(3) + s * kx + (1.0 - c) * np.outer(k, k)


@dataclass(frozen=True, eq=False)
class RigidTransform:
    """``x -> rotation @ x + translation``.

    Attributes
    ----------
    rotation : (3, 3) ndarray of float
        Proper orthonormal matrix.
    translation : (3,) ndarray of float
        Translation (model units).
    """

    rotation: NDArray[np.float64]
    translation: NDArray[np.float64]

    def __post_init__(self) -> None:
        r = np.array(self.rotation, dtype=np.float64).reshape(3, 3)
        t = np.array(self.translation, dtype=np.float64).reshape(3)
        r.flags.writeable = False
        t.flags.writeable = False
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation", t)

    @classmethod
    def identity(cls) -> RigidTransform:
        """The identity transform."""
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def about_axis(cls, point: ArrayLike, direction: ArrayLike, angle_deg: float) -> RigidTransform:
        """Rotation by ``angle_deg`` about the line through ``point`` along ``direction``."""
        r = rotation_matrix(direction, angle_deg)
        p = np.asarray(point, dtype=np.float64)
        return cls(r, p - r @ p)

    @classmethod
    def from_matrix(cls, matrix: ArrayLike) -> RigidTransform:
        """From a (4, 4) homogeneous matrix."""
        m = np.asarray(matrix, dtype=np.float64)
        return cls(m[:3, :3], m[:3, 3])

    @property
    def matrix(self) -> NDArray[np.float64]:
        """(4, 4) homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.translation
        return m

    def apply(self, points: ArrayLike) -> NDArray[np.float64]:
        """Transform points (..., 3) -> new array (..., 3)."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.rotation.T + self.translation

    def apply_vector(self, vectors: ArrayLike) -> NDArray[np.float64]:
        """Rotate direction vectors (..., 3) (no translation)."""
        return np.asarray(vectors, dtype=np.float64) @ self.rotation.T

    def then(self, other: RigidTransform) -> RigidTransform:
        """The transform that applies ``self`` first, then ``other``."""
        return RigidTransform(
            other.rotation @ self.rotation, other.rotation @ self.translation + other.translation
        )

    def inverse(self) -> RigidTransform:
        """The inverse transform."""
        rt = self.rotation.T
        return RigidTransform(rt, -rt @ self.translation)

    def angle_deg(self) -> float:
        """Rotation angle (degrees, 0..180)."""
        c = (np.trace(self.rotation) - 1.0) / 2.0
        return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def best_fit_transform(source: ArrayLike, target: ArrayLike) -> RigidTransform:
    """Least-squares rigid transform mapping ``source`` points onto ``target`` (Kabsch).

    Parameters
    ----------
    source, target : (M, 3) array_like of float
        Corresponding points, M >= 3 and not collinear.
    """
    a = np.asarray(source, dtype=np.float64)
    b = np.asarray(target, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3 or len(a) < 3:
        raise GeometryError(f"best-fit transform needs two (M>=3, 3) arrays, got {a.shape}")
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    h = (a - ca).T @ (b - cb)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return RigidTransform(r, cb - r @ ca)
