"""Real (or simulated) two-camera RGB-D captures: the annotator's input format, read and written.

A capture is a directory per sequence (see DATASHEET.md, "Capture format")::

    captures/seq_042/
      capture.json        format marker, name, number of pushes T, camera names, provenance
      calibration.json    per camera: height, width, intrinsics (3x3 px), extrinsics (4x4 camera-to-table,
                          OpenCV axes, m), depth_scale (m per depth unit)
      actions.json        actions (T, 3) [d, row, col] and pushes_world (T, 2, 3) start/end in metres
      objects.json        per object: name, mesh (path relative to the capture), identity
      meshes/...          object meshes (.ply / .obj / .stl) in the object frame, metres
      steps/000/<camera>_color.png (H, W, 3) uint8, <camera>_depth.png (H, W) uint16, 0 = missing ... steps/T/
      truth.json          simulated captures only: true poses and calibration (never read by the annotator)

Everything read from disk is validated on load (`load_capture`); images are decoded lazily per step.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, cast

import numpy as np

from dsr_bench.atomic import atomic_directory
from dsr_bench.constants import GRID_BOUNDS, NUM_DIRECTIONS
from dsr_bench.errors import UserError
from dsr_bench.geometry import Camera
from dsr_bench.dataset.manifest import mesh_sha256

CAPTURE_FORMAT = "dsr-bench-capture"
CAPTURE_VERSION = 1
#: Margin (m) around the grid bounds kept by `Capture.cloud`.
CLOUD_MARGIN = 0.02
MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off")


class CaptureFormatError(UserError):
    """A capture directory does not follow the capture format."""


@dataclass(frozen=True)
class CaptureCamera:
    """One calibrated RGB-D camera: intrinsics (3,3) px, camera-to-table extrinsics (4,4) m, depth scale m/unit."""

    name: str
    height: int
    width: int
    intrinsics: np.ndarray
    extrinsics: np.ndarray
    depth_scale: float

    @property
    def camera(self) -> Camera:
        return Camera(self.name, self.height, self.width, self.intrinsics, self.extrinsics)

    def as_json(self) -> dict:
        return {"height": int(self.height), "width": int(self.width),
                "intrinsics": np.asarray(self.intrinsics).tolist(), "extrinsics": np.asarray(self.extrinsics).tolist(),
                "depth_scale": float(self.depth_scale)}


@dataclass(frozen=True)
class CaptureObject:
    """One object of a capture: its name, mesh file and identity (set, category, model id, ...)."""

    index: int
    name: str
    mesh_path: Path
    identity: dict = field(default_factory=dict)


def _fail(path: Path, message: str) -> CaptureFormatError:
    return CaptureFormatError(f"{path}: {message}")


def _read_json(path: Path) -> Any:
    if not path.is_file():
        raise _fail(path, "missing; a capture needs capture.json, calibration.json, actions.json and objects.json "
                          "(see DATASHEET.md, 'Capture format')")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise _fail(path, f"not valid JSON ({exc}); fix or re-export the file") from None


def _matrix(path: Path, where: str, value: Any, shape: tuple[int, int]) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = None
    if m is None or m.shape != shape or not np.all(np.isfinite(m)):
        raise _fail(path, f"{where} must be a finite {shape[0]}x{shape[1]} matrix")
    return m


def parse_camera(path: Path, name: str, spec: Any) -> CaptureCamera:
    """Validate one calibration entry (see the module docstring) and return it."""
    if not isinstance(spec, dict):
        raise _fail(path, f"camera {name!r} must be an object with height, width, intrinsics, extrinsics, depth_scale")
    missing = [k for k in ("height", "width", "intrinsics", "extrinsics", "depth_scale") if k not in spec]
    if missing:
        raise _fail(path, f"camera {name!r} lacks {', '.join(missing)}")
    try:
        height, width, scale = int(spec["height"]), int(spec["width"]), float(spec["depth_scale"])
    except (TypeError, ValueError):
        raise _fail(path, f"camera {name!r}: height, width must be integers and depth_scale a number") from None
    if height <= 0 or width <= 0:
        raise _fail(path, f"camera {name!r}: image size {height}x{width} must be positive")
    if not (0 < scale < 0.1):
        raise _fail(path, f"camera {name!r}: depth_scale {scale} must be metres per unit, e.g. 0.001 (1 mm)")
    k = _matrix(path, f"camera {name!r} intrinsics", spec["intrinsics"], (3, 3))
    if k[0, 0] <= 0 or k[1, 1] <= 0 or not np.allclose(k[2], [0, 0, 1]) or k[1, 0] != 0:
        raise _fail(path, f"camera {name!r}: intrinsics must be [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
    if k[0, 1] != 0:
        raise _fail(path, f"camera {name!r}: intrinsics skew {k[0, 1]} must be 0 (pixels are projected with fx, fy, "
                          "cx, cy alone; fx != fy is fine): rectify the images or write [[fx,0,cx],[0,fy,cy],[0,0,1]]")
    e = _matrix(path, f"camera {name!r} extrinsics", spec["extrinsics"], (4, 4))
    r = e[:3, :3]
    if not np.allclose(e[3], [0, 0, 0, 1]) or not np.allclose(r @ r.T, np.eye(3), atol=1e-4) \
            or np.linalg.det(r) < 0.999:
        raise _fail(path, f"camera {name!r}: extrinsics must be a rigid 4x4 camera-to-table transform (rotation "
                          "orthonormal with det +1, last row 0 0 0 1)")
    return CaptureCamera(name, height, width, k, e, scale)


class Capture:
    """A validated capture directory; images are read per step on request."""

    def __init__(self, path: Path, meta: dict, cameras: dict[str, CaptureCamera], objects: list[CaptureObject],
                 actions: np.ndarray, pushes_world: np.ndarray):
        self.path = path
        self.name: str = str(meta["name"])
        self.num_steps: int = int(meta["num_steps"])
        self.num_observations: int = self.num_steps + 1
        self.source: dict = dict(meta.get("source", {}))
        self.cameras = cameras
        self.objects = objects
        self.num_objects = len(objects)
        self.actions = actions
        self.pushes_world = pushes_world
        self._mesh = lru_cache(maxsize=None)(self._load_mesh)

    def __repr__(self) -> str:
        return (f"Capture({self.name!r}, steps={self.num_steps}, objects={self.num_objects}, "
                f"cameras={list(self.cameras)})")

    # images ------------------------------------------------------------------------------------------
    def image_path(self, step: int, camera: str, kind: str) -> Path:
        """Path of `steps/<step:03d>/<camera>_<kind>.png` (kind 'color' or 'depth')."""
        if not 0 <= step < self.num_observations:
            raise IndexError(f"step {step} out of range 0..{self.num_steps}")
        if camera not in self.cameras:
            raise KeyError(f"no camera {camera!r}; this capture has {', '.join(self.cameras)}")
        return self.path / "steps" / f"{step:03d}" / f"{camera}_{kind}.png"

    def _image(self, step: int, camera: str, kind: str) -> np.ndarray:
        from PIL import Image

        path = self.image_path(step, camera, kind)
        try:
            with Image.open(path) as im:
                array = np.asarray(im)
        except (OSError, ValueError) as exc:
            raise _fail(path, f"unreadable image ({exc})") from None
        cam = self.cameras[camera]
        if kind == "color":
            if array.ndim == 3 and array.shape[2] == 4:
                array = array[..., :3]
            expected: tuple[int, ...] = (cam.height, cam.width, 3)
            ok = array.shape == expected and array.dtype == np.uint8
            what = "8-bit RGB"
        else:
            expected = (cam.height, cam.width)
            ok = array.shape == expected and array.dtype in (np.uint16, np.int32, np.uint32) and array.min() >= 0
            what = "16-bit depth"
        if not ok:
            raise _fail(path, f"expected a {what} PNG of shape {expected} (calibration.json), got {array.shape} "
                              f"{array.dtype}")
        return array

    def color(self, step: int, camera: str = "front") -> np.ndarray:
        """Colour image (H, W, 3) uint8."""
        return self._image(step, camera, "color")

    def depth(self, step: int, camera: str = "front") -> np.ndarray:
        """z-depth (H, W) float32 in metres, 0 where missing."""
        return (self._image(step, camera, "depth").astype(np.float64) * self.cameras[camera].depth_scale).astype(
            np.float32)

    def points(self, step: int, camera: str = "front", depth: np.ndarray | None = None) -> np.ndarray:
        """World points (H, W, 3) float32 in metres, NaN where depth is missing. `depth`: this step's
        `depth(step, camera)` when the caller has already read it (the image is then not decoded again)."""
        depth = self.depth(step, camera) if depth is None else depth
        return self.cameras[camera].camera.backproject(depth.astype(np.float64)).astype(np.float32)

    def cloud(self, step: int, cameras: list[str] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Fused valid points of the cameras inside the grid bounds (+ margin), table included.

        Returns points (M, 3) float64 m, colours (M, 3) float64 in 0..1, camera index (M,) int64 (position of the
        camera in `cameras`, default all of the capture's cameras in order).
        """
        names = list(self.cameras) if cameras is None else cameras
        lo, hi = GRID_BOUNDS[:, 0] - CLOUD_MARGIN, GRID_BOUNDS[:, 1] + CLOUD_MARGIN
        lo[2] = -CLOUD_MARGIN
        pts, cols, idx = [], [], []
        for i, name in enumerate(names):
            p = self.points(step, name).reshape(-1, 3).astype(np.float64)
            c = self.color(step, name).reshape(-1, 3)
            keep = np.all(np.isfinite(p), 1) & np.all((p >= lo) & (p <= hi), 1)
            pts.append(p[keep])
            cols.append(c[keep] / 255.0)
            idx.append(np.full(int(keep.sum()), i, dtype=np.int64))
        return np.vstack(pts), np.vstack(cols), np.concatenate(idx)

    # objects ---------------------------------------------------------------------------------------------
    def _load_mesh(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        import trimesh

        path = self.objects[index].mesh_path
        try:
            mesh = cast("trimesh.Trimesh", trimesh.load(path, force="mesh", process=False))  # force="mesh": a Trimesh
        except Exception as exc:  # trimesh raises many types for corrupt files
            raise _fail(path, f"unreadable mesh ({exc}); use a .ply, .obj or .stl triangle mesh in metres") from None
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64)
        if len(vertices) < 4 or len(faces) < 4 or not np.all(np.isfinite(vertices)) \
                or faces.min() < 0 or faces.max() >= len(vertices):
            raise _fail(path, "mesh must have finite vertices and at least 4 valid triangles")
        size = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        if not 0.005 < size < 1.0:
            raise _fail(path, f"mesh diagonal {size:.4g} is not an object size in metres (0.005-1 m); rescale it")
        return vertices, faces

    def mesh(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Mesh of object `index`: vertices (V, 3) float64 m in the object frame, faces (F, 3) int64."""
        return self._mesh(index)

    # truth -------------------------------------------------------------------------------------------------
    def _truth(self) -> dict | None:
        path = self.path / "truth.json"
        return _read_json(path) if path.is_file() else None

    def truth_poses(self) -> np.ndarray | None:
        """True poses (T+1, N, 7) of a simulated capture, or None for a real one."""
        truth = self._truth()
        if truth is None:
            return None
        poses = np.asarray(truth.get("poses"), dtype=np.float64)
        if poses.shape != (self.num_observations, self.num_objects, 7):
            raise _fail(self.path / "truth.json",
                        f"poses must have shape {(self.num_observations, self.num_objects, 7)}")
        return poses

    def truth_calibration(self) -> dict[str, CaptureCamera] | None:
        """True calibration of a simulated capture (the stored one carries simulated errors), or None."""
        truth = self._truth()
        if truth is None or "calibration" not in truth:
            return None
        path = self.path / "truth.json"
        return {name: parse_camera(path, name, spec) for name, spec in truth["calibration"].items()}


def load_capture(path: str | Path) -> Capture:
    """Read and validate a capture directory (layout, JSON, calibration, every step and camera, image sizes)."""
    path = Path(path)
    if not path.is_dir():
        raise CaptureFormatError(f"{path}: capture directory not found; give a directory holding capture.json "
                                 "(make simulated ones with `dsr-bench generate-captures`)")
    meta = _read_json(path / "capture.json")
    where = path / "capture.json"
    if not isinstance(meta, dict) or meta.get("format") != CAPTURE_FORMAT:
        raise _fail(where, f"format must be {CAPTURE_FORMAT!r}")
    if meta.get("version") != CAPTURE_VERSION:
        raise _fail(where, f"version {meta.get('version')!r}; this toolkit reads version {CAPTURE_VERSION}")
    if not isinstance(meta.get("name"), str) or not isinstance(meta.get("num_steps"), int) or meta["num_steps"] < 1:
        raise _fail(where, "needs a string 'name' and an integer 'num_steps' >= 1 (pushes)")
    names = meta.get("cameras")
    if not isinstance(names, list) or not names or "front" not in names:
        raise _fail(where, "'cameras' must list the camera names and include 'front' (the view models see)")
    steps = meta["num_steps"]

    calib_path = path / "calibration.json"
    calib = _read_json(calib_path)
    if not isinstance(calib, dict):
        raise _fail(calib_path, "must map camera names to calibrations")
    missing = [n for n in names if n not in calib]
    if missing:
        raise _fail(calib_path, f"no calibration for camera(s) {', '.join(missing)}")
    cameras = {n: parse_camera(calib_path, n, calib[n]) for n in names}

    act_path = path / "actions.json"
    act = _read_json(act_path)
    try:
        actions = np.asarray(act["actions"], dtype=np.float64)
        pushes = np.asarray(act["pushes_world"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise _fail(act_path,
                    "needs 'actions' (T x [d, row, col]) and 'pushes_world' (T x [[x,y,z],[x,y,z]])") from None
    if actions.shape != (steps, 3) or pushes.shape != (steps, 2, 3):
        raise _fail(act_path, f"expected {steps} actions of [d, row, col] and {steps} pushes of 2 points, got "
                              f"shapes {actions.shape} and {pushes.shape}")
    if not np.all(np.isfinite(pushes)) or np.any(actions != np.round(actions)) or np.any(actions[:, 0] < 0) \
            or np.any(actions[:, 0] >= NUM_DIRECTIONS):
        raise _fail(act_path, f"actions must be integers with direction 0..{NUM_DIRECTIONS - 1}; pushes finite")

    obj_path = path / "objects.json"
    obj = _read_json(obj_path)
    entries = obj.get("objects") if isinstance(obj, dict) else None
    if not isinstance(entries, list) or not entries:
        raise _fail(obj_path, "needs a non-empty 'objects' list of {name, mesh, identity}")
    objects = []
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict) or not isinstance(entry.get("mesh"), str):
            raise _fail(obj_path, f"object {i} needs a 'mesh' path relative to the capture")
        mesh_path = (path / entry["mesh"]).resolve()
        if mesh_path.suffix.lower() not in MESH_SUFFIXES:
            raise _fail(obj_path, f"object {i} mesh {entry['mesh']!r}: use one of {', '.join(MESH_SUFFIXES)}")
        if not mesh_path.is_file():
            raise _fail(obj_path, f"object {i} mesh file {entry['mesh']!r} not found")
        objects.append(CaptureObject(i, str(entry.get("name", f"object_{i}")), mesh_path,
                                     dict(entry.get("identity", {}))))

    absent = [str(p.relative_to(path)) for step in range(steps + 1) for n in names for kind in ("color", "depth")
              if not (p := path / "steps" / f"{step:03d}" / f"{n}_{kind}.png").is_file()]
    if absent:
        more = f" and {len(absent) - 3} more" if len(absent) > 3 else ""
        raise _fail(path, f"missing image(s) {', '.join(absent[:3])}{more} for {steps} pushes ({steps + 1} steps)")
    capture = Capture(path, meta, cameras, objects, actions.astype(np.int64), pushes)
    _check_image_sizes(capture)
    return capture


def _check_image_sizes(capture: Capture) -> None:
    """Compare every PNG header with the calibration's image size (headers only, no decoding)."""
    from PIL import Image

    for step in range(capture.num_observations):
        for name, cam in capture.cameras.items():
            for kind in ("color", "depth"):
                p = capture.image_path(step, name, kind)
                try:
                    with Image.open(p) as im:
                        size, mode = im.size, im.mode
                except OSError as exc:
                    raise _fail(p, f"not a readable PNG ({exc})") from None
                if size != (cam.width, cam.height):
                    raise _fail(p, f"image is {size[0]}x{size[1]} but calibration.json gives {name!r} "
                                   f"{cam.width}x{cam.height} (width x height)")
                if kind == "depth" and mode not in ("I;16", "I;16B", "I;16L", "I"):
                    raise _fail(p, f"depth must be a 16-bit single-channel PNG (mode {mode}); store depth / "
                                   "depth_scale as uint16")


def _write_png(path: Path, array: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(array).save(path, format="PNG")


def write_capture(path: str | Path, *, name: str, cameras: dict[str, CaptureCamera],
                  colors: list[dict[str, np.ndarray]], depths: list[dict[str, np.ndarray]], actions: np.ndarray,
                  pushes_world: np.ndarray, objects: list[tuple[str, np.ndarray, np.ndarray, dict]],
                  truth_poses: np.ndarray | None = None, truth_cameras: dict[str, CaptureCamera] | None = None,
                  source: dict | None = None, overwrite: bool = False) -> Path:
    """Write a capture directory atomically (`dsr_bench.atomic.atomic_directory`: a temporary sibling directory
    renamed into place, replacing an existing one only with `overwrite`).

    colors / depths: one dict per observation (T + 1) of camera -> (H, W, 3) uint8 / (H, W) z-depth in metres (0 or
    NaN = missing, quantised to each camera's depth_scale); actions (T, 3) [d, row, col]; pushes_world (T, 2, 3) m;
    objects: (name, vertices (V, 3) m, faces (F, 3), identity) per object, meshes written as PLY.
    """
    import trimesh

    path = Path(path)
    steps = len(actions)
    if len(colors) != steps + 1 or len(depths) != steps + 1:
        raise ValueError(f"need {steps + 1} observations for {steps} actions, got {len(colors)} / {len(depths)}")
    if path.exists() and not overwrite:
        raise UserError(f"{path} already exists; pass --overwrite to replace it or choose another --out")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_directory(path) as tmp:  # a temporary directory renamed into place (dsr_bench.atomic)
        meta = {"format": CAPTURE_FORMAT, "version": CAPTURE_VERSION, "name": name, "num_steps": steps,
                "cameras": list(cameras), "source": source or {}}
        (tmp / "capture.json").write_text(json.dumps(meta, indent=1))
        (tmp / "calibration.json").write_text(json.dumps({n: c.as_json() for n, c in cameras.items()}, indent=1))
        (tmp / "actions.json").write_text(json.dumps({"actions": np.asarray(actions).astype(int).tolist(),
                                                      "pushes_world": np.asarray(pushes_world, float).tolist()}))
        (tmp / "meshes").mkdir()
        entries = []
        for i, (obj_name, vertices, faces, identity) in enumerate(objects):
            rel = f"meshes/{i}.ply"
            trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False).export(
                tmp / rel)
            identity = dict(identity)
            if "mesh_sha256" in identity:  # PLY keeps float32 vertices: the digest must name the stored mesh
                identity["source_mesh_sha256"] = identity["mesh_sha256"]
                identity["mesh_sha256"] = mesh_sha256(np.asarray(vertices, np.float32), faces)
            entries.append({"name": obj_name, "mesh": rel, "identity": identity})
        (tmp / "objects.json").write_text(json.dumps({"objects": entries}, indent=1))
        for step in range(steps + 1):
            folder = tmp / "steps" / f"{step:03d}"
            folder.mkdir(parents=True)
            for cam_name, cam in cameras.items():
                _write_png(folder / f"{cam_name}_color.png", np.ascontiguousarray(colors[step][cam_name], np.uint8))
                d = np.nan_to_num(np.asarray(depths[step][cam_name], np.float64), nan=0.0)
                units = np.clip(np.round(d / cam.depth_scale), 0, np.iinfo(np.uint16).max).astype(np.uint16)
                _write_png(folder / f"{cam_name}_depth.png", units)
        if truth_poses is not None:
            truth = {"poses": np.asarray(truth_poses, float).tolist()}
            if truth_cameras is not None:
                truth["calibration"] = {n: c.as_json() for n, c in truth_cameras.items()}
            (tmp / "truth.json").write_text(json.dumps(truth))
    return path
