"""The annotator's interactive window: open3d's legacy visualizer driving an annotation `Session`.

Two legacy open3d windows (they render under `xvfb-run` with Debian's Mesa GL; open3d's newer `gui`
windows need Vulkan and captured black there):

- the 3D window (`VisualizerWithKeyCallback`): the fused point cloud of both cameras at the current
  step (capture colours, or depth-residual colours with key R), every object mesh at its current pose
  (the selected one orange, the others coloured by status), an axes gizmo at the selected object's
  centre showing the nudge frame (table or object axes) and the table frame at the origin. Mouse
  navigation is open3d's own; every key updates the geometries in place (`update_geometry`).
- the panel (a second legacy `Visualizer` showing an `open3d.geometry.Image`): the legacy visualizer
  draws no text, so the help / status text (keys, step, selected object, its status and fit score,
  undo depth, last message) is drawn with PIL into one image beside the colour images of both cameras
  with every mesh's projected silhouette outline. An image geometry in its own window is the one image
  path of the legacy visualizer that renders under Xvfb, keeps the 3D view free and is updated in place.

Messages (errors) and the progress table (key F) also go to the terminal (rich). Pick mode (key M)
opens open3d's `VisualizerWithEditing` twice (cloud, then mesh); it runs after the key callback returns,
and the main window ignores keys meanwhile. The display is checked before open3d is asked (open3d 0.20
otherwise falls back silently to an invisible offscreen context).

Everything but the windows is pure and testable without a display: `silhouette_masks`,
`outline_overlay`, `help_lines`, `panel_image`, `KEYMAP` and the `Controller` (keys -> Session calls).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

from dsr_bench.errors import UserError
from dsr_bench.geometry import Camera, pose_to_matrix

#: Nudge sizes: fine / coarse translation (m) and rotation (rad).
TRANSLATION_STEPS: dict[str, float] = {"fine": 0.001, "coarse": 0.01}
ROTATION_STEPS: dict[str, float] = {"fine": float(np.deg2rad(1.0)), "coarse": float(np.deg2rad(5.0))}
#: RGB 0..1 colours: the selected object, and the others by annotation status.
SELECTED_COLOR = (1.0, 0.55, 0.0)
STATUS_COLORS: dict[str, tuple[float, float, float]] = {
    "unset": (0.6, 0.6, 0.6),
    "initialised": (0.35, 0.55, 0.95),
    "snapped": (0.2, 0.8, 0.85),
    "confirmed": (0.25, 0.8, 0.3),
}
#: Panel layout (pixels): text column width, camera image width, font size.
PANEL_TEXT_WIDTH = 380
PANEL_IMAGE_WIDTH = 480
PANEL_FONT_SIZE = 14
#: Axes gizmo at the selected object: arrow length = GIZMO_SCALE x the mesh's bounding-box diagonal, at least
#: GIZMO_MIN_SIZE (m), so that it sticks out of the object. Table frame at the origin: TABLE_AXES_SIZE (m).
GIZMO_SCALE = 0.8
GIZMO_MIN_SIZE = 0.04
TABLE_AXES_SIZE = 0.1
#: Where unset objects' meshes are collapsed to (the workspace centre on the table, m).
HIDDEN_POINT = np.array([0.5, 0.0, 0.0])
#: Keys acted on after the key callback returns (they open a window of their own).
DEFERRED_KEYS = ("M",)
#: GLFW key codes of the non-character keys used in KEYMAP.
GLFW_SPECIAL_KEYS: dict[str, int] = {"Space": 32, "Esc": 256, "Enter": 257, "Tab": 258}
NO_DISPLAY_HINT = ("run it where a display is (e.g. ssh -X), under a virtual one for scripted use "
                   "(`xvfb-run -a dsr-bench annotate ...`), or use the CLI's --status / --auto / --export")


# --- Pure rendering helpers ------------------------------------------------------------------------


def _posed(vertices: np.ndarray, pose: np.ndarray) -> np.ndarray:
    m = pose_to_matrix(pose)
    return np.asarray(vertices, np.float64) @ m[:3, :3].T + m[:3, 3]


def silhouette_masks(camera: Camera, meshes: Sequence[tuple[np.ndarray, np.ndarray]], poses: np.ndarray) -> np.ndarray:
    """Amodal silhouettes (N, H, W) bool of meshes (vertices (V,3) m object frame, faces (F,3)) at poses (N,7).

    Unset poses (NaN rows) give empty silhouettes.
    Pixel (v, u) is inside object i when the ray through the pixel centre (integer u, v, as in
    `Camera.ray_directions_world`) hits mesh i in front of the camera, ignoring the other objects.
    Only the pixels of the mesh's projected bounding rectangle are cast (all of them when the mesh
    reaches behind the camera).
    """
    import open3d as o3d

    h, w = camera.height, camera.width
    to_world = np.asarray(camera.extrinsics[:3, :3], np.float64) @ np.linalg.inv(camera.intrinsics)
    origin = np.asarray(camera.extrinsics[:3, 3], np.float64)
    out = np.zeros((len(meshes), h, w), dtype=bool)
    for i, ((vertices, faces), pose) in enumerate(zip(meshes, np.asarray(poses, np.float64))):
        if len(faces) == 0 or not np.all(np.isfinite(pose)):  # unset poses (NaN rows) have no silhouette
            continue
        world = _posed(vertices, pose)
        uv, z = camera.project(world)
        if np.all(z > 1e-6):
            u0, v0 = np.maximum(np.floor(uv.min(0)).astype(int) - 1, 0)
            u1, v1 = np.minimum(np.ceil(uv.max(0)).astype(int) + 1, [w - 1, h - 1])
        else:
            u0, v0, u1, v1 = 0, 0, w - 1, h - 1
        if u1 < u0 or v1 < v0:
            continue  # projects outside the image
        vv, uu = np.meshgrid(np.arange(v0, v1 + 1), np.arange(u0, u1 + 1), indexing="ij")
        pix = np.stack([uu, vv, np.ones_like(uu)], -1).reshape(-1, 3).astype(np.float64)
        dirs = pix @ to_world.T
        rays = np.hstack([np.broadcast_to(origin, dirs.shape), dirs]).astype(np.float32)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(world.astype(np.float32)),
                            o3d.core.Tensor(np.asarray(faces).astype(np.uint32)))
        hit = np.isfinite(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy())
        out[i, v0:v1 + 1, u0:u1 + 1] = hit.reshape(vv.shape)
    return out


def mask_boundary(mask: np.ndarray, thickness: int = 1) -> np.ndarray:
    """Inner boundary (H, W) bool of a mask: its pixels within `thickness` pixels of the outside."""
    from scipy.ndimage import binary_erosion

    mask = np.asarray(mask, bool)
    if thickness <= 0 or not mask.any():
        return np.zeros_like(mask)
    return mask & ~binary_erosion(mask, iterations=thickness, border_value=0)


def object_colors(statuses: Sequence[str], selected: int | None) -> np.ndarray:
    """(N, 3) RGB 0..1: the selected object orange, the others by status (`STATUS_COLORS`)."""
    colors = np.array([STATUS_COLORS.get(s, STATUS_COLORS["unset"]) for s in statuses], dtype=np.float64)
    colors = colors.reshape(-1, 3)
    if selected is not None and 0 <= selected < len(colors):
        colors[selected] = SELECTED_COLOR
    return colors


def outline_overlay(color: np.ndarray, camera: Camera, meshes: Sequence[tuple[np.ndarray, np.ndarray]],
                    poses: np.ndarray, *, colors: np.ndarray | None = None, selected: int | None = None,
                    thickness: int = 1) -> np.ndarray:
    """A copy of a colour image (H, W, 3) uint8 with each mesh's projected silhouette outline drawn on it.

    camera: the image's calibration (its size must match); meshes: (vertices (V,3) m object frame,
    faces (F,3)) per object; poses (N,7) world. Outline = the inner boundary of the amodal silhouette
    (`silhouette_masks`), `thickness` px wide (the selected object's one pixel wider), in `colors`
    (N,3) RGB 0..1 (default: the selected object orange, the others white). Objects are drawn in
    index order with the selected one last, so its outline is on top.
    """
    color = np.asarray(color)
    if color.shape != (camera.height, camera.width, 3):
        raise ValueError(f"image {color.shape} does not match camera {camera.name!r} "
                         f"({camera.height}, {camera.width}, 3)")
    out = color.astype(np.uint8, copy=True)
    n = len(meshes)
    if n == 0:
        return out
    if colors is None:
        colors = np.ones((n, 3))
        if selected is not None and 0 <= selected < n:
            colors[selected] = SELECTED_COLOR
    rgb = np.round(np.clip(np.asarray(colors, np.float64), 0, 1) * 255).astype(np.uint8)
    masks = silhouette_masks(camera, meshes, poses)
    order = [i for i in range(n) if i != selected] + ([selected] if selected is not None and 0 <= selected < n else [])
    for i in order:
        edge = mask_boundary(masks[i], thickness + (1 if i == selected else 0))
        out[edge] = rgb[i]
    return out


def scaled_camera(camera: Camera, width: int) -> Camera:
    """The same camera at another image width (height scaled alike); pixel centres stay at integers."""
    s = width / camera.width
    height = max(1, int(round(camera.height * s)))
    k = np.array(camera.intrinsics, np.float64, copy=True)
    k[:2] *= s
    return Camera(camera.name, height, width, k, camera.extrinsics)


def resize_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """An (H, W, 3) uint8 image resized to (height, width) (bilinear, PIL)."""
    from PIL import Image

    if image.shape[:2] == (height, width):
        return np.asarray(image, np.uint8)
    return np.asarray(Image.fromarray(np.asarray(image, np.uint8)).resize((width, height), Image.BILINEAR))


# --- Session-facing helpers ------------------------------------------------------------------------


def last_step(session) -> int:
    """Index of the last observation of the session's capture (observations 0..T)."""
    return int(session.capture.num_observations) - 1


def undo_depth(session) -> tuple[int | None, int | None]:
    """(undo, redo) depths of the session's history (`undo_depth` / `redo_depth`, or the lengths of
    `state.undo_stack` / `state.redo_stack`), None where the session exposes neither."""
    def _get(name: str, stack: str) -> int | None:
        value = getattr(session, name, None)
        if value is None:
            value = getattr(getattr(session, "state", None), stack, None)
            value = None if value is None else len(value)
        try:
            return None if value is None else int(value() if callable(value) else value)
        except (TypeError, ValueError):
            return None

    return _get("undo_depth", "undo_stack"), _get("redo_depth", "redo_stack")


def format_score(score) -> str:
    """One line of a FitScore: inlier RMSE (mm), coverage, fitness, accepted/reason."""
    if score is None:
        return "fit: -"
    rmse = float(getattr(score, "rmse", float("nan")))
    if not np.isfinite(rmse):
        return f"fit: - ({getattr(score, 'reason', '') or 'no fit'})"
    line = (f"fit: rmse {rmse * 1000:.1f} mm, coverage {float(getattr(score, 'coverage', float('nan'))):.2f}, "
            f"fitness {float(getattr(score, 'fitness', float('nan'))):.2f}")
    if not getattr(score, "accepted", True):
        line += f", poor: {getattr(score, 'reason', '')}"
    return line


@dataclass
class ViewState:
    """What the window shows and how keys act, beyond the Session's own state."""

    frame: str = "table"  # nudge axes: "table" or "object"
    coarse: bool = False  # coarse (1 cm / 5 deg) or fine (1 mm / 1 deg) nudges
    residual: bool = False  # cloud coloured by depth residual instead of the capture colours
    quit: bool = False
    reset_view: bool = False  # set by the key, cleared by the window once it reset the 3D view
    message: str = ""
    score_cache: dict = field(default_factory=dict)

    @property
    def translation_step(self) -> float:
        return TRANSLATION_STEPS["coarse" if self.coarse else "fine"]

    @property
    def rotation_step(self) -> float:
        return ROTATION_STEPS["coarse" if self.coarse else "fine"]


def _object_name(session, obj: int) -> str:
    try:
        return str(session.capture.objects[obj].name)
    except (AttributeError, IndexError):
        return f"object {obj}"


def cached_score(session, view: ViewState, obj: int):
    """session.score(obj) at the current step, cached on (step, obj, pose) (None when it fails)."""
    pose = np.asarray(session.poses()[obj], np.float64)
    key = (int(session.step), obj, pose.round(9).tobytes())
    if key not in view.score_cache:
        if len(view.score_cache) > 256:
            view.score_cache.clear()
        try:
            view.score_cache[key] = session.score(obj)
        except UserError:
            view.score_cache[key] = None
    return view.score_cache[key]


def help_lines(session, view: ViewState | None = None) -> list[str]:
    """The panel's text: status of the step and selected object, nudge settings, then the keys."""
    view = view or ViewState()
    obj = int(session.selected)
    n = int(session.num_objects)
    statuses = list(session.status())
    undo, redo = undo_depth(session)
    step_mm = view.translation_step * 1000
    step_deg = np.rad2deg(view.rotation_step)
    lines = [
        f"step {int(session.step)}/{last_step(session)}   object {obj + 1}/{n}: {_object_name(session, obj)}",
        f"status: {statuses[obj] if 0 <= obj < len(statuses) else '-'}",
        format_score(cached_score(session, view, obj) if 0 <= obj < n else None),
        f"done here: {sum(s == 'confirmed' for s in statuses)}/{n} confirmed",
        f"nudge: {'coarse' if view.coarse else 'fine'} {step_mm:g} mm / {step_deg:g} deg, {view.frame} axes",
        f"cloud: {'depth residual' if view.residual else 'capture colours'}",
        f"undo {'-' if undo is None else undo}   redo {'-' if redo is None else redo}",
        f"> {view.message}" if view.message else ">",
        "",
        "keys (mouse: rotate / pan / zoom the view)",
    ]
    return lines + key_help_lines()


# --- Keys ------------------------------------------------------------------------------------------


class Binding(NamedTuple):
    """One key: its label, the Session method its action calls (None: view-only) and the action."""

    label: str
    method: str | None
    action: Callable[["Controller"], Any]
    group: str


def _select(ctl: "Controller", obj: int) -> None:
    if obj >= ctl.session.num_objects:
        ctl.view.message = f"no object {obj + 1}: this capture has {ctl.session.num_objects}"
        return
    ctl.session.select(obj)
    ctl.view.message = f"selected {obj + 1}: {_object_name(ctl.session, obj)}"


def _select_next(ctl: "Controller") -> None:
    _select(ctl, (int(ctl.session.selected) + 1) % max(1, int(ctl.session.num_objects)))


def _translate(axis: int, sign: int, ctl: "Controller") -> None:
    vec = np.zeros(3)
    vec[axis] = sign * ctl.view.translation_step
    ctl.session.nudge(int(ctl.session.selected), translation=tuple(vec), rotation=(0.0, 0.0, 0.0),
                      frame=ctl.view.frame)
    ctl.view.message = f"moved {'+' if sign > 0 else '-'}{'xyz'[axis]} {vec[axis] * 1000:+g} mm ({ctl.view.frame})"


def _rotate(axis: int, sign: int, ctl: "Controller") -> None:
    vec = np.zeros(3)
    vec[axis] = sign * ctl.view.rotation_step
    ctl.session.nudge(int(ctl.session.selected), translation=(0.0, 0.0, 0.0), rotation=tuple(vec),
                      frame=ctl.view.frame)
    name = ("roll", "pitch", "yaw")[axis]
    ctl.view.message = f"rotated {name} {np.rad2deg(vec[axis]):+g} deg ({ctl.view.frame})"


def _toggle_frame(ctl: "Controller") -> None:
    ctl.view.frame = "object" if ctl.view.frame == "table" else "table"
    ctl.view.message = f"nudges in {ctl.view.frame} axes"


def _toggle_coarse(ctl: "Controller") -> None:
    ctl.view.coarse = not ctl.view.coarse
    ctl.view.message = f"{'coarse' if ctl.view.coarse else 'fine'} steps"


def _snap(ctl: "Controller") -> None:
    score = ctl.session.snap(int(ctl.session.selected))
    verdict = "snapped" if getattr(score, "accepted", True) else "snap rejected"
    ctl.view.message = f"{verdict}: {format_score(score)[5:]}"


def _confirm(ctl: "Controller") -> None:
    ctl.session.confirm(int(ctl.session.selected))
    ctl.view.message = f"confirmed {_object_name(ctl.session, int(ctl.session.selected))}"


def _go(delta: int, ctl: "Controller") -> None:
    target = int(ctl.session.step) + delta
    if not 0 <= target <= last_step(ctl.session):
        ctl.view.message = f"no step {target}: steps are 0..{last_step(ctl.session)}"
        return
    snapped = ctl.session.go_to(target)
    ctl.view.message = f"step {target}" + (f", snapped objects {[i + 1 for i in snapped]}" if snapped else "")


def _undo(ctl: "Controller") -> None:
    ctl.view.message = "undone" if ctl.session.undo() else "nothing to undo"


def _redo(ctl: "Controller") -> None:
    ctl.view.message = "redone" if ctl.session.redo() else "nothing to redo"


def _from_previous(ctl: "Controller") -> None:
    ctl.session.init_from_previous(int(ctl.session.selected))
    ctl.view.message = "pose taken from the previous step"


def _pick(ctl: "Controller") -> None:
    ctl.pick()


def _toggle_residual(ctl: "Controller") -> None:
    ctl.view.residual = not ctl.view.residual
    if ctl.view.residual:
        ctl.session.residual_colors()  # fail here (message) rather than while drawing
    ctl.view.message = f"cloud coloured by {'depth residual' if ctl.view.residual else 'capture colours'}"


def _progress(ctl: "Controller") -> None:
    ctl.echo(ctl.session.progress_table())
    ctl.view.message = "progress table printed to the terminal"


def _reset_view(ctl: "Controller") -> None:
    ctl.view.reset_view = True
    ctl.view.message = "view reset"


def _quit(ctl: "Controller") -> None:
    ctl.view.quit = True
    ctl.view.message = "bye"


def _build_keymap() -> dict[str, Binding]:
    km: dict[str, Binding] = {}
    for i in range(5):
        km[str(i + 1)] = Binding(f"select object {i + 1}", "select", partial(_select, obj=i), "select object / next")
    km["Tab"] = Binding("select the next object", "select", _select_next, "select object / next")
    for key, axis, sign in (("D", 0, 1), ("A", 0, -1), ("W", 1, 1), ("S", 1, -1), ("E", 2, 1), ("Q", 2, -1)):
        km[key] = Binding(f"move {'+-'[sign < 0]}{'xyz'[axis]}", "nudge", partial(_translate, axis, sign),
                          "move +x -x +y -y +z -z")
    for key, axis, sign in (("L", 0, 1), ("J", 0, -1), ("I", 1, 1), ("K", 1, -1), ("O", 2, 1), ("U", 2, -1)):
        km[key] = Binding(f"rotate {'+-'[sign < 0]}{('roll', 'pitch', 'yaw')[axis]}", "nudge",
                          partial(_rotate, axis, sign), "rotate +-roll +-pitch +-yaw")
    km["T"] = Binding("table / object axes", None, _toggle_frame, "table / object axes")
    km["G"] = Binding("fine / coarse steps", None, _toggle_coarse, "fine / coarse steps")
    km["Space"] = Binding("snap (ICP)", "snap", _snap, "snap (ICP)")
    km["Enter"] = Binding("confirm", "confirm", _confirm, "confirm")
    km["N"] = Binding("next step", "go_to", partial(_go, 1), "next / previous step")
    km["P"] = Binding("previous step", "go_to", partial(_go, -1), "next / previous step")
    km["Z"] = Binding("undo", "undo", _undo, "undo / redo")
    km["Y"] = Binding("redo", "redo", _redo, "undo / redo")
    km["C"] = Binding("pose from the previous step", "init_from_previous", _from_previous,
                      "pose from the previous step")
    km["M"] = Binding("pick >= 3 point pairs", "init_from_picks", _pick, "pick >= 3 pairs cloud <-> mesh")
    km["R"] = Binding("depth-residual colours", "residual_colors", _toggle_residual, "depth-residual colours")
    km["F"] = Binding("progress table (terminal)", "progress_table", _progress, "progress table (terminal)")
    km["V"] = Binding("reset the 3D view", None, _reset_view, "reset the 3D view")
    km["Esc"] = Binding("quit", None, _quit, "quit (all saved)")
    return km


#: Key name -> Binding. Letters are case-insensitive; see `glfw_code` for the key codes.
KEYMAP: dict[str, Binding] = _build_keymap()


def glfw_code(key: str) -> int:
    """GLFW key code of a KEYMAP key name (upper-case letters and digits are their ASCII codes)."""
    if key in GLFW_SPECIAL_KEYS:
        return GLFW_SPECIAL_KEYS[key]
    if len(key) == 1 and (key.isdigit() or "A" <= key <= "Z"):
        return ord(key)
    raise ValueError(f"no GLFW code for key {key!r}")


def key_help_lines(keymap: dict[str, Binding] | None = None) -> list[str]:
    """One line per key group: the group's keys, a tab, its label ("D A W S E Q\tmove +x -x ...")."""
    groups: dict[str, list[str]] = {}
    for key, binding in (keymap or KEYMAP).items():
        groups.setdefault(binding.group, []).append(key)
    return [f"{' '.join(keys)}\t{group}" for group, keys in groups.items()]


def pick_points(points: np.ndarray, colors: np.ndarray | None, title: str) -> np.ndarray:
    """Indices of the points a user shift-clicks in an open3d `VisualizerWithEditing` (closed with Q / Esc)."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    if colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.asarray(colors, np.float64))
    vis = o3d.visualization.VisualizerWithEditing()
    if not vis.create_window(title, width=1024, height=768):
        raise UserError(f"could not open the picking window; {NO_DISPLAY_HINT}")
    vis.add_geometry(pcd)
    vis.get_render_option().point_size = 4.0  # bigger targets for shift + click
    vis.run()
    vis.destroy_window()
    return np.asarray(vis.get_picked_points(), dtype=np.int64)


def mesh_samples(vertices: np.ndarray, faces: np.ndarray, count: int = 6000, seed: int = 0) -> np.ndarray:
    """Points (M, 3) on a mesh surface (object frame, m) for picking: its vertices plus uniform samples."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
                                     o3d.utility.Vector3iVector(np.asarray(faces, np.int32)))
    o3d.utility.random.seed(seed)
    samples = np.asarray(mesh.sample_points_uniformly(count).points) if len(faces) else np.zeros((0, 3))
    return np.vstack([np.asarray(vertices, np.float64), samples])


