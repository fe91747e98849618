"""Write the README / user-guide screenshots of the real window (needs a display: xvfb-run).

``xvfb-run -a -s "-screen 0 1600x1000x24" python scripts/screenshots.py`` opens the main window on
the default demo leg and saves:

- docs/images/gui-flexion90-jacobian.png: the knee at 90°, relaxed and smoothed (Relax +
  smooth, what the export writes), with the Jacobian heat-map (skin hidden, lateral half cut
  away) and the Quality panel;
- docs/images/gui-landmarks.png: the femur with the picked condyle nodes, the fitted circles,
  the F-E and L-R axes and the Landmarks panel;
- docs/images/gui-exported90.png: the same pose as exported, its banner ("AS EXPORTED" with
  its figures) and the quality-against-flexion plot;
- docs/images/gui-ligaments.png: ligament stretch at 90° and the length-vs-flexion plot;
- docs/images/gui-tet-collapse60.png: the tetrahedral demo leg (``kneegui demo --element-type
  tet``) at 60° as exported, coloured by tet collapse (skin hidden, lateral half cut away)
  with the Quality panel (``--tet-only`` writes this one alone).
"""

from __future__ import annotations

import kneegui.reproducible  # noqa: F401  (before numpy: the same kernels on every machine)

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _pump(app, seconds: float = 0.3) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        app.processEvents()
        time.sleep(0.01)


def _wait(app, window) -> None:
    start = time.monotonic()
    ws = window.ws
    while ws.poser is None or ws.tasks.busy or ws.preview_pending or ws.pose_pending:
        app.processEvents()
        time.sleep(0.01)
        if time.monotonic() - start > 1800:
            raise RuntimeError(f"window not ready: {window.last_error}")
    _pump(app)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--outdir", type=Path, default=ROOT / "docs" / "images")
    parser.add_argument("--elements", type=int, default=None)
    parser.add_argument("--tet-only", action="store_true", help="only the tet heat-map shot")
    args = parser.parse_args(argv)
    os.environ.setdefault("QT_API", "pyside6")
    from PySide6.QtCore import QSettings
    from PySide6.QtWidgets import QApplication

    from app.demo import DEFAULT_DEMO_ELEMENTS, demo_files
    from app.main_window import MainWindow
    from app.qt_compat import protect_singletons

    protect_singletons()
    tmp = Path(tempfile.mkdtemp(prefix="kneegui-shots-"))
    QSettings.setPath(QSettings.Format.IniFormat, QSettings.Scope.UserScope, str(tmp))
    app = QApplication.instance() or QApplication([])
    args.outdir.mkdir(parents=True, exist_ok=True)
    if args.tet_only:
        print(_tet_heatmap_shot(app, args.outdir, tmp))
        return 0
    deck, setup = demo_files(args.elements or DEFAULT_DEMO_ELEMENTS, cache_dir=tmp / "cache")
    window = MainWindow()
    window.resize(1500, 920)
    window.show()
    window.open_deck(deck, setup)
    _wait(app, window)
    ws, vp = window.ws, window.viewport
    args.outdir.mkdir(parents=True, exist_ok=True)
    roles = ws.setup_dict["roles"]

    # 1. landmarks: femur (and tibia) only, lateral view, fitted circles and axes
    window.docks["Landmarks"].raise_()
    for pid in vp.actors:
        ws.set_part_visible(pid, pid in roles["femur"] or pid in roles["tibia"])
    ws.set_pick_target("lateral_condyle")
    vp.flush()
    vp.camera_preset("lateral")
    # turn towards the back so both condyle sets and both circles are seen
    frame = ws.knee_frame()
    cam = vp.plotter.camera
    distance = float(np.linalg.norm(np.asarray(cam.position) - np.asarray(cam.focal_point)))
    view = 0.75 * frame["lateral"] - 0.65 * frame["anterior"] - 0.15 * frame["superior"]
    cam.position = frame["center"] + distance * view / np.linalg.norm(view)
    cam.focal_point = frame["center"]
    cam.up = frame["superior"]
    cam.zoom(2.2)
    vp.plotter.reset_camera_clipping_range()
    _pump(app)
    out1 = window.save_screenshot(args.outdir / "gui-landmarks.png")
    ws.set_pick_target("")

    # 2. 90 degrees, relaxed and smoothed as the export writes it (Relax + smooth), Jacobian
    # heat-map, skin hidden, lateral half cut away
    window.flexion_panel.slider.setValue(900)
    _wait(app, window)
    window.guard(ws.smooth)
    _wait(app, window)
    qp = _cut_away_heatmap(app, window, "jacobian")
    out2 = window.save_screenshot(args.outdir / "gui-flexion90-jacobian.png")

    # 2b. the same pose as exported: the banner and the quality-against-flexion plot
    qp.clip_on.setChecked(False)
    window.docks["Quality vs flexion"].raise_()
    vp.flush()
    vp.camera_preset("lateral")
    vp.plotter.camera.zoom(1.1)
    _pump(app, 0.8)
    out2b = window.save_screenshot(args.outdir / "gui-exported90.png")

    # 3. ligament stretch at 90 degrees with the length curves
    qp.clip_on.setChecked(False)
    keep = (
        set(roles["femur"])
        | set(roles["tibia"])
        | set(roles["fibula"])
        | set(roles["ligament"])
        | set(roles["patella"])
    )
    for pid in vp.actors:
        ws.set_part_visible(pid, pid in keep)
    window.docks["Ligaments"].raise_()
    ws.compute_ligament_curve()
    _wait(app, window)
    window.ligament_panel.show_stretch.click()
    vp.flush()
    vp.camera_preset("medial")
    vp.plotter.camera.zoom(1.5)
    _pump(app, 0.5)
    out3 = window.save_screenshot(args.outdir / "gui-ligaments.png")
    window.close()
    out4 = _tet_heatmap_shot(app, args.outdir, tmp)
    for out in (out1, out2, out2b, out3, out4):
        print(out)
    return 0


