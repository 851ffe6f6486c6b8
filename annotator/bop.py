"""Annotated poses -> a BOP dataset (the format of the BOP toolkit's docs/bop_datasets_format.md), beside the DSR
sequence export (`annotator.export`): `dsr-bench annotate CAPTURE --bop DIR`.

DIR is one BOP dataset of one split, `test`, holding one scene per camera of the capture, numbered in the capture's
camera order (`test/000000` the front camera, `test/000001` the back one; `DIR/dsr_bop.json` names them); the image
id of a scene is the step (0..T). Units: millimetres and pixels; rotations row-major.

- `DIR/camera.json`: the front camera's `fx`, `fy`, `cx`, `cy` (pixels), `width`, `height` and `depth_scale` (mm per
  depth unit); each image's own camera is in its scene's scene_camera.json;
- `DIR/models/obj_{obj_id:06d}.ply`: the meshes in millimetres, ASCII PLY with vertex normals, each moved so that
  its origin is the centre of its 3D bounding box (BOP's model frame; the poses are moved with them, so the scene is
  unchanged: `dsr_bop.json`'s `model_offset_mm` is where that centre was in the DSR mesh's frame);
- `DIR/models/models_info.json`: per obj_id `diameter` (the largest distance between two vertices), `min_x`,
  `min_y`, `min_z` and `size_x`, `size_y`, `size_z` (the 3D bounding box), and where the mesh has them,
  `symmetries_discrete` (4x4 model -> model transforms, row-major 16 numbers, translation in mm) and
  `symmetries_continuous` ([{axis, offset}]: a rotation by any angle about `axis` through the point `offset`, mm),
  found on the mesh (`annotator.symmetry.find_symmetries`, 1 mm tolerance);
- `DIR/test/<scene>/rgb/{im_id:06d}.png`, `depth/{im_id:06d}.png`: the capture's own images, byte for byte;
- `<scene>/scene_camera.json`: per image id `cam_K` (3x3 row-major), `depth_scale` (mm per depth unit) and the
  camera's pose `cam_R_w2c` (row-major 9) / `cam_t_w2c` (mm): table frame -> camera;
- `<scene>/scene_gt.json`: per image id a list of {obj_id, cam_R_m2c (row-major 9), cam_t_m2c (mm)}, one per object
  in object order (gt_idx = object index, obj_id = object number from 1), model -> camera: a model point X (mm) is
  at R X + t in the camera's OpenCV frame (x right, y down, z forward) and projects to K (R X + t);
- `<scene>/scene_gt_info.json`: per image id and gt_idx `bbox_obj`, `bbox_visib`, `px_count_all`,
  `px_count_valid`, `px_count_visib` and `visib_fract`, from the object rendered alone at its pose
  (`gt_info`, as the toolkit's calc_gt_info defines them);
- `<scene>/mask/{im_id:06d}_{gt_idx:06d}.png`: 255 on the object's silhouette in the image, `mask_visib/...`: 255 on
  its visible part (`gt_info`), else 0;
- `DIR/test_targets_bop19.json`: [{scene_id, im_id, obj_id, inst_count 1}] for every object visible in an image;
- `DIR/dsr_bop.json`: the capture, the scenes' cameras, the object names by obj_id, the model offsets, the found
  symmetries' errors, the annotation's statuses.
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
#: The split the scenes are written to.
SPLIT = "test"
#: Visibility tolerance (mm) of `gt_info`: BOP's delta for its real datasets (15 mm; calc_gt_info).
VISIBILITY_DELTA_MM = 15.0


def _png(array: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def _row_major(m: np.ndarray) -> list[float]:
    return [float(x) + 0.0 for x in np.asarray(m, dtype=np.float64).reshape(-1)]  # + 0.0: no -0.0


def model_to_camera(pose_matrix: np.ndarray, camera_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R (3, 3), t (3,) mm) of BOP's cam_R_m2c / cam_t_m2c: object -> table (4x4, m) then table -> camera."""
    w2c = np.linalg.inv(np.asarray(camera_to_world, dtype=np.float64))
    m2c = w2c @ np.asarray(pose_matrix, dtype=np.float64)
    return m2c[:3, :3], m2c[:3, 3] * 1000.0


