"""Quality-metric and smoothing speed.

``python -m bench.quality_bench`` prints a table and writes bench/results/quality.json.

- all metrics (both Jacobians, aspect, warpage, skew, volume) of 200,000 and 1,000,000 randomly
  perturbed hexes (target: 1,000,000 in <= 2 s);
- a 10,000-element row subset of the 1,000,000 (the GUI's per-slider-step update), with every
  metric and with each measure a heat-map shows alone (``evaluate(..., only=...)``);
- smoothing a ~20,000-element block (bone layer, flesh, skin shells) with a few hundred
  distorted elements: random node jiggle, and a twisted core with inverted elements
  (target: <= 5 s);
- smoothing the demo leg posed to 90 degrees, when ``kneegui.demo`` and the repositioner are
  available.

Every time is the median of ``--repeats`` runs; wall-clock and process CPU seconds are both
recorded (CPU time is less sensitive to other jobs on the machine; it counts every thread).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np

from bench.machine import machine_description
from kneegui.meshopt import degraded_elements, smooth_posed_model, smoothing_free_nodes
from kneegui.model import ElementBlock, Model, Part
from kneegui.quality import QualityEvaluator, compute_quality
from kneegui.topology import SOLID_FACES, row_multiplicity

ROOT = Path(__file__).resolve().parent.parent


_CPU: list[float] = []  # process CPU seconds of the last _median_time call (median)


def _median_time(fn, repeats: int) -> tuple[float, object]:
    """Median wall time of ``repeats`` calls (the median CPU time goes to ``_CPU``)."""
    times, cpu, out = [], [], None
    for _ in range(repeats):
        c = time.process_time()
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    _CPU[:] = [statistics.median(cpu)]
    return statistics.median(times), out


def perturbed_hexes(n: int, amplitude: float = 0.2, seed: int = 0):
    """An n^3 grid of unit hexes with every node moved by up to ``amplitude``."""
    g = np.arange(n + 1, dtype=float)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    coords = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    coords += np.random.default_rng(seed).uniform(-amplitude, amplitude, coords.shape)
    idx = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    c = idx[:-1, :-1, :-1].ravel()
    dx, dy, dz = (n + 1) ** 2, n + 1, 1
    conn = np.column_stack(
        [c, c + dx, c + dx + dy, c + dy, c + dz, c + dx + dz, c + dx + dy + dz, c + dy + dz]
    )
    block = ElementBlock("hex8", np.arange(1, len(conn) + 1), np.ones(len(conn)), conn)
    return coords, {"hex8": block}


def layered_block(nx: int, ny: int, nz: int) -> Model:
    """Hex block: part 1 "bone" (bottom layer), part 2 "flesh", part 3 skin quads on the rest."""
    g = [np.arange(k + 1, dtype=float) for k in (nx, ny, nz)]
    x, y, z = np.meshgrid(*g, indexing="ij")
    coords = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    idx = np.arange(len(coords)).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(*(np.arange(n) for n in (nx, ny, nz)), indexing="ij"))
    conn = np.column_stack(
        [idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
         idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1]]
    )  # fmt: skip
    part = np.where(k < 1, 1, 2)
    # skin: every outer face of the flesh part
    flesh = conn[part == 2]
    faces = np.concatenate([flesh[:, list(face)] for face in SOLID_FACES["hex8"]])
    outer = faces[row_multiplicity(np.sort(faces, axis=1)) == 1]
    outer = outer[~np.all(coords[outer][:, :, 2] == 1.0, axis=1)]  # not the bone interface
    n_hex = len(conn)
    blocks = {
        "hex8": ElementBlock("hex8", np.arange(1, n_hex + 1), part, conn),
        "quad4": ElementBlock(
            "quad4", np.arange(n_hex + 1, n_hex + len(outer) + 1), np.full(len(outer), 3), outer
        ),
    }
    parts = {1: Part(1, "Bone"), 2: Part(2, "Flesh"), 3: Part(3, "Skin")}
    return Model(np.arange(1, len(coords) + 1), coords, blocks, parts)


def jiggled(model: Model, fraction: float, amplitude: float, seed: int = 0) -> Model:
    rng = np.random.default_rng(seed)
    idx = np.flatnonzero(smoothing_free_nodes(model, [2], [1]))
    pick = rng.choice(idx, size=int(fraction * len(idx)), replace=False)
    c = model.coords.copy()
    c[pick] += rng.uniform(-amplitude, amplitude, (len(pick), 3))
    return model.with_coords(c)


def twisted(model: Model, angle: float, width: float) -> Model:
    c = model.coords
    centre = (c.min(axis=0) + c.max(axis=0)) / 2
    th = angle * np.exp(-((np.linalg.norm(c - centre, axis=1) / width) ** 2))
    dx, dy = c[:, 0] - centre[0], c[:, 1] - centre[1]
    out = c.copy()
    out[:, 0] = centre[0] + dx * np.cos(th) - dy * np.sin(th)
    out[:, 1] = centre[1] + dx * np.sin(th) + dy * np.cos(th)
    return model.with_coords(out)


def bench_smoothing(initial: Model, posed: Model, soft, fixed, repeats: int, **options) -> dict:
    q0 = compute_quality(initial.coords, initial.blocks)
    q = compute_quality(posed.coords, posed.blocks)
    degraded = int(sum(m.sum() for m in degraded_elements(q, q0).values()))
    seconds, (smoothed, report) = _median_time(
        lambda: smooth_posed_model(posed, soft, fixed, initial=q0, **options), repeats
    )
    q1 = compute_quality(smoothed.coords, smoothed.blocks)
    return {
        "elements": posed.n_elements,
        "degraded_elements": degraded,
        "free_nodes": report.free_nodes,
        "worst_jacobian_initial": q0.worst_jacobian(),
        "worst_jacobian_posed": q.worst_jacobian(),
        "worst_jacobian_smoothed": q1.worst_jacobian(),
        "inverted_posed": q.n_inverted,
        "inverted_smoothed": q1.n_inverted,
        "seconds": seconds,
        "cpu_seconds": _CPU[0],
        "options": options,
        "report": report.to_dict(),
    }


def bench_demo(repeats: int, angle: float = 90.0, **options) -> dict:
    """Smoothing the demo leg posed to ``angle`` (skipped when the demo is not available)."""
    try:
        from kneegui.demo import generate_demo_leg
        from kneegui.reposition import Repositioner
        from kneegui.setup import load_setup
    except ImportError as exc:
        return {"skipped": f"not available: {exc}"}
    leg = generate_demo_leg()
    setup = load_setup(leg.setup, leg.model)
    repositioner = Repositioner(leg.model, setup)
    posed = leg.model.with_coords(repositioner.pose_detailed(angle).coords)
    soft_roles = ("flesh", "ligament", "meniscus", "tendon", "capsule")
    soft = [p for r in soft_roles if r in setup.roles for p in setup.roles[r]]
    fixed_roles = ("femur", "tibia", "fibula", "patella", "fixed")
    fixed = [p for r in fixed_roles if r in setup.roles for p in setup.roles[r]]
    fixed += list(setup.unassigned_parts)
    out = bench_smoothing(leg.model, posed, soft, fixed, repeats, **options)
    out["flexion_deg"] = angle
    return out


def run(repeats: int = 5, with_demo: bool = True) -> dict:
    results: dict = {}
    for n in (59, 100):  # 205,379 and 1,000,000 hexes
        coords, blocks = perturbed_hexes(n)
        ev = QualityEvaluator(blocks)
        ev.evaluate(coords)  # warm-up
        seconds, q = _median_time(lambda ev=ev, coords=coords: ev.evaluate(coords), repeats)
        results[f"metrics_{n**3}_hexes"] = {
            "elements": n**3,
            "seconds": seconds,
            "cpu_seconds": _CPU[0],
            "worst_jacobian": q.worst_jacobian(),
        }
    rows = {"hex8": np.random.default_rng(1).choice(n**3, 10_000, replace=False)}
    seconds, _ = _median_time(lambda: ev.evaluate(coords, rows=rows), repeats)
    results["metrics_10000_of_1000000_hexes"] = {
        "elements": 10_000,
        "seconds": seconds,
        "cpu_seconds": _CPU[0],
    }
    for only in ("jacobian_corner", "aspect", "warpage", "skew", "volume"):
        seconds, _ = _median_time(
            lambda only=only: ev.evaluate(coords, rows=rows, only=only), repeats
        )
        results[f"only_{only}_10000_hexes"] = {
            "elements": 10_000,
            "seconds": seconds,
            "cpu_seconds": _CPU[0],
        }
    block = layered_block(28, 28, 26)
    smooth_repeats = max(1, min(repeats, 3))
    results["smoothing_jiggle"] = bench_smoothing(
        block, jiggled(block, 0.01, 0.6), [2], [1], smooth_repeats
    )
    twist = twisted(block, 3.0, 3.0)
    results["smoothing_twist"] = bench_smoothing(block, twist, [2], [1], smooth_repeats)
    if with_demo:
        results["smoothing_demo_90deg"] = bench_demo(smooth_repeats)
    return results


def _table(results: dict) -> str:
    lines = [f"{'case':<30} {'elements':>9} {'wall s':>7} {'CPU s':>7}  notes", "-" * 100]
    for name, r in results.items():
        if "skipped" in r:
            lines.append(f"{name:<30} {'':>9} {'':>7} {'':>7}  skipped ({r['skipped']})")
            continue
        note = ""
        if "worst_jacobian_posed" in r:
            note = (
                f"{r['degraded_elements']} degraded; worst J {r['worst_jacobian_posed']:.3f} -> "
                f"{r['worst_jacobian_smoothed']:.3f} (initial {r['worst_jacobian_initial']:.3f}); "
                f"inverted {r['inverted_posed']} -> {r['inverted_smoothed']}; "
                f"stage 2 on {r['report']['stage2_nodes']} nodes"
            )
        lines.append(
            f"{name:<30} {r['elements']:>9} {r['seconds']:>7.3f} {r['cpu_seconds']:>7.3f}  {note}"
        )
    return "\n".join(lines)


def to_markdown(results: dict, machine: dict, repeats: int) -> str:
    """docs/quality-benchmark.md: the table and the machine."""
    return (
        "# Quality metrics and smoothing: measured speed\n\n"
        "Generated by `python -m bench.quality_bench` (do not edit by hand); raw numbers in "
        "bench/results/quality.json. Times are the median of "
        f"{repeats} runs (smoothing: {max(1, min(repeats, 3))}).\n\n"
        "```\n" + _table(results) + "\n```\n\n"
        f"Machine: {machine['cpu']}, {machine['cores']} cores, {machine['memory_gb']} GB, "
        f"Python {machine['python']}, numpy {machine['numpy']}, scipy {machine['scipy']}.\n"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-demo", action="store_true", help="skip the demo-leg case")
    args = parser.parse_args(argv)
    load_before = os.getloadavg()
    results = run(args.repeats, with_demo=not args.no_demo)
    load_after = os.getloadavg()
    print(_table(results))
    out = ROOT / "bench" / "results" / "quality.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "result": results,
        "repeats": args.repeats,
        "machine": machine_description(),
        "load_average_1min": {"before": load_before[0], "after": load_after[0]},
    }
    out.write_text(json.dumps(payload, indent=2) + "\n", encoding="utf-8")
    doc = ROOT / "docs" / "quality-benchmark.md"
    text = to_markdown(results, payload["machine"], args.repeats)
    text += (
        f"\nOne-minute load average before / after the run: {load_before[0]:.2f} / "
        f"{load_after[0]:.2f} (other jobs share the machine; CPU seconds are less affected).\n"
    )
    doc.write_text(text, encoding="utf-8")
    print(f"\nwritten {out.relative_to(ROOT)} and {doc.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
