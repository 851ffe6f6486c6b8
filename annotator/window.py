"""The annotator's interactive window: open3d's legacy visualizer driving an annotation `Session`.

Two legacy open3d windows (they render under `xvfb-run` with Debian's Mesa GL; open3d's newer `gui`
windows need Vulkan and captured black there):

- the 3D window (`VisualizerWithKeyCallback`): the fused point cloud of both cameras at the current
  step (capture colours, or depth-residual colours with key R), every object mesh at its current pose
  (the selected one orange, the others coloured by status), an axes gizmo at the selected object's
  centre showing the nudge frame (table or object axes) and the table frame at the origin. Mouse
  navigation is open3d's own; the geometries are updated in place (`update_geometry`).
- the panel (a second legacy `Visualizer` showing an `open3d.geometry.Image`, drawn by `annotator.panel`):
  an image geometry in its own window is the one image path of the legacy visualizer that renders under
  Xvfb, keeps the 3D view free and is updated in place.

Frames: the key callbacks only queue keys (`annotator.keys.KeyCoalescer`); each frame (`render`) processes the
window events, acts on the queued keys through `annotator.keys.Controller` (keys -> Session calls; a held nudge
key's repeats merged into one nudge, at most `MAX_REPEAT` steps a frame, so releasing it stops the motion at the
next frame), then redraws what changed once from the session's latest state (`redraw`: cloud, meshes, panel), not
once per key, and drawn at once (key to frame within the frame). The 3D view draws the step's cloud subset
`Session.shown` (one point per 2 mm cube above the table, per 6 mm cube on it: every surface covered, a fraction of
the points), the residual colours computed for those points only; a nudge re-uploads only the moved mesh and the
gizmo (and, with residual colours, the cloud's colours), and the panel redraws only the moved object's outline
(`annotator.panel`). When the panel window's size changes (the user or the window manager resized it) its text
and images are laid out again for the new size (`annotator.layout.panel_layout`) and drawn 1:1. Messages are shown
in the panel (errors also go to the terminal, as does the progress table, key F).
Pick mode (key M) opens a `annotator.picking.ClickPicker` twice over the 3D view's place (the cloud, then the
mesh shaded and opaque with its samples; a shift + click picks the nearest visible point within a tolerance), its
messages in the panel; it runs after the key callbacks return, and the main window ignores keys meanwhile. The
windows are laid out within the screen (`annotator.layout`); the window manager moves and resizes them. The
display is checked before open3d is asked (open3d 0.20 otherwise falls back silently to an invisible offscreen
context).
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from functools import partial

import numpy as np

from dsr_bench.annotator.images import muted_colors, object_colors, posed
from dsr_bench.annotator.keys import KEYMAP, Controller, KeyCoalescer, glfw_code
from dsr_bench.annotator.layout import Layout, panel_layout, screen_size, window_layout
from dsr_bench.annotator.opening import ensure_runtime_dir, fit_zoom, workspace_corners
from dsr_bench.annotator.panel import Panel
from dsr_bench.display import no_display
from dsr_bench.errors import UserError
from dsr_bench.geometry import pose_to_matrix

#: Axes gizmo at the selected object: arrow length = GIZMO_SCALE x the mesh's bounding-box diagonal, at least
#: GIZMO_MIN_SIZE (m), so that it sticks out of the object. Table frame at the origin: TABLE_AXES_SIZE (m).
GIZMO_SCALE = 0.8
GIZMO_MIN_SIZE = 0.04
TABLE_AXES_SIZE = 0.1
#: Where unset objects' meshes are collapsed to (the workspace centre on the table, m).
HIDDEN_POINT = np.array([0.5, 0.0, 0.0])
NO_DISPLAY_HINT = ("place step 0 without the window with --place POSES.json (poses or picks, docs/annotator.md), "
                   "then --auto and --export; or run where a display is (ssh -X) or under `xvfb-run -a`")


def display_problem() -> str | None:
    """Why no window can be opened here, or None when one can: no display (`dsr_bench.display.no_display`),
    or, on Linux, no X display open3d can reach (its windows need X11: DISPLAY unset, as under Wayland without
    XWayland, or unreachable).

    Checked before open3d is asked: open3d 0.20 silently falls back to an invisible offscreen EGL context
    when it cannot reach a display, which would leave a window nobody can see or quit.
    """
    if no_display():
        return "DISPLAY is not set"
    if not sys.platform.startswith("linux"):
        return None  # open3d opens native windows there
    display = os.environ.get("DISPLAY")
    if not display:
        return "DISPLAY is not set (open3d's windows need an X display; XWayland provides one under Wayland)"
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("X11") or "libX11.so.6"
    try:
        xlib = ctypes.CDLL(name)
    except OSError:
        return None  # cannot check without libX11; let open3d try
    xlib.XOpenDisplay.restype = ctypes.c_void_p
    xlib.XOpenDisplay.argtypes = [ctypes.c_char_p]
    xlib.XCloseDisplay.argtypes = [ctypes.c_void_p]
    handle = xlib.XOpenDisplay(display.encode())
    if not handle:
        return f"cannot connect to X display {display!r}"
    xlib.XCloseDisplay(handle)
    return None


def pick_points(points: np.ndarray, colors: np.ndarray | None, title: str,
                mesh: tuple[np.ndarray, np.ndarray] | None = None, *, idle: Callable[[], None] | None = None,
                **window) -> np.ndarray:
    """Indices of the points a user shift-clicks in a `annotator.picking.ClickPicker` window (closed with Q / Esc);
    `window`: the picker's other keywords (default: messages to the terminal; the annotator window passes its panel,
    place and size), `idle`: called each frame (`ClickPicker.run`)."""
    from dsr_bench.annotator.picking import ClickPicker

    try:
        picker = ClickPicker(points, colors, title, mesh=mesh, **window)
    except RuntimeError:
        raise UserError(f"could not open the picking window; {NO_DISPLAY_HINT}") from None
    return picker.run(idle=idle)


class AnnotatorWindow:
    """The 3D window and the panel window over a Controller. `press(key)` is what a key callback does.

    session: an `annotator.session.Session`; picker, echo: as for `Controller` (default: `pick_points`, rich).
    """

    def __init__(self, session, *, width: int | None = None, height: int | None = None, picker=None, echo=None,
                 screen: tuple[int, int] | None = None):
        """screen: (width, height) px to lay the windows out in (`annotator.layout.window_layout`; default the
        display's, `screen_size`); width, height: the 3D view's size instead of the layout's (px)."""
        import open3d as o3d

        problem = display_problem()
        if problem is not None:
            raise UserError(f"no display for the annotator window ({problem}); {NO_DISPLAY_HINT}")
        ensure_runtime_dir()
        self._o3d = o3d
        self.layout = layout_for(session, screen)
        vx, vy, vw, vh = self.layout.view
        width, height = width or vw, height or vh
        self.ctl = Controller(session, picker=picker or self.pick, echo=echo)
        self.panel = Panel(session, self.ctl.view, text_width=self.layout.text_width,
                           image_width=self.layout.image_width, font_size=self.layout.font_size,
                           height=self.layout.panel[3], width=self.layout.panel[2])
        self._panel_size: tuple[int, int] | None = None  # the panel window's size (px) the panel was laid out for
        self.vis = o3d.visualization.VisualizerWithKeyCallback()
        if not self.vis.create_window("dsr-bench annotator: 3D (Esc quits)", width=width, height=height, left=vx,
                                      top=vy):
            raise UserError(f"could not create the annotator window (no OpenGL display); {NO_DISPLAY_HINT}")
        self.panel_vis = None
        self.keys = KeyCoalescer()
        self._dirty: set[str] = set()
        self._busy = False
        try:
            self._build_scene()
            panel = self.panel.image()
            self.panel_vis = o3d.visualization.Visualizer()
            px, py, _, _ = self.layout.panel
            if not self.panel_vis.create_window("dsr-bench annotator: cameras and keys", width=panel.shape[1],
                                                height=panel.shape[0], left=px, top=py):
                raise UserError(f"could not create the annotator's panel window; {NO_DISPLAY_HINT}")
            self.panel_image = o3d.geometry.Image(np.ascontiguousarray(panel))
            self.panel_vis.add_geometry(self.panel_image)
            self._dirty.add("view")  # the first frame draws both windows
            for key in KEYMAP:
                self.vis.register_key_callback(glfw_code(key), partial(self._on_key, key))
        except BaseException:
            self.close()
            raise

    # scene ---------------------------------------------------------------------------------------
    def _build_scene(self) -> None:
        o3d, ctl = self._o3d, self.ctl
        points, colors = self._cloud()
        self.cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        self.cloud.colors = o3d.utility.Vector3dVector(colors)
        self._cloud_step = ctl.session.step  # the step whose points the cloud holds
        self.mesh_data = ctl.meshes()
        self.centres = [0.5 * (v.min(0) + v.max(0)) if len(v) else np.zeros(3) for v, _ in self.mesh_data]
        self.gizmo_sizes = [max(GIZMO_MIN_SIZE, GIZMO_SCALE * float(np.linalg.norm(v.max(0) - v.min(0))))
                            if len(v) else GIZMO_MIN_SIZE for v, _ in self.mesh_data]
        self.meshes = []
        for vertices, faces in self.mesh_data:
            mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
                                             o3d.utility.Vector3iVector(np.asarray(faces, np.int32)))
            self.meshes.append(mesh)
        axes = o3d.geometry.TriangleMesh.create_coordinate_frame(size=1.0)
        self.gizmo_base = np.asarray(axes.vertices).copy()
        self.gizmo = axes
        self._drawn: dict[int, tuple[bytes, bytes]] = {}  # (pose, colour) each mesh was last drawn at
        self._update_meshes()
        self.vis.add_geometry(self.cloud)
        self.vis.add_geometry(o3d.geometry.TriangleMesh.create_coordinate_frame(size=TABLE_AXES_SIZE),
                              reset_bounding_box=False)
        for mesh in self.meshes:
            self.vis.add_geometry(mesh, reset_bounding_box=False)
        self.vis.add_geometry(self.gizmo, reset_bounding_box=False)
        opt = self.vis.get_render_option()
        opt.point_size = 2.0
        opt.mesh_show_back_face = True
        opt.background_color = np.array([0.12, 0.12, 0.14])
        self.reset_view()

    def reset_view(self) -> None:
        """Look at the workspace from above the front camera (table z up), as close as shows all of it: every corner
        of the workspace grid (`dsr_bench.constants.GRID_BOUNDS`) inside the view, a margin from its edges
        (`annotator.opening.fit_zoom`)."""
        from dsr_bench.constants import CAMERAS, WORKSPACE_CENTER

        eye, target = np.array(CAMERAS["front"]["eye"]), np.array([*WORKSPACE_CENTER, 0.03])
        front = (eye - target) / np.linalg.norm(eye - target)
        up = np.array([0.0, 0.0, 1.0]) - front[2] * front  # orthogonal to front: open3d does not fix it
        ctr = self.vis.get_view_control()
        ctr.set_lookat(target)
        ctr.set_front(front)
        ctr.set_up(up / np.linalg.norm(up))
        fit_zoom(ctr, workspace_corners())

    def _update_meshes(self) -> list:
        """Posed vertices and colours of the meshes whose pose or colour changed (returned), and the gizmo."""
        o3d, s = self._o3d, self.ctl.session
        poses = np.asarray(s.poses(), np.float64)
        colors = object_colors(s.status(), int(s.selected))
        changed = []
        for k, ((vertices, _), mesh, pose, color) in enumerate(zip(self.mesh_data, self.meshes, poses, colors)):
            drawn = (pose.tobytes(), color.tobytes())
            if self._drawn.get(k) == drawn:
                continue  # unchanged since the last redraw: no new vertices to upload
            self._drawn[k] = drawn
            changed.append(mesh)
            if np.all(np.isfinite(pose)):
                world = posed(vertices, pose)
            else:  # unset: collapse to one point (degenerate triangles draw nothing; no hide in the legacy API)
                world = np.zeros((len(vertices), 3)) + HIDDEN_POINT
            mesh.vertices = o3d.utility.Vector3dVector(world)
            mesh.compute_vertex_normals()
            mesh.paint_uniform_color(color)
        sel = int(s.selected)
        if 0 <= sel < len(poses) and np.all(np.isfinite(poses[sel])):
            m = pose_to_matrix(poses[sel])
            centre = m[:3, :3] @ self.centres[sel] + m[:3, 3]
            rot = m[:3, :3] if self.ctl.view.frame == "object" else np.eye(3)
            scaled = self.gizmo_base * self.gizmo_sizes[sel]
            self.gizmo.vertices = o3d.utility.Vector3dVector(scaled @ rot.T + centre)
        else:
            self.gizmo.vertices = o3d.utility.Vector3dVector(np.zeros_like(self.gizmo_base) + HIDDEN_POINT)
        return changed

    def _cloud(self) -> tuple[np.ndarray, np.ndarray]:
        """The points the 3D view draws (the step's `Session.shown` subset) and their colours: the residual's, or
        the capture's muted (`muted_colors`: no object's own colour reads as a status colour)."""
        points, colors = self.ctl.cloud()
        return points, (colors if self.ctl.view.residual else muted_colors(colors))

    def _update_cloud(self) -> None:
        """New points at a new step; else (the residual colours follow a pose) new colours only."""
        points, colors = self._cloud()
        step = self.ctl.session.step
        if step != self._cloud_step or len(points) != len(self.cloud.points):
            self.cloud.points = self._o3d.utility.Vector3dVector(points)
            self._cloud_step = step
        self.cloud.colors = self._o3d.utility.Vector3dVector(colors)

    # pick mode -------------------------------------------------------------------------------------------------
    def say(self, text: str) -> None:
        """Show a message in the panel now (while a pick window runs its own loop)."""
        self.ctl.view.message = text
        self._update_panel()
        if self.panel_vis is not None:
            self.panel_vis.update_renderer()
            self.panel_vis.poll_events()

    def pick(self, points: np.ndarray, colors: np.ndarray | None, title: str,
             mesh: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """The Controller's picker: `pick_points` over the 3D view's place, its messages in the panel."""
        x, y, w, h = self.layout.view
        self.say(self.ctl.view.message)  # what to pick (the Controller set it)
        return pick_points(points, colors, title, mesh, idle=self._poll_panel, say=self.say, width=w, height=h,
                           left=x, top=y)

    def _poll_panel(self) -> None:
        if self.panel_vis is not None:
            self.panel_vis.poll_events()

    # keys and frames ---------------------------------------------------------------------------------
    def _on_key(self, key: str, _vis) -> bool:
        """The GLFW key callback: only queues the key (`KeyCoalescer`); `render` acts on the queued keys after the
        events are processed (so a key that opens another window, pick mode, never re-enters GLFW's event
        processing from inside a callback). While such a window is open, this window's keys are ignored (its
        events are still delivered)."""
        if not self._busy:
            self.keys.push(key, time.monotonic())
        return False

    def press(self, key: str, count: int = 1) -> set[str]:
        """Do what pressing `key` (a KEYMAP name; `count` presses for a nudge key) does; the changed geometries
        are redrawn once, by the next `redraw` (`render` calls it)."""
        changed = self.ctl.press(key, count)
        self._dirty |= changed
        if self.ctl.view.reset_view:
            self.ctl.view.reset_view = False
            self.reset_view()
            self._dirty.add("view")
        if self.ctl.view.quit:
            self.vis.close()
        return changed

    def refresh(self) -> None:
        """Re-read everything from the session (after changes made outside the window's keys)."""
        self._dirty |= {"cloud", "meshes", "panel"}
        self.redraw()

    def redraw(self) -> set[str]:
        """Update what changed since the last redraw, once, from the session's latest state; returns what was
        updated (a subset of {"cloud", "meshes", "panel", "view"})."""
        return self._redraw_view() | self._redraw_panel()

    def _redraw_view(self) -> set[str]:
        """The 3D view's part of `redraw`: the cloud and the meshes that changed; returns what it updated (and
        "view" when the view was reset)."""
        dirty = self._dirty & {"cloud", "meshes", "view"}
        self._dirty -= dirty
        if "cloud" in dirty:
            self._update_cloud()
            self.vis.update_geometry(self.cloud)
        if "meshes" in dirty:
            for mesh in self._update_meshes():
                self.vis.update_geometry(mesh)
            self.vis.update_geometry(self.gizmo)
        return dirty

    def _redraw_panel(self) -> set[str]:
        """The panel's part of `redraw`: {"panel"} when it was redrawn, else empty."""
        if "panel" not in self._dirty:
            return set()
        self._dirty.discard("panel")
        self._update_panel()
        return {"panel"}

    def panel_window_size(self) -> tuple[int, int] | None:
        """The panel window's current (width, height) px (None when it is not open)."""
        if self.panel_vis is None:
            return None
        intrinsic = self.panel_vis.get_view_control().convert_to_pinhole_camera_parameters().intrinsic
        return int(intrinsic.width), int(intrinsic.height)

    def _fit_panel(self) -> bool:
        """Lay the panel out again when its window's size changed since it was laid out (`panel_layout`: the text
        column, the camera images as large as the new height and width allow, the image exactly the window's size,
        so that it is drawn 1:1, not stretched); True when it did (the panel is then redrawn this frame)."""
        size = self.panel_window_size()
        if size is None or size == self._panel_size:
            return False
        self._panel_size = size
        width, height = size
        if width < 64 or height < 64:  # minimised, or being resized through nothing: wait for a real size
            return False
        cam = next(iter(self.ctl.session.capture.cameras.values())).camera
        text_width, image_width = panel_layout(width, height, self.layout.text_width,
                                               image_aspect=cam.height / cam.width, max_image_width=cam.width)
        if (text_width, image_width, width, height) == (self.panel.text_width, self.panel.image_width,
                                                        self.panel.width, self.panel.height):
            return False
        self.panel.resize(text_width, image_width, width, height)
        self._dirty.add("panel")
        return True

    def _update_panel(self) -> None:
        if self.panel_vis is None:
            return
        panel = self.panel.image()
        target = np.asarray(self.panel_image)
        if panel.shape == target.shape:
            target[...] = panel
        else:  # more text lines than at start: a new image of the new size
            self.panel_vis.remove_geometry(self.panel_image, reset_bounding_box=False)
            self.panel_image = self._o3d.geometry.Image(np.ascontiguousarray(panel))
            self.panel_vis.add_geometry(self.panel_image)
        self.panel_vis.update_geometry(self.panel_image)

    def render(self) -> bool:
        """One frame: process window events (the key callbacks queue keys), act on the queued keys (a held key's
        repeats merged, `KeyCoalescer`), lay the panel out again if its window was resized, update what changed,
        once, and draw it in this frame; an idle frame draws nothing. False once either window was closed."""
        alive = self.vis.poll_events()
        if self.panel_vis is not None:
            alive = self.panel_vis.poll_events() and alive
            self._fit_panel()
        self._busy = True  # a pick window's event loop delivers this window's keys too: ignored meanwhile
        try:
            for action in self.keys.drain(time.monotonic()):
                self.press(action.key, action.count)
                if self.ctl.view.quit:
                    break
        finally:
            self._busy = False
        # draw what changed now (open3d draws a window flagged for redrawing when its events are polled), not at
        # the next frame, the 3D view first (what a nudge moves), then the panel; else nothing to draw (open3d
        # flags on its own what the mouse changes)
        redrawn = self._redraw_view()
        if redrawn:
            self.vis.update_renderer()
            alive = self.vis.poll_events() and alive
        if (self._redraw_panel() or "view" in redrawn) and self.panel_vis is not None:
            self.panel_vis.update_renderer()
            alive = self.panel_vis.poll_events() and alive
        return bool(alive) and not self.ctl.view.quit

    def screenshot(self) -> np.ndarray:
        """The 3D window's current image (H, W, 3) uint8."""
        img = np.asarray(self.vis.capture_screen_float_buffer(do_render=True))
        return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)

    def panel_screenshot(self) -> np.ndarray:
        """The panel window's current image (H, W, 3) uint8."""
        assert self.panel_vis is not None, "the panel window is open"
        img = np.asarray(self.panel_vis.capture_screen_float_buffer(do_render=True))
        return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)

    def loop(self, frame_seconds: float = 1 / 60) -> None:
        """Run until the user quits (Esc) or closes a window."""
        while self.render():
            time.sleep(frame_seconds)

    def close(self) -> None:
        for vis in (self.panel_vis, self.vis):
            if vis is not None:
                try:
                    vis.destroy_window()
                except RuntimeError:
                    pass
        self.panel_vis = None


