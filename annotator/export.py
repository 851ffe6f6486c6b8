"""Annotated poses -> a sequence file in the generator's format (`dsr_bench.dataset.schema`), with provenance.

From the capture's front camera: colour, depth and world points at the benchmark's image size (IMAGE_SHAPE,
`stored_camera`), and the TSDF of its full-resolution depth image; from the poses and
meshes: amodal `mask_3d` (voxel centres inside each mesh's solid, `dsr_bench.render.SceneRenderer.amodal_mask`),
`scene_flow_3d` and `scene_flow_2d` (`dsr_bench.geometry.groundtruth`), the heightmap of the posed meshes, the
front view's visible instance mask (rendered ids where the measured depth agrees) and visible fractions. Actions and
pushes come from the capture. Attributes carry "source": "annotated" and an "annotation" record: annotator and state
versions, capture name and provenance, per-step/object status and fit scores, user action counts.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np

from dsr_bench.errors import UserError

#: A rendered object pixel is kept in the visible mask when the measured depth is within this (m) of the render.
MASK_DEPTH_TOLERANCE = 0.015
#: Version of the export's provenance record.
ANNOTATOR_VERSION = "1"


def _parts(vertices: np.ndarray, faces: np.ndarray) -> list:
    """Closed connected components of a mesh as renderer parts (occupancy needs each part closed on its own)."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    pieces = mesh.split(only_watertight=False) if len(faces) else [mesh]
    if len(pieces) <= 1:
        return [SimpleNamespace(vertices=np.asarray(vertices, np.float64), faces=np.asarray(faces, np.int64))]
    return [SimpleNamespace(vertices=np.asarray(p.vertices, np.float64), faces=np.asarray(p.faces, np.int64))
            for p in pieces]


def _renderer(capture, front):
    """A SceneRenderer of the capture's meshes whose 'front' camera is the capture's calibrated front camera."""
    return renderer_for(capture, {"front": front})


def renderer_for(capture, cameras: dict):
    """A SceneRenderer of the capture's meshes with the given cameras {name: Camera}."""
    from dsr_bench.render import create_renderer

    objects = []
    for i, obj in enumerate(capture.objects):
        color = obj.identity.get("color", (0.6, 0.6, 0.6))
        objects.append(SimpleNamespace(parts=_parts(*capture.mesh(i)), color=tuple(float(c) for c in color)))
    return create_renderer(objects, cameras=dict(cameras))


def stored_camera(camera, shape: tuple[int, int]):
    """The camera of the stored 2D data (H', W') = `shape` and the full-resolution pixel each stored pixel takes.

    Focal lengths and principal point scale by W'/W and H'/H (`dsr_bench.geometry.resized_camera`), so stored
    pixel (u', v') looks along the ray of full-resolution pixel (u' W / W', v' H / H') (exactly for integer ratios,
    e.g. 480 x 640 -> 240 x 320; to the nearest pixel otherwise). Returns (Camera, rows (H',) int, cols (W',) int).
    """
    from dsr_bench.geometry import resized_camera

    h, w = shape
    sx, sy = w / camera.width, h / camera.height
    rows = np.clip(np.rint(np.arange(h) / sy).astype(np.int64), 0, camera.height - 1)
    cols = np.clip(np.rint(np.arange(w) / sx).astype(np.int64), 0, camera.width - 1)
    return resized_camera(camera, h, w), rows, cols


def _identity(capture, i: int) -> dict:
    from dsr_bench.dataset.manifest import mesh_sha256

    ident = dict(capture.objects[i].identity)
    ident.update({"name": capture.objects[i].name, "mesh_file": capture.objects[i].mesh_path.name,
                  "mesh_sha256": mesh_sha256(*capture.mesh(i))})
    return ident


def check_exportable(session, allow_unchecked: bool) -> list[tuple[int, int, str]]:
    """The unchecked (step, object, status) of a session; UserError while any pose is unset, or while any is not
    snapped or confirmed unless `allow_unchecked`."""
    capture = session.capture
    bad = session.unchecked()
    unset = [(s, i) for s, i, st in bad if st == "unset"]
    if unset:
        listed = ", ".join(f"step {s} object {i + 1}" for s, i in unset[:6]) + (" ..." if len(unset) > 6 else "")
        raise UserError(f"cannot export {capture.name}: {len(unset)} objects have no pose ({listed}); annotate them "
                        "(or run `dsr-bench annotate CAPTURE --auto` once step 0 is placed)")
    if bad and not allow_unchecked:
        listed = ", ".join(f"step {s} object {i + 1} ({st})" for s, i, st in bad[:6]) + (" ..." if len(bad) > 6 else "")
        raise UserError(f"cannot export {capture.name}: {len(bad)} poses are neither snapped nor confirmed ({listed}); "
                        "snap or confirm them, or pass --allow-unchecked")
    return bad


