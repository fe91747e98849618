"""Pose-pipeline timings per model size, and the baseline comparison at paper scale.

Two measurements, each run in a fresh child process with a wall-clock budget (the child saves its
results after every stage, so what finished before the budget ran out is kept and what did not is
reported as such):

- :func:`measure_size`: on the demo leg of a given size, the stages deck read, deck write,
  setup precompute, one ``pose()`` call (a slider step), full pose with quality (``pose_model``
  without smoothing), smoothing (``pose_model`` with smoothing, its smoothing time), quality metrics
  alone (``compute_quality``).
- :func:`measure_baselines`: on one demo leg, at the same angles and with the same bone transforms,
  rigid segment rotation and the RBF morph (:mod:`bench.baselines`), and kneegui with every
  repositioning method, without and with smoothing: time, worst Jacobian, inverted elements, worst
  aspect / warpage / skew, elements worse than the initial worst aspect ratio, largest element
  volume change, bone rigidity error.

Every time is the median of its ``repeats`` (cheap stages) or ``heavy_repeats`` (smoothing, and
precompute above paper scale; at most paper scale the precompute runs at least
:data:`SMALL_PRECOMPUTE_REPEATS` times); the count is stored beside each figure.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
#: Flexion angles of the baseline comparison (degrees).
ANGLES = (0.0, 30.0, 60.0, 90.0, 120.0)
#: Flexion the per-size stages pose to (degrees).
SLIDER_ANGLE = 90.0
#: Stage names in the order they run, with their table labels.
STAGES: dict[str, str] = {
    "precompute": "setup precompute (`Repositioner(...)`)",
    "pose": "one `pose()` call (slider step)",
    "quality": "quality metrics alone (`compute_quality`)",
    "deck_read": "deck read (`read_deck`)",
    "deck_write": "deck write, posed (`write_deck`)",
    "pose_with_quality": "full pose: mapping, relaxation, quality (`pose_model` less smoothing)",
    "smoothing": "smoothing (`pose_model` smoothing stage)",
    "gui_frame": "GUI frame, slider step (real window, Xvfb)",
}
BONE_ROLES = ("femur", "tibia", "fibula", "patella")
#: Precompute runs up to paper scale (a few seconds at most); larger models use ``heavy_repeats``.
SMALL_PRECOMPUTE_REPEATS = 3


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def timed(fn: Callable[[], Any], repeats: int) -> tuple[dict[str, Any], Any]:
    """Run ``fn`` ``repeats`` times; return ``({"seconds": median, "runs_s", "repeats"}, last)``."""
    runs, out = [], None
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        out = fn()
        runs.append(time.perf_counter() - t)
    return {"seconds": statistics.median(runs), "runs_s": runs, "repeats": len(runs)}, out


class _Recorder:
    """A dict saved to ``path`` (atomically) every time a stage finishes."""

    def __init__(self, path: Path, record: dict[str, Any]):
        self.path = path
        self.record = record
        self.save()

    def save(self) -> None:
        self.record["peak_rss_mb"] = round(_peak_rss_mb(), 1)
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.record, indent=1, default=_json_default), encoding="utf-8")
        os.replace(tmp, self.path)


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value)}")


def _finite(value: Any) -> Any:
    """JSON has no infinity: keep floats finite or turn them into strings."""
    if isinstance(value, float) and not np.isfinite(value):
        return str(value)
    return value


# ------------------------------------------------------------------------------------ per size
def measure_size(elements: int, repeats: int, heavy_repeats: int, out: Path) -> dict[str, Any]:
    """Time every pipeline stage on the demo leg of ``elements`` solids (see module docstring).

    Parameters
    ----------
    elements : int
        Requested demo size (the generator builds the nearest its block structure allows).
    repeats, heavy_repeats : int
        Runs per cheap stage and per precompute / smoothing stage (median reported).
    out : Path
        JSON file rewritten after every stage.
    """
    from kneegui.demo import generate_demo_leg
    from kneegui.io.lsdyna import read_deck, write_deck, write_model
    from kneegui.quality import compute_quality
    from kneegui.reposition import Repositioner
    from kneegui.reposition.pipeline import pose_model
    from kneegui.setup import load_setup
    from kneegui.topology import SOLID_TYPES

    rec = _Recorder(out, {"requested_elements": elements, "stages": {}})
    stages = rec.record["stages"]
    t = time.perf_counter()
    leg = generate_demo_leg(elements)
    rec.record["generate_s"] = time.perf_counter() - t
    rec.record["nodes"] = leg.model.n_nodes
    rec.record["elements"] = leg.model.n_elements
    rec.record["solids"] = int(sum(len(b) for t, b in leg.model.blocks.items() if t in SOLID_TYPES))
    rec.save()
    model = leg.model
    setup = load_setup(leg.setup, model)
    # headline stages first, so a size that runs out of budget still reports them
    pre_repeats = (
        max(heavy_repeats, SMALL_PRECOMPUTE_REPEATS) if elements <= 20_000 else heavy_repeats
    )
    stages["precompute"], rep = timed(lambda: Repositioner(model, setup), pre_repeats)
    stages["precompute"]["method"] = rep.options.method
    stages["precompute"]["breakdown_s"] = dict(rep.timings_s)
    rec.save()
    rep.pose(SLIDER_ANGLE - 1.0)  # warm-up
    steps = iter(SLIDER_ANGLE + 0.5 * k for k in range(10_000))
    stages["pose"], posed = timed(lambda: rep.pose(next(steps)), repeats)
    rec.save()
    stages["quality"], _ = timed(lambda: compute_quality(posed, model.blocks), repeats)
    rec.save()
    with tempfile.TemporaryDirectory(prefix="kneegui-bench-") as tmp:
        deck = Path(tmp) / "demo.k"
        write_model(model, deck)
        rec.record["deck_mb"] = round(deck.stat().st_size / 1e6, 1)
        stages["deck_read"], read_model = timed(lambda: read_deck(deck), repeats)
        rec.save()
        posed_model = read_model.with_coords(posed)
        stages["deck_write"], _ = timed(
            lambda: write_deck(posed_model, Path(tmp) / "posed.k"), repeats
        )
        rec.save()
    # the relaxation takes seconds, not milliseconds: heavy repeats, and one pose_model run
    # gives both figures (the smoothing is its last stage; running the relaxation once for
    # each made the paper-scale size overrun its budget)
    full_runs, smooth_runs = [], []
    for _ in range(max(1, heavy_repeats)):
        t = time.perf_counter()
        pm = pose_model(rep, SLIDER_ANGLE, smooth=True)
        wall = time.perf_counter() - t
        smooth_runs.append(pm.report["timings_s"]["smoothing"])
        full_runs.append(wall - smooth_runs[-1])
        stages["pose_with_quality"] = {
            "seconds": statistics.median(full_runs),
            "runs_s": list(full_runs),
            "repeats": len(full_runs),
            "relax_s": pm.report["timings_s"].get("pose_relax"),
        }
        rec.record["posed_90"] = {
            "worst_jacobian": pm.report["quality"]["posed"]["jacobian"]["worst"],
            "inverted": pm.report["quality"]["posed"]["inverted"],
        }
        stages["smoothing"] = {
            "seconds": statistics.median(smooth_runs),
            "runs_s": list(smooth_runs),
            "repeats": len(smooth_runs),
            "inverted_before": pm.report["quality"]["posed"]["inverted"],
            "inverted_after": pm.report["quality"]["smoothed"]["inverted"],
        }
        rec.save()
    rec.record["complete"] = True
    rec.save()
    return rec.record


# ------------------------------------------------------------------------------------ baselines
def pose_metrics(
    model, coords, initial_quality, bone_nodes: dict[str, np.ndarray]
) -> dict[str, Any]:
    """Quality of ``coords`` against the initial pose: the columns of the comparison table.

    Worst Jacobian (corner), inverted elements, worst aspect / warpage / skew over every solid and
    shell; elements worse than the initial worst aspect ratio; largest element volume change of
    the solids (percent, signed); bone rigidity error (:func:`bench.baselines.bone_rigidity_error`).
    """
    from bench.baselines import bone_rigidity_error
    from kneegui.quality import compute_quality, summarize_quality
    from kneegui.topology import SOLID_TYPES

    q = compute_quality(coords, model.blocks)
    s = summarize_quality(model.with_coords(coords), q, initial=initial_quality)["model"]
    inverted_solids = sum(int(q[t].inverted.sum()) for t in q if t in SOLID_TYPES)
    rigidity = bone_rigidity_error(model.coords, coords, bone_nodes)
    return {
        "worst_jacobian": _finite(s["jacobian"]["worst"]),
        "inverted": s["inverted"],
        "inverted_solids": inverted_solids,
        "worst_aspect": _finite(s["aspect"]["worst"]),
        "worst_warpage": _finite(s["warpage"]["worst"]),
        "worst_skew": _finite(s["skew"]["worst"]),
        "worse_than_initial_aspect": s["aspect"]["worse_than_initial"],
        "max_volume_change_pct": _finite(s["volume_change"]["max_element_pct"]),
        "bone_rigidity_error": rigidity["max"],
        "bone_rigidity_by_bone": rigidity,
    }


def measure_baselines(
    elements: int,
    repeats: int,
    heavy_repeats: int,
    out: Path,
    angles: tuple[float, ...] = ANGLES,
    methods: tuple[str, ...] | None = None,
) -> dict[str, Any]:
    """Compare the baselines and kneegui's methods on one demo leg at ``angles``.

    Parameters
    ----------
    elements : int
        Requested demo size.
    repeats : int
        Runs per posing time (median).
    heavy_repeats : int
        Runs per precompute and per smoothing (median).
    out : Path
        JSON file rewritten after every row.
    angles : tuple of float
        Target flexion angles (degrees).
    methods : tuple of str, optional
        kneegui methods besides the default (default: every one in ``METHODS``).
    """
    from bench.baselines import (
        RBF_CONTROL_POINTS,
        rbf_control_points,
        rbf_morph,
        rigid_segment_rotation,
    )
    from kneegui.demo import generate_demo_leg
    from kneegui.geometry.axes import compute_joint_axes
    from kneegui.kinematics.posing import solve_bone_pose
    from kneegui.quality import compute_quality
    from kneegui.reposition import METHODS, Repositioner, RepositionOptions, classify_nodes
    from kneegui.reposition.pipeline import pose_model
    from kneegui.setup import load_setup
    from kneegui.topology import SOLID_TYPES

    default_method = RepositionOptions().method
    others = [m for m in (METHODS if methods is None else methods) if m != default_method]
    leg = generate_demo_leg(elements)
    model = leg.model
    setup = load_setup(leg.setup, model)
    rec = _Recorder(
        out,
        {
            "requested_elements": elements,
            "nodes": model.n_nodes,
            "elements": model.n_elements,
            "solids": int(sum(len(b) for t, b in model.blocks.items() if t in SOLID_TYPES)),
            "angles": list(angles),
            "default_method": default_method,
            "methods": [default_method, *others],
            "rows": [],
            "precompute": {},
        },
    )
    q0 = compute_quality(model.coords, model.blocks)
    bone_nodes = {r: model.part_node_indices(setup.parts_of(r)) for r in BONE_ROLES}
    rec.record["initial"] = pose_metrics(model, model.coords, q0, bone_nodes)
    groups = classify_nodes(model, setup)
    axes = compute_joint_axes(model.coords, setup)
    rec.record["precompute"]["rbf"], control = timed(
        lambda: rbf_control_points(model.coords, groups), heavy_repeats
    )
    rec.record["rbf_control"] = {
        "requested": RBF_CONTROL_POINTS,
        "count": len(control.nodes),
        "per_segment": {s: int((control.segment == s).sum()) for s in np.unique(control.segment)},
    }
    rec.save()

    def add_row(angle: float, method: str, label: str, timing: dict, coords) -> None:
        row = {"angle": angle, "method": method, "label": label, **timing}
        row.update(pose_metrics(model, coords, q0, bone_nodes))
        rec.record["rows"].append(row)
        rec.save()

    def moving(deg: float):
        return solve_bone_pose(axes, setup, deg)

    for angle in angles:
        timing, coords = timed(
            lambda a=angle: rigid_segment_rotation(
                model, groups, axes, moving(a), setup.moving_segment
            ),
            repeats,
        )
        add_row(angle, "rigid", "rigid segment rotation", timing, coords)
        timing, coords = timed(
            lambda a=angle: rbf_morph(model, groups, moving(a), control), repeats
        )
        add_row(angle, "rbf", "RBF morph (thin-plate spline)", timing, coords)
    for method in (default_method, *others):
        # the default runs the whole export pipeline; the other methods are compared as
        # mappings (their relaxation from a badly tangled start would eat the time budget)
        relax = method == default_method
        rec.record["precompute"][method], rep = timed(
            lambda m=method, r=relax: Repositioner(
                model, setup, RepositionOptions(method=m, relax=r)
            ),
            max(heavy_repeats, SMALL_PRECOMPUTE_REPEATS),
        )
        rec.save()
        suffix = " (default)" if method == default_method else ""
        after = " + relaxation + smoothing" if relax else " + smoothing"
        for angle in angles:
            timing, coords = timed(lambda a=angle, r=rep: r.pose(a), repeats)
            add_row(angle, method, f"kneegui {method}{suffix}", timing, coords)
            smooth_runs, total_runs, posed = [], [], None
            for _ in range(max(1, heavy_repeats)):
                posed = pose_model(rep, angle, smooth=True)
                t = posed.report["timings_s"]
                smooth_runs.append(t["smoothing"])
                total_runs.append(t["pose"] + t["smoothing"])
            timing = {
                "seconds": statistics.median(total_runs),
                "runs_s": total_runs,
                "repeats": len(total_runs),
                "smoothing_s": statistics.median(smooth_runs),
            }
            add_row(angle, method, f"kneegui {method}{suffix}{after}", timing, posed.model.coords)
            rec.record["rows"][-1]["smoothed"] = True
            rec.save()
    rec.record["complete"] = True
    rec.save()
    return rec.record


# ------------------------------------------------------------------------------------ children
def run_child(
    kind: str, elements: int, repeats: int, heavy_repeats: int, budget_s: float, **extra: Any
) -> dict[str, Any]:
    """Run :func:`measure_size` or :func:`measure_baselines` in a fresh process within a budget.

    Returns whatever the child saved; ``status`` is ``"complete"``, ``"budget"`` (stopped after
    ``budget_s`` seconds; stages it had not finished are absent) or ``"failed"`` (with the
    child's last error lines).
    """
    with tempfile.TemporaryDirectory(prefix="kneegui-bench-") as tmp:
        out = Path(tmp) / "result.json"
        cmd = [
            sys.executable,
            "-m",
            "bench.pose_bench",
            kind,
            "--elements",
            str(elements),
            "--repeats",
            str(repeats),
            "--heavy-repeats",
            str(heavy_repeats),
            "--out",
            str(out),
        ]
        if extra.get("angles"):
            cmd += ["--angles", ",".join(f"{a:g}" for a in extra["angles"])]
        if extra.get("methods") is not None:
            cmd += ["--methods", ",".join(extra["methods"])]
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        try:
            _, stderr = proc.communicate(timeout=budget_s)
            status = "complete" if proc.returncode == 0 else "failed"
        except subprocess.TimeoutExpired:
            proc.kill()
            _, stderr = proc.communicate()
            status = "budget"
        wall = time.perf_counter() - t0
        record = json.loads(out.read_text(encoding="utf-8")) if out.exists() else {}
    record.setdefault("requested_elements", elements)  # the child may not have saved anything
    record.setdefault("stages", {})
    record["status"] = status
    record["budget_s"] = budget_s
    record["wall_s"] = round(wall, 1)
    if status == "failed":
        record["error"] = "\n".join(stderr.strip().splitlines()[-3:])
    return record


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("kind", choices=("size", "baselines"))
    parser.add_argument("--elements", type=int, required=True)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--heavy-repeats", type=int, default=1)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--angles", help="comma-separated degrees (baselines)")
    parser.add_argument("--methods", help="comma-separated kneegui methods (baselines)")
    args = parser.parse_args(argv)
    if args.kind == "size":
        measure_size(args.elements, args.repeats, args.heavy_repeats, args.out)
    else:
        angles = tuple(float(a) for a in args.angles.split(",")) if args.angles else ANGLES
        methods = None if args.methods is None else tuple(m for m in args.methods.split(",") if m)
        measure_baselines(
            args.elements, args.repeats, args.heavy_repeats, args.out, angles, methods
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
