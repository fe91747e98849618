"""The 3-D view: a pyvistaqt interactor wrapped in a widget that listens to the workspace.

Scene = one actor per part (its boundary faces, :func:`app.scene.part_surfaces`), plus overlays
(threshold highlight, focused element, condyle nodes, axis points, fitted circles, F-E and L-R
axes). When the pose changes, every actor's VTK points are overwritten IN PLACE from the
workspace's coordinate array (a numpy view on the VTK buffer) and one render is scheduled on a
timer, so a burst of slider events costs one redraw. Colours (heat-map, stretch) likewise update
the faces' ``value`` array in place.

Picking (landmark panel): with a pick target set, a left click picks the nearest surface node of
the pickable parts under the cursor, a left drag box-selects the visible surface nodes inside
the rectangle; Ctrl removes instead of adding. Other buttons still pan and zoom.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
import vtk
from numpy.typing import NDArray
from PySide6.QtCore import QEvent, QObject, QPoint, QRect, QSize, Qt, QTimer
from PySide6.QtWidgets import QVBoxLayout, QWidget
from vtk.util.numpy_support import numpy_to_vtkIdTypeArray, vtk_to_numpy

from app.colors import ROLE_COLOURS, UNASSIGNED_COLOUR
from app.native_view import NativeInteractor, interactor_class
from app.scene import PartSurface, build_grid, hidden_faces, part_surfaces
from app.workspace import HEATMAP_METRICS, Workspace
from kneegui.topology import sorted_unique

PICK_CLICK_PIXELS = 4
#: Camera presets frame the visible geometry within this distance of the knee centre (mm).
KNEE_VIEW_RADIUS_MM = 250.0
CAMERA_PRESETS = ("lateral", "medial", "anterior", "posterior")


class Viewport(QWidget):
    """The VTK view of the workspace's model (wraps, does not subclass, ``QtInteractor``)."""

    def __init__(self, workspace: Workspace, parent: QWidget | None = None):
        super().__init__(parent)
        self.ws = workspace
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        view_class = interactor_class()
        if view_class is NativeInteractor:
            self.plotter = NativeInteractor(self)
        else:  # pyvistaqt's QtInteractor (a QOpenGLWidget): Wayland, or asked for
            self.plotter = view_class(self, auto_update=False)
        # flat background: a gradient costs ~10 ms a frame in software GL
        self.plotter.set_background("#2b3038")
        # one headlight instead of pyvista's five-light kit: ~40 % less render time in software
        # GL, and the side facing the camera is always lit
        self.plotter.remove_all_lights()
        self.plotter.add_light(pv.Light(light_type="headlight"))
        # software GL (Mesa llvmpipe under Xvfb) renders 2-3x faster without multisampling
        self.plotter.ren_win.SetMultiSamples(0)
        self.plotter.ren_win.AddObserver("EndEvent", self._count_render)
        # landmarks, circles and axes live in a second layer drawn over the bones
        self._overlay = vtk.vtkRenderer()
        self._overlay.SetLayer(1)
        self._overlay.InteractiveOff()
        self.plotter.ren_win.SetNumberOfLayers(2)
        self.plotter.ren_win.AddRenderer(self._overlay)
        self.overlay_actors: dict[str, vtk.vtkActor] = {}
        layout.addWidget(self.plotter)
        self.plotter.add_axes()
        self.surfaces: dict[int, PartSurface] = {}
        self.actors: dict[int, vtk.vtkActor] = {}
        self._points: dict[int, NDArray[np.float64]] = {}
        # per part, the cells of its surface the actor draws (None: all, the surface itself)
        self._drawn_rows: dict[int, NDArray[np.int64] | None] = {}
        self.grid: pv.UnstructuredGrid | None = None
        self._overlays: dict[str, object] = {}
        self._highlight: tuple[pv.UnstructuredGrid, NDArray[np.int64]] | None = None
        self._focus: tuple[pv.UnstructuredGrid, NDArray[np.int64]] | None = None
        self._scalar_title = ""
        self._clip_plane = vtk.vtkPlane()
        self._dirty: set[str] = set()
        self.renders = 0  # VTK renders done (counted by the render window)
        self.flushes = 0  # batched updates applied
        self.pose_frames = 0  # batched updates that moved the points
        self._timer = QTimer(self)
        self._timer.setSingleShot(True)
        self._timer.setInterval(0)
        self._timer.timeout.connect(self.flush)
        # circles and axes are re-fitted once the pose has settled, not on every slider step
        self._axes_timer = QTimer(self)
        self._axes_timer.setSingleShot(True)
        self._axes_timer.setInterval(200)
        self._axes_timer.timeout.connect(lambda: self.request("axes"))
        self._landmark_points: dict[str, tuple[pv.PolyData, object]] = {}
        self._shown_cells: NDArray[np.int64] = np.zeros(0, dtype=np.int64)
        self._selection: _SelectionRect | None = None
        self._picker = _PickFilter(self)
        self.plotter.installEventFilter(self._picker)
        ws = workspace
        ws.model_changed.connect(self._on_model)
        ws.coords_changed.connect(self._on_coords)
        ws.setup_changed.connect(lambda: self.request("landmarks", "colour"))
        ws.poser_changed.connect(lambda: self.request("landmarks"))
        ws.display_changed.connect(self._on_display)
        ws.pick_target_changed.connect(lambda _t: self.request("landmarks"))

    # ------------------------------------------------------------------ batching
    def request(self, *what: str) -> None:
        """Ask for a redraw of ``what`` (points, colour, visibility, clip, landmarks, ...)."""
        self._dirty.update(what)
        if not self._timer.isActive():
            self._timer.start()

    def _on_coords(self) -> None:
        # Applied at once (poses are already coalesced by the workspace), so the view's repaint
        # joins the other widgets' (slider, spin box) in the same window composition.
        self._dirty.add("points")
        self.flush()

    def _on_display(self, what: str) -> None:
        if what in ("colour", "threshold", "visibility", "clip", "landmarks"):
            self.request(what)

    def flush(self) -> None:
        """Apply every pending change and render once."""
        dirty, self._dirty = self._dirty, set()
        if not dirty or self.ws.model is None or not self.actors:
            return
        self.flushes += 1
        self._overlay.SetActiveCamera(self.plotter.renderer.GetActiveCamera())
        if "points" in dirty:
            self.pose_frames += 1
            self._update_points()
            if not dirty & {"colour", "threshold", "visibility"}:
                self._update_values()
            self._move_landmarks()
            self._axes_timer.start()
        drawn_changed = False
        if dirty & {"visibility", "clip", "threshold", "colour"}:
            drawn_changed = self._apply_visibility()
            if drawn_changed:
                self._update_points()  # parts not drawn do not follow the pose
        if dirty & {"colour", "threshold", "visibility"} or drawn_changed:
            self._update_colours()
        if "clip" in dirty:
            self._update_clip()
        if "landmarks" in dirty:
            self._build_landmarks()
            dirty.add("axes")
        if "axes" in dirty:
            self._update_axes_overlay()
        self.render()

    def flush_all(self) -> None:
        """Apply everything pending now, including the deferred re-fit of circles and axes."""
        if self._axes_timer.isActive():
            self._axes_timer.stop()
            self._dirty.add("axes")
        self.flush()

    def render(self, now: bool = False) -> None:
        """Schedule one repaint of the 3-D view (``now``: repaint before returning).

        The interactor's paint event renders the VTK scene (into its native window, or into the
        framebuffer of pyvistaqt's ``QOpenGLWidget`` where that is used), so asking Qt for a
        repaint renders exactly once (``plotter.render()`` would render, then paint again).
        """
        if now:
            self.plotter.repaint()
        else:
            self.plotter.update()

    def _count_render(self, *_args) -> None:
        self.renders += 1

    # ------------------------------------------------------------------ scene
    def _on_model(self) -> None:
        model = self.ws.model
        self.plotter.clear_actors()
        self._overlays.clear()
        self._highlight = self._focus = None
        if self._scalar_title:
            self.plotter.remove_scalar_bar(self._scalar_title)
            self._scalar_title = ""
        self.surfaces = part_surfaces(model)
        self.grid = build_grid(model)
        self.actors.clear()
        self._points.clear()
        self._drawn_rows.clear()
        for pid, surf in self.surfaces.items():
            # the mapper reads the mesh directly: pyvista's add_mesh would put a Python
            # algorithm (active scalars) between them, run on every render of every part
            surf.mesh.GetCellData().SetActiveScalars("value")
            mapper = pv.DataSetMapper()
            mapper.SetInputData(surf.mesh)
            mapper.SetScalarModeToUseCellData()
            mapper.SetScalarVisibility(False)
            actor = pv.Actor(mapper=mapper)
            actor.prop.line_width = 3
            self.plotter.add_actor(
                actor, reset_camera=False, name=f"part-{pid}", render=False, pickable=True
            )
            self.actors[pid] = actor
            self._points[pid] = vtk_to_numpy(surf.mesh.GetPoints().GetData())
        self._colour_parts()
        self.request("points", "visibility", "colour", "clip", "landmarks")
        self.flush()
        self.camera_preset("lateral")

    def _see_through(self) -> bool:
        """Whether the parts are drawn translucent (the threshold highlight shows through)."""
        return self.ws.colour_mode == "quality" and self.ws.threshold is not None

    def _apply_visibility(self) -> bool:
        """Draw the parts the user shows, less the faces no one can see from outside: a face
        two shown parts share (the trabecular bone under its cortical shell, flesh against
        flesh, bone or skin; :func:`app.scene.hidden_faces`) costs render time and changes no
        pixel: on the demo leg the four trabecular bones are a quarter of the default view's
        render, and with skin and flesh shown two faces in three are such. A part left
        without a face or a line is not drawn. Every face is drawn while the view is cut open
        or see-through. Returns whether what is drawn changed."""
        ws = self.ws
        shown = {pid for pid in self.actors if pid not in ws.hidden_parts}
        whole = ws.clip_enabled or self._see_through()
        hidden = {} if whole else hidden_faces(self.surfaces, shown)
        changed = False
        for pid, actor in self.actors.items():
            surf = self.surfaces[pid]
            rows = None  # every cell of surf.mesh
            if pid in hidden and hidden[pid].any():
                n_lines = surf.mesh.GetNumberOfLines()
                rows = np.concatenate([np.arange(n_lines), n_lines + np.flatnonzero(~hidden[pid])])
            drawn = pid in shown and (rows is None or len(rows) > 0)
            old = self._drawn_rows.get(pid)
            if drawn and not (
                (rows is None and old is None)
                or (rows is not None and old is not None and np.array_equal(rows, old))
            ):
                actor.mapper.SetInputData(
                    surf.mesh if rows is None else _cell_subset(surf.mesh, rows)
                )
                self._drawn_rows[pid] = rows
                changed = True
            if bool(actor.GetVisibility()) != drawn:
                actor.SetVisibility(drawn)
                changed = True
        return changed

    def drawn_parts(self) -> list[int]:
        """Parts whose surface is drawn now (shown, with a face not hidden by other parts)."""
        return [pid for pid, actor in self.actors.items() if actor.GetVisibility()]

    def drawn_cells(self, pid: int) -> NDArray[np.int64]:
        """Global cells of the faces and lines of part ``pid`` that are drawn now."""
        surf, rows = self.surfaces[pid], self._drawn_rows.get(pid)
        return surf.cell_index if rows is None else surf.cell_index[rows]

    def _colour_parts(self) -> None:
        for pid, actor in self.actors.items():
            role = self.ws.part_role(pid)
            actor.prop.color = ROLE_COLOURS.get(role, UNASSIGNED_COLOUR)
            actor.prop.opacity = 1.0
            actor.prop.ambient = 0.15

    def _update_points(self) -> None:
        """Overwrite the points of the drawn parts in place (a part's points are brought up to
        date when it is drawn again)."""
        coords = self.ws.coords
        for pid, surf in self.surfaces.items():
            if not self.actors[pid].GetVisibility():
                continue
            np.take(coords, surf.model_index, axis=0, out=self._points[pid])
            surf.mesh.GetPoints().Modified()
        for item in (self._highlight, self._focus):
            if item is not None:
                grid, idx = item
                vtk_to_numpy(grid.GetPoints().GetData())[:] = coords[idx]
                grid.GetPoints().Modified()

    # ------------------------------------------------------------------ colours
    def _displayed_cells(self) -> NDArray[np.int64]:
        """Global cells that own a face of a drawn part (the ones the heat-map shows)."""
        chunks = [self.drawn_cells(p) for p in self.drawn_parts()]
        return sorted_unique(np.concatenate(chunks)) if chunks else np.zeros(0, dtype=np.int64)

    def _colour_values(self, cells: NDArray[np.int64] | None) -> NDArray[np.float64]:
        ws = self.ws
        if ws.colour_mode == "quality":
            return ws.element_values(ws.metric, cells)
        return ws.ligament_stretch_values()

    def _update_colours(self) -> None:
        """Set up the colouring (mode, metric, look-up table, scalar bar) and all face values."""
        ws = self.ws
        self._colour_parts()
        mode = ws.colour_mode
        # the elements on screen: measured with every slider pose (in the pose thread)
        self._shown_cells = self._displayed_cells()
        live = mode == "quality" and ws.threshold is None
        ws.set_live_cells(self._shown_cells if live else None)
        if self._scalar_title:
            self.plotter.remove_scalar_bar(self._scalar_title)
            self._scalar_title = ""
        if mode == "part":
            for actor in self.actors.values():
                actor.mapper.SetScalarVisibility(False)
            self._set_highlight(None)
            return
        values = self._colour_values(None)
        if mode == "quality":
            title = HEATMAP_METRICS[ws.metric][0]
            cmap = "RdYlBu" if HEATMAP_METRICS[ws.metric][2] else "RdYlBu_r"
            clim = _quality_clim(ws.metric, values)
        else:
            title = "Fibre stretch"
            cmap = "coolwarm"
            finite = values[np.isfinite(values)]
            spread = np.abs(np.percentile(finite, [2, 98]) - 1.0) if len(finite) else [0.1]
            half = max(0.02, float(np.max(spread)))
            clim = (max(0.0, 1.0 - half), 1.0 + half)
        lut = pv.LookupTable(cmap=cmap)
        lut.scalar_range = clim
        lut.nan_color = "#b0b0b0"
        first = None
        for pid, surf in self.surfaces.items():
            face_values = values[surf.cell_index]
            self._write_values(pid, face_values)
            actor = self.actors[pid]
            has = bool(np.isfinite(face_values).any())
            actor.mapper.SetScalarVisibility(has)
            if has:
                actor.mapper.lookup_table = lut
                actor.mapper.scalar_range = clim
                first = first or actor.mapper
        if first is not None:
            self._scalar_title = title
            self.plotter.add_scalar_bar(
                title,
                mapper=first,
                n_labels=5,
                fmt="%.2f",
                vertical=True,
                position_x=0.88,
                position_y=0.2,
                height=0.6,
                width=0.06,
            )
        self._update_highlight(values)

    def _update_values(self) -> None:
        """After a pose change: new face values of the visible parts, written in place.

        Only the elements that show a face are measured (the heat-map is evaluated for what is
        on screen); the threshold highlight, when on, uses every element.
        """
        ws = self.ws
        if ws.colour_mode == "part":
            return
        full = ws.colour_mode == "quality" and ws.threshold is not None
        values = self._colour_values(None if full else self._shown_cells)
        for pid in self.drawn_parts():
            surf = self.surfaces[pid]
            self._write_values(pid, values[surf.cell_index])
        if full:
            self._update_highlight(values)

    def _write_values(self, pid: int, face_values: NDArray[np.float64]) -> None:
        """Write one value per cell of part ``pid``'s surface into the surface and, where its
        actor draws only some of the cells, into those too."""
        targets = [(self.surfaces[pid].mesh, face_values)]
        rows = self._drawn_rows.get(pid)
        if rows is not None:
            targets.append((self.actors[pid].mapper.GetInput(), face_values[rows]))
        for data, values in targets:
            array = data.GetCellData().GetArray("value")
            vtk_to_numpy(array)[:] = values
            array.Modified()

    def _update_highlight(self, values: NDArray[np.float64]) -> None:
        ws = self.ws
        if ws.colour_mode == "quality" and ws.threshold is not None:
            low_bad = HEATMAP_METRICS[ws.metric][2]
            with np.errstate(invalid="ignore"):
                bad = values < ws.threshold if low_bad else values > ws.threshold
            self._set_highlight(np.flatnonzero(bad))
            for actor in self.actors.values():
                actor.prop.opacity = 0.25
        else:
            self._set_highlight(None)

    def highlighted_cells(self) -> NDArray[np.int64]:
        """Global cell indices currently highlighted by the threshold."""
        if self._highlight is None:
            return np.zeros(0, dtype=np.int64)
        return np.asarray(self._highlight[0].cell_data["vtkOriginalCellIds"], dtype=np.int64)

    def _extract(self, cells: NDArray[np.int64]) -> tuple[pv.UnstructuredGrid, NDArray[np.int64]]:
        assert self.grid is not None
        sub = self.grid.extract_cells(cells)
        idx = np.asarray(sub.point_data["vtkOriginalPointIds"], dtype=np.int64)
        vtk_to_numpy(sub.GetPoints().GetData())[:] = self.ws.coords[idx]
        return sub, idx

    def _set_highlight(self, cells: NDArray[np.int64] | None) -> None:
        if cells is None or not len(cells):
            self._highlight = None
            self.plotter.remove_actor("highlight", render=False)
            return
        current = self.highlighted_cells()
        if self._highlight is not None and np.array_equal(current, cells):
            return
        sub, idx = self._extract(cells)
        self._highlight = (sub, idx)
        self.plotter.add_mesh(
            sub,
            color="#ff00ff",
            show_edges=True,
            edge_color="black",
            name="highlight",
            reset_camera=False,
            render=False,
        )

    def zoom_to_element(self, cell: int) -> None:
        """Centre the camera on one element (global cell index) and outline it."""
        sub, idx = self._extract(np.array([cell], dtype=np.int64))
        self._focus = (sub, idx)
        self.plotter.add_mesh(
            sub,
            style="wireframe",
            color="#00ffff",
            line_width=4,
            name="focus",
            reset_camera=False,
            render=False,
        )
        centre = self.ws.coords[idx].mean(axis=0)
        size = float(np.ptp(self.ws.coords[idx], axis=0).max()) or 1.0
        cam = self.plotter.camera
        direction = np.asarray(cam.position) - np.asarray(cam.focal_point)
        direction /= np.linalg.norm(direction) or 1.0
        cam.focal_point = centre
        cam.position = centre + direction * size * 12.0
        self.plotter.reset_camera_clipping_range()
        self.render()

    # ------------------------------------------------------------------ clip
    def _update_clip(self) -> None:
        ws = self.ws
        frame = ws.knee_frame()
        direction = {
            "lateral": frame["lateral"],
            "medial": -frame["lateral"],
            "anterior": frame["anterior"],
            "posterior": -frame["anterior"],
        }[ws.clip_normal]
        origin = frame["center"] + ws.clip_offset * direction
        # keep the side opposite to the named one: the named half is cut away
        self._clip_plane.SetOrigin(*origin)
        self._clip_plane.SetNormal(*(-direction))
        for actor in self.actors.values():
            mapper = actor.GetMapper()
            mapper.RemoveAllClippingPlanes()
            if ws.clip_enabled:
                mapper.AddClippingPlane(self._clip_plane)

    # ------------------------------------------------------------------ landmarks
    def _set_overlay(
        self,
        name: str,
        mesh: pv.PolyData | None,
        colour: str = "white",
        point_size: float = 0.0,
        line_width: float = 0.0,
    ) -> None:
        """Put ``mesh`` in the overlay layer under ``name`` (None removes it)."""
        old = self.overlay_actors.pop(name, None)
        if old is not None:
            self._overlay.RemoveActor(old)
        if mesh is None:
            return
        mapper = vtk.vtkPolyDataMapper()
        mapper.SetInputData(mesh)
        mapper.ScalarVisibilityOff()
        actor = vtk.vtkActor()
        actor.SetMapper(mapper)
        actor.PickableOff()
        prop = actor.GetProperty()
        prop.SetColor(pv.Color(colour).float_rgb)
        if point_size:
            prop.SetPointSize(point_size)
            prop.SetRenderPointsAsSpheres(True)
        if line_width:
            prop.SetLineWidth(line_width)
            prop.LightingOff()
        self._overlay.AddActor(actor)
        self.overlay_actors[name] = actor

    def _build_landmarks(self) -> None:
        """(Re)create the condyle-node and axis-point overlays after a setup or pick change."""
        ws = self.ws
        for name in ("lateral_nodes", "medial_nodes", "axis_points"):
            self._set_overlay(name, None)
        self._landmark_points.clear()
        model = ws.model
        if model is None:
            return
        sets = [
            ("medial_condyle", "#40a0ff", "medial_nodes"),
            ("lateral_condyle", "#ff4040", "lateral_nodes"),
        ]
        if ws.pick_target == "medial_condyle":  # the set being picked is drawn last (on top)
            sets.reverse()
        for key, colour, name in sets:
            ids = [i for i in ws.condyle_ids(key) if model.has_nodes([i])[0]]
            if ids:
                idx = model.node_index(ids)
                self._add_landmark_points(name, colour, 11, idx)
        sources: list[object] = []
        for key in ("lr_axis", "femur_axis", "tibia_axis"):
            points = ws.setup_dict.get("landmarks", {}).get(key, []) or []
            checked = ws.setup.axis(key) if ws.setup is not None else None
            for which, p in enumerate(points):
                if isinstance(p, int) and model.has_nodes([p])[0]:
                    sources.append(int(model.node_index(p)))
                elif isinstance(p, list) and len(p) == 3:
                    landmark = checked[which] if checked is not None else None
                    same = landmark is not None and np.allclose(landmark.coords, p)
                    sources.append(landmark if same else np.asarray(p, dtype=float))
        if sources:
            self._add_landmark_points("axis_points", "#ffd700", 14, sources)

    def _add_landmark_points(self, name: str, colour: str, size: int, sources) -> None:
        mesh = pv.PolyData(self._landmark_positions(sources))
        self.plotter.add_points(
            mesh,
            color=colour,
            point_size=size,
            render_points_as_spheres=True,
            name=name,
            reset_camera=False,
            render=False,
            pickable=False,
        )
        self._landmark_points[name] = (mesh, sources)

    def _landmark_positions(self, sources) -> NDArray[np.float64]:
        coords = self.ws.coords
        if isinstance(sources, np.ndarray):
            return np.array(coords[sources], dtype=np.float64)
        out = []
        for src in sources:
            if isinstance(src, int):
                out.append(coords[src])
            elif isinstance(src, np.ndarray):
                out.append(src)
            else:  # a coordinate landmark of the setup: follows its bone
                out.append(src.position(coords))
        return np.array(out, dtype=np.float64)

    def _move_landmarks(self) -> None:
        """Overwrite the overlay points in place from the current coordinates."""
        for mesh, sources in self._landmark_points.values():
            vtk_to_numpy(mesh.GetPoints().GetData())[:] = self._landmark_positions(sources)
            mesh.GetPoints().Modified()

    def _update_axes_overlay(self) -> None:
        """Fitted circles and the F-E / L-R axes of the current pose."""
        for name in ("circles", "axes_lines"):
            self._set_overlay(name, None)
        if self.ws.model is None:
            return
        axes = self.current_axes()
        if axes is None:
            return
        circles = []
        for fit, centre in (
            (axes.lateral_fit, axes.lateral_center),
            (axes.medial_fit, axes.medial_center),
        ):
            t = np.linspace(0, 2 * np.pi, 73)
            ring = np.asarray(centre)[None] + fit.radius * (
                np.cos(t)[:, None] * axes.anterior[None] + np.sin(t)[:, None] * axes.superior[None]
            )
            circles.append(ring)
        merged = _polylines(circles)
        self._set_overlay("circles", merged, "#00ff80", line_width=3)
        span = 1.6 * float(np.linalg.norm(axes.lateral_center - axes.medial_center)) + 20.0
        fe = axes.fe_axis
        lr = axes.lr_axis
        lines = [
            np.array([fe.point - span * fe.direction, fe.point + span * fe.direction]),
            np.array([lr.point, lr.point - 400.0 * lr.direction]),
        ]
        merged = _polylines(lines)
        self._set_overlay("axes_lines", merged, "#ffffff", line_width=2)

    def current_axes(self):
        """Joint axes of the current pose (None without a valid setup)."""
        ws = self.ws
        if ws.setup is None or ws.setup_problem is not None:
            return None
        if ws.coords is ws.model.coords or np.array_equal(ws.coords, ws.model.coords):
            return ws.axes
        from kneegui.geometry import compute_joint_axes

        try:
            return compute_joint_axes(ws.coords, ws.setup)
        except Exception:
            return ws.axes

    # ------------------------------------------------------------------ camera
    def camera_preset(self, name: str) -> None:
        """Look at the knee from the lateral, medial, anterior or posterior side."""
        if name not in CAMERA_PRESETS or self.ws.model is None:
            raise ValueError(f"unknown camera preset {name!r}")
        frame = self.ws.knee_frame()
        direction = {
            "lateral": frame["lateral"],
            "medial": -frame["lateral"],
            "anterior": frame["anterior"],
            "posterior": -frame["anterior"],
        }[name]
        visible = [
            self.surfaces[p].model_index for p in self.surfaces if p not in self.ws.hidden_parts
        ]
        pts = self.ws.coords[np.concatenate(visible)] if visible else self.ws.coords
        centre = frame["center"]
        near = pts[np.linalg.norm(pts - centre, axis=1) < KNEE_VIEW_RADIUS_MM]
        extent = float(np.linalg.norm(np.ptp(near if len(near) > 10 else pts, axis=0))) or 1.0
        cam = self.plotter.camera
        cam.focal_point = centre
        cam.position = centre + direction * extent * 1.4
        cam.up = frame["superior"]
        cam.view_angle = 30.0  # undo any zoom
        self.plotter.reset_camera_clipping_range()
        self.render()

    # ------------------------------------------------------------------ picking
    def pickable_parts(self) -> list[int]:
        """Parts the current pick target may pick on (drawn ones: a part inside another has
        the same surface nodes as the part drawn over it)."""
        ws = self.ws
        target = ws.pick_target
        if not target or ws.model is None:
            return []
        roles = ws.setup_dict.get("roles", {})
        if target in ("lateral_condyle", "medial_condyle") or target.startswith("femur_axis"):
            pids = roles.get("femur", [])
        else:
            pids = [p for r in ("femur", "tibia", "fibula", "patella") for p in roles.get(r, [])]
        return [
            int(p) for p in pids if int(p) in self.actors and self.actors[int(p)].GetVisibility()
        ]

    def _display_size(self) -> tuple[int, int]:
        w, h = self.plotter.ren_win.GetSize()
        return int(w), int(h)

    def _to_display(self, pos: QPoint) -> tuple[float, float]:
        ratio = self.plotter.devicePixelRatioF()
        _, h = self._display_size()
        return pos.x() * ratio, h - 1 - pos.y() * ratio

    def pick_at(self, pos: QPoint) -> int | None:
        """Node id of the nearest pickable surface node under widget position ``pos``."""
        pids = self.pickable_parts()
        if not pids:
            return None
        picker = vtk.vtkCellPicker()
        picker.SetTolerance(0.002)
        picker.PickFromListOn()
        for pid in pids:
            picker.AddPickList(self.actors[pid])
        x, y = self._to_display(pos)
        if not picker.Pick(x, y, 0, self.plotter.renderer):
            return None
        actor = picker.GetActor()
        pid = next((p for p in pids if self.actors[p] is actor), None)
        if pid is None:
            return None
        surf = self.surfaces[pid]
        point = np.array(picker.GetPickPosition())
        cell = picker.GetDataSet().GetCell(picker.GetCellId())  # the faces drawn: same points
        ids = np.array([cell.GetPointId(i) for i in range(cell.GetNumberOfPoints())])
        local = ids[np.argmin(np.linalg.norm(self._points[pid][ids] - point, axis=1))]
        return int(self.ws.model.node_ids[surf.model_index[local]])

    def show_selection_rect(self, rect: QRect | None) -> None:
        """Draw the box-selection rectangle (widget coordinates) over the scene, or hide it."""
        if self._selection is None:
            if rect is None:
                return
            self._selection = _SelectionRect(self._overlay)
        if rect is None:
            self._selection.place(None)
        else:
            (x0, y0), (x1, y1) = (
                self._to_display(rect.topLeft()),
                self._to_display(rect.bottomRight()),
            )
            self._selection.place([(x0, y0), (x1, y0), (x1, y1), (x0, y1)])
        self.render()

    def selection_rect_shown(self) -> bool:
        """Whether the box-selection rectangle is drawn (a drag is in progress)."""
        return self._selection is not None and bool(self._selection.actors[0].GetVisibility())

    def nodes_in_rect(self, rect: QRect) -> list[int]:
        """Node ids of the visible pickable surface nodes inside a widget rectangle."""
        pids = self.pickable_parts()
        if not pids:
            return []
        index = sorted_unique(np.concatenate([self.surfaces[p].model_index for p in pids]))
        xyz = self.ws.coords[index]
        ren = self.plotter.renderer
        w, h = self._display_size()
        matrix = ren.GetActiveCamera().GetCompositeProjectionTransformMatrix(
            ren.GetTiledAspectRatio(), -1, 1
        )
        m = np.array([[matrix.GetElement(i, j) for j in range(4)] for i in range(4)])
        hom = np.column_stack([xyz, np.ones(len(xyz))]) @ m.T
        ndc = hom[:, :3] / hom[:, 3:4]
        vx0, vy0, vx1, vy1 = ren.GetViewport()
        dx = (vx0 + (ndc[:, 0] + 1) / 2 * (vx1 - vx0)) * w
        dy = (vy0 + (ndc[:, 1] + 1) / 2 * (vy1 - vy0)) * h
        a = self._to_display(rect.topLeft())
        b = self._to_display(rect.bottomRight())
        x0, x1 = sorted((a[0], b[0]))
        y0, y1 = sorted((a[1], b[1]))
        inside = (dx >= x0) & (dx <= x1) & (dy >= y0) & (dy <= y1) & (np.abs(ndc[:, 2]) <= 1)
        if not inside.any():
            return []
        cand = np.flatnonzero(inside)
        visible = self._unoccluded(xyz[cand], pids)
        if self.ws.clip_enabled:
            origin = np.array(self._clip_plane.GetOrigin())
            normal = np.array(self._clip_plane.GetNormal())
            visible &= (xyz[cand] - origin) @ normal >= 0
        chosen = index[cand[visible]]
        return [int(i) for i in self.ws.model.node_ids[chosen]]

    def _unoccluded(self, points: NDArray[np.float64], pids: list[int]) -> NDArray[np.bool_]:
        """Which points the camera sees: no pickable surface between the eye and the point.

        Casts a ray from the camera to each point through a cell locator of the pickable
        surfaces (geometric, so it does not depend on reading the GL depth buffer).
        """
        merged = pv.merge([self.surfaces[p].mesh for p in pids], merge_points=False)
        locator = vtk.vtkStaticCellLocator()
        locator.SetDataSet(merged)
        locator.BuildLocator()
        cam = self.plotter.camera
        eye = np.asarray(cam.position, dtype=float)
        if cam.parallel_projection:
            direction = np.asarray(cam.focal_point) - eye
            direction /= np.linalg.norm(direction)
        extent = float(np.linalg.norm(np.ptp(points, axis=0))) if len(points) else 1.0
        out = np.zeros(len(points), dtype=bool)
        t, sub = vtk.reference(0.0), vtk.reference(0)
        hit, pcoords = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        for i, p in enumerate(points):
            start = p - direction * 1e4 if cam.parallel_projection else eye
            ray = p - start
            length = float(np.linalg.norm(ray))
            stop = p - ray / length * max(1e-3 * length, 1e-3 * extent)
            out[i] = not locator.IntersectWithLine(start, stop, 1e-9, t, hit, pcoords, sub)
        return out

    def apply_pick(self, ids: list[int], remove: bool) -> None:
        """Hand picked node ids to the workspace."""
        self.ws.pick_nodes(ids, remove=remove)