class Controller:
    """Keys -> Session calls and the view state; no window (testable without a display).

    session: an annotator Session; picker(points (M,3), colors (M,3) or None, title) -> picked indices
    (default: `pick_points`); echo(text): terminal output (default: rich).
    """

    def __init__(self, session, picker: Callable[..., np.ndarray] | None = None,
                 echo: Callable[[str], None] | None = None):
        self.session = session
        self.view = ViewState()
        self.picker = picker or pick_points
        self.echo = echo or _rich_echo
        self._clouds: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._images: dict[tuple[int, str], np.ndarray] = {}  # panel-sized colour images by (step, camera)

    def press(self, key: str) -> set[str]:
        """Act on one key (a KEYMAP name, letters case-insensitive); returns what changed: a subset of
        {"cloud", "meshes", "panel"}. A UserError from the session becomes the panel's message."""
        name = key.upper() if len(key) == 1 else key
        binding = KEYMAP.get(name)
        if binding is None:
            self.view.message = f"key {key!r} does nothing; see the keys listed below"
            return {"panel"}
        before = self._snapshot()
        try:
            binding.action(self)
        except UserError as exc:
            self.view.message = f"{binding.label}: {exc}"
            self.echo(f"[{binding.label}] {exc}")
        after = self._snapshot()
        changed = {"panel"}
        if before[:2] != after[:2]:
            changed.add("cloud")
        if before[2:] != after[2:]:
            changed.add("meshes")
            if self.view.residual and before[2] != after[2]:  # the residual colours follow the poses only
                changed.add("cloud")
        return changed

    def _snapshot(self) -> tuple:
        s = self.session
        return (int(s.step), self.view.residual, np.asarray(s.poses(), np.float64).tobytes(),
                tuple(s.status()), int(s.selected), self.view.frame)

    def cloud(self) -> tuple[np.ndarray, np.ndarray]:
        """Points (M,3) world m and colours (M,3) 0..1 of the current step's fused cloud."""
        step = int(self.session.step)
        if step not in self._clouds:
            if len(self._clouds) >= 4:
                self._clouds.pop(next(iter(self._clouds)))
            source = getattr(self.session, "cloud", None) or self.session.capture.cloud  # the session's is cached
            points, colors, _ = source(step)
            self._clouds[step] = (np.asarray(points, np.float64), np.asarray(colors, np.float64))
        points, colors = self._clouds[step]
        if self.view.residual:
            try:
                colors = np.asarray(self.session.residual_colors(), np.float64)
            except UserError as exc:
                self.view.message = f"residual colours: {exc}"
        return points, colors

    def pick(self) -> None:
        """Pick mode: >= 3 cloud points, then as many mesh points (same order) -> session.init_from_picks."""
        s, obj = self.session, int(self.session.selected)
        points, colors = self.cloud()
        cloud_idx = self.picker(points, colors, "pick >= 3 cloud points (shift+click), then close with Q")
        if len(cloud_idx) < 3:
            self.view.message = f"pick: {len(cloud_idx)} cloud points picked; need 3 or more (shift+click)"
            return
        vertices, faces = s.capture.mesh(obj)
        samples = mesh_samples(vertices, faces)
        shade = np.tile(np.asarray(SELECTED_COLOR), (len(samples), 1))
        mesh_idx = self.picker(samples, shade, f"pick the same {len(cloud_idx)} points on the mesh, in order, "
                                               "then close with Q")
        if len(mesh_idx) != len(cloud_idx):
            self.view.message = (f"pick: {len(mesh_idx)} mesh points for {len(cloud_idx)} cloud points; "
                                 "pick the same number in the same order (M to retry)")
            return
        s.init_from_picks(obj, samples[np.asarray(mesh_idx)], points[np.asarray(cloud_idx)])
        self.view.message = f"pose initialised from {len(cloud_idx)} picked pairs"

    def meshes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        return [self.session.capture.mesh(i) for i in range(int(self.session.num_objects))]

    def panel(self) -> np.ndarray:
        """The panel image (H, W, 3) uint8: help/status text beside both cameras' outline overlays."""
        s = self.session
        colors = object_colors(s.status(), int(s.selected))
        overlays = []
        for name, cam in s.capture.cameras.items():
            small = scaled_camera(cam.camera, PANEL_IMAGE_WIDTH)
            key = (int(s.step), name)
            if key not in self._images:
                if len(self._images) >= 8:
                    self._images.pop(next(iter(self._images)))
                self._images[key] = resize_image(s.capture.color(*key), small.width, small.height)
            image = self._images[key]
            overlays.append((name, outline_overlay(image, small, self.meshes(), s.poses(), colors=colors,
                                                   selected=int(s.selected))))
        return panel_image(help_lines(s, self.view), overlays)