def _cut_away_heatmap(app, window, metric: str):
    """Skin hidden, the Quality panel's heat-map of ``metric``, the lateral half cut away, a
    lateral view; returns the Quality panel."""
    ws, vp = window.ws, window.viewport
    skin = set(ws.setup_dict["roles"].get("skin", []))
    for pid in vp.actors:
        ws.set_part_visible(pid, pid not in skin)
    window.docks["Quality"].raise_()
    qp = window.quality_panel
    qp.mode.setCurrentIndex(qp.mode.findData("quality"))
    qp.metric.setCurrentIndex(qp.metric.findData(metric))
    qp.clip_side.setCurrentText("lateral")
    qp.clip_on.setChecked(True)
    vp.flush()
    vp.camera_preset("lateral")
    vp.plotter.camera.zoom(1.1)
    qp.refresh()
    _pump(app, 0.5)
    return qp


def _tet_heatmap_shot(app, outdir: Path, tmp: Path) -> Path:
    """The tetrahedral demo leg at 60 deg as exported, coloured by tet collapse (the measure
    the window offers first on a tet model), skin hidden, lateral half cut away."""
    from app.demo import demo_files
    from app.main_window import MainWindow

    deck, setup = demo_files(2000, cache_dir=tmp / "cache", element_type="tet")
    window = MainWindow()
    window.resize(1500, 920)
    window.show()
    window.open_deck(deck, setup)
    _wait(app, window)
    ws = window.ws
    window.flexion_panel.slider.setValue(600)
    ws.settle_flexion()  # the release: the export of 60 deg is shown
    _wait(app, window)
    _cut_away_heatmap(app, window, "tet_collapse")
    if ws.view_kind != "as exported":
        raise RuntimeError(f"the tet demo's export at 60 deg is not shown: {window.last_error}")
    out = window.save_screenshot(outdir / "gui-tet-collapse60.png")
    window.close()
    return out


if __name__ == "__main__":
    raise SystemExit(main())
