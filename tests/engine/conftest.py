"""Models built in memory for the quality, mesh-improvement and other engine tests."""

from __future__ import annotations

from itertools import product

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from kneegui.model import ElementBlock, Model, Part
from kneegui.topology import HEX_REFERENCE_COORDS


def build_block_model(
    nx: int = 6,
    ny: int = 6,
    nz: int = 6,
    bone_layers: int = 1,
    skin: bool = True,
    spacing: float = 1.0,
) -> Model:
    """A structured hex block: part 1 "bone" (lowest layers), part 2 "flesh", part 3 skin quads.

    The skin is a quad shell on every outer face of the flesh part (sharing its nodes).
    """
    gx, gy, gz = (np.arange(n + 1) * spacing for n in (nx, ny, nz))
    x, y, z = np.meshgrid(gx, gy, gz, indexing="ij")
    coords = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    idx = np.arange(len(coords)).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = (
        a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    )
    conn = np.stack(
        [
            idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
            idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1],
        ],
        1,
    )  # fmt: skip
    part_ids = np.where(k < bone_layers, 1, 2)
    blocks = {"hex8": ElementBlock("hex8", np.arange(1, len(conn) + 1), part_ids, conn)}
    parts = {1: Part(1, "Bone"), 2: Part(2, "Flesh")}
    if skin:
        quads = []
        for a in range(nx):
            for b in range(ny):
                quads.append(
                    [idx[a, b, nz], idx[a + 1, b, nz], idx[a + 1, b + 1, nz], idx[a, b + 1, nz]]
                )
        for c in range(bone_layers, nz):
            for a in range(nx):
                quads.append(
                    [idx[a, 0, c], idx[a + 1, 0, c], idx[a + 1, 0, c + 1], idx[a, 0, c + 1]]
                )
                quads.append(
                    [idx[a, ny, c], idx[a, ny, c + 1], idx[a + 1, ny, c + 1], idx[a + 1, ny, c]]
                )
            for b in range(ny):
                quads.append(
                    [idx[0, b, c], idx[0, b, c + 1], idx[0, b + 1, c + 1], idx[0, b + 1, c]]
                )
                quads.append(
                    [idx[nx, b, c], idx[nx, b + 1, c], idx[nx, b + 1, c + 1], idx[nx, b, c + 1]]
                )
        quads = np.array(quads)
        n0 = len(conn)
        blocks["quad4"] = ElementBlock(
            "quad4", np.arange(n0 + 1, n0 + len(quads) + 1), np.full(len(quads), 3), quads
        )
        parts[3] = Part(3, "Skin")
    return Model(np.arange(1, len(coords) + 1) * 10, coords, blocks, parts)


@pytest.fixture
def block_model():
    return build_block_model


#: An undistorted element of each type the smoother handles (node order of kneegui.topology).
REFERENCE_SHAPES: dict[str, list[tuple[float, float, float]]] = {
    "hex8": list(HEX_REFERENCE_COORDS),
    "wedge6": [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (0, 1, 1)],
    "pyramid5": [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0.5, 0.5, 0.7)],
    "tet4": [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)],
    "quad4": [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)],
}


@pytest.fixture
def reference_shape():
    """``reference_shape(etype)``: an undistorted element's node coordinates (k, 3)."""
    return lambda etype: np.array(REFERENCE_SHAPES[etype], dtype=float)


def _box_triangles(lo, hi) -> np.ndarray:
    """(12, 3, 3) outward triangles of the axis-aligned box from ``lo`` to ``hi``."""
    points = np.array(list(product(*zip(lo, hi, strict=True))), dtype=float)
    tris = points[ConvexHull(points).simplices]
    centre = points.mean(axis=0)
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    flip = np.einsum("ij,ij->i", normal, tris.mean(axis=1) - centre) < 0
    tris[flip] = tris[flip][:, [0, 2, 1]]
    return tris


@pytest.fixture
def box_surface():
    """``box_surface(lo, hi)``: (12, 3, 3) outward triangles of an axis-aligned box (a bone)."""
    return _box_triangles
