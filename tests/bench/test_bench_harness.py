"""Smoke test of the benchmark harness on the small demo: tables come from measured numbers."""

from __future__ import annotations

import json
import statistics
from types import SimpleNamespace

import numpy as np
import pytest

from bench import report
from bench.__main__ import build_parser, run_from_args
from bench.baselines import (
    bone_rigidity_error,
    farthest_point_subsample,
    rbf_control_points,
    rbf_morph,
    rigid_segment_rotation,
)
from bench.pose_bench import pose_metrics, run_child
from kneegui.demo import generate_demo_leg
from kneegui.geometry.axes import compute_joint_axes
from kneegui.geometry.transforms import RigidTransform
from kneegui.kinematics.posing import solve_bone_pose
from kneegui.quality import compute_quality
from kneegui.reposition import classify_nodes
from kneegui.setup import load_setup

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    args = build_parser().parse_args(["--quick", "--out-dir", str(out)])
    assert run_from_args(args, log=lambda *a: None) == 0
    results = json.loads((out / "benchmarks.json").read_text(encoding="utf-8"))
    return out, results, (out / "benchmarks.md").read_text(encoding="utf-8")


@pytest.fixture(scope="module")
def small_leg():
    leg = generate_demo_leg(2_000)
    setup = load_setup(leg.setup, leg.model)
    return (
        leg.model,
        setup,
        classify_nodes(leg.model, setup),
        compute_joint_axes(leg.model.coords, setup),
    )


def test_quick_run_measures_every_stage_and_writes_the_outputs(quick_run):
    out, results, md = quick_run
    (size,) = results["sizes"]
    assert size["status"] == "complete"
    for stage in (
        "precompute",
        "pose",
        "pose_with_quality",
        "quality",
        "deck_read",
        "deck_write",
        "smoothing",
    ):
        entry = size["stages"][stage]
        assert entry["repeats"] == len(entry["runs_s"]) >= 1
        assert entry["seconds"] == pytest.approx(statistics.median(entry["runs_s"]))
        assert entry["seconds"] > 0
    assert size["stages"]["gui_frame"] == {"skipped": "--quick"}
    for name in ("bench-scaling.png", "bench-inverted.png"):
        assert (out / "images" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for heading in ("## Headline", "## Targets", "## Stages by model size", "### 120°"):
        assert heading in md


def test_tables_print_the_measured_figures(quick_run):
    _, results, md = quick_run
    (size,) = results["sizes"]
    pose_line = next(line for line in md.splitlines() if line.startswith("| one `pose()` call"))
    assert report.fmt_seconds(size["stages"]["pose"]["seconds"]) in pose_line
    rows = results["baselines"]["rows"]
    labels = {r["label"] for r in rows}
    assert {"rigid segment rotation", "RBF morph (thin-plate spline)"} <= labels
    assert any(r.get("smoothed") for r in rows)
    section_120 = md.split("### 120°")[1].split("###")[0]
    for r in (r for r in rows if r["angle"] == 120.0):
        line = next(x for x in section_120.splitlines() if x.startswith(f"| {r['label']} |"))
        assert f"| {r['inverted']} |" in line
        assert f"{r['worst_jacobian']:.3f}" in line
    # the 1M and paper-scale targets were not measured in a quick run: they must say "missed"
    targets = md.split("## Targets")[1].split("##")[0]
    assert targets.count("**missed**") >= 3


def test_a_baseline_row_matches_an_independent_measurement(quick_run, small_leg):
    _, results, _ = quick_run
    model, setup, groups, axes = small_leg
    row = next(
        r for r in results["baselines"]["rows"] if r["method"] == "rigid" and r["angle"] == 120.0
    )
    coords = rigid_segment_rotation(
        model, groups, axes, solve_bone_pose(axes, setup, 120.0), setup.moving_segment
    )
    q = compute_quality(coords, model.blocks)
    assert row["inverted"] == q.n_inverted
    assert row["worst_jacobian"] == pytest.approx(q.worst_jacobian())


def test_a_stage_cut_by_its_budget_is_reported_missed_not_estimated():
    rec = run_child("size", 1_000_000, 1, 1, budget_s=2.0)
    assert rec["status"] == "budget"
    assert "pose" not in rec.get("stages", {})
    text = "\n".join(report.targets_table({"sizes": [rec], "baselines": {}}))
    line = next(x for x in text.splitlines() if "1M elements" in x)
    assert "**missed** (not finished within this size's 2 s budget)" in line


def test_verdicts():
    assert report.verdict(0.04, 0.05) == "met"
    assert report.verdict(0.06, 0.05) == "**missed**"
    assert report.verdict(None, 0.05, "size not run") == "**missed** (size not run)"


def test_rigid_rotation_is_identity_at_the_initial_pose(small_leg):
    model, setup, groups, axes = small_leg
    identity = SimpleNamespace(
        transforms={s: RigidTransform.identity() for s in ("femur", "tibia", "patella")}
    )
    coords = rigid_segment_rotation(model, groups, axes, identity, setup.moving_segment)
    np.testing.assert_array_equal(coords, model.coords)


def test_rbf_reproduces_a_common_rigid_motion_exactly(small_leg):
    # thin-plate splines with a linear polynomial interpolate affine fields exactly
    model, _, groups, _ = small_leg
    motion = RigidTransform.about_axis([10.0, 0.0, 0.0], [0.3, 1.0, 0.2], 40.0)
    same = SimpleNamespace(transforms={s: motion for s in ("femur", "tibia", "patella")})
    control = rbf_control_points(model.coords, groups, total=200)
    assert len(np.unique(control.nodes)) == len(control.nodes) >= 150
    coords = rbf_morph(model, groups, same, control)
    soft = groups.soft
    np.testing.assert_allclose(coords[soft], motion.apply(model.coords[soft]), atol=1e-6)


def test_rigidity_error_is_zero_for_rigid_motion_and_sees_a_stretch():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(300, 3)) * 20
    bones = {"femur": np.arange(150), "tibia": np.arange(150, 300)}
    moved = RigidTransform.about_axis([0, 0, 0], [1, 2, 3], 70.0).apply(pts)
    assert bone_rigidity_error(pts, moved, bones)["max"] < 1e-12
    stretched = pts.copy()
    stretched[150:] *= 1.02
    err = bone_rigidity_error(pts, stretched, bones)
    assert err["femur"] == 0.0 and err["tibia"] == pytest.approx(0.02)