class _PickFilter(QObject):
    """Qt event filter on the interactor: left click / drag = pick while a target is set."""

    def __init__(self, viewport: Viewport):
        super().__init__(viewport)
        self.vp = viewport
        self._start: QPoint | None = None

    def eventFilter(self, obj, event) -> bool:
        if not self.vp.ws.pick_target:
            return False
        t = event.type()
        if t == QEvent.Type.MouseButtonPress and event.button() == Qt.MouseButton.LeftButton:
            self._start = event.position().toPoint()
            self.vp.show_selection_rect(QRect(self._start, QSize()))
            return True
        if t == QEvent.Type.MouseMove and self._start is not None:
            rect = QRect(self._start, event.position().toPoint()).normalized()
            self.vp.show_selection_rect(rect)
            return True
        if (
            t == QEvent.Type.MouseButtonRelease
            and self._start is not None
            and event.button() == Qt.MouseButton.LeftButton
        ):
            end = event.position().toPoint()
            start, self._start = self._start, None
            self.vp.show_selection_rect(None)
            remove = bool(event.modifiers() & Qt.KeyboardModifier.ControlModifier)
            if (end - start).manhattanLength() <= PICK_CLICK_PIXELS:
                node = self.vp.pick_at(end)
                ids = [] if node is None else [node]
            else:
                ids = self.vp.nodes_in_rect(QRect(start, end).normalized())
            self.vp.apply_pick(ids, remove)
            return True
        return False


