"""The same export on every x86-64 machine with AVX2 (issue 23, item 6; kneegui/reproducible.py).

On a CPU with AVX-512 numpy's transcendental kernels and OpenBLAS's kernels differ in the last
bits from an AVX2 machine's, and the export followed them: the coarse demo's export at 90 deg
wrote another deck here (an AVX-512 machine) than with an AVX2 machine's kernels. kneegui pins
both to the AVX2 ones before numpy loads.
"""

from __future__ import annotations

from kneegui.reproducible import NUMPY_AVX512_TARGETS, OPT_OUT, dispatch_state

import json
import os
import platform
import subprocess
import sys

import pytest

X86 = platform.machine().lower() in ("x86_64", "amd64")
pytestmark = pytest.mark.skipif(
    not X86 or os.environ.get(OPT_OUT) == "1", reason="the pin is for x86-64 machines"
)
#: The kernels an x86-64 machine with AVX2 and FMA but no AVX-512 runs.
AVX2_MACHINE = {
    "NPY_DISABLE_CPU_FEATURES": " ".join(NUMPY_AVX512_TARGETS),
    "OPENBLAS_CORETYPE": "Haswell",
}


def test_the_engine_runs_the_pinned_kernels():
    """The test process imported kneegui (tests/conftest.py) before numpy: no AVX-512 kernel
    of numpy is active and OpenBLAS runs its Haswell kernels (on a CPU with AVX2), unless the
    user chose other kernels (as when the suite runs with an older CPU's kernels)."""
    state = dispatch_state()
    chosen = {k: v for k, v in state["user_settings"].items() if AVX2_MACHINE.get(k) != v}
    if chosen:
        pytest.skip(f"the dispatch was set by the user, and the pin yields to it: {chosen}")
    assert state["numpy_avx512_targets"] == [], state
    assert state["pinned"], state


def test_the_users_own_dispatch_wins_and_is_reported():
    code = "import kneegui, json; from kneegui.reproducible import dispatch_state; "
    code += "print(json.dumps(dispatch_state()))"
    env = {**os.environ, "OPENBLAS_CORETYPE": "Nehalem"}
    env.pop(OPT_OUT, None)
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    state = json.loads(out.stdout.strip().splitlines()[-1])
    assert state["openblas_coretype"] == "Nehalem" and not state["pinned"]
    assert state["user_settings"]["OPENBLAS_CORETYPE"] == "Nehalem"


def _pose(folder, out, env_update: dict[str, str | None]) -> dict:
    env = dict(os.environ)
    for key, value in env_update.items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    deck, setup = folder / "demo_leg.k", folder / "demo_leg.setup.json"
    report = out.with_suffix(".json")
    cmd = [sys.executable, "-m", "kneegui.cli", "pose", str(deck), "--setup", str(setup)]
    cmd += ["--flexion", "90", "--out", str(out), "--report", str(report), "--force"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode in (0, 3), proc.stdout + proc.stderr  # 3: the gate failed
    return json.loads(report.read_text())


def test_the_export_is_the_same_with_an_avx2_machine_s_kernels(tmp_path):
    """``kneegui pose`` at 90 deg writes the same deck, bit for bit, with the kernels it picks
    itself (on this machine the pinned ones) and with those of an AVX2 machine. Before the pin
    the two decks differed here (sha256 947cb79c... against 90179fa1... on 4 December)."""
    from kneegui.demo import write_demo

    folder = tmp_path / "demo"
    write_demo(folder, elements=2000)
    own = _pose(folder, tmp_path / "own.k", dict.fromkeys(AVX2_MACHINE))
    other = _pose(folder, tmp_path / "avx2.k", AVX2_MACHINE)
    assert own["numerics"]["pinned"] and own["numerics"]["numpy_avx512_targets"] == []
    assert (tmp_path / "own.k").read_bytes() == (tmp_path / "avx2.k").read_bytes()
    assert own["quality"] == other["quality"]
