"""The volume-restoring step: volumes back, pinned nodes unmoved, the same bits on any thread
count, every solid type's volume."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from kneegui.meshopt.volume_correction import (
    VolumeCorrection,
    VolumeCorrectionOptions,
    _element_volumes,
)
from kneegui.model import ElementBlock


def hex_bar(nx: int = 4, ny: int = 4, nz: int = 12) -> tuple[np.ndarray, ElementBlock]:
    """A bar of unit hexes along z: coordinates and its block (LS-DYNA node order)."""
    grid = (
        np.stack(
            np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1
        )
        .reshape(-1, 3)
        .astype(float)
    )

    def node(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    conn = []
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                bottom = [
                    node(i, j, k),
                    node(i + 1, j, k),
                    node(i + 1, j + 1, k),
                    node(i, j + 1, k),
                ]
                top = [node(*_up(n, ny, nz)) for n in bottom]
                conn.append(bottom + top)
    conn = np.array(conn)
    block = ElementBlock("hex8", np.arange(1, len(conn) + 1), np.ones(len(conn), int), conn)
    return grid, block


def _up(n: int, ny: int, nz: int) -> tuple[int, int, int]:
    k = n % (nz + 1)
    j = (n // (nz + 1)) % (ny + 1)
    i = n // ((nz + 1) * (ny + 1))
    return i, j, k + 1


def squeezed(rest: np.ndarray, nz: int) -> np.ndarray:
    """The bar's middle third squeezed smoothly along z (a mapping's long-wavelength volume
    loss): its ends stay where they are."""
    z = rest[:, 2] / nz
    bump = np.sin(np.pi * z) ** 2
    out = rest.copy()
    out[:, 0] = 2.0 + (rest[:, 0] - 2.0) * (1.0 - 0.35 * bump)
    out[:, 1] = 2.0 + (rest[:, 1] - 2.0) * (1.0 - 0.35 * bump)
    return out


@pytest.fixture(scope="module")
def bar():
    rest, block = hex_bar()
    free = (rest[:, 2] > 0) & (rest[:, 2] < 12)  # the end faces pin it
    corr = VolumeCorrection({"hex8": block}, {"hex8": np.arange(len(block))}, free, rest)
    return rest, block, free, corr


def relative_change(corr: VolumeCorrection, x: np.ndarray) -> np.ndarray:
    volume = _element_volumes(x, corr.elem_nodes, corr.elem_tets)
    return np.abs(volume / corr.rest_volume - 1.0)


def test_a_squeezed_bar_gets_its_volume_back_and_its_pinned_ends_stay(bar):
    rest, _, free, corr = bar
    x = squeezed(rest, 12)
    before = relative_change(corr, x)
    assert np.percentile(before, 95) > 0.4  # a strong squeeze: 95th percentile about 55 %
    out, report = corr(x)
    after = relative_change(corr, out)
    assert report.converged and report.aimed == len(corr)
    # one linearised step takes most of it away (measured: 95th percentile 0.56 -> 0.08)
    assert np.percentile(after, 95) < 0.4 * np.percentile(before, 95)
    assert np.array_equal(out[~free], x[~free])
    assert report.largest_move > 0.1


def test_the_rest_pose_is_left_alone(bar):
    rest, _, _, corr = bar
    out, report = corr(rest)
    assert np.array_equal(out, rest) and report.iterations == 0


def test_a_folded_element_is_left_to_the_untangling(bar):
    rest, _, _, corr = bar
    x = squeezed(rest, 12)
    # one interior node pushed through its neighbours: the elements around it fall below the
    # floor and are not aimed at
    centre = int(np.flatnonzero((rest == [2.0, 2.0, 6.0]).all(axis=1))[0])
    x[centre, 2] += 3.0
    ratio = _element_volumes(x, corr.elem_nodes, corr.elem_tets) / corr.rest_volume
    below = int((ratio < corr.options.floor).sum())
    assert below > 0
    _, report = corr(x)
    assert report.aimed == len(corr) - below


def test_the_same_bits_with_one_thread_or_two(bar):
    rest, _, _, corr = bar
    x = squeezed(rest, 12)
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one, _ = corr(x)
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        two, _ = corr(x)
    finally:
        numba.set_num_threads(threads)
    assert np.array_equal(one, two)


@pytest.mark.parametrize(
    ("etype", "conn", "volume"),
    [
        ("hex8", [0, 1, 2, 3, 4, 5, 6, 7], 1.0),
        ("wedge6", [0, 1, 3, 4, 5, 7], 0.5),
        ("pyramid5", [0, 1, 2, 3, 8], 1.0 / 3.0),
        ("tet4", [0, 1, 3, 4], 1.0 / 6.0),
        # node order reversed (a mirrored deck): the split is oriented by the rest pose
        ("tet4", [0, 3, 1, 4], 1.0 / 6.0),
    ],
)
def test_every_solid_type_has_its_volume(etype, conn, volume):
    cube = np.array(
        [
            [0, 0, 0],
            [1, 0, 0],
            [1, 1, 0],
            [0, 1, 0],
            [0, 0, 1],
            [1, 0, 1],
            [1, 1, 1],
            [0, 1, 1],
            [0.5, 0.5, 1.0],
        ],
        dtype=float,
    )
    block = ElementBlock(etype, [1], [1], [conn])
    corr = VolumeCorrection(
        {etype: block},
        {etype: np.array([0])},
        np.ones(len(cube), bool),
        cube,
        VolumeCorrectionOptions(),
    )
    assert corr.rest_volume[0] == pytest.approx(volume, rel=1e-12)


def test_the_set_up_asks_cancel_between_its_steps():
    """On a whole-body model the set-up takes seconds (2.9 s at 1M, asked nothing before):
    a cancel during it stops it."""
    from kneegui.errors import Cancelled

    rest, block = hex_bar()
    free = (rest[:, 2] > 0) & (rest[:, 2] < 12)
    rows = {"hex8": np.arange(len(block))}
    asked = []
    VolumeCorrection({"hex8": block}, rows, free, rest, cancel=lambda: bool(asked.append(1)))
    assert len(asked) >= 6
    calls = []

    def cancel_at_the_third() -> bool:
        calls.append(1)
        return len(calls) == 3

    with pytest.raises(Cancelled, match="volume correction"):
        VolumeCorrection({"hex8": block}, rows, free, rest, cancel=cancel_at_the_third)


def test_the_solve_asks_cancel_at_every_iteration(bar):
    """25 iterations took up to 2.1 s on the 1M demo: each one asks."""
    rest, _, _, corr = bar
    asked = []
    _, report = corr(squeezed(rest, 12), cancel=lambda: bool(asked.append(1)))
    assert report.iterations > 25 and len(asked) >= report.iterations