class _SelectionRect:
    """The box-selection rectangle, drawn by VTK in the overlay layer.

    A Qt rubber band cannot be blended over the native GL window the scene is drawn in (it
    would hide what is being selected), so the rectangle is a translucent 2-D actor instead.
    """

    def __init__(self, renderer: vtk.vtkRenderer):
        self.points = vtk.vtkPoints()
        self.points.SetNumberOfPoints(4)
        fill = vtk.vtkPolyData()
        fill.SetPoints(self.points)
        quad = vtk.vtkCellArray()
        quad.InsertNextCell(4, [0, 1, 2, 3])
        fill.SetPolys(quad)
        outline = vtk.vtkPolyData()
        outline.SetPoints(self.points)
        loop = vtk.vtkCellArray()
        loop.InsertNextCell(5, [0, 1, 2, 3, 0])
        outline.SetLines(loop)
        self.actors = []
        for data, opacity in ((fill, 0.25), (outline, 1.0)):
            mapper = vtk.vtkPolyDataMapper2D()
            mapper.SetInputData(data)
            actor = vtk.vtkActor2D()
            actor.SetMapper(mapper)
            actor.GetProperty().SetColor(0.55, 0.75, 1.0)
            actor.GetProperty().SetOpacity(opacity)
            actor.GetProperty().SetLineWidth(1.5)
            actor.SetVisibility(False)
            actor.SetPickable(False)
            renderer.AddViewProp(actor)
            self.actors.append(actor)

    def place(self, corners: list[tuple[float, float]] | None) -> None:
        """Show the rectangle at four display-coordinate corners, or hide it (None)."""
        for actor in self.actors:
            actor.SetVisibility(corners is not None)
        if corners is None:
            return
        for i, (x, y) in enumerate(corners):
            self.points.SetPoint(i, x, y, 0.0)
        self.points.Modified()


