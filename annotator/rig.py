"""What both forms of `dsr-bench import-capture` share (the PNG folder, `annotator.importer`, and RealSense bags,
`annotator.realsense`): the rig file and its objects, the output check, the default input files, the board
calibration of cameras without extrinsics, and undistortion through OpenCV's model. Both forms import this module
and neither imports the other for these: `annotator.importer` only dispatches a folder of bags to
`annotator.realsense`, which never imports `annotator.importer`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import cast

import numpy as np

from dsr_bench.annotator.inputs import inside, plain_name
from dsr_bench.atomic import check_writable
from dsr_bench.dataset.capture import CaptureCamera
from dsr_bench.errors import UserError

RIG_FILE = "rig.json"
PUSHES_FILE = "pushes.json"


def rig_error(path: Path, message: str) -> UserError:
    return UserError(f"{path}: {message}; see docs/annotator.md, 'Real captures in'")


def undistort_maps(camera: CaptureCamera, distortion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV remap tables (H, W) float32 x, y: for each undistorted pixel (same intrinsics, no distortion), where
    it lies in the distorted image."""
    import cv2

    k = np.asarray(camera.intrinsics, np.float64)
    return cv2.initUndistortRectifyMap(k, distortion, None, k, (camera.width, camera.height), cv2.CV_32FC1)


def undistort(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray], nearest: bool) -> np.ndarray:
    """An image resampled through `undistort_maps` (bilinear, or nearest for depth); pixels from outside the image
    become 0 (black, no depth)."""
    import cv2

    flags = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.remap(image, maps[0], maps[1], flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def read_objects(path: Path, src: Path, entries) -> list[tuple[str, np.ndarray, np.ndarray, dict]]:
    """(name, vertices (V, 3) m, faces (F, 3), identity) of the rig file's "objects" (meshes relative to SRC)."""
    import trimesh

    if not isinstance(entries, list) or not entries:
        raise rig_error(path, 'needs "objects": [{"name": ..., "mesh": "meshes/can.ply"}, ...] (meshes in metres, '
                               "relative to the folder)")
    out = []
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict) or not isinstance(entry.get("mesh"), str):
            raise rig_error(path, f"object {i + 1} needs a 'mesh' path relative to {src}")
        if not isinstance(entry.get("name", ""), str) or not isinstance(entry.get("identity", {}), dict):
            raise rig_error(path, f"object {i + 1}: 'name' must be a string and 'identity' an object")
        mesh_path = inside(src, entry["mesh"], f"object {i + 1} mesh", path)
        if not mesh_path.is_file():
            raise rig_error(path, f"object {i + 1} mesh {entry['mesh']!r} not found under {src}")
        try:
            mesh = cast("trimesh.Trimesh", trimesh.load(mesh_path, force="mesh", process=False))  # force="mesh"
            vertices, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
        except Exception as exc:  # trimesh raises many types for corrupt files
            raise rig_error(path, f"object {i + 1} mesh {entry['mesh']!r} is unreadable ({exc})") from None
        size = float(np.linalg.norm(vertices.max(0) - vertices.min(0))) if len(vertices) else 0.0
        if len(faces) < 4 or not 0.005 < size < 1.0:
            raise rig_error(path, f"object {i + 1} mesh {entry['mesh']!r} is not an object in metres (diagonal "
                                   f"{size:.4g}, {len(faces)} triangles); rescale it to metres")
        identity = dict(entry.get("identity", {}))
        name = plain_name(entry.get("name", mesh_path.stem), f"object {i + 1} name", path, f"object_{i + 1}")
        out.append((name, vertices, faces, identity))
    return out


