"""Running a plan: local workers and a Dask cluster give the same decks; results are recorded,
resumed and summarised; a bad posture fails alone."""

from __future__ import annotations

import csv
import json
import shutil

import pytest

from kneegui.batch import load_plan, run_plan
from kneegui.batch.runner import BatchError
from kneegui.io.lsdyna import read_deck

from .conftest import ANGLES, deck_digests, write_plan

EXPECTED = {f"{side}/setup/flex_{a}" for side in ("right", "left") for a in ANGLES}


def test_the_local_run_writes_one_deck_and_report_per_posture(reference_run):
    out = reference_run
    assert set(deck_digests(out)) == EXPECTED
    manifest = json.loads((out / "manifest.json").read_text())
    assert [e["status"] for e in manifest["postures"]] == ["gate-failed"] * 8
    for posture in EXPECTED:
        report = json.loads((out / posture / "report.json").read_text())
        assert report["batch"]["posture"] == posture
        assert set(report["batch"]["files"]) == {"demo_leg.k"}
        assert abs(report["achieved_flexion"] - report["target_flexion"]) < 1e-6
    # each worker precomputed each deck at most once
    reused = [
        json.loads((out / p / "report.json").read_text())["batch"]["precompute_reused"]
        for p in EXPECTED
    ]
    assert reused.count(False) <= 4
    with open(out / "summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["posture"] for r in rows] == [e["id"] for e in manifest["postures"]]
    assert rows[-1]["inverted"] == "58"
    for row, entry in zip(rows, manifest["postures"], strict=True):
        # the sliding demo has no locked element: every inverted element has a movable node
        report = json.loads((out / entry["id"] / "report.json").read_text())
        assert row["inverted_locked"] == "0" == str(report["inverted"]["locked"])
        assert row["inverted_movable"] == row["inverted"] == str(report["inverted"]["movable"])
    assert "| right/setup/flex_0 | gate-failed |" in (out / "summary.md").read_text()
    for side in ("right", "left"):
        assert (out / side / "quality_vs_flexion.png").read_bytes()[:4] == b"\x89PNG"


def test_the_posed_decks_do_not_depend_on_the_thread_count(reference_run, demo_decks):
    """The test process runs with its default thread counts; the workers with one thread."""
    from kneegui.batch.runner import make_tasks
    from kneegui.batch.worker import run_posture

    plan = load_plan(reference_run.parent / "plan.toml")
    task = next(t for t in make_tasks(plan) if t.posture.id == "left/setup/flex_80")
    reference = task.posture.deck_out.read_bytes()
    moved = task.posture.folder.with_name("in_process")
    shutil.copytree(task.posture.folder, moved)
    result = run_posture(task)
    assert result.status == "gate-failed"
    assert task.posture.deck_out.read_bytes() == reference
    shutil.rmtree(task.posture.folder)
    moved.rename(task.posture.folder)


@pytest.mark.slow
def test_a_dask_cluster_gives_the_same_decks_byte_for_byte(reference_run, demo_decks, tmp_path):
    distributed = pytest.importorskip("distributed")
    plan = load_plan(write_plan(tmp_path, demo_decks))
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        outcome = run_plan(plan, scheduler=cluster.scheduler_address)
    assert (outcome.gate_failed, outcome.errors) == (8, 0)
    assert deck_digests(plan.out) == deck_digests(reference_run)


def test_resume_redoes_only_postures_whose_outputs_are_incomplete(reference_run, tmp_path):
    shutil.copytree(reference_run.parent, tmp_path / "run")
    plan = load_plan(tmp_path / "run" / "plan.toml")
    with pytest.raises(BatchError, match="already holds a batch run"):
        run_plan(plan, workers=1)
    out = plan.out
    (out / "right/setup/flex_40/demo_leg.k").unlink()  # lost
    torn = out / "left/setup/flex_120/demo_leg.k"
    torn.write_bytes(torn.read_bytes()[:5000])  # torn (what atomic writes prevent)
    report = out / "left/setup/flex_0/report.json"
    report.write_text(report.read_text()[:100])  # torn report
    outcome = run_plan(plan, workers=1, resume=True)
    assert outcome.skipped == 5 and outcome.gate_failed == 8
    assert deck_digests(out) == deck_digests(reference_run)
    read_deck(torn)
    manifest = json.loads((out / "manifest.json").read_text())
    redone = {e["id"] for e in manifest["postures"] if not e["skipped"]}
    assert redone == {"right/setup/flex_40", "left/setup/flex_120", "left/setup/flex_0"}


def small_plan(folder, defaults: str, decks: list[tuple]):
    """A plan in ``folder/plan.toml`` (output ``folder/out``) with these ``[defaults]`` lines and
    one ``[[deck]]`` per ``(name, deck, setup, flexion, extra lines)``, loaded."""
    entries = "".join(
        f'[[deck]]\nname = "{name}"\ndeck = "{deck}"\nsetup = "{setup}"\nflexion = {flexion}\n'
        f"{extra}\n"
        for name, deck, setup, flexion, extra in decks
    )
    path = folder / "plan.toml"
    path.write_text(f'[output]\nfolder = "out"\n[defaults]\n{defaults}\n{entries}')
    return load_plan(path)


def test_a_failing_posture_is_recorded_and_the_others_go_on(demo_decks, tmp_path):
    deck, setup = demo_decks["right"]
    bad_setup = tmp_path / "bad.setup.json"
    bad_setup.write_text(setup.read_text().replace('"femur": [', '"femur": [999999, '))
    plan = small_plan(
        tmp_path,
        "relax = false\nsmooth = false",
        [("bad", deck, bad_setup, "[30, 60]", ""), ("good", deck, setup, "40", "")],
    )
    outcome = run_plan(plan, workers=1)
    assert (outcome.ok, outcome.gate_failed, outcome.errors) == (0, 1, 2)
    entries = json.loads((plan.out / "manifest.json").read_text())["postures"]
    assert [e["status"] for e in entries] == ["error", "error", "gate-failed"]
    assert "SetupError" in entries[0]["reason"] and "999999" in entries[0]["reason"]
    assert "below the initial" in entries[2]["reason"]
    # without force a gate failure writes the report, not the deck
    assert not (plan.out / "good/setup/flex_40/demo_leg.k").exists()
    assert json.loads((plan.out / "good/setup/flex_40/report.json").read_text())["written"] == []
    summary = (plan.out / "summary.md").read_text()
    assert "| bad/setup/flex_30 | error |" in summary


def test_restore_volume_in_a_plan_runs_the_volume_step(demo_decks, tmp_path):
    """``restore_volume = true`` for one deck: its report has the step, the other's has none."""
    deck, setup = demo_decks["right"]
    plan = small_plan(
        tmp_path,
        "smooth = false\nforce = true",
        [
            ("plain", deck, setup, "60", ""),
            ("restored", deck, setup, "60", "restore_volume = true"),
        ],
    )
    assert [p.options.restore_volume for p in plan.postures] == [False, True]
    outcome = run_plan(plan, workers=1)
    assert outcome.errors == 0
    plain = json.loads((plan.out / "plain/setup/flex_60/report.json").read_text())
    restored = json.loads((plan.out / "restored/setup/flex_60/report.json").read_text())
    assert plain["volume_correction"] is None
    assert restored["volume_correction"]["aimed"] > 0
