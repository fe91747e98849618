"""`kneegui pose`: deck in, posed deck(s) and reports out, with the documented exit codes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kneegui.io.lsdyna import read_deck


def kneegui(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "kneegui.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.fixture(scope="module")
def demo_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("demo")
    result = kneegui("demo", str(folder), "--elements", "2000", cwd=folder)
    assert result.returncode == 0, result.stderr
    return folder / "demo_leg.k", folder / "demo_leg.setup.json"


def test_pose_at_the_initial_angle_passes_and_reports(demo_files, tmp_path):
    deck, setup = demo_files
    out, report = tmp_path / "posed" / "leg.k", tmp_path / "posed" / "leg.json"
    result = kneegui(
        "pose",
        str(deck),
        "--setup",
        str(setup),
        "--flexion",
        "9",
        "--out",
        str(out),
        "--report",
        str(report),
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    data = json.loads(report.read_text())
    for key in (
        "initial_flexion",
        "target_flexion",
        "achieved_flexion",
        "quality",
        "volume_change",
        "timings_s",
    ):
        assert key in data
    for stage in ("initial", "posed", "smoothed"):
        for metric in ("jacobian", "aspect", "warpage", "skew"):
            assert {"worst", "mean", "std"} <= set(data["quality"][stage][metric])
        assert "inverted" in data["quality"][stage]
    assert {"max_element_pct", "soft_tissue_total_pct"} <= set(data["volume_change"])
    assert abs(data["achieved_flexion"] - 9.0) < 0.1
    assert data["bones"]["overlap"] == [] and data["warnings"] == []
    assert "warning" not in result.stderr
    # only node coordinate lines may differ from the input deck
    before = deck.read_text().splitlines()
    after = out.read_text().splitlines()
    assert len(before) == len(after)
    in_node_block = False
    for a, b in zip(before, after, strict=True):
        if a.startswith("*"):
            in_node_block = a.strip().upper().startswith("*NODE")
        if a != b:
            assert in_node_block and a[:8] == b[:8]


def test_several_angles_one_deck_each_and_gate_exit_code(demo_files, tmp_path):
    """Each angle is gated on its own: at 30 deg the small demo keeps its initial worst
    Jacobian and is written; at 120 deg it does not (flesh and the demo's PCL pressed between
    tibia and femur), so that deck is only written with --force and the exit code is 3."""
    deck, setup = demo_files
    out = tmp_path / "angles"
    argv = [
        "pose",
        str(deck),
        "--setup",
        str(setup),
        "--flexion",
        "30",
        "120",
        "--out",
        str(out),
        "--no-smooth",
    ]
    result = kneegui(*argv, cwd=tmp_path)
    assert result.returncode == 3, result.stdout + result.stderr
    assert "120 deg" in result.stdout and "fails the quality gate" in result.stdout
    assert (out / "flex_30" / "demo_leg.k").is_file()
    assert not (out / "flex_120" / "demo_leg.k").exists()
    result = kneegui(*argv, "--force", cwd=tmp_path)
    assert result.returncode == 3
    for angle in ("30", "120"):
        posed = read_deck(out / f"flex_{angle}" / "demo_leg.k")
        report = json.loads((out / f"flex_{angle}" / "report.json").read_text())
        assert report["target_flexion"] == float(angle)
        assert report["gate"]["passed"] == (angle == "30")
        assert posed.n_nodes == read_deck(deck).n_nodes
        assert not np.allclose(posed.coords, read_deck(deck).coords)


def test_bones_reaching_into_each_other_are_reported_and_warned_about(demo_files, tmp_path):
    """Flexed to 140 deg, beyond what the demo is built for, the back of its tibia reaches
    into the posterior femur above the condyle arcs: the report says how deep, the CLI
    warns."""
    deck, setup = demo_files
    out, report = tmp_path / "leg.k", tmp_path / "leg.json"
    argv = ["pose", str(deck), "--setup", str(setup), "--flexion", "140", "--out", str(out)]
    result = kneegui(*argv, "--report", str(report), "--force", "--no-smooth", cwd=tmp_path)
    data = json.loads(report.read_text())
    overlaps = {(o["inner"], o["outer"]): o for o in data["bones"]["overlap"]}
    tibia = overlaps["tibia", "femur"]
    assert tibia["depth"] > 1.0 and tibia["nodes"] > 0 and tibia["rest_depth"] == 0.0
    assert any("the tibia reaches" in w and "into the femur" in w for w in data["warnings"])
    assert "kneegui: warning: 140 deg: the tibia reaches" in result.stderr


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--flexion", "500"], "flexion"),
        (["--flexion", "30", "--setup", "missing.json"], "missing.json"),
    ],
)
def test_bad_input_exit_2_one_line_nothing_written(demo_files, tmp_path, args, fragment):
    deck, setup = demo_files
    argv = ["pose", str(deck), "--out", str(tmp_path / "o" / "x.k")]
    if "--setup" not in args:
        argv += ["--setup", str(setup)]
    result = kneegui(*argv, *args, cwd=tmp_path)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and fragment in lines[0] and "Traceback" not in result.stderr
    assert not (tmp_path / "o").exists()


def test_restore_volume_runs_the_step_and_reports_it(demo_files, tmp_path):
    """``--restore-volume``: the export restores the soft solids' volumes before relaxing; the
    report says what the step did, and without the flag it does not run."""
    deck, setup = demo_files
    reports = {}
    for flag in ((), ("--restore-volume",)):
        report = tmp_path / f"leg{len(flag)}.json"
        result = kneegui(
            "pose", str(deck), "--setup", str(setup), "--flexion", "60",
            "--out", str(tmp_path / f"leg{len(flag)}.k"), "--report", str(report), "--force",
            *flag, cwd=tmp_path,
        )  # fmt: skip
        assert result.returncode in (0, 3), result.stdout + result.stderr
        reports[bool(flag)] = json.loads(report.read_text())
    assert reports[False]["volume_correction"] is None
    step = reports[True]["volume_correction"]
    assert step["converged"] and step["aimed"] > 0 and step["largest_move"] > 0
    assert reports[True]["timings_s"]["volume_correction"] == step["seconds"]
    assert reports[True]["quality"]["smoothed"]["inverted"] == 0
