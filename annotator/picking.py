"""Picking points with the mouse in the annotator's pick windows: a shift + click picks the visible point nearest
the click within a tolerance (`nearest_pick`, pure), so a click between the samples of a mesh picks the nearest
sample instead of nothing; `ClickPicker` is the open3d window around it, which says what happened through a
callback (the annotator shows it in its panel) instead of the terminal.

Pixels: (u, v) = (x right, y down) from the window's top-left corner, as GLFW reports the cursor; camera frame as
open3d's pinhole parameters (extrinsic world -> camera, camera z forward, metres).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

#: A click picks the nearest visible point within this many pixels of it.
PICK_TOLERANCE_PX = 12.0
#: A point counts as visible when its camera depth is at most this far (m) behind the depth drawn at its pixel.
PICK_DEPTH_MARGIN = 0.005
#: GLFW mouse buttons, actions and the shift modifier bit.
LEFT, RIGHT, MIDDLE = 0, 1, 2
PRESS, RELEASE = 1, 0
SHIFT = 0x0001


def project(points: np.ndarray, intrinsic: np.ndarray, extrinsic: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (M, 2) (u, v) and camera depths (M,) m of world points (M, 3) m seen by a pinhole camera
    (intrinsic (3, 3) px, extrinsic (4, 4) world -> camera); points behind the camera get depth <= 0."""
    p = np.asarray(points, np.float64) @ np.asarray(extrinsic)[:3, :3].T + np.asarray(extrinsic)[:3, 3]
    z = p[:, 2]
    safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
    k = np.asarray(intrinsic, np.float64)
    uv = np.stack([k[0, 0] * p[:, 0] / safe + k[0, 2], k[1, 1] * p[:, 1] / safe + k[1, 2]], axis=1)
    return uv, z


def nearest_pick(uv: np.ndarray, depth: np.ndarray, click: tuple[float, float], *,
                 tolerance: float = PICK_TOLERANCE_PX, depth_buffer: np.ndarray | None = None,
                 margin: float = PICK_DEPTH_MARGIN) -> int | None:
    """Index of the point nearest a click among the visible ones within `tolerance` px of it, or None.

    uv (M, 2) px and depth (M,) m: the points' pixels and camera depths (`project`); click (u, v) px.
    depth_buffer (H, W) m: the depth drawn at each pixel (0 or non-finite: nothing drawn); a point is visible when
    it lies in front of the camera, inside the image, and at most `margin` behind the depth drawn at its pixel
    (so the far side of a mesh, behind its near side, is never picked). Ties: the nearer to the camera.
    """
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    depth = np.asarray(depth, np.float64).reshape(-1)
    d2 = ((uv - np.asarray(click, np.float64)) ** 2).sum(1)
    ok = (depth > 0) & (d2 <= float(tolerance) ** 2)
    if depth_buffer is not None and ok.any():
        h, w = depth_buffer.shape
        px = np.round(uv).astype(np.int64)
        inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        ok &= inside
        idx = np.flatnonzero(ok)
        drawn = depth_buffer[px[idx, 1], px[idx, 0]]
        hidden = np.isfinite(drawn) & (drawn > 0) & (depth[idx] > drawn + margin)
        ok[idx[hidden]] = False
    if not ok.any():
        return None
    idx = np.flatnonzero(ok)
    best = np.lexsort((depth[idx], d2[idx]))[0]  # nearest in pixels, then nearest to the camera
    return int(idx[best])


