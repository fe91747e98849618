"""Shared fixtures: the small demo leg and its repositioner (built once per session)."""

from __future__ import annotations

import pytest

from kneegui import demo
from kneegui.reposition import Repositioner, RepositionOptions
from kneegui.setup import load_setup


@pytest.fixture(scope="session")
def small_leg():
    return demo.generate_demo_leg(2000)


@pytest.fixture(scope="session")
def small_setup(small_leg):
    return load_setup(small_leg.setup, small_leg.model)


@pytest.fixture(scope="session")
def small_repositioner(small_leg, small_setup):
    return Repositioner(small_leg.model, small_setup, RepositionOptions())


@pytest.fixture(scope="session")
def small_posed(small_repositioner):
    """``small_posed(angle)``: the relaxed pose (what the export writes), once per angle."""
    cache = {}

    def pose(angle: float):
        if angle not in cache:
            cache[angle] = small_repositioner.pose_detailed(angle)
        return cache[angle]

    return pose