def test_farthest_point_subsample_spreads_out():
    line = np.column_stack([np.linspace(0, 1, 101), np.zeros(101), np.zeros(101)])
    picked = farthest_point_subsample(line, 3)
    assert sorted(line[picked, 0]) == pytest.approx([0.0, 0.5, 1.0])


def test_pose_metrics_of_the_initial_model_show_no_change(small_leg):
    model, setup, _, _ = small_leg
    q0 = compute_quality(model.coords, model.blocks)
    bones = {r: model.part_node_indices(setup.parts_of(r)) for r in ("femur", "tibia")}
    m = pose_metrics(model, model.coords, q0, bones)
    assert m["inverted"] == 0 and m["worse_than_initial_aspect"] == 0
    assert m["max_volume_change_pct"] == 0.0 and m["bone_rigidity_error"] == 0.0


def test_gui_summary_reads_both_output_formats_and_refuses_unknown_ones():
    old = {"results": {"part_colours": {"median_frame_ms": 70.0, "updates": 40}}}
    new = {
        "target_updates_per_s": 20.0,
        "results": {
            "part_colours": {
                "stepwise_median_update_ms": 50.0,
                "slider_positions": 30,
                "drag_updates_per_s": 18.0,
            },
            "jacobian_heatmap": {"stepwise_median_update_ms": 60.0},
        },
    }
    assert report.gui_summary(old)["frame_ms"] == 70.0
    summary = report.gui_summary(new)
    assert summary["frame_ms"] == 50.0 and summary["heatmap_frame_ms"] == 60.0
    assert summary["steps"] == 30 and summary["drag_updates_per_s"] == 18.0
    assert report.gui_summary({"results": {"part_colours": {"fps": 3}}}) is None