def _rich_echo(text: str) -> None:
    try:
        from rich.console import Console

        Console(highlight=False, soft_wrap=True).print(text, markup=False)
    except ImportError:  # pragma: no cover - rich is a core dependency
        print(text)


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: the fixed bitmap font
        return ImageFont.load_default()


def panel_image(lines: Sequence[str], images: Sequence[tuple[str, np.ndarray]], *,
                text_width: int = PANEL_TEXT_WIDTH, font_size: int = PANEL_FONT_SIZE) -> np.ndarray:
    """(H, W, 3) uint8: the text lines in a dark column on the left, the titled images stacked on the right.

    A line "keys\tlabel" is drawn in two aligned columns; other lines wrap at the column width. H fits
    the taller of the text and the images; W = text_width + the widest image.
    """
    from PIL import Image, ImageDraw

    font = _font(font_size)
    line_h = font_size + 5
    title_h = line_h
    tab_x = 8 + 9 * font_size  # second column of "keys\tlabel" lines
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    rows: list[tuple[str, str]] = []
    for line in lines:
        left, _, right = line.partition("\t")
        if right:
            rows.append((left, right))
            continue
        words, current = left.split(" "), ""
        for word in words:  # wrap to the column width
            trial = f"{current} {word}" if current else word
            if current and measure.textlength(trial, font=font) > text_width - 16:
                rows.append((current, ""))
                current = "  " + word
            else:
                current = trial
        rows.append((current, ""))
    img_w = max([im.shape[1] for _, im in images], default=0)
    img_h = sum(im.shape[0] + title_h for _, im in images)
    height = max(img_h, len(rows) * line_h + 10)
    canvas = Image.new("RGB", (text_width + img_w, height), (24, 24, 28))
    draw = ImageDraw.Draw(canvas)
    for k, (left, right) in enumerate(rows):
        draw.text((8, 5 + k * line_h), left, fill=(235, 235, 235), font=font)
        if right:
            draw.text((tab_x, 5 + k * line_h), right, fill=(200, 220, 255), font=font)
    y = 0
    for title, im in images:
        draw.text((text_width + 6, y + 2), title, fill=(255, 210, 120), font=font)
        canvas.paste(Image.fromarray(np.asarray(im, np.uint8)), (text_width, y + title_h))
        y += im.shape[0] + title_h
    return np.asarray(canvas)


