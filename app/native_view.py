"""A pyvista plotter in a native child window: VTK draws straight into it, Qt composes nothing.

pyvistaqt's ``QtInteractor`` is a ``QOpenGLWidget``: VTK renders into a framebuffer object and
Qt then composes the *whole* window through OpenGL on every repaint. With software OpenGL
(Mesa llvmpipe under Xvfb, remote desktops, virtual machines) that composition costs as much as
the VTK render itself, about 20 ms per frame on the paper-scale demo (docs/gui-benchmark.md).

:class:`NativeInteractor` pairs VTK's own Qt interactor in its native-window form
(``vtkmodules.qt.QVTKRenderWindowInteractor`` with the ``QWidget`` base: the render window
draws into the widget's X11/Win32/Cocoa window and swaps its buffers there) with pyvista's
``BasePlotter``, so the view keeps the whole pyvista plotting API while the other widgets are
painted by Qt's raster engine. Widget grabs do not contain a native GL window's pixels; the
main window's screenshot paints the plotter's own screenshot over it
(:meth:`app.main_window.MainWindow.save_screenshot`).

Wayland sessions cannot embed a native GL child this way; there the viewport falls back to
pyvistaqt's ``QtInteractor`` (:func:`interactor_class`).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import vtkmodules.qt

vtkmodules.qt.QVTKRWIBase = "QWidget"  # both read when the module below is imported
vtkmodules.qt.PyQtImpl = "PySide6"

from PySide6.QtGui import QGuiApplication  # noqa: E402
from PySide6.QtWidgets import QWidget  # noqa: E402
from pyvista.plotting.plotter import BasePlotter  # noqa: E402
from pyvista.plotting.render_window_interactor import RenderWindowInteractor  # noqa: E402
from vtkmodules.qt.QVTKRenderWindowInteractor import (  # noqa: E402
    QVTKRenderWindowInteractor as _NativeWindowInteractor,
)

#: ``KNEEGUI_VIEW`` = ``native`` | ``opengl-widget`` overrides the automatic choice.
VIEW_ENV = "KNEEGUI_VIEW"


@contextmanager
def _without_base_plotter_init() -> Iterator[None]:
    # Qt's cooperative __init__ chain would call BasePlotter.__init__ with no arguments from
    # inside QWidget.__init__; it is called explicitly afterwards instead.
    original = BasePlotter.__init__
    BasePlotter.__init__ = lambda *_a, **_k: None  # type: ignore[method-assign]
    try:
        yield
    finally:
        BasePlotter.__init__ = original  # type: ignore[method-assign]


class NativeInteractor(_NativeWindowInteractor, BasePlotter):
    """pyvista plotter whose render window draws into a native child window of ``parent``.

    Parameters
    ----------
    parent : QWidget or None
        The widget it is placed in.
    multi_samples : int
        Multisample anti-aliasing samples (0: none, the fastest in software OpenGL).
    """

    def __init__(self, parent: QWidget | None = None, multi_samples: int = 0) -> None:
        with _without_base_plotter_init():
            _NativeWindowInteractor.__init__(self, parent)
        BasePlotter.__init__(self)
        self.interactor = self
        self.ren_win = self.GetRenderWindow()
        self.ren_win.SetMultiSamples(multi_samples)
        for renderer in self.renderers:
            renderer.view_isometric()
            self.ren_win.AddRenderer(renderer)
        self._off_screen = False
        self.iren: Any = RenderWindowInteractor(self, interactor=self.ren_win.GetInteractor())
        # pyvista's own mouse-move observer re-renders on every move; Qt drives rendering here
        self.iren.interactor.RemoveObservers("MouseMoveEvent")
        self.iren.initialize()
        self.enable_trackball_style()
        self._first_time = False  # BasePlotter: the window exists and renders through Qt
        self._closed = False

    def render(self) -> None:
        """Render the scene now (what ``BasePlotter.render`` does, unless closed)."""
        if self._closed:
            return
        self._rendered = True
        BasePlotter.render(self)

    def close(self) -> None:  # type: ignore[override]
        """Release the render window and the widget."""
        if self._closed:
            return
        self._closed = True
        BasePlotter.close(self)
        QWidget.close(self)

    def closeEvent(self, event: Any) -> None:
        """Finalize the render window once (Qt calls this on close)."""
        if not self._closed:
            self._closed = True
            BasePlotter.close(self)
        event.accept()


def native_view_supported() -> bool:
    """Whether a native GL child window can be embedded (X11 or Windows; not Wayland)."""
    platform = QGuiApplication.platformName() if QGuiApplication.instance() else ""
    return platform in ("xcb", "windows", "cocoa")


def interactor_class() -> type:
    """The interactor class the viewport uses: native where it works, pyvistaqt's otherwise."""
    choice = os.environ.get(VIEW_ENV, "").strip().lower()
    if choice == "opengl-widget":
        from pyvistaqt import QtInteractor

        return QtInteractor
    if choice == "native" or native_view_supported():
        return NativeInteractor
    from pyvistaqt import QtInteractor

    return QtInteractor
