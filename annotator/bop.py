"""Annotated poses -> the BOP format (https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md),
beside the DSR sequence export (`annotator.export`): `dsr-bench annotate CAPTURE --bop DIR`.

DIR holds one BOP scene per camera of the capture, numbered in the capture's camera order (`000000` the front
camera, `000001` the back one; `DIR/dsr_bop.json` names them), the image id of a scene being the step (0..T):

- `<scene>/rgb/{im_id:06d}.png`, `<scene>/depth/{im_id:06d}.png`: the capture's own images, byte for byte (depth in
  units of `depth_scale` mm, the capture's depth scale in mm);
- `<scene>/scene_camera.json`: per image id `cam_K` (3x3 intrinsics, row-major, 9 floats, pixels), `depth_scale`
  (mm per depth unit) and the camera's pose `cam_R_w2c` (row-major 9) / `cam_t_w2c` (mm): table frame -> camera;
- `<scene>/scene_gt.json`: per image id a list of {obj_id, cam_R_m2c (row-major 9), cam_t_m2c (mm)}, one per object
  in object order (gt_idx = object index, obj_id = object number from 1), model -> camera: a model point X (mm) is
  at R X + t in the camera's OpenCV frame (x right, y down, z forward) and projects to K (R X + t);
- `<scene>/mask_visib/{im_id:06d}_{gt_idx:06d}.png`: 255 where the object is visible (its rendered pixels where the
  measured depth agrees within `annotator.export.MASK_DEPTH_TOLERANCE`, as the DSR export's mask), else 0;
- `DIR/models/obj_{obj_id:06d}.ply`: the meshes in millimetres (BOP models are in mm);
- `DIR/dsr_bop.json`: the capture, the scenes' cameras, the object names by obj_id, the annotation's statuses.
"""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np

from dsr_bench.errors import UserError

#: The marker file of a BOP export (a DIR holding other things is never replaced).
MARKER = "dsr_bop.json"


def _png(array: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def _row_major(m: np.ndarray) -> list[float]:
    return [float(x) for x in np.asarray(m, dtype=np.float64).reshape(-1)]


def model_to_camera(pose_matrix: np.ndarray, camera_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R (3, 3), t (3,) mm) of BOP's cam_R_m2c / cam_t_m2c: object -> table (4x4, m) then table -> camera."""
    w2c = np.linalg.inv(np.asarray(camera_to_world, dtype=np.float64))
    m2c = w2c @ np.asarray(pose_matrix, dtype=np.float64)
    return m2c[:3, :3], m2c[:3, 3] * 1000.0


def export_bop(session, out: str | Path, allow_unchecked: bool = False) -> Path:
    """Write the session's annotation in the BOP format at directory `out` (see the module docstring), atomically
    (a finished export replaces an earlier one; a directory holding anything else is refused). The same poses are
    refused as by the DSR export (`annotator.export.check_exportable`). Returns `out`."""
    import trimesh

    from annotator.export import MASK_DEPTH_TOLERANCE, check_exportable, renderer_for
    from dsr_bench.atomic import atomic_directory
    from dsr_bench.geometry import pose_to_matrix

    out = Path(out)
    if out.exists() and not (out.is_dir() and ((out / MARKER).is_file() or not any(out.iterdir()))):
        raise UserError(f"--bop {out}: exists and is not an earlier BOP export of the annotator; give a new or empty "
                        "directory")
    check_exportable(session, allow_unchecked)
    capture = session.capture
    steps, n = capture.num_steps, capture.num_objects
    poses = np.stack([session.poses(s) for s in range(steps + 1)]).astype(np.float64)
    poses[..., 3:] /= np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True)
    cams = {name: cam.camera for name, cam in capture.cameras.items()}
    renderer = renderer_for(capture, cams)
    scenes = {f"{k:06d}": name for k, name in enumerate(cams)}
    with atomic_directory(out) as tmp:
        (tmp / "models").mkdir()
        for i in range(n):
            v, f = capture.mesh(i)
            trimesh.Trimesh(np.asarray(v) * 1000.0, f, process=False).export(tmp / "models" / f"obj_{i + 1:06d}.ply")
        for scene_id, name in scenes.items():
            cam = capture.cameras[name]
            root = tmp / scene_id
            for sub in ("rgb", "depth", "mask_visib"):
                (root / sub).mkdir(parents=True)
            w2c = np.linalg.inv(cam.extrinsics)
            scene_camera, scene_gt = {}, {}
            for s in range(steps + 1):
                shutil.copyfile(capture.image_path(s, name, "color"), root / "rgb" / f"{s:06d}.png")
                shutil.copyfile(capture.image_path(s, name, "depth"), root / "depth" / f"{s:06d}.png")
                scene_camera[str(s)] = {"cam_K": _row_major(cam.intrinsics),
                                        "depth_scale": float(cam.depth_scale) * 1000,
                                        "cam_R_w2c": _row_major(w2c[:3, :3]),
                                        "cam_t_w2c": _row_major(w2c[:3, 3] * 1000)}
                gts = []
                for i in range(n):
                    rot, t = model_to_camera(pose_to_matrix(poses[s, i]), cam.extrinsics)
                    gts.append({"obj_id": i + 1, "cam_R_m2c": _row_major(rot), "cam_t_m2c": _row_major(t)})
                scene_gt[str(s)] = gts
                scene, ids = renderer.scene(poses[s])
                rendered = renderer.render_camera(scene, ids, name)
                depth = capture.depth(s, name)
                agree = (depth > 0) & (np.abs(depth - rendered.depth) < MASK_DEPTH_TOLERANCE)
                for i in range(n):
                    visible = (agree & (rendered.mask == i + 1)).astype(np.uint8) * 255
                    (root / "mask_visib" / f"{s:06d}_{i:06d}.png").write_bytes(_png(visible))
            (root / "scene_camera.json").write_text(json.dumps(scene_camera, indent=1))
            (root / "scene_gt.json").write_text(json.dumps(scene_gt, indent=1))
        progress = session.progress()
        marker = {"format": "bop", "capture": capture.name, "scenes": {k: {"camera": v} for k, v in scenes.items()},
                  "im_id": "step (0..T)", "objects": {str(i + 1): capture.objects[i].name for i in range(n)},
                  "units": "mm", "status": [[o["status"] for o in st["objects"]] for st in progress["steps"]],
                  "unchecked_allowed": bool(allow_unchecked and session.unchecked())}
        (tmp / MARKER).write_text(json.dumps(marker, indent=1))
    return out
