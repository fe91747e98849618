"""Two small demo decks (right and left leg) and a 2 x 4 posture plan over them.

The plan poses with ``relax = false, smooth = false, force = true`` (a quick preview family: the
slider's mapping, written although it fails the quality gate), which a user may set too; it keeps
each posture under a second, so the batch machinery, not the relaxation, is what these tests
spend their time on.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

demo = pytest.importorskip("kneegui.demo")

ANGLES = (0, 40, 80, 120)


@pytest.fixture(scope="session")
def demo_decks(tmp_path_factory):
    """``{"right": (deck, setup), "left": (deck, setup)}``: the smallest demo, both sides."""
    root = tmp_path_factory.mktemp("batch_decks")
    return {
        side: demo.write_demo(root / side, elements=2000, side=side) for side in ("right", "left")
    }


def write_plan(folder: Path, decks: dict, out: str = "out", extra: str = "") -> Path:
    """The 2 decks x 4 angles plan in ``folder/plan.toml`` (output ``folder/out``)."""
    entries = "".join(
        f"""
[[deck]]
name = "{side}"
deck = "{deck}"
setup = "{setup}"
flexion = [{", ".join(str(a) for a in ANGLES)}]
"""
        for side, (deck, setup) in decks.items()
    )
    text = f"""# 2 demo variants x 4 angles
[output]
folder = "{out}"

[defaults]
relax = false
smooth = false
force = true
{extra}{entries}"""
    path = folder / "plan.toml"
    path.write_text(text, encoding="utf-8")
    return path


def deck_digests(out: Path) -> dict[str, str]:
    """Posture folder -> sha256 of its posed deck, for every deck under ``out``."""
    return {
        str(p.parent.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(out.rglob("demo_leg.k"))
    }


@pytest.fixture(scope="session")
def reference_run(demo_decks, tmp_path_factory):
    """The plan run uninterrupted with the local default (2 workers): its output folder."""
    from kneegui.batch import load_plan, run_plan

    folder = tmp_path_factory.mktemp("batch_reference")
    plan = load_plan(write_plan(folder, demo_decks))
    outcome = run_plan(plan, workers=2)
    assert (outcome.ok, outcome.gate_failed, outcome.errors) == (0, 8, 0)
    return plan.out