def export_sequence(session, out: str | Path, allow_unchecked: bool = False) -> Path:
    """Write the session's annotation as a sequence file at `out` (.h5), atomically; returns the path.

    Refuses (UserError listing them) while any object at any step is not 'snapped' or 'confirmed', unless
    `allow_unchecked` (objects still 'unset' are refused always: they have no pose). The file is written under a
    temporary name and checked as `dsr-bench validate` checks it (`validate_sequence`); a file that fails is
    removed and refused (UserError naming the first problem) unless `allow_unchecked`: confirmed poses can still
    be wrong (two objects in one place leave one of them without voxels).
    """
    from dsr_bench.constants import GRID_SHAPE, IMAGE_SHAPE
    from dsr_bench.dataset.schema import sequence_header
    from dsr_bench.geometry.groundtruth import rigid_scene_flow_2d, rigid_scene_flow_3d
    from dsr_bench.geometry.tsdf import ProjectiveTSDF
    from dsr_bench.annotator.state import STATE_VERSION

    out = Path(out)
    if out.suffix != ".h5":
        raise UserError(f"--export {out}: the sequence file must end in .h5")
    capture = session.capture
    bad = check_exportable(session, allow_unchecked)

    steps, n = capture.num_steps, capture.num_objects
    poses = np.stack([session.poses(s) for s in range(steps + 1)]).astype(np.float64)
    poses[..., 3:] /= np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True)
    full = capture.cameras["front"].camera
    front, rows, cols = stored_camera(full, IMAGE_SHAPE)
    renderer = _renderer(capture, front)
    tsdf_of = ProjectiveTSDF(full)  # the TSDF from the full-resolution depth image
    arrays: dict[str, np.ndarray] = {
        "tsdf": np.zeros((steps + 1,) + GRID_SHAPE, np.float32),
        "mask_3d": np.zeros((steps + 1,) + GRID_SHAPE, np.uint8),
        "heightmap": np.zeros((steps + 1,) + GRID_SHAPE[:2], np.float32),
        "visible_fraction": np.zeros((steps + 1, n), np.float32),
        "object_poses": poses,
        "scene_flow_3d": np.zeros((steps, 3) + GRID_SHAPE, np.float32),
        "action": np.asarray(capture.actions, np.int64).reshape(steps, 3),
        "push_start": np.asarray(capture.pushes_world[:, 0], np.float64).reshape(steps, 3),
        "push_end": np.asarray(capture.pushes_world[:, 1], np.float64).reshape(steps, 3),
    }
    h, w = front.height, front.width
    colors, depths, masks, points = [], [], [], []
    for s in range(steps + 1):
        depth_full = capture.depth(s, "front")
        arrays["tsdf"][s] = tsdf_of(depth_full)
        depth = depth_full[np.ix_(rows, cols)]
        pts = capture.points(s, "front", depth_full)[np.ix_(rows, cols)]
        arrays["mask_3d"][s] = renderer.amodal_mask(poses[s])
        scene, ids = renderer.scene(poses[s])
        arrays["heightmap"][s] = renderer.heightmap(scene)
        rendered = renderer.render_camera(scene, ids, "front")
        agree = (depth > 0) & (np.abs(depth - rendered.depth) < MASK_DEPTH_TOLERANCE)
        mask = np.where(agree, rendered.mask, 0).astype(np.uint8)
        arrays["visible_fraction"][s] = renderer.visible_fraction(poses[s], mask)
        colors.append(capture.color(s, "front")[np.ix_(rows, cols)])
        depths.append(depth.astype(np.float32))
        masks.append(mask)
        points.append(pts.astype(np.float32))
    for t in range(steps):
        rigid_scene_flow_3d(arrays["mask_3d"][t], poses[t], poses[t + 1], out=arrays["scene_flow_3d"][t])
    arrays["cameras/front/color"] = np.stack(colors)
    arrays["cameras/front/depth"] = np.stack(depths)
    arrays["cameras/front/mask"] = np.stack(masks)
    arrays["cameras/front/points"] = np.stack(points).reshape(steps + 1, h, w, 3)
    arrays["cameras/front/scene_flow_2d"] = np.stack(
        [rigid_scene_flow_2d(points[t], masks[t], poses[t], poses[t + 1]) for t in range(steps)]).reshape(
        steps, h, w, 3).astype(np.float32)

    identities = [_identity(capture, i) for i in range(n)]
    sets = {str(o.get("set", "")) for o in identities}
    progress = session.progress()
    annotation = {
        "annotator_version": ANNOTATOR_VERSION, "state_version": STATE_VERSION, "capture": capture.name,
        "capture_source": capture.source,
        "status": [[o["status"] for o in st["objects"]] for st in progress["steps"]],
        "fit_scores": [[o["score"] for o in st["objects"]] for st in progress["steps"]],
        "action_counts": session.action_counts, "unchecked_allowed": bool(allow_unchecked and bad),
        "calibration": {name: cam.as_json() for name, cam in capture.cameras.items()},
    }
    attrs = sequence_header(
        sequence=capture.name, seed=-1, num_steps=steps, num_objects=n,
        object_set=sets.pop() if len(sets) == 1 and "" not in sets else "annotated",
        policy=str(capture.source.get("policy", "recorded")),
        generator_args={"annotator": ANNOTATOR_VERSION, "capture": capture.name}, source="annotated",
        objects=identities, cameras={"front": front},
        tsdf_image_shape=[full.height, full.width], annotation=annotation,
        mesh_frames="capture mesh frames; poses map object frame -> world (table) frame",
    )
    meshes = {i: capture.mesh(i) for i in range(n)}
    return _write_checked(out, arrays, attrs, meshes, capture.name, allow_unchecked)


def _write_checked(out: Path, arrays: dict, attrs: dict, meshes: dict, name: str, allow_unchecked: bool) -> Path:
    """Write the sequence under a temporary name next to `out`, run `validate_sequence` on it, and rename it to
    `out`, or remove it and raise UserError when it fails validation (unless `allow_unchecked`)."""
    import os

    from dsr_bench.dataset.sequence import write_sequence
    from dsr_bench.dataset.validate import validate_sequence

    tmp = out.with_name(f".{out.stem}.{os.getpid()}.checking.h5")
    try:
        write_sequence(tmp, arrays, attrs, meshes)
        problems = validate_sequence(tmp)
        if problems and not allow_unchecked:
            more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
            raise UserError(f"cannot export {name}: the sequence fails `dsr-bench validate`: {problems[0]}{more}; fix "
                            "the poses of the step and object it names (`dsr-bench annotate` shows them), or pass "
                            "--allow-unchecked to write it anyway")
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return out
