"""Live slider speed of the real window on the default demo leg (needs a display: xvfb-run).

``xvfb-run -a -s "-screen 0 1600x1000x24" python -m bench.gui_bench`` opens the main window on
the default demo leg, drives the flexion slider over ``steps`` positions from -5 to 140 degrees
and times each update from the slider move to the end of the render (pose through the engine's
repositioner, VTK points overwritten in place, one render). It runs in part colours and again
with the Jacobian heat-map (quality recomputed every step), splits one update into its parts
(pose, points, scalars, VTK render, Qt composition of the window), with ``--rest-export`` times
the export shown once the slider rests at 90 degrees, and writes bench/results/gui.json and
docs/gui-benchmark.md.

The drags run with the export at rest switched off (the slider rests between passes, and an
export running then would share the cores with the next pass).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from bench.machine import machine_description

ROOT = Path(__file__).resolve().parent.parent
TARGET_UPDATES_PER_S = 30.0
REST_ANGLE_DEG = 90.0
#: What follows this line in the Markdown file is kept when a run rewrites the file.
NOTES_MARKER = "<!-- notes: kept when python -m bench.gui_bench rewrites this file -->"


def _wait_until(app, done, timeout_s: float = 120.0) -> None:
    """Run the event loop until ``done()``, sleeping between events as a real window does.

    A loop spinning ``processEvents()`` would keep one of the machine's cores busy, and on a
    2-core machine that core is what the pose thread and the software renderer share. A
    heartbeat timer wakes the loop every few milliseconds so a condition that changes without
    an event of this thread is still seen.
    """
    from PySide6.QtCore import QEventLoop, QTimer

    heartbeat = QTimer()
    heartbeat.setInterval(5)
    heartbeat.start()
    start = time.perf_counter()
    try:
        while not done():
            app.processEvents(QEventLoop.ProcessEventsFlag.WaitForMoreEvents)
            if time.perf_counter() - start > timeout_s:
                raise RuntimeError(f"the window did not become idle within {timeout_s:.0f} s")
    finally:
        heartbeat.stop()


def _drive(app, window, steps: int, drag_hz: float) -> dict[str, float]:
    """Two passes over the slider range.

    - stepwise: move the slider, wait until that pose is drawn, repeat (latency per update);
    - drag: a timer moves the slider ``drag_hz`` times per second to where a hand moving over
      the range at constant speed would be, whatever the window is doing (a position the busy
      window cannot take is skipped, as Qt compresses mouse motion), and the poses actually
      drawn are counted (throughput).

    Between events the harness sleeps in the event loop (:func:`_wait_until`).
    """
    from PySide6.QtCore import QTimer

    ws, vp = window.ws, window.viewport
    slider = window.flexion_panel.slider
    lo, hi = slider.minimum(), slider.maximum()
    values = [round(lo + (hi - lo) * i / (steps - 1)) for i in range(steps)]
    applied = []
    ws.coords_changed.connect(lambda: applied.append(time.perf_counter()))
    poser = ws.poser
    pose_ms = []
    for deg in (0.0, 45.0, 90.0, 135.0):
        t = time.perf_counter()
        poser.pose(deg)
        pose_ms.append(1e3 * (time.perf_counter() - t))

    def idle() -> bool:
        return not ws.pose_pending and not vp._timer.isActive()

    def settle():
        _wait_until(app, idle)
        before = vp.renders
        vp.render()
        _wait_until(app, lambda: vp.renders > before)

    # stepwise
    frame_ms = []
    slider.setValue(values[-1])
    settle()
    start = time.perf_counter()
    for v in values:
        t = time.perf_counter()
        before = vp.renders
        slider.setValue(v)
        _wait_until(app, lambda before=before: not ws.pose_pending and vp.renders > before)
        frame_ms.append(1e3 * (time.perf_counter() - t))
    stepwise_s = time.perf_counter() - start
    # drag
    slider.setValue(values[-1])
    settle()
    applied.clear()
    renders0, frames0 = vp.renders, vp.pose_frames
    state = {"last": None, "moves": 0, "i": 0}
    hand = QTimer()
    hand.setInterval(max(1, round(1000.0 / drag_hz)))

    def move_hand() -> None:
        elapsed = time.perf_counter() - start
        i = min(int(elapsed * drag_hz), len(values) - 1)
        state["i"] = i
        if values[i] != state["last"]:
            state["last"] = values[i]
            slider.setValue(values[i])
            state["moves"] += 1
        if i == len(values) - 1:
            hand.stop()

    hand.timeout.connect(move_hand)
    start = time.perf_counter()
    hand.start()
    _wait_until(app, lambda: state["i"] == len(values) - 1, timeout_s=600.0)
    settle()
    drag_s = time.perf_counter() - start
    shown = vp.pose_frames - frames0  # batched updates that moved the points, each rendered
    return {
        "slider_positions": len(values),
        "stepwise_median_update_ms": statistics.median(frame_ms),
        "stepwise_p90_update_ms": sorted(frame_ms)[int(0.9 * len(frame_ms))],
        "stepwise_updates_per_s": len(values) / stepwise_s,
        "drag_events_per_s": drag_hz,
        "drag_slider_moves": state["moves"],
        "drag_poses_computed": len(applied),
        "drag_poses_drawn": shown,
        "drag_renders": vp.renders - renders0,
        "drag_seconds": drag_s,
        "drag_updates_per_s": shown / drag_s,
        "median_pose_ms": statistics.median(pose_ms),
    }


def _breakdown(app, window, repeats: int = 30) -> dict[str, float]:
    """Median cost of the pieces of an update: the pose (in the pose thread), the points and
    the scalars written into VTK, the VTK render, and Qt composing the window (what one other
    widget's repaint costs: with pyvistaqt's QOpenGLWidget view the whole window is composed
    through OpenGL; with the native view, Qt's raster engine repaints only that widget)."""
    vp, ws = window.viewport, window.ws
    label = window.flexion_panel.info
    poses = [ws.poser.pose(-5.0 + 145.0 * i / repeats) for i in range(repeats)]
    measure = ws._live_quality_job()

    def median_ms(fn) -> float:
        times = []
        for i in range(repeats):
            t = time.perf_counter()
            fn(i)
            times.append(1e3 * (time.perf_counter() - t))
        return statistics.median(times)

    def repaint(i: int) -> None:  # another widget changes: Qt composes the window again
        label.setText(f"bench {i:04d}")  # same width: no layout change
        app.processEvents()

    def points(i: int) -> None:
        ws.coords = poses[i]
        vp._update_points()

    def scalars(i: int) -> None:  # measured in the pose thread, written on the GUI thread
        ws.coords = poses[i]
        ws._pose_quality = measure(poses[i]) if measure is not None else None
        vp._update_values()

    out = {
        "pose": median_ms(lambda i: ws.poser.pose(-5.0 + 145.0 * i / repeats)),
        "points": median_ms(points),
        "scalars": median_ms(scalars) if ws.colour_mode != "part" else 0.0,
        "vtk_render": median_ms(lambda i: vp.plotter.ren_win.Render()),
        "qt_compose": median_ms(repaint),
    }
    ws.set_flexion(-5.0, force=True)  # back to a consistent pose
    return out


def _rest_export_seconds(
    app, window, degrees: float, timeout_s: float = 900.0
) -> tuple[float, float | None]:
    """Seconds from the slider's release at ``degrees`` to the export shown in the view, and
    to the first stage of that export shown (its untangled pose; None when none was)."""
    ws = window.ws
    window.set_rest_export(True)
    slider = window.flexion_panel.slider
    _wait_until(app, lambda: not (ws.preview_pending or ws.pose_pending), timeout_s)
    start = time.perf_counter()
    first_stage: list[float] = []

    def exported() -> bool:
        if not first_stage and ws.view_kind == "relaxing" and ws.flexion == degrees:
            first_stage.append(time.perf_counter() - start)
        return ws.view_kind == "as exported" and ws.flexion == degrees

    slider.setValue(round(degrees * 10))
    ws.settle_flexion()  # the release
    _wait_until(app, exported, timeout_s)
    seconds = time.perf_counter() - start
    window.set_rest_export(False)
    return seconds, (first_stage[0] if first_stage else None)


def run(
    elements: int | None = None,
    steps: int = 200,
    drag_hz: float = 60.0,
    repeats: int = 3,
    rest_export: bool = False,
    element_type: str = "hex",
    joint: str = "sliding",
    heatmaps: Sequence[str] | None = None,
    all_parts: bool = False,
) -> dict:
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
    deck, setup = demo_files(
        elements, cache_dir=tmp / "cache", element_type=element_type, joint=joint
    )
    window = MainWindow()
    window.resize(1500, 920)
    window.show()
    window.set_rest_export(False)  # see the module docstring
    t0 = time.perf_counter()
    window.open_deck(deck, setup)
    try:
        _wait_until(app, lambda: window.ws.poser is not None and not window.ws.tasks.busy, 300)
    except RuntimeError as exc:
        raise RuntimeError(f"the window did not get ready: {window.last_error}") from exc
    ready_s = time.perf_counter() - t0
    _wait_until(app, lambda: not window.ws.preview_pending, 600)  # the live quality curve
    if all_parts:  # skin and flesh too: the view an analyst checks the skin in
        for pid in sorted(window.ws.hidden_parts):
            window.ws.set_part_visible(pid, True)
    window.viewport.flush()
    size = window.viewport.plotter.ren_win.GetSize()
    load_before = os.getloadavg()
    breakdown = {"part_colours": _breakdown(app, window)}

    def repeated() -> dict[str, float]:
        runs = [_drive(app, window, steps, drag_hz) for _ in range(repeats)]
        out = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
        out["runs"] = runs
        return out

    results = {"part_colours": repeated()}
    # by default what the window offers first on this model
    for metric in heatmaps or window.ws.heatmap_metrics()[:1]:
        if metric not in window.ws.heatmap_metrics():
            raise ValueError(f"the window offers no {metric!r} heat-map on this model")
        window.ws.set_metric(metric)
        window.ws.set_colour_mode("quality")
        window.viewport.flush()
        breakdown[f"{metric}_heatmap"] = _breakdown(app, window)
        results[f"{metric}_heatmap"] = repeated()
    rest_s = kept_s = stage_s = None
    if rest_export:
        rest_s, stage_s = _rest_export_seconds(app, window, REST_ANGLE_DEG)
        # away (the live mapping) and back: the window shows the export it keeps for that angle
        window.ws.set_flexion(REST_ANGLE_DEG - 30.0, force=True)
        kept_s, _ = _rest_export_seconds(app, window, REST_ANGLE_DEG)
    model = window.ws.model
    out = {
        "benchmark": "gui slider",
        "view_class": type(window.viewport.plotter).__name__,
        "demo_elements_requested": elements,
        "demo_variant": {"element_type": element_type, "joint": joint},
        "all_parts_shown": all_parts,
        "model": {
            "nodes": model.n_nodes,
            "elements": model.n_elements,
            "parts": len(model.part_ids()),
            "element_types": {t: len(b) for t, b in model.blocks.items() if len(b)},
        },
        "poser": getattr(window.ws.poser, "kind", type(window.ws.poser).__name__),
        "open_to_ready_s": ready_s,
        "viewport_pixels": list(size),
        "target_updates_per_s": TARGET_UPDATES_PER_S,
        "repeats": repeats,
        "results": results,
        "breakdown_ms": breakdown,
        "rest_export_angle_deg": REST_ANGLE_DEG,
        "rest_export_s": rest_s,
        "rest_export_first_stage_s": stage_s,
        "rest_export_kept_s": kept_s,
        "machine": machine_description(),
        # other processes share the 2 cores: the 1-minute load average before / after the run
        "load_average_1min": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
    }
    window.close()
    return out


#: The default demo's variant (element type, joint): its results keep the plain file names.
DEFAULT_VARIANT = ("hex", "sliding")


def variant_suffix(element_type: str, joint: str, all_parts: bool = False) -> str:
    """``""`` for the default demo, else ``"-tet-sliding"`` etc., and ``"-all-parts"`` with
    every part shown (result and page names)."""
    name = "" if (element_type, joint) == DEFAULT_VARIANT else f"-{element_type}-{joint}"
    return name + ("-all-parts" if all_parts else "")


def _variant(result: dict) -> tuple[str, str]:
    v = result.get("demo_variant")
    return (v["element_type"], v["joint"]) if v else DEFAULT_VARIANT


def _variant_flags(result: dict) -> str:
    element_type, joint = _variant(result)
    flags = (
        []
        if (element_type, joint) == DEFAULT_VARIANT
        else [f"--element-type {element_type} --joint {joint}"]
    )
    if result.get("all_parts_shown"):
        flags.append("--all-parts")
    return f"with `{' '.join(flags)}` " if flags else ""


def _variant_words(result: dict) -> str:
    element_type, joint = _variant(result)
    if (element_type, joint) == DEFAULT_VARIANT:
        words = "the default demo leg"
    else:
        words = f"the demo leg's {element_type} variant ({joint} joint)"
    if result.get("all_parts_shown"):
        words += ", every part shown (skin and flesh too, which the window starts hidden)"
    return words


def _type_counts(model: dict) -> str:
    counts = model.get("element_types") or {}
    return ", ".join(f"{n:,} {t}" for t, n in counts.items()) or "?"


def write_markdown(result: dict, path: Path) -> None:
    m = result["model"]
    r0 = next(iter(result["results"].values()))
    lines = [
        "# GUI slider benchmark",
        "",
        'Produced by `xvfb-run -a -s "-screen 0 1600x1000x24" python -m bench.gui_bench` '
        f"{_variant_flags(result)}(bench/results/gui"
        f"{variant_suffix(*_variant(result), bool(result.get('all_parts_shown')))}.json). "
        "The real main window on "
        f"{_variant_words(result)} ({m['nodes']} nodes, {m['elements']} elements: "
        f"{_type_counts(m)}; {m['parts']} parts); the flexion slider "
        f"is moved over the whole range (-5° to 140°) in {r0['slider_positions']} positions, "
        "(a) stepwise: each move waits until its pose is drawn (time from the slider move to the "
        "end of the render); (b) drag: the slider follows a hand moving over the range at "
        f"{r0['drag_events_per_s']:.0f} positions/s (positions the busy window cannot take are "
        "skipped, as Qt does with mouse motion) and the poses actually drawn are counted (the "
        "pose of the latest position is computed in a pose thread while the "
        "previous one is drawn; positions passed meanwhile are skipped). "
        "Between events the harness sleeps in Qt's event loop, as a real window does (it does "
        "not spin, which would take one of the cores the pose thread and the renderer share). "
        f"Each figure is the median of {result['repeats']} runs. "
        "Software OpenGL (Mesa llvmpipe) under Xvfb, "
        f"{result['viewport_pixels'][0]}x{result['viewport_pixels'][1]} pixel view "
        f"({result.get('view_class', '?')}), poser: {result['poser']}.",
        "",
        "| colouring | stepwise: median update (ms) | stepwise updates/s | drag: poses drawn/s "
        "| median pose (ms) |",
        "|---|---|---|---|---|",
    ]
    for name, r in result["results"].items():
        lines.append(
            f"| {name.replace('_', ' ')} | {r['stepwise_median_update_ms']:.1f} | "
            f"{r['stepwise_updates_per_s']:.1f} | {r['drag_updates_per_s']:.1f} | "
            f"{r['median_pose_ms']:.1f} |"
        )
    lines += [
        "",
        "Where the time of one update goes (median ms; the pose runs in the pose thread while "
        "the GUI thread draws the previous one; Qt compose = what the repaint of one other "
        "widget costs: small with the native view, the order of the VTK render when the 3-D "
        "view is a QOpenGLWidget and Qt composes the whole window through OpenGL):",
        "",
        "| colouring | pose | points | scalars | VTK render | Qt compose |",
        "|---|---|---|---|---|---|",
    ]
    for name, b in result["breakdown_ms"].items():
        lines.append(
            f"| {name.replace('_', ' ')} | {b['pose']:.1f} | {b['points']:.1f} | "
            f"{b['scalars']:.1f} | {b['vtk_render']:.1f} | {b['qt_compose']:.1f} |"
        )
    if result.get("rest_export_s") is not None:
        lines += [
            "",
            f"Export at rest: from the slider's release at {result['rest_export_angle_deg']:g}° "
            f"to the exported pose shown: {result['rest_export_s']:.1f} s.",
        ]
        if result.get("rest_export_first_stage_s") is not None:
            lines[-1] += (
                " Its first stage, the untangled pose (marked RELAXING, not written by File >"
                f" Export), was shown after {result['rest_export_first_stage_s']:.1f} s."
            )
        if result.get("rest_export_kept_s") is not None:
            lines[-1] += (
                f" Back at {result['rest_export_angle_deg']:g}° after a move away, the export"
                f" kept for that angle is shown {result['rest_export_kept_s']:.2f} s after the"
                " release (no solve)."
            )
    mach = result["machine"]
    lines += [
        "",
        f"Target: ≥ {result['target_updates_per_s']:.0f} updates/s. Window open to poser ready: "
        f"{result['open_to_ready_s']:.1f} s.",
        "",
        f"Machine: {mach.get('cpu', '?')}, {mach.get('cores', '?')} cores; 1-minute load "
        f"average {result['load_average_1min'][0]} before and {result['load_average_1min'][1]} "
        "after the run (other work on the same cores slows every figure down).",
        "",
    ]
    text = "\n".join(lines)
    # hand-written notes after the marker survive a new run
    old = path.read_text(encoding="utf-8") if path.exists() else ""
    if NOTES_MARKER in old:
        text += "\n" + old[old.index(NOTES_MARKER) :]
    path.write_text(text, encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--elements", type=int, default=None, help="demo size (default: app's)")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3, help="runs per mode (medians kept)")
    parser.add_argument(
        "--rest-export",
        action="store_true",
        help="also time the export shown when the slider rests at 90 degrees (the export path: "
        "seconds to minutes)",
    )
    parser.add_argument(
        "--element-type",
        default="hex",
        choices=("hex", "tet", "mixed", "tet10"),
        help="demo variant's solid elements (as kneegui demo); the heat-map pass uses the "
        "first measure the window offers on it (tet collapse on tetrahedra)",
    )
    parser.add_argument("--joint", default="sliding", choices=("sliding", "welded"))
    parser.add_argument(
        "--heatmaps",
        default=None,
        help="comma-separated heat-maps to time (keys of app.heatmaps.HEATMAP_METRICS, e.g. "
        "jacobian,warpage,volume_change); default the first the window offers",
    )
    parser.add_argument(
        "--all-parts",
        action="store_true",
        help="show every part (skin and flesh too, which the window starts hidden)",
    )
    parser.add_argument("--out", type=Path, default=None, help="default bench/results/gui.json")
    parser.add_argument("--markdown", type=Path, default=None, help="default docs/gui-benchmark.md")
    args = parser.parse_args(argv)
    variant = variant_suffix(args.element_type, args.joint, args.all_parts)
    args.out = args.out or ROOT / "bench" / "results" / f"gui{variant}.json"
    args.markdown = args.markdown or ROOT / "docs" / f"gui-benchmark{variant}.md"
    result = run(
        args.elements,
        args.steps,
        repeats=args.repeats,
        rest_export=args.rest_export,
        element_type=args.element_type,
        joint=args.joint,
        heatmaps=args.heatmaps.split(",") if args.heatmaps else None,
        all_parts=args.all_parts,
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    if args.markdown:
        write_markdown(result, args.markdown)
    for name, r in result["results"].items():
        print(
            f"{name}: stepwise median {r['stepwise_median_update_ms']:.1f} ms/update "
            f"({r['stepwise_updates_per_s']:.1f}/s); drag {r['drag_updates_per_s']:.1f} poses/s"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
