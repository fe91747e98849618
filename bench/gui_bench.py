"""Live slider speed of the real window on the default demo leg (needs a display: xvfb-run).

``xvfb-run -a -s "-screen 0 1600x1000x24" python -m bench.gui_bench`` opens the main window on
the default demo leg, drives the flexion slider over ``steps`` positions from -5 to 140 degrees
and times each update from the slider move to the end of the render (pose through the engine's
repositioner, VTK points overwritten in place, one render). It runs in part colours and again
with the Jacobian heat-map (quality recomputed every step), and writes bench/results/gui.json
and docs/gui-benchmark.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

from bench.machine import machine_description

ROOT = Path(__file__).resolve().parent.parent
TARGET_UPDATES_PER_S = 20.0


def _drive(app, window, steps: int) -> dict[str, float]:
    ws, vp = window.ws, window.viewport
    slider = window.flexion_panel.slider
    lo, hi = slider.minimum(), slider.maximum()
    values = [round(lo + (hi - lo) * i / (steps - 1)) for i in range(steps)]
    frame_ms, pose_ms = [], []
    poser = ws.poser
    original_pose = poser.pose

    def timed_pose(deg):
        t = time.perf_counter()
        out = original_pose(deg)
        pose_ms.append(1e3 * (time.perf_counter() - t))
        return out

    poser.pose = timed_pose
    try:
        start = time.perf_counter()
        for v in values:
            t = time.perf_counter()
            before = vp.renders
            slider.setValue(v)
            while vp.renders == before:
                app.processEvents()
            frame_ms.append(1e3 * (time.perf_counter() - t))
        total = time.perf_counter() - start
    finally:
        del poser.pose
    return {
        "updates": len(values),
        "median_frame_ms": statistics.median(frame_ms),
        "p90_frame_ms": sorted(frame_ms)[int(0.9 * len(frame_ms))],
        "median_pose_ms": statistics.median(pose_ms),
        "updates_per_s": len(values) / total,
    }


def run(elements: int | None = None, steps: int = 200) -> dict:
    os.environ.setdefault("QT_API", "pyside6")
    from PySide6.QtCore import QSettings
    from PySide6.QtWidgets import QApplication

    from app.demo import DEFAULT_DEMO_ELEMENTS, demo_files
    from app.main_window import MainWindow
    from app.qt_compat import protect_singletons

    protect_singletons()
    tmp = Path(tempfile.mkdtemp(prefix="kneegui-gui-bench-"))
    QSettings.setPath(QSettings.Format.IniFormat, QSettings.Scope.UserScope, str(tmp))
    app = QApplication.instance() or QApplication([])
    elements = elements or DEFAULT_DEMO_ELEMENTS
    deck, setup = demo_files(elements, cache_dir=tmp / "cache")
    window = MainWindow()
    window.resize(1500, 920)
    window.show()
    t0 = time.perf_counter()
    window.open_deck(deck, setup)
    while window.ws.poser is None or window.ws.tasks.busy:
        app.processEvents()
        if time.perf_counter() - t0 > 300:
            raise RuntimeError(f"the window did not get ready: {window.last_error}")
    ready_s = time.perf_counter() - t0
    window.viewport.flush()
    size = window.viewport.plotter.ren_win.GetSize()
    results = {"part_colours": _drive(app, window, steps)}
    window.ws.set_metric("jacobian")
    window.ws.set_colour_mode("quality")
    window.viewport.flush()
    results["jacobian_heatmap"] = _drive(app, window, steps)
    model = window.ws.model
    out = {
        "benchmark": "gui slider",
        "demo_elements_requested": elements,
        "model": {
            "nodes": model.n_nodes,
            "elements": model.n_elements,
            "parts": len(model.part_ids()),
        },
        "poser": getattr(window.ws.poser, "kind", type(window.ws.poser).__name__),
        "open_to_ready_s": ready_s,
        "viewport_pixels": list(size),
        "target_updates_per_s": TARGET_UPDATES_PER_S,
        "results": results,
        "machine": machine_description(),
    }
    window.close()
    return out


def write_markdown(result: dict, path: Path) -> None:
    m = result["model"]
    lines = [
        "# GUI slider benchmark",
        "",
        'Produced by `xvfb-run -a -s "-screen 0 1600x1000x24" python -m bench.gui_bench` '
        "(bench/results/gui.json). The real main window on the default demo leg "
        f"({m['nodes']} nodes, {m['elements']} elements, {m['parts']} parts); the flexion slider "
        "is moved over the whole range (-5° to 140°) and each update is timed from the slider "
        "move to the end of the render. Software OpenGL (Mesa llvmpipe) under Xvfb, "
        f"{result['viewport_pixels'][0]}x{result['viewport_pixels'][1]} pixel view, "
        f"poser: {result['poser']}.",
        "",
        "| colouring | updates | median frame (ms) | 90th pct (ms) | median pose (ms) "
        "| updates/s |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in result["results"].items():
        lines.append(
            f"| {name.replace('_', ' ')} | {r['updates']} | {r['median_frame_ms']:.1f} | "
            f"{r['p90_frame_ms']:.1f} | {r['median_pose_ms']:.1f} | {r['updates_per_s']:.1f} |"
        )
    mach = result["machine"]
    lines += [
        "",
        f"Target: ≥ {result['target_updates_per_s']:.0f} updates/s. Window open to poser ready: "
        f"{result['open_to_ready_s']:.1f} s.",
        "",
        f"Machine: {mach.get('cpu', '?')}, {mach.get('cores', '?')} cores.",
        "",
    ]
    path.write_text("\n".join(lines), encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--elements", type=int, default=None, help="demo size (default: app's)")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "gui.json")
    parser.add_argument("--markdown", type=Path, default=ROOT / "docs" / "gui-benchmark.md")
    args = parser.parse_args(argv)
    result = run(args.elements, args.steps)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    if args.markdown:
        write_markdown(result, args.markdown)
    for name, r in result["results"].items():
        print(
            f"{name}: median {r['median_frame_ms']:.1f} ms/update, "
            f"{r['updates_per_s']:.1f} updates/s"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
