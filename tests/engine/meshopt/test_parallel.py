"""The kernels summed in fixed parts: the same bits on one thread as on several, the same bits
as the parts run one after the other, and the same values (to rounding) as one serial pass."""

from __future__ import annotations

import numba
import numpy as np
import pytest

import kneegui.meshopt.parallel as parallel
from kneegui.meshopt.foldover import FoldoverEnergy
from kneegui.meshopt.foldover_kernel import foldover_free_energy
from kneegui.meshopt.quality_kernel import corner_ratio_penalty, face_shape_penalty
from kneegui.meshopt.quality_optimiser import (
    QUAD_TRIPLES,
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
def one_thread():
    """Run the parts on a single thread (as on a one-core machine)."""
    threads = numba.get_num_threads()
    yield lambda: numba.set_num_threads(1)
    numba.set_num_threads(threads)


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
    # the parts one after the other, in Python, added in order: the same bits
    buffers, v_parts = np.zeros((parallel.PARTS, *x.shape)), 0.0
    e_cut, q_cut, f_cut = (
        parallel.part_bounds(n) for n in (len(pr.elem_ptr) - 1, len(pr.quads), len(pr.faces))
    )
    for k in range(parallel.PARTS):
        (e0, e1), (q0, q1), (f0, f1) = e_cut[k : k + 2], q_cut[k : k + 2], f_cut[k : k + 2]
        c0, c1 = pr.elem_ptr[e0], pr.elem_ptr[e1]
        corner_args = (pr.corners[c0:c1], pr.elem_ptr[e0 : e1 + 1] - c0)
        value = corner_ratio_penalty(
            x,
            *corner_args,
            pr.log_aim[e0:e1],
            pr.log_collapse_aim[e0:e1],
            pr.log_sine_aim[e0:e1],
            pr.log_ratio_aim[e0:e1],
            pr.element_weight[e0:e1],
            pr.log_volume[e0:e1],
            pr.volume_band[e0:e1],
            pr.volume_weight,
            pr.quads[q0:q1],
            QUAD_TRIPLES,
            pr.quad_log_aim[q0:q1],
            buffers[k],
        )
        faces = (pr.faces[f0:f1], pr.face_aims[f0:f1], pr.weights)
        v_parts += float(value) + float(face_shape_penalty(x, *faces, buffers[k]))
    assert v_parts == v_many and np.array_equal(buffers.sum(axis=0), g_many)
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
    # the parts one after the other, in Python, added in order: the same bits
    cut = parallel.part_bounds(len(sub.tets))
    buffers, d_parts, e_parts = np.empty((parallel.PARTS, *xa.shape)), np.empty(len(d_one)), 0.0
    for k in range(parallel.PARTS):
        a, b = cut[k], cut[k + 1]
        e_parts += float(
            foldover_free_energy(
                xa,
                sub.tets[a:b],
                sub.inv_rest,
                sub.weights,
                sub.rows[a:b],
                sub.theta,
                1e-3,
                buffers[k],
                d_parts[a:b],
                np.zeros(0),
            )
        )
    assert len(sub.quads) == 0  # (the energy adds the shells' barrier after the parts)
    assert e_parts == e_many and np.array_equal(buffers.sum(axis=0), g_many)
    np.testing.assert_array_equal(d_parts, d_many)

    def one_pass(theta):
        """The compiled energy over every corner at once: energy, gradient, det J."""
        grad, det = np.empty_like(xa), np.empty(len(sub.tets))
        energy = foldover_free_energy(
            xa, sub.tets, sub.inv_rest, sub.weights, sub.rows, sub.theta, 1e-3, grad, det, theta
        )
        return energy, grad, det

    e_serial, _, d_serial = one_pass(np.zeros(0))
    assert e_many == pytest.approx(e_serial, rel=1e-12)
    np.testing.assert_array_equal(d_many[: len(d_serial)], d_serial)
    # each corner's own volume weight: its part's slice, the same as one pass
    theta = np.random.default_rng(5).uniform(0.2, 0.95, len(sub.tets))
    e_own, g_own, _ = sub.energy(x, 1e-3, theta)
    e_one_pass, g_one, _ = one_pass(theta)
    assert e_own == pytest.approx(e_one_pass, rel=1e-12) and e_own != pytest.approx(e_many)
    np.testing.assert_allclose(g_own, g_one, rtol=1e-9, atol=1e-9 * np.abs(g_one).max())
