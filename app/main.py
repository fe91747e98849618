"""``kneegui-gui [DECK] [--setup S] [--screenshot PNG] [--flexion DEG] [--demo-elements N]``.

With no deck the window opens the built-in demo leg with its setup (``--demo-element-type`` and
``--demo-joint`` choose a variant, as ``kneegui demo``). With ``--screenshot`` it
saves a PNG of the real window once the model is posed and rendered (and, as in the window, the
export of the resting angle is shown: ``--live`` keeps the live mapping), then exits (0 on
success).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from app.heatmaps import HEATMAP_METRICS

READY_TIMEOUT_S = 300.0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="kneegui-gui", description=__doc__.splitlines()[0])
    parser.add_argument("deck", nargs="?", help="LS-DYNA deck (.k/.key/.dyn); default: demo leg")
    parser.add_argument("--setup", help="joint setup JSON for the deck")
    parser.add_argument("--screenshot", metavar="PNG", help="save a window screenshot and exit")
    parser.add_argument("--flexion", type=float, help="pose the knee at this angle (degrees)")
    parser.add_argument(
        "--colour",
        choices=("part", "quality", "stretch"),
        help="colour mode to show (with --metric for quality)",
    )
    parser.add_argument(
        "--metric",
        default=None,
        choices=tuple(HEATMAP_METRICS),
        help="heat-map measure (default: the first the model offers: the tet collapse on a "
        "tetrahedral model, the Jacobian otherwise)",
    )
    parser.add_argument(
        "--relax",
        action="store_true",
        help="relax and smooth the pose (as the toolbar button) before the screenshot",
    )
    parser.add_argument(
        "--live",
        action="store_true",
        help="keep the live mapping: do not show the export when the slider rests",
    )
    parser.add_argument(
        "--demo-elements", type=int, default=None, help="size of the generated demo leg (elements)"
    )
    parser.add_argument(
        "--demo-element-type",
        default="hex",
        choices=("hex", "tet", "mixed", "tet10"),
        help="solid elements of the demo leg (as kneegui demo --element-type)",
    )
    parser.add_argument(
        "--demo-joint",
        default="sliding",
        choices=("sliding", "welded"),
        help="joint meshing of the demo leg (as kneegui demo --joint)",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    os.environ.setdefault("QT_API", "pyside6")
    from PySide6.QtCore import QTimer
    from PySide6.QtWidgets import QApplication

    from app.main_window import APPLICATION, ORGANIZATION, MainWindow
    from app.qt_compat import protect_singletons

    protect_singletons()

    app = QApplication.instance() or QApplication(sys.argv[:1])
    app.setOrganizationName(ORGANIZATION)
    app.setApplicationName(APPLICATION)
    window = MainWindow()
    if args.screenshot:
        window.ws.autosave_enabled = False  # nobody to ask: leave any autosave as it is
    if args.live:
        window.set_rest_export(False)
    window.show()
    status = {"code": 0}

    def start() -> None:
        if args.deck:
            window.guard(window.open_deck, args.deck, args.setup)
        else:
            window.guard(
                window.open_demo, args.demo_elements, args.demo_element_type, args.demo_joint
            )

    QTimer.singleShot(0, start)
    started = time.monotonic()

    def when_ready() -> None:
        ws = window.ws
        ready = ws.poser is not None and not ws.tasks.busy
        failed = window.last_error is not None and not ws.tasks.busy and ws.poser is None
        if not ready and not failed and time.monotonic() - started < READY_TIMEOUT_S:
            QTimer.singleShot(100, when_ready)
            return
        if ready:
            if args.flexion is not None:
                ws.set_flexion(args.flexion)
            if args.colour:
                ws.set_metric(args.metric or ws.heatmap_metrics()[0])
                ws.set_colour_mode(args.colour)
            if args.relax:
                window.guard(ws.smooth)
        if args.screenshot:
            QTimer.singleShot(300, lambda: finish_when_idle(ready))

    def finish_when_idle(ready: bool) -> None:
        busy = window.ws.tasks.busy or window.ws.preview_pending
        if busy and time.monotonic() - started < READY_TIMEOUT_S + 300:
            QTimer.singleShot(200, lambda: finish_when_idle(ready))
            return
        QTimer.singleShot(300, lambda: finish(ready))

    def finish(ready: bool) -> None:
        window.viewport.flush()
        out = window.save_screenshot(Path(args.screenshot))
        ws = window.ws
        shown = ws.colour_mode + (f": {ws.metric}" if ws.colour_mode == "quality" else "")
        print(
            f"screenshot: {out} ({shown}, {ws.view_kind})"
            + ("" if ready else f" (not ready: {window.last_error})")
        )
        status["code"] = 0 if ready else 1
        window.close()
        app.quit()

    QTimer.singleShot(200, when_ready)
    app.exec()
    return status["code"]


if __name__ == "__main__":
    raise SystemExit(main())