def test_export_bench_keeps_the_median_run_of_its_repeats(monkeypatch):
    from pathlib import Path

    import bench.export_bench as export_bench

    walls = iter([9.0, 7.0, 8.0])

    def fake_measure(folder, angle=90.0, timeout_s=None, restore_volume=False):
        wall = next(walls)
        return {
            "folder": str(folder),
            "export": {"wall_s": wall, "split_s": {"relaxation": wall - 1.0}},
            "precompute": {"wall_s": wall / 10},
        }

    monkeypatch.setattr(export_bench, "measure", fake_measure)
    run = export_bench.measure_repeated(Path("deck"), repeats=3)
    assert run["export"]["wall_s"] == 8.0 and run["export"]["split_s"]["relaxation"] == 7.0
    assert run["repeats"] == 3 and run["export_runs_s"] == [7.0, 8.0, 9.0]


def test_export_bench_merge_replaces_the_same_deck_measured_in_another_folder():
    """A deck regenerated in another folder (a new machine's scratch space) replaced nothing
    and the table grew a second column for every size."""
    import bench.export_bench as export_bench

    deck = {"variant": "hex8", "nodes": 20, "elements": 30}
    old = {**deck, "folder": "/old/d20000"}
    assert export_bench._same_deck(old, {**deck, "folder": "/new/d20000"})
    assert export_bench._same_deck(old, {"folder": "/old/d20000"})  # same folder, failed run
    assert not export_bench._same_deck(old, {**deck, "elements": 31, "folder": "/new/x"})
    assert not export_bench._same_deck(old, {**deck, "variant": "tet4", "folder": "/new/x"})
    assert not export_bench._same_deck(old, {"folder": "/new/failed"})


def test_export_table_accounts_for_the_time_outside_the_timed_stages():
    """The 1M demo's export took 167.7 s of which its timed stages covered 133.3 s: the table
    shows the remainder as its own row, so that the split adds up to the export."""
    import bench.export_bench as export_bench

    run = {
        "solids": 10,
        "nodes": 20,
        "elements": 30,
        "precompute": {"wall_s": 1.0, "cpu_s": 1.0},
        "export": {"wall_s": 10.0, "cpu_s": 12.0, "split_s": {"relaxation": 6.0, "write": 1.5}},
        "region": dict.fromkeys(
            ("relaxed_nodes", "relaxed_corners", "optimised_nodes", "optimised_elements"), 1
        )
        | {"smoothed_nodes": 1},
        "worst_jacobian": 0.3,
        "inverted": 0,
        "peak_rss_mb": 100.0,
    }
    tets = {**run, "solids": 20, "elements": 40, "variant": "tet4, 7 locked"}
    lines = export_bench.markdown({"runs": [run, tets]})
    rest = [line for line in lines if line.startswith(f"| — {export_bench.UNSTAGED}")]
    assert rest == [f"| — {export_bench.UNSTAGED} | 2.50 s | 2.50 s |"]
    # a variant's column says what it is; a run that recorded none is left unnamed
    assert "| | 10 solids | 20 solids (tet4, 7 locked) |" in lines
    # the tissue in the bones is a row of its own; a run saved before it was recorded says so
    bones = {**run, "tissue_in_bones": {"nodes": 316, "deepest": 4.654, "tolerance": 0.5}}
    lines = export_bench.markdown({"runs": [bones, run]})
    row = [line for line in lines if "soft-tissue nodes in a bone" in line]
    assert len(row) == 1 and row[0].endswith("| 316 (4.65 mm) | not recorded |")
    # so is the soft solids' volume change
    volume = {**run, "p95_volume_change_pct": 62.84}
    lines = export_bench.markdown({"runs": [volume, run]})
    row = [line for line in lines if "volume change" in line]
    assert len(row) == 1 and row[0].endswith("| 62.8 % | not recorded |")
