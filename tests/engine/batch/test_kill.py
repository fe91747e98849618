"""Killed runs: a killed worker fails only its posture, a killed run leaves no torn deck, and
``--resume`` completes both into the decks of an uninterrupted run, byte for byte."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .conftest import deck_digests, write_plan

psutil = pytest.importorskip("psutil")

pytestmark = pytest.mark.slow


def start(plan: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "kneegui.cli", "batch", str(plan), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, workers included
    )


def wait_until_finished(out: Path, n: int, proc: subprocess.Popen, timeout: float = 180) -> None:
    """Wait until the manifest records ``n`` finished postures."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        assert proc.poll() is None, proc.communicate()
        try:
            entries = json.loads((out / "manifest.json").read_text())["postures"]
        except (OSError, ValueError):
            entries = []
        if sum(e["status"] != "pending" for e in entries) >= n:
            return
        time.sleep(0.02)
    raise AssertionError(f"fewer than {n} postures finished in {timeout} s")


def resume(plan: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "kneegui.cli", "batch", str(plan), "--resume", "--workers", "2"],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_a_killed_worker_fails_its_posture_only_and_resume_completes_it(
    reference_run, demo_decks, tmp_path
):
    plan = write_plan(tmp_path, demo_decks)
    out = tmp_path / "out"
    proc = start(plan, "--workers", "2")
    try:
        wait_until_finished(out, 2, proc)
        workers = [
            p for p in psutil.Process(proc.pid).children() if "spawn_main" in " ".join(p.cmdline())
        ]
        assert len(workers) == 2
        workers[0].send_signal(signal.SIGKILL)
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 4, stdout + stderr
    assert "8 postures: 0 ok, 7 failed the quality gate, 1 failed" in stdout
    entries = json.loads((out / "manifest.json").read_text())["postures"]
    failed = [e for e in entries if e["status"] == "error"]
    assert len(failed) == 1 and "worker process died" in failed[0]["reason"]
    assert sum(e["status"] == "gate-failed" for e in entries) == 7

    result = resume(plan)
    assert result.returncode == 3, result.stdout + result.stderr
    assert "7 already complete" in result.stdout
    assert deck_digests(out) == deck_digests(reference_run)


def test_a_killed_run_leaves_no_torn_deck_and_resume_completes_it(
    reference_run, demo_decks, tmp_path
):
    plan = write_plan(tmp_path, demo_decks)
    out = tmp_path / "out"
    proc = start(plan, "--workers", "1")
    try:
        wait_until_finished(out, 2, proc)
        os.killpg(proc.pid, signal.SIGKILL)  # the run and its worker, mid-plan
        proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    reference = deck_digests(reference_run)
    partial = deck_digests(out)
    assert 2 <= len(partial) < len(reference)
    for posture, digest in partial.items():  # every deck there is complete
        assert digest == reference[posture], posture

    result = resume(plan)
    assert result.returncode == 3, result.stdout + result.stderr
    # a posture killed between its deck and its report is redone
    complete = int(re.search(r"(\d+) already complete", result.stdout).group(1))
    assert complete in (len(partial) - 1, len(partial))
    assert deck_digests(out) == reference
    # a kill mid-write may leave a hidden temp file, never a visible one
    assert all(p.name.startswith(".") for p in out.rglob("*.part"))