class ClickPicker:
    """An open3d window in which shift + left click picks points (`nearest_pick`) and shift + right click drops the
    last pick; plain left drag rotates the view, right or middle drag pans, the wheel zooms; Q, Esc or closing the
    window ends picking. Picked points are marked with red balls.

    points (M, 3) m world, colors (M, 3) 0..1 or None; mesh: (vertices (V, 3) m, faces (F, 3)) drawn shaded and
    opaque under the points (its far side hidden), or None; say(text): where messages go (the annotator's panel);
    wanted: how many points the caller expects (for the messages), or None.
    """

    def __init__(self, points: np.ndarray, colors: np.ndarray | None, title: str, *,
                 mesh: tuple[np.ndarray, np.ndarray] | None = None, say: Callable[[str], None] = print,
                 wanted: int | None = None, width: int = 1024, height: int = 768, left: int = 60, top: int = 60,
                 tolerance: float = PICK_TOLERANCE_PX):
        import open3d as o3d

        self._o3d = o3d
        self.points = np.asarray(points, np.float64)
        self.say, self.wanted, self.tolerance = say, wanted, float(tolerance)
        self.picked: list[int] = []
        self._marks: list = []
        self._cursor = (0.0, 0.0)
        self._dragging: int | None = None
        self._changed = True  # the view or the marks changed since the last frame: draw again
        self.done = False
        self.vis = o3d.visualization.VisualizerWithKeyCallback()
        if not self.vis.create_window(title, width=width, height=height, left=left, top=top):
            raise RuntimeError("could not open the picking window")
        extent = np.ptp(self.points, axis=0) if len(self.points) else np.ones(3)
        self.mark_radius = float(max(0.002, 0.012 * np.linalg.norm(extent)))
        if mesh is not None:
            shaded = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh[0], np.float64)),
                                               o3d.utility.Vector3iVector(np.asarray(mesh[1], np.int32)))
            shaded.compute_vertex_normals()
            shaded.paint_uniform_color([0.72, 0.72, 0.75])
            self.vis.add_geometry(shaded)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points))
        if colors is not None:
            cloud.colors = o3d.utility.Vector3dVector(np.asarray(colors, np.float64))
        self.vis.add_geometry(cloud, reset_bounding_box=mesh is None)
        opt = self.vis.get_render_option()
        opt.point_size = 3.0 if mesh is not None else 2.0
        opt.mesh_show_back_face = False
        if mesh is not None:  # from the side and above, not from the top: both ends of a can stay apart
            ctr = self.vis.get_view_control()
            ctr.set_lookat(0.5 * (self.points.min(0) + self.points.max(0)))
            front = np.array([0.55, -0.65, 0.52]) / np.linalg.norm([0.55, -0.65, 0.52])
            up = np.array([0.0, 0.0, 1.0]) - front[2] * front  # orthogonal to front: open3d does not fix it
            ctr.set_front(front)
            ctr.set_up(up / np.linalg.norm(up))
        self.vis.register_mouse_button_callback(self._on_button)
        self.vis.register_mouse_move_callback(self._on_move)
        for code in (ord("Q"), 256):  # Q, Esc
            self.vis.register_key_callback(code, self._on_quit)

    # callbacks ---------------------------------------------------------------------------------------------------
    def _on_quit(self, _vis) -> bool:
        self.done = True
        return False

    def _on_move(self, _vis, x: float, y: float) -> bool:
        dx, dy = x - self._cursor[0], y - self._cursor[1]
        self._cursor = (float(x), float(y))
        ctr = self.vis.get_view_control()
        if self._dragging == LEFT:
            ctr.rotate(dx, dy)
            self._changed = True
        elif self._dragging in (RIGHT, MIDDLE):
            ctr.translate(dx, dy)
            self._changed = True
        return False

    def _on_button(self, _vis, button: int, action: int, mods: int) -> bool:
        if action == RELEASE:
            self._dragging = None
        elif action == PRESS and mods & SHIFT and button == LEFT:
            self.click(*self._cursor)
        elif action == PRESS and mods & SHIFT and button == RIGHT:
            self.drop_last()
        elif action == PRESS:
            self._dragging = int(button)
        return False

    # picking -----------------------------------------------------------------------------------------------------
    def _count(self) -> str:
        return f"{len(self.picked)}" + (f" of {self.wanted}" if self.wanted else "")

    def click(self, x: float, y: float) -> int | None:
        """Pick the visible point nearest window pixel (x, y) within the tolerance; returns its index or None
        (and says why)."""
        params = self.vis.get_view_control().convert_to_pinhole_camera_parameters()
        uv, z = project(self.points, params.intrinsic.intrinsic_matrix, params.extrinsic)
        depth = np.asarray(self.vis.capture_depth_float_buffer(do_render=True), np.float64)
        index = nearest_pick(uv, z, (x, y), tolerance=self.tolerance, depth_buffer=depth)
        if index is None:
            self.say(f"no point within {self.tolerance:g} px of the click: shift + click on the shown points "
                     f"({self._count()} picked)")
            return None
        self.picked.append(index)
        mark = self._o3d.geometry.TriangleMesh.create_sphere(radius=self.mark_radius, resolution=8)
        mark.translate(self.points[index])
        mark.paint_uniform_color([0.95, 0.1, 0.1])
        mark.compute_vertex_normals()
        self.vis.add_geometry(mark, reset_bounding_box=False)
        self._marks.append(mark)
        self._changed = True
        self.say(f"picked point {len(self.picked)} ({self._count()}); shift + right click drops it, Q when done")
        return index

    def drop_last(self) -> None:
        """Drop the last pick (and its mark)."""
        if not self.picked:
            self.say("no pick to drop")
            return
        self.picked.pop()
        self.vis.remove_geometry(self._marks.pop(), reset_bounding_box=False)
        self._changed = True
        self.say(f"dropped the last pick ({self._count()} picked)")

    def run(self, idle: Callable[[], None] | None = None, frame_seconds: float = 1 / 60) -> np.ndarray:
        """Run until Q / Esc or the window is closed; `idle()` is called each frame (the annotator redraws its
        panel there). Returns the picked indices (K,) in order."""
        import time

        try:
            while not self.done and self.vis.poll_events():
                if self._changed:  # drawn at the next poll; an idle frame draws nothing
                    self.vis.update_renderer()
                    self._changed = False
                if idle is not None:
                    idle()
                time.sleep(frame_seconds)
        finally:
            self.vis.destroy_window()
        return np.asarray(self.picked, dtype=np.int64)
