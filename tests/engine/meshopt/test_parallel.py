"""The kernels summed in fixed parts: the same bits on one thread as on several, and the same
values (to rounding) as one serial pass."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

import kneegui.meshopt.parallel as parallel
from kneegui.meshopt.foldover import FoldoverEnergy
from kneegui.meshopt.foldover_kernel import foldover_free_energy
from kneegui.meshopt.quality_optimiser import (
    QualityOptions,
    _penalty,
    _SplitPenalty,
    _Stage,
    quality_aims,
)
from kneegui.quality import compute_quality
from kneegui.reposition.relax import ElasticRelaxation
from kneegui.topology import corner_tetrahedra


@pytest.fixture
def one_thread(monkeypatch):
    """Run the parts on a single thread (as on a one-core machine)."""

    def use_one_thread():
        pool = ThreadPoolExecutor(1)
        monkeypatch.setattr(parallel, "_POOL", [pool])

    return use_one_thread


def distorted(block_model, seed=2):
    model = block_model(14, 14, 14)  # 2,744 hexes: above the parallel threshold
    rng = np.random.default_rng(seed)
    coords = model.coords + rng.normal(0.0, 0.06, model.coords.shape)
    return model, coords


def test_penalty_in_parts_is_the_same_on_one_thread_and_matches_one_pass(block_model, one_thread):
    model, coords = distorted(block_model)
    aims = quality_aims(compute_quality(model.coords, model.blocks), model.blocks)
    free = np.arange(len(coords))
    stage = _Stage(model.blocks, coords, free, aims, QualityOptions())
    pr = stage.pr
    assert len(pr.elem_ptr) - 1 >= parallel.PARALLEL_MIN_ELEMENTS
    x = coords[pr.nodes]
    split = _SplitPenalty(pr)
    g_many = np.zeros_like(x)
    v_many = split(x, g_many)
    one_thread()
    g_one = np.zeros_like(x)
    v_one = _SplitPenalty(pr)(x, g_one)
    assert v_one == v_many and np.array_equal(g_one, g_many)  # bit for bit
    g_serial = np.zeros_like(x)
    v_serial = _penalty(pr, x, g_serial)
    assert v_serial > 0
    assert v_many == pytest.approx(v_serial, rel=1e-12)
    np.testing.assert_allclose(g_many, g_serial, rtol=1e-9, atol=1e-9 * np.abs(g_serial).max())


def test_energy_in_parts_is_the_same_on_one_thread_and_matches_one_pass(block_model, one_thread):
    model, coords = distorted(block_model, seed=4)
    tets = corner_tetrahedra(model.blocks, {"hex8": np.ones(len(model.blocks["hex8"]), bool)})
    relaxation = ElasticRelaxation(model.coords, tets, np.arange(len(coords)))
    sub: FoldoverEnergy = relaxation.energy(relaxation.free)
    assert len(sub.tets) >= parallel.PARALLEL_MIN_ELEMENTS
    x = coords[sub.nodes]
    e_many, g_many, d_many = sub.energy(x, 1e-3)
    one_thread()
    e_one, g_one, d_one = sub.energy(x, 1e-3)
    assert e_one == e_many and np.array_equal(g_one, g_many) and np.array_equal(d_one, d_many)
    xa = np.ascontiguousarray(sub.augment(x))
    g_serial, d_serial = np.empty_like(xa), np.empty(len(sub.tets))
    e_serial = foldover_free_energy(
        xa, sub.tets, sub.g_rows, sub.weight, sub.theta, 1e-3, g_serial, d_serial
    )
    assert e_many == pytest.approx(e_serial, rel=1e-12)
    np.testing.assert_array_equal(d_many[: len(d_serial)], d_serial)
