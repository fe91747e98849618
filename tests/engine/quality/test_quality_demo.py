"""Quality and smoothing on the built-in demo leg (kneegui.demo) posed by the repositioner."""

from __future__ import annotations

import numpy as np
import pytest

from kneegui import demo
from kneegui.meshopt import (
    degraded_elements,
    smooth_posed_model,
    smoothing_free_nodes,
)
from kneegui.quality import compute_quality, summarize_quality

SOFT = ("flesh", "ligament", "meniscus", "tendon", "capsule")
BONES = ("femur", "tibia", "fibula", "patella", "fixed")


@pytest.fixture(scope="module")
def leg():
    from kneegui.setup import load_setup

    generated = demo.generate_demo_leg()
    return generated.model, load_setup(generated.setup, generated.model)


def test_demo_quality_summary_per_role(leg):
    model, setup = leg
    q = compute_quality(model.coords, model.blocks)
    roles = {r: list(p) for r, p in setup.roles.items() if p}
    s = summarize_quality(model, q, roles)
    assert s["model"]["elements"] == sum(len(b) for t, b in model.blocks.items() if t in q.by_type)
    assert sum(g["elements"] for g in s["parts"].values()) == s["model"]["elements"]
    for role, pids in roles.items():
        expected = sum(s["parts"][str(p)]["elements"] for p in pids if str(p) in s["parts"])
        assert s["roles"][role]["elements"] == expected
    bone_parts = [p for r in ("femur", "tibia") for p in setup.roles[r]]
    for p in bone_parts:
        if str(p) in s["parts"]:
            assert s["parts"][str(p)]["inverted"] == 0


@pytest.mark.slow
def test_smoothing_the_posed_demo_keeps_its_guarantees(leg):
    from kneegui.reposition import Repositioner

    model, setup = leg
    posed = model.with_coords(Repositioner(model, setup).pose(90.0))
    soft = [p for r in SOFT for p in setup.roles.get(r, ())]
    fixed = [p for r in BONES for p in setup.roles.get(r, ())] + list(setup.unassigned_parts)
    q0 = compute_quality(model.coords, model.blocks)
    q_posed = compute_quality(posed.coords, posed.blocks)
    smoothed, report = smooth_posed_model(posed, soft, fixed, initial=q0)
    q = compute_quality(smoothed.coords, smoothed.blocks)
    assert q.worst_jacobian() >= q_posed.worst_jacobian()
    assert q.n_inverted <= q_posed.n_inverted
    free = smoothing_free_nodes(posed, soft, fixed, degraded_elements(q_posed, q0, 0.6, 0.02))
    assert np.array_equal(smoothed.coords[~free], posed.coords[~free])
    bones = posed.part_node_indices(fixed)
    assert np.array_equal(smoothed.coords[bones], posed.coords[bones])
    assert report.seconds < 60
