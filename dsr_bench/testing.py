"""Small, exactly consistent synthetic sequences for tests (numpy + h5py only, no simulator).

Boxes slide and turn on the table; every array is derived from their poses with the same
definitions the generator uses (analytic ray casting for images, solid occupancy for `mask_3d`,
`dsr_bench.geometry.groundtruth` for flow, `dsr_bench.geometry.tsdf` for the TSDF). Use it to test readers, metrics,
models and viewers without pybullet.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dsr_bench.constants import GRID_SHAPE, IMAGE_SHAPE, VOXEL_SIZE
from dsr_bench.dataset.schema import sequence_header
from dsr_bench.geometry import make_camera, pixel_to_world, pose_to_matrix, voxel_points, world_to_pixel
from dsr_bench.geometry.groundtruth import rigid_scene_flow_2d, rigid_scene_flow_3d
from dsr_bench.dataset.sequence import write_sequence
from dsr_bench.geometry.tsdf import integrate_tsdf

_COLORS = np.array([[230, 60, 60], [60, 180, 75], [60, 100, 230], [240, 200, 40], [160, 80, 200]], np.uint8)


def _box_mesh(half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float) * half
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return corners, faces


def _raycast_boxes(origins: np.ndarray, dirs: np.ndarray, poses: np.ndarray, halves: np.ndarray):
    """Hit distance t (along dirs) and instance id (0 = table, -1 = none) for rays (M, 3)."""
    best_t = np.full(origins.shape[0], np.inf)
    best_id = np.full(origins.shape[0], -1, dtype=np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_table = np.where(dirs[:, 2] < 0, -origins[:, 2] / dirs[:, 2], np.inf)
    best_t, best_id = np.where(t_table < best_t, t_table, best_t), np.where(t_table < best_t, 0, best_id)
    for i, (pose, half) in enumerate(zip(poses, halves)):
        inv = np.linalg.inv(pose_to_matrix(pose))
        o = origins @ inv[:3, :3].T + inv[:3, 3]
        d = dirs @ inv[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-half - o) / d, (half - o) / d
        tmin = np.nanmax(np.minimum(t1, t2), axis=1)
        tmax = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (tmax >= tmin) & (tmin > 0) & (tmin < best_t)
        best_t[hit], best_id[hit] = tmin[hit], i + 1
    return best_t, best_id


def _render(camera, poses, halves):
    dirs = camera.ray_directions_world().reshape(-1, 3)
    origins = np.broadcast_to(camera.extrinsics[:3, 3], dirs.shape)
    t, ids = _raycast_boxes(origins, dirs, poses, halves)
    valid = np.isfinite(t)
    depth = np.where(valid, t, 0.0).reshape(camera.height, camera.width).astype(np.float32)
    mask = np.where(ids > 0, ids, 0).reshape(camera.height, camera.width).astype(np.uint8)
    points = np.where(valid[:, None], origins + dirs * np.where(valid, t, 0)[:, None], np.nan)
    color = np.where(mask[..., None] > 0, _COLORS[np.maximum(mask, 1) - 1], np.uint8(200)).astype(np.uint8)
    return depth, mask, points.reshape(camera.height, camera.width, 3).astype(np.float32), color


def _amodal_mask(poses: np.ndarray, halves: np.ndarray, centers: np.ndarray) -> np.ndarray:
    mask = np.zeros(centers.shape[:-1], dtype=np.uint8)
    for i, (pose, half) in enumerate(zip(poses, halves)):
        inv = np.linalg.inv(pose_to_matrix(pose))
        local = centers @ inv[:3, :3].T + inv[:3, 3]
        mask[np.all(np.abs(local) <= half, axis=-1) & (mask == 0)] = i + 1
    return mask


def _yaw_quat(yaw: float) -> np.ndarray:
    return np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])


def synthetic_arrays(num_steps: int = 3, num_objects: int = 2, seed: int = 0):
    """Arrays, attributes and meshes of a synthetic box sequence, ready for `write_sequence`."""
    rng = np.random.default_rng(seed)
    halves = rng.uniform([0.02, 0.02, 0.025], [0.035, 0.035, 0.04], size=(num_objects, 3))
    poses = np.zeros((num_steps + 1, num_objects, 7))
    xy = np.stack([np.linspace(0.40, 0.60, num_objects), rng.uniform(-0.08, 0.08, num_objects)], axis=1)
    yaw = rng.uniform(-np.pi, np.pi, num_objects)
    actions = np.zeros((num_steps, 3), dtype=np.int64)
    push_start, push_end = np.zeros((num_steps, 3)), np.zeros((num_steps, 3))
    chosen = np.zeros(num_steps, dtype=np.int64)
    for t in range(num_steps + 1):
        poses[t, :, :2], poses[t, :, 2] = xy, halves[:, 2]
        poses[t, :, 3:] = np.stack([_yaw_quat(a) for a in yaw])
        if t == num_steps:
            break
        k, d = t % num_objects, int(rng.integers(0, 8))
        direction = np.array([np.cos(d * np.pi / 4), np.sin(d * np.pi / 4)])
        start = xy[k] - direction * (halves[k, :2].max() * 1.5 + 0.01)
        actions[t] = [d, *world_to_pixel(start)]
        push_start[t] = [*pixel_to_world(actions[t, 1:]), 0.005]
        push_end[t] = push_start[t] + np.r_[direction * 0.15, 0.0]
        chosen[t] = k
        xy = xy.copy()
        xy[k] = xy[k] + direction * 0.03
        yaw = yaw.copy()
        yaw[k] += 0.2
    front = make_camera("front", *IMAGE_SHAPE)
    tsdf_camera = make_camera("front", 2 * IMAGE_SHAPE[0], 2 * IMAGE_SHAPE[1])
    centers = voxel_points(GRID_SHAPE)
    images = [_render(front, poses[t], halves) for t in range(num_steps + 1)]
    masks = np.stack([_amodal_mask(poses[t], halves, centers) for t in range(num_steps + 1)])
    tsdf = np.stack([integrate_tsdf(_render(tsdf_camera, poses[t], halves)[0], tsdf_camera)
                     for t in range(num_steps + 1)])
    flow3d = np.stack([rigid_scene_flow_3d(masks[t], poses[t], poses[t + 1]) for t in range(num_steps)])
    points = np.stack([im[2] for im in images])
    mask2d = np.stack([im[1] for im in images])
    flow2d = np.stack([rigid_scene_flow_2d(points[t], mask2d[t], poses[t], poses[t + 1]) for t in range(num_steps)])
    visible = np.zeros((num_steps + 1, num_objects), dtype=np.float32)
    for t in range(num_steps + 1):
        for i in range(num_objects):
            alone = _render(front, poses[t, i:i + 1], halves[i:i + 1])[1] > 0
            visible[t, i] = (mask2d[t] == i + 1).sum() / max(alone.sum(), 1)
    heightmap = np.zeros((num_steps + 1,) + GRID_SHAPE[:2], dtype=np.float32)
    for t in range(num_steps + 1):
        occupied = masks[t] > 0
        top = np.where(occupied.any(-1), (GRID_SHAPE[2] - np.argmax(occupied[..., ::-1], -1)) * VOXEL_SIZE, 0.0)
        heightmap[t] = top
    probs = np.full((num_steps, num_objects), 1.0 / num_objects, np.float32)
    arrays = {
        "tsdf": tsdf, "mask_3d": masks, "scene_flow_3d": flow3d, "action": actions,
        "push_start": push_start, "push_end": push_end, "object_poses": poses,
        "visible_fraction": visible, "heightmap": heightmap,
        "cameras/front/color": np.stack([im[3] for im in images]),
        "cameras/front/depth": np.stack([im[0] for im in images]),
        "cameras/front/mask": mask2d, "cameras/front/points": points, "cameras/front/scene_flow_2d": flow2d,
        "policy/chosen_object": chosen, "policy/object_probs": probs,
        "policy/direction_scores": np.full((num_steps, 8), np.nan, np.float32),
        "policy/direction_probs": np.full((num_steps, 8), 1 / 8, np.float32),
        "policy/attempts": np.ones(num_steps, dtype=np.int64),
    }
    objects = [{"set": "synthetic", "category": "box", "model_id": f"box_{i}", "scale": 1.0,
                "mesh_sha256": "", "half_extents": halves[i].tolist()} for i in range(num_objects)]
    attrs = sequence_header(
        sequence=f"synthetic_{seed:04d}", seed=seed, num_steps=num_steps, num_objects=num_objects,
        object_set="synthetic", policy="scripted", generator_args={"seed": seed, "steps": num_steps},
        source="synthetic", objects=objects, cameras={"front": front},
    )
    meshes = {i: _box_mesh(halves[i]) for i in range(num_objects)}
    return arrays, attrs, meshes


def write_synthetic_sequence(path: str | Path, num_steps: int = 3, num_objects: int = 2, seed: int = 0) -> Path:
    """Write a synthetic box sequence to `path` (an .h5 file) and return the path."""
    arrays, attrs, meshes = synthetic_arrays(num_steps, num_objects, seed)
    attrs["sequence"] = Path(path).stem
    return write_sequence(path, arrays, attrs, meshes)


def write_synthetic_dataset(data_dir: str | Path, num_sequences: int = 2, num_steps: int = 3, num_objects: int = 2,
                            split: str = "test") -> Path:
    """A dataset directory of synthetic sequences with splits/<split>.txt and manifest.json."""
    from dsr_bench.dataset.manifest import build_manifest, write_manifest

    data_dir = Path(data_dir)
    names = [f"seq_{i:04d}" for i in range(num_sequences)]
    for i, name in enumerate(names):
        write_synthetic_sequence(data_dir / f"{name}.h5", num_steps, num_objects, seed=i)
    (data_dir / "splits").mkdir(parents=True, exist_ok=True)
    (data_dir / "splits" / f"{split}.txt").write_text("".join(f"{n}\n" for n in names))
    write_manifest(data_dir, build_manifest(data_dir))
    return data_dir
