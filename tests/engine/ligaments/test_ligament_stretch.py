"""Ligament fibre stretch: direction, per-element stretch, end-cap length, length curve."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui.errors import Cancelled
from kneegui.geometry import rotation_matrix
from kneegui.ligaments import length_curve, ligament_fibres, ligament_short_name
from kneegui.model import ElementBlock, Model, Part


def _bar(nx=2, ny=2, nz=10, size=(4.0, 3.0, 40.0), axis=(0.3, -0.2, 1.0)):
    """A hex bar along ``axis`` (part 7, 'Lig_MCL_R'), plus a stray hex of part 9."""
    xs = np.linspace(0, size[0], nx + 1)
    ys = np.linspace(0, size[1], ny + 1)
    zs = np.linspace(0, size[2], nz + 1)
    grid = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)
    # rotate z onto axis
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    v = np.cross([0, 0, 1.0], a)
    angle = np.degrees(np.arccos(a[2]))
    rot = rotation_matrix(v, angle) if np.linalg.norm(v) > 0 else np.eye(3)
    coords = grid @ rot.T
    idx = np.arange(len(grid)).reshape(nx + 1, ny + 1, nz + 1)
    conn = []
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                c = [idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k]]
                conn.append(c + [n + 1 for n in c])
    conn = np.array(conn)
    extra = np.array(
        [
            [0, 0, 100],
            [1, 0, 100],
            [1, 1, 100],
            [0, 1, 100],
            [0, 0, 101],
            [1, 0, 101],
            [1, 1, 101],
            [0, 1, 101],
        ],
        float,
    )
    n = len(coords)
    coords = np.vstack([coords, extra])
    conn = np.vstack([conn, np.arange(n, n + 8)[None]])
    pids = np.r_[np.full(len(conn) - 1, 7), 9]
    block = ElementBlock("hex8", np.arange(1, len(conn) + 1), pids, conn)
    model = Model(
        np.arange(1, len(coords) + 1),
        coords,
        {"hex8": block},
        {7: Part(7, "Lig_MCL_R"), 9: Part(9, "Flesh")},
    )
    return model, a


def test_short_names():
    assert ligament_short_name("Lig_ACL_R") == "ACL"
    assert ligament_short_name("LX-Lig-MCL-R") == "MCL"
    assert ligament_short_name("Posterior cruciate") == "PCL"
    assert ligament_short_name("fibular collateral ligament") == "LCL"
    assert ligament_short_name("Flesh_Thigh") is None


def test_fibre_direction_and_edges_follow_the_bar():
    model, axis = _bar()
    (lig,) = ligament_fibres(model, [7])
    assert lig.name == "MCL"
    assert abs(abs(lig.direction @ axis) - 1.0) < 1e-9
    vec = model.coords[lig.fibre_edges[:, 1]] - model.coords[lig.fibre_edges[:, 0]]
    cos = np.abs(vec @ axis) / np.linalg.norm(vec, axis=1)
    np.testing.assert_allclose(cos, 1.0, atol=1e-9)
    assert len(lig.fibre_edges) == 2 * 2 * 10
    # end caps: the node layers within 6 mm of either end (z = 0, 4 and 36, 40): 38 - 2
    assert lig.initial_length == pytest.approx(36.0, rel=1e-9)
    np.testing.assert_allclose(lig.element_stretch(model.coords), 1.0)


def test_stretch_along_the_fibre_and_rigid_motion():
    model, axis = _bar()
    (lig,) = ligament_fibres(model, [7])
    centre = model.coords.mean(axis=0)
    along = (model.coords - centre) @ axis
    stretched = model.coords + 0.1 * along[:, None] * axis[None]  # 10 % along the fibre
    np.testing.assert_allclose(lig.element_stretch(stretched), 1.1, rtol=1e-9)
    assert lig.length(stretched) / lig.initial_length == pytest.approx(1.1, rel=1e-9)
    rot = rotation_matrix([1.0, 2.0, 0.5], 70.0)
    moved = (model.coords - centre) @ rot.T + centre + [5.0, -3.0, 2.0]
    np.testing.assert_allclose(lig.element_stretch(moved), 1.0, atol=1e-12)
    assert lig.length(moved) == pytest.approx(lig.initial_length, rel=1e-12)
    # a non-uniform bend: one end shortens, the other does not
    half = along < 0
    bent = model.coords.copy()
    bent[half] = centre + (model.coords[half] - centre) * 0.8
    s = lig.element_stretch(bent)
    assert s.min() < 0.95 and s.max() == pytest.approx(1.0, abs=1e-12)


def test_inputs_not_mutated_and_other_parts_ignored():
    model, _ = _bar()
    before = model.coords.copy()
    ligs = ligament_fibres(model, [7, 12345])
    assert [lig.part_id for lig in ligs] == [7]
    np.testing.assert_array_equal(model.coords, before)


def test_length_curve_and_cancel():
    model, axis = _bar()
    ligs = ligament_fibres(model, [7])
    centre = model.coords.mean(axis=0)
    along = (model.coords - centre) @ axis

    def pose(deg):
        return model.coords + (deg / 100.0) * along[:, None] * axis[None]

    seen = []
    curve = length_curve(ligs, pose, [0.0, 50.0, 100.0], progress=lambda f, m: seen.append(f))
    np.testing.assert_allclose(curve[:, 0] / ligs[0].initial_length, [1.0, 1.5, 2.0])
    assert seen[-1] == 1.0
    with pytest.raises(Cancelled):
        length_curve(ligs, pose, [0.0, 10.0], cancelled=lambda: True)


def test_bad_end_fraction():
    model, _ = _bar()
    with pytest.raises(ValueError):
        ligament_fibres(model, [7], end_fraction=0.6)