def layout_for(session, screen: tuple[int, int] | None = None) -> Layout:
    """The windows' layout for a session's cameras (image aspect and native width of the first) on `screen`
    ((width, height) px; default the display's, `annotator.layout.screen_size`)."""
    cams = list(session.capture.cameras.values())
    cam = cams[0].camera if cams else None
    aspect = cam.height / cam.width if cam is not None else 0.75
    max_width = cam.width if cam is not None else 960
    if screen is not None:
        return window_layout(int(screen[0]), int(screen[1]), image_aspect=aspect, max_image_width=max_width)
    w, h, x, y = screen_size()
    return window_layout(w, h, image_aspect=aspect, max_image_width=max_width, origin=(x, y))


def run(session, *, screen: tuple[int, int] | None = None) -> None:
    """Open the annotator window on the session's current step; return when the user quits.

    screen: (width, height) px to lay the windows out in (default: the display's size, else 1600 x 1000).
    Every key acts through the Session, which autosaves each change, so quitting (Esc, or closing a
    window) loses nothing. Raises UserError when no window can be created (no display).
    """
    window = AnnotatorWindow(session, screen=screen)
    try:
        window.ctl.echo("annotator: keys are listed in the panel window; Esc quits (every change is saved)")
        window.loop()
    finally:
        window.close()
    from dsr_bench.annotator.guide import next_hint

    window.ctl.echo(f"annotator: saved; {next_hint(session)}")