def load_rig(src: Path, rig: str | Path | None) -> tuple[Path, dict]:
    """(path, parsed JSON object) of the rig file (`rig`, default SRC/rig.json); UserError naming it and the fix."""
    rig_path = Path(rig) if rig is not None else inside(src, RIG_FILE, "the rig file", src)
    if not rig_path.is_file():
        raise UserError(f"{rig_path}: no rig file; write one (cameras, board or extrinsics, objects: "
                        "docs/annotator.md, 'Real captures in') or give it with --rig")
    try:
        spec = json.loads(rig_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise rig_error(rig_path, f"unreadable JSON ({exc})") from None
    if not isinstance(spec, dict):
        raise rig_error(rig_path, 'expected {"cameras": {"front": {...}, "back": {...}}, "objects": [...], ...}')
    if not isinstance(spec.get("name", ""), str):
        raise rig_error(rig_path, f"'name' must be a string (the capture's name), got {json.dumps(spec['name'])[:40]}")
    if spec.get("name"):
        plain_name(spec["name"], "'name' (the capture's)", rig_path)
    return rig_path, spec


def capture_name(name: str | None, spec: dict, rig_path: Path, out: Path) -> str:
    """The capture's name: `--name`, else the rig file's "name", else OUT's directory name; each checked to be one
    plain name (`annotator.inputs.plain_name`: it becomes part of output paths and identities)."""
    if name is not None:
        return plain_name(name, "the capture name", "--name")
    if spec.get("name"):
        return plain_name(spec["name"], "'name' (the capture's)", rig_path)
    return plain_name(out.name, "its directory name (the capture's name without --name or a rig file 'name')",
                      f"--out {out}")


def default_file(src: Path, given: str | Path | None, name: str, what: str) -> Path:
    """The file given on the command line, or SRC/`name` checked to stay inside SRC (not a link out of it)."""
    return Path(given) if given is not None else inside(src, name, what, src)


def check_out(out: Path, overwrite: bool) -> None:
    """Refuse (one line) an existing `out` without --overwrite, and an `out` that cannot be written (the capture is
    written as a temporary directory beside it, then renamed over it), and an `out` that names no directory of its own
    (`..`, `/`: with --overwrite it would replace its parent), before any work."""
    if out.name in ("", ".", ".."):
        raise UserError(f"--out {out}: names no capture directory of its own (it ends in {out.name or str(out)!r}); "
                        "give the capture's directory, e.g. captures/real_0042")
    if out.exists() and not overwrite:
        raise UserError(f"{out} already exists; pass --overwrite to replace it or choose another --out")
    check_writable(out, "--out")
    if out.exists():
        check_writable(out.parent, "--out")


def calibrate_cameras(rig_path: Path, spec: dict, cameras: dict[str, CaptureCamera], given: dict[str, bool],
                      board_image) -> dict:
    """Calibrate (in place) the cameras whose extrinsics were not `given` from the rig file's board, check the
    residuals and that the front camera sees the whole grid; returns the calibration report (`annotator.calibrate`).
    board_image(name) -> (where: the image named in errors, colour (H, W, 3) uint8 RGB undistorted, depth (H, W) m
    aligned to it, 0 = none) of the board seen by that camera."""
    from dsr_bench.annotator.calibrate import (board_view, calibration_residuals, check_grid_visible, check_residuals,
                                               parse_board)

    report: dict = {"extrinsics": {n: "rig file" if given[n] else "board" for n in cameras}}
    need_board = [n for n in cameras if not given[n]]
    if need_board:
        if "board" not in spec:
            raise rig_error(rig_path, f"camera(s) {', '.join(need_board)} have no 'extrinsics' (4x4 camera-to-table, "
                                       "m) and there is no 'board' to calibrate them from: give either")
        board = parse_board(str(rig_path), spec["board"])
        views, calib_depth = {}, {}
        for n in need_board:
            where, image, calib_depth[n] = board_image(n)
            views[n] = board_view(image, cameras[n].intrinsics, board, f"{where} ({rig_path} board)")
            cameras[n] = CaptureCamera(n, cameras[n].height, cameras[n].width, cameras[n].intrinsics,
                                       views[n].extrinsics, cameras[n].depth_scale)
        report.update(calibration_residuals({n: cameras[n].camera for n in need_board}, views, calib_depth, board))
        report["board"] = dict(spec["board"])
        check_residuals(f"{rig_path} board", report)
    check_grid_visible(f"{rig_path} camera 'front'", cameras["front"].camera)
    return report