# --- The window ------------------------------------------------------------------------------------


def display_problem() -> str | None:
    """Why no X window can be opened here (DISPLAY unset or unreachable), or None when one can.

    Checked before open3d is asked: open3d 0.20 silently falls back to an invisible offscreen EGL context
    when it cannot reach a display, which would leave a window nobody can see or quit.
    """
    display = os.environ.get("DISPLAY")
    if not display:
        return "DISPLAY is not set"
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


class AnnotatorWindow:
    """The 3D window and the panel window over a Controller. `press(key)` is what a key callback does."""

    def __init__(self, session, *, width: int = 1280, height: int = 800, picker=None, echo=None):
        import open3d as o3d

        problem = display_problem()
        if problem is not None:
            raise UserError(f"no display for the annotator window ({problem}); {NO_DISPLAY_HINT}")
        self._o3d = o3d
        self.ctl = Controller(session, picker=picker, echo=echo)
        self.vis = o3d.visualization.VisualizerWithKeyCallback()
        if not self.vis.create_window("dsr-bench annotator: 3D (Esc quits)", width=width, height=height):
            raise UserError(f"could not create the annotator window (no OpenGL display); {NO_DISPLAY_HINT}")
        self.panel_vis = None
        self._deferred: list[str] = []
        self._busy = False
        try:
            self._build_scene()
            panel = self.ctl.panel()
            self.panel_vis = o3d.visualization.Visualizer()
            if not self.panel_vis.create_window("dsr-bench annotator: cameras and keys", width=panel.shape[1],
                                                height=panel.shape[0], left=width + 60, top=50):
                raise UserError(f"could not create the annotator's panel window; {NO_DISPLAY_HINT}")
            self.panel_image = o3d.geometry.Image(np.ascontiguousarray(panel))
            self.panel_vis.add_geometry(self.panel_image)
            for key in KEYMAP:
                self.vis.register_key_callback(glfw_code(key), partial(self._on_key, key))
        except BaseException:
            self.close()
            raise

    # scene ---------------------------------------------------------------------------------------
    def _build_scene(self) -> None:
        o3d, ctl = self._o3d, self.ctl
        points, colors = ctl.cloud()
        self.cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        self.cloud.colors = o3d.utility.Vector3dVector(colors)
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
        """Look at the workspace from above the front camera (table z up)."""
        from dsr_bench.constants import CAMERAS, WORKSPACE_CENTER

        eye, target = np.array(CAMERAS["front"]["eye"]), np.array([*WORKSPACE_CENTER, 0.03])
        front = (eye - target) / np.linalg.norm(eye - target)
        up = np.array([0.0, 0.0, 1.0]) - front[2] * front  # orthogonal to front: open3d does not fix it
        ctr = self.vis.get_view_control()
        ctr.set_lookat(target)
        ctr.set_front(front)
        ctr.set_up(up / np.linalg.norm(up))
        ctr.set_zoom(0.45)

    def _update_meshes(self) -> None:
        o3d, s = self._o3d, self.ctl.session
        poses = np.asarray(s.poses(), np.float64)
        colors = object_colors(s.status(), int(s.selected))
        for (vertices, _), mesh, pose, color in zip(self.mesh_data, self.meshes, poses, colors):
            if np.all(np.isfinite(pose)):
                world = _posed(vertices, pose)
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

    def _update_cloud(self) -> None:
        points, colors = self.ctl.cloud()
        self.cloud.points = self._o3d.utility.Vector3dVector(points)
        self.cloud.colors = self._o3d.utility.Vector3dVector(colors)

    # keys ----------------------------------------------------------------------------------------
    def _on_key(self, key: str, _vis) -> bool:
        """The GLFW key callback. Keys that open another window (pick mode) wait for `render`: GLFW's
        event processing must not be re-entered from inside a callback. While such a window is open, this
        window's keys are ignored (its events are still delivered)."""
        if self._busy:
            return False
        if key in DEFERRED_KEYS:
            self._deferred.append(key)
        else:
            self.press(key)
        return False

    def press(self, key: str) -> set[str]:
        """Do what pressing `key` (a KEYMAP name) does, and update the changed geometries in place."""
        changed = self.ctl.press(key)
        if "cloud" in changed:
            self._update_cloud()
            self.vis.update_geometry(self.cloud)
        if "meshes" in changed:
            self._update_meshes()
            for mesh in self.meshes:
                self.vis.update_geometry(mesh)
            self.vis.update_geometry(self.gizmo)
        if "panel" in changed:
            self._update_panel()
        if self.ctl.view.reset_view:
            self.ctl.view.reset_view = False
            self.reset_view()
        if self.ctl.view.quit:
            self.vis.close()
        return changed

    def refresh(self) -> None:
        """Re-read everything from the session (after changes made outside the window's keys)."""
        self.ctl._clouds.clear()
        self._update_cloud()
        self.vis.update_geometry(self.cloud)
        self._update_meshes()
        for mesh in self.meshes:
            self.vis.update_geometry(mesh)
        self.vis.update_geometry(self.gizmo)
        self._update_panel()

    def _update_panel(self) -> None:
        if self.panel_vis is None:
            return
        panel = self.ctl.panel()
        target = np.asarray(self.panel_image)
        if panel.shape == target.shape:
            target[...] = panel
        else:  # more text lines than at start: a new image of the new size
            self.panel_vis.remove_geometry(self.panel_image, reset_bounding_box=False)
            self.panel_image = self._o3d.geometry.Image(np.ascontiguousarray(panel))
            self.panel_vis.add_geometry(self.panel_image)
        self.panel_vis.update_geometry(self.panel_image)
        self.panel_vis.update_renderer()

    def render(self) -> bool:
        """Process window events and redraw both windows; False once either window was closed."""
        alive = self.vis.poll_events()
        while self._deferred:
            self._busy = True
            try:
                self.press(self._deferred.pop(0))
            finally:
                self._busy = False
        self.vis.update_renderer()
        if self.panel_vis is not None:
            alive = self.panel_vis.poll_events() and alive
            self.panel_vis.update_renderer()
        return bool(alive) and not self.ctl.view.quit

    def screenshot(self) -> np.ndarray:
        """The 3D window's current image (H, W, 3) uint8."""
        img = np.asarray(self.vis.capture_screen_float_buffer(do_render=True))
        return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)

    def panel_screenshot(self) -> np.ndarray:
        """The panel window's current image (H, W, 3) uint8."""
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


def run(session, *, width: int = 1280, height: int = 800) -> None:
    """Open the annotator window on the session's current step; return when the user quits.

    Every key acts through the Session, which autosaves each change, so quitting (Esc, or closing a
    window) loses nothing. Raises UserError when no window can be created (no display).
    """
    window = AnnotatorWindow(session, width=width, height=height)
    try:
        window.ctl.echo("annotator: keys are listed in the panel window; Esc quits (every change is saved)")
        window.loop()
    finally:
        window.close()