def _polylines(chains: list[NDArray[np.float64]]) -> pv.PolyData:
    """One PolyData holding each (k, 3) point chain as a polyline."""
    points = np.concatenate(chains)
    cells, start = [], 0
    for chain in chains:
        cells.append(np.r_[len(chain), np.arange(start, start + len(chain))])
        start += len(chain)
    return pv.PolyData(points, lines=np.concatenate(cells))


def _quality_clim(metric: str, values: NDArray[np.float64]) -> tuple[float, float]:
    finite = values[np.isfinite(values)]
    if metric in ("jacobian", "tet_collapse", "vol_skew"):
        return (0.0, 1.0)
    regular_dihedral = float(np.degrees(np.arccos(1.0 / 3.0)))  # 70.53, the regular tet's
    if metric == "dihedral_min":
        return (0.0, regular_dihedral)
    if metric == "dihedral_max":
        return (regular_dihedral, 180.0)
    if metric == "midside_tangent":
        return (0.0, 0.25)
    if metric in ("warpage", "skew"):
        hi = float(np.percentile(finite, 99.5)) if len(finite) else 1.0
        return (0.0, max(hi, 1.0))
    if metric == "aspect":
        hi = float(np.percentile(finite, 99.5)) if len(finite) else 2.0
        return (1.0, max(hi, 1.5))
    span = float(np.percentile(np.abs(finite), 99.5)) if len(finite) else 1.0
    return (-max(span, 0.5), max(span, 0.5))