def bbox_centre(vertices: np.ndarray) -> np.ndarray:
    """Centre (3,) of the axis-aligned 3D bounding box of vertices (V, 3), their units: BOP's model origin."""
    v = np.asarray(vertices, dtype=np.float64)
    return (v.min(axis=0) + v.max(axis=0)) / 2.0


def diameter(vertices: np.ndarray) -> float:
    """The largest distance between two of the vertices (V, 3), their units (over the convex hull's vertices)."""
    v = np.asarray(vertices, dtype=np.float64)
    try:
        from scipy.spatial import ConvexHull

        v = v[ConvexHull(v).vertices]
    except Exception:  # noqa: BLE001 - flat or degenerate: every vertex (QhullError has no stable import path)
        pass
    best = 0.0
    for start in range(0, len(v), 2048):  # (chunk, V) distances at a time
        d = np.linalg.norm(v[start:start + 2048, None, :] - v[None, :, :], axis=-1)
        best = max(best, float(d.max()))
    return best


def model_info(vertices_mm: np.ndarray, faces: np.ndarray) -> tuple[dict, dict]:
    """BOP's models_info entry of a model whose origin is its bounding-box centre (vertices (V, 3) mm): diameter,
    min / size per axis and the symmetries found (`annotator.symmetry`); and what the symmetry search measured
    (largest surface distance per transform, mm) for dsr_bop.json."""
    from dsr_bench.annotator.symmetry import TOLERANCE_MM, find_symmetries

    v = np.asarray(vertices_mm, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    info: dict = {"diameter": diameter(v)}
    for k, axis in enumerate("xyz"):
        info[f"min_{axis}"] = float(lo[k])
    for k, axis in enumerate("xyz"):
        info[f"size_{axis}"] = float(hi[k] - lo[k])
    sym = find_symmetries(v, faces, TOLERANCE_MM)
    if sym.discrete:
        info["symmetries_discrete"] = [_row_major(np.round(m, 12)) for m in sym.discrete]
    if sym.continuous:
        info["symmetries_continuous"] = [{"axis": _row_major(a), "offset": _row_major(np.round(o, 12))}
                                         for a, o in sym.continuous]
    found = {"tolerance_mm": TOLERANCE_MM, "discrete_max_mm": [round(e, 4) for e in sym.discrete_errors],
             "continuous_max_mm": [round(e, 4) for e in sym.continuous_errors]}
    return info, found


def _silhouette(vertices_mm: np.ndarray, faces: np.ndarray, rot: np.ndarray, t_mm: np.ndarray, k: np.ndarray,
                width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The model alone at (rot, t_mm) seen by intrinsics `k` over the image and one image size beyond it on every
    side (BOP renders three times the image to count the silhouette that leaves it): pixel columns (M,), rows (M,)
    (image pixel coordinates, negative or past the image where outside) and z-depth (M,) mm of its pixels."""
    from dsr_bench.render import raster

    cam = np.asarray(vertices_mm, dtype=np.float64) @ np.asarray(rot).T + np.asarray(t_mm)
    z = cam[:, 2]
    front = z > 1.0  # mm; a face with a vertex behind the camera is left out (as the renderer's near plane)
    uv = np.full((len(cam), 2), np.nan)
    uv[front] = cam[front, :2] / z[front, None] * np.array([k[0, 0], k[1, 1]]) + np.array([k[0, 2], k[1, 2]])
    if not front.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    lo = np.maximum(np.floor(np.nanmin(uv, axis=0)), [-width, -height]).astype(np.int64)
    hi = np.minimum(np.ceil(np.nanmax(uv, axis=0)), [2 * width - 1, 2 * height - 1]).astype(np.int64)
    if np.any(hi < lo):
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    w, h = int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)
    fragments = raster.rasterize(uv - lo, np.asarray(faces, np.int64), h, w)
    depth = raster.perspective_depth(fragments, np.asarray(faces, np.int64), np.where(front, z, 1.0))
    nearest, _ = raster.nearest(fragments, depth, h * w)
    on = np.flatnonzero(np.isfinite(nearest))
    return on % w + lo[0], on // w + lo[1], nearest[on]


def _bbox(cols: np.ndarray, rows: np.ndarray) -> list[int]:
    """(x, y, width, height) of pixels, width = last column - first (the toolkit's calc_2d_bbox); -1s if none."""
    if len(cols) == 0:
        return [-1, -1, -1, -1]
    x0, y0 = int(cols.min()), int(rows.min())
    return [x0, y0, int(cols.max()) - x0, int(rows.max()) - y0]


def gt_info(vertices_mm: np.ndarray, faces: np.ndarray, rot: np.ndarray, t_mm: np.ndarray, k: np.ndarray,
            depth_mm: np.ndarray, delta_mm: float = VISIBILITY_DELTA_MM) -> tuple[dict, np.ndarray, np.ndarray]:
    """scene_gt_info's entry of one object at (rot (3, 3), t_mm (3,)) in an image of intrinsics `k` and measured
    depth `depth_mm` (H, W) (0 = no measurement), as the BOP format defines it (the toolkit's calc_gt_info, 'bop19'
    visibility): the model is rendered alone; `px_count_all` counts its silhouette (also beyond the image, up to one
    image size on each side), `px_count_valid` its pixels in the image with a measured depth, `px_count_visib` its
    visible pixels: in the image, where the measured distance from the camera centre is no more than `delta_mm`
    nearer than the model's or there is no measurement; `visib_fract` = visib / all (0 when all is 0); `bbox_obj`
    the silhouette's box (not clipped to the image), `bbox_visib` the visible part's. Returns (the entry, silhouette
    mask (H, W) bool, visible mask (H, W) bool)."""
    height, width = depth_mm.shape
    cols, rows, z = _silhouette(vertices_mm, faces, rot, t_mm, k, width, height)
    inside = (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
    c, r, z_in = cols[inside], rows[inside], z[inside]
    measured = np.asarray(depth_mm, dtype=np.float64)[r, c]
    ray = np.sqrt(1.0 + ((c - k[0, 2]) / k[0, 0]) ** 2 + ((r - k[1, 2]) / k[1, 1]) ** 2)  # distance per unit z
    visible = (measured == 0) | (z_in * ray - measured * ray <= delta_mm)
    silhouette = np.zeros((height, width), bool)
    silhouette[r, c] = True
    visib = np.zeros((height, width), bool)
    visib[r[visible], c[visible]] = True
    px_all, px_visib = int(len(cols)), int(visible.sum())
    entry = {"bbox_obj": _bbox(cols, rows), "bbox_visib": _bbox(c[visible], r[visible]), "px_count_all": px_all,
             "px_count_valid": int((measured > 0).sum()), "px_count_visib": px_visib,
             "visib_fract": float(px_visib / px_all) if px_all else 0.0}
    return entry, silhouette, visib


def _write_ply(path: Path, vertices_mm: np.ndarray, faces: np.ndarray) -> None:
    import trimesh
    from trimesh.exchange.ply import export_ply

    mesh = trimesh.Trimesh(vertices_mm, faces, process=False)
    path.write_bytes(export_ply(mesh, encoding="ascii", vertex_normal=True))


def export_bop(session, out: str | Path, allow_unchecked: bool = False) -> Path:
    """Write the session's annotation as a BOP dataset at directory `out` (see the module docstring), atomically
    (a finished export replaces an earlier one; a directory holding anything else is refused). The same poses are
    refused as by the DSR export (`annotator.export.check_exportable`). Returns `out`."""
    from PIL import Image

    from dsr_bench.annotator.export import check_exportable
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
    names = list(capture.cameras)
    scenes = {f"{k:06d}": name for k, name in enumerate(names)}
    meshes = [capture.mesh(i) for i in range(n)]
    offsets = [bbox_centre(v) for v, _ in meshes]  # m, in the DSR mesh's frame
    # the model vertices as the PLY stores them (float32), so that models_info holds what a reader computes
    models = [(((np.asarray(v, np.float64) - c) * 1000.0).astype(np.float32).astype(np.float64),
               np.asarray(f, np.int64)) for (v, f), c in zip(meshes, offsets)]
    shift = []  # DSR pose (object -> table) @ shift = BOP model -> table
    for c in offsets:
        m = np.eye(4)
        m[:3, 3] = c
        shift.append(m)
    with atomic_directory(out) as tmp:
        (tmp / "models").mkdir()
        infos, found = {}, {}
        for i, (v_mm, f) in enumerate(models):
            _write_ply(tmp / "models" / f"obj_{i + 1:06d}.ply", v_mm, f)
            infos[str(i + 1)], found[str(i + 1)] = model_info(v_mm, f)
        (tmp / "models" / "models_info.json").write_text(json.dumps(infos, indent=1))
        front = capture.cameras[names[0]]
        k0 = np.asarray(front.intrinsics, np.float64)
        (tmp / "camera.json").write_text(json.dumps(
            {"cx": float(k0[0, 2]), "cy": float(k0[1, 2]), "fx": float(k0[0, 0]), "fy": float(k0[1, 1]),
             "width": int(front.width), "height": int(front.height), "depth_scale": float(front.depth_scale) * 1000},
            indent=1))
        targets = []
        for scene_id, name in scenes.items():
            cam = capture.cameras[name]
            k = np.asarray(cam.intrinsics, np.float64)
            scale_mm = float(cam.depth_scale) * 1000
            root = tmp / SPLIT / scene_id
            for sub in ("rgb", "depth", "mask", "mask_visib"):
                (root / sub).mkdir(parents=True)
            w2c = np.linalg.inv(cam.extrinsics)
            scene_camera, scene_gt, scene_info = {}, {}, {}
            for s in range(steps + 1):
                depth_path = capture.image_path(s, name, "depth")
                shutil.copyfile(capture.image_path(s, name, "color"), root / "rgb" / f"{s:06d}.png")
                shutil.copyfile(depth_path, root / "depth" / f"{s:06d}.png")
                with Image.open(depth_path) as im:
                    depth_mm = np.asarray(im, dtype=np.float64) * scale_mm
                scene_camera[str(s)] = {"cam_K": _row_major(k), "depth_scale": scale_mm,
                                        "cam_R_w2c": _row_major(w2c[:3, :3]),
                                        "cam_t_w2c": _row_major(w2c[:3, 3] * 1000)}
                gts, infos_s = [], []
                for i in range(n):
                    rot, t = model_to_camera(pose_to_matrix(poses[s, i]) @ shift[i], cam.extrinsics)
                    gts.append({"obj_id": i + 1, "cam_R_m2c": _row_major(rot), "cam_t_m2c": _row_major(t)})
                    entry, silhouette, visib = gt_info(*models[i], rot, t, k, depth_mm)
                    infos_s.append(entry)
                    (root / "mask" / f"{s:06d}_{i:06d}.png").write_bytes(_png(silhouette.astype(np.uint8) * 255))
                    (root / "mask_visib" / f"{s:06d}_{i:06d}.png").write_bytes(_png(visib.astype(np.uint8) * 255))
                    if entry["px_count_visib"] > 0:
                        targets.append({"im_id": s, "inst_count": 1, "obj_id": i + 1, "scene_id": int(scene_id)})
                scene_gt[str(s)], scene_info[str(s)] = gts, infos_s
            (root / "scene_camera.json").write_text(json.dumps(scene_camera, indent=1))
            (root / "scene_gt.json").write_text(json.dumps(scene_gt, indent=1))
            (root / "scene_gt_info.json").write_text(json.dumps(scene_info, indent=1))
        (tmp / "test_targets_bop19.json").write_text(json.dumps(targets, indent=1))
        progress = session.progress()
        marker = {"format": "bop", "split": SPLIT, "capture": capture.name,
                  "scenes": {k: {"camera": v} for k, v in scenes.items()}, "im_id": "step (0..T)",
                  "objects": {str(i + 1): capture.objects[i].name for i in range(n)}, "units": "mm",
                  "model_offset_mm": {str(i + 1): _row_major(c * 1000.0) for i, c in enumerate(offsets)},
                  "symmetry_search": found, "visibility_delta_mm": VISIBILITY_DELTA_MM,
                  "status": [[o["status"] for o in st["objects"]] for st in progress["steps"]],
                  "unchecked_allowed": bool(allow_unchecked and session.unchecked())}
        (tmp / MARKER).write_text(json.dumps(marker, indent=1))
    return out