def _cell_subset(mesh: pv.PolyData, rows: NDArray[np.int64]) -> pv.PolyData:
    """The cells ``rows`` of ``mesh`` (its lines first, then its faces, as VTK orders them) as a
    new polydata on the SAME points object, so that moving the surface's points in place moves
    it too; with its own ``value`` cell array, the active scalars."""
    sub = pv.PolyData()
    sub.SetPoints(mesh.GetPoints())
    n_lines = mesh.GetNumberOfLines()
    if n_lines:
        sub.SetLines(mesh.GetLines())
    polys = mesh.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray()).astype(np.int64)
    connectivity = vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64)
    faces = rows[rows >= n_lines] - n_lines
    starts, stops = offsets[faces], offsets[faces + 1]
    sizes = stops - starts
    new_offsets = np.concatenate([[0], np.cumsum(sizes)])
    take = np.repeat(starts - new_offsets[:-1], sizes) + np.arange(new_offsets[-1])
    cells = vtk.vtkCellArray()
    cells.SetData(
        numpy_to_vtkIdTypeArray(new_offsets, deep=True),
        numpy_to_vtkIdTypeArray(connectivity[take], deep=True),
    )
    sub.SetPolys(cells)
    sub.cell_data["value"] = np.zeros(len(rows))
    sub.GetCellData().SetActiveScalars("value")
    return sub
