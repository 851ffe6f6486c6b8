"""One simulated pushing sequence: sample a scene, push T times, observe T + 1 times.

simulate (generators.physics) -> observe (dsr_bench.render) -> arrays in the sequence schema.
Everything random is drawn from one numpy Generator seeded with the sequence seed, and the world is
rebuilt for every scene attempt, so a sequence is a pure function of (arguments, sequence seed).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from dsr_bench.constants import (
    DEFAULT_OBJECTS_PER_SCENE,
    DEFAULT_STEPS,
    GRID_BOUNDS,
    GRID_SHAPE,
    MIN_LARGE_SEPARATION,
    MIN_OBJECT_SEPARATION,
    MIN_VISIBLE_FRACTION,
    TSDF_IMAGE_SHAPE,
    WORKSPACE_CENTER,
)
from dsr_bench.dataset.schema import sequence_header
from dsr_bench.geometry import pose_to_matrix, transform_points, world_to_pixel
from dsr_bench.geometry.groundtruth import rigid_scene_flow_2d, rigid_scene_flow_3d

MAX_SCENE_ATTEMPTS = 30
#: Official scene sampling: xy uniform in a square of this half size around the workspace centre (m),
#: redrawn until every pair is MIN_OBJECT_SEPARATION apart (MIN_LARGE_SEPARATION from a large
#: object), then shifted so that the mean is the centre; dropped from DROP_HEIGHT with Euler angles
#: uniform in [0, pi).
DROP_REGION_HALF = 0.13
DROP_HEIGHT = 0.2
MAX_LAYOUT_DRAWS = 10_000


class SceneRejected(Exception):
    """A sampled scene or push could not be used (resampled; never written)."""


@dataclass(frozen=True)
class EpisodeConfig:
    """Arguments that define a sequence besides its seed (all written to the file's attributes)."""

    objects: str = "procedural"
    steps: int = DEFAULT_STEPS
    objects_per_scene: int = DEFAULT_OBJECTS_PER_SCENE
    policy: str = "heuristic"
    cameras: tuple[str, ...] = ("front",)
    object_root: str | None = None
    extra: dict = field(default_factory=dict)
    #: Objects sleep through each push until touched (`generators.physics`; bulk training data only).
    sleep_at_rest: bool = False

    def as_attrs(self) -> dict:
        """The arguments as a file records them (`sleep_at_rest` only when set, so files made without it
        read as before)."""
        out = asdict(self)
        out["cameras"] = list(self.cameras)
        if not self.sleep_at_rest:
            del out["sleep_at_rest"]
        return out


@dataclass
class Episode:
    """A generated sequence, ready for `dsr_bench.dataset.sequence.write_sequence`."""

    arrays: dict[str, np.ndarray]
    attrs: dict
    meshes: dict[int, tuple[np.ndarray, np.ndarray]]
    scene_attempts: int
    timings: dict[str, float]


def _world_vertices(spec, pose: np.ndarray) -> np.ndarray:
    m = pose_to_matrix(pose)
    return transform_points(m, np.vstack([np.asarray(p.vertices) for p in spec.parts]))


def in_workspace(specs, poses: np.ndarray) -> bool:
    """Whether every object lies inside the grid (xy within bounds, above the table, under the top)."""
    for spec, pose in zip(specs, poses):
        v = _world_vertices(spec, pose)
        lo, hi = v.min(0), v.max(0)
        if np.any(lo[:2] < GRID_BOUNDS[:2, 0]) or np.any(hi[:2] > GRID_BOUNDS[:2, 1]):
            return False
        if lo[2] < -0.01 or hi[2] > GRID_BOUNDS[2, 1]:
            return False
    return True


def euler_quaternion(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Quaternion (x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll), as pybullet's getQuaternionFromEuler
    (glibc's sin and cos: the same bits on every CPU)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
                     cr * cp * cy + sr * sp * sy])


def drop_poses(rng: np.random.Generator, specs) -> np.ndarray:
    """The official scene layout: drop poses (N, 7) at DROP_HEIGHT, xy uniform in the drop square and
    redrawn together until they are apart, then centred on the workspace centre; random orientations."""
    centre = np.asarray(WORKSPACE_CENTER)
    n = len(specs)
    large = np.array([s.is_large for s in specs])
    need = np.where(large[:, None] | large[None, :], MIN_LARGE_SEPARATION, MIN_OBJECT_SEPARATION)
    for _ in range(MAX_LAYOUT_DRAWS):
        xy = centre + rng.uniform(-DROP_REGION_HALF, DROP_REGION_HALF, (n, 2))
        d = xy[:, None, :] - xy[None, :, :]
        dist = np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1])
        if np.all((dist >= need) | np.eye(n, dtype=bool)):
            break
    else:
        raise SceneRejected("could not place the objects apart")
    xy = xy - (xy.mean(axis=0) - centre)
    poses = np.zeros((n, 7))
    poses[:, :2], poses[:, 2] = xy, DROP_HEIGHT
    for i in range(n):
        poses[i, 3:] = euler_quaternion(*rng.uniform(0.0, np.pi, 3))
    return poses


def generate_episode(config: EpisodeConfig, object_set, seed: int, name: str,
                     generator_args: dict | None = None) -> Episode:
    """Simulate and observe one sequence from its seed; raise SceneRejected if no scene works. `generator_args`:
    the attribute recording what made the sequence (default `config.as_attrs()`; a run adds its seed, index and
    split: `generators.run.RunPlan.generator_args`)."""
    import time

    from dsr_bench.generators.physics import PushWorld, import_pybullet
    from dsr_bench.generators.policy import make_policy
    from dsr_bench.render import create_renderer

    rng = np.random.default_rng(seed)
    # wall seconds per phase, and process CPU seconds ("<phase>_cpu": all threads, e.g. open3d's)
    timings = {key: 0.0 for key in ("physics", "render", "policy", "physics_cpu", "render_cpu", "policy_cpu")}
    last_reason = ""
    for attempt in range(1, MAX_SCENE_ATTEMPTS + 1):
        specs = object_set.sample(rng, config.objects_per_scene)
        large = [i for i, s in enumerate(specs) if s.is_large]
        renderer = create_renderer(specs, cameras=config.cameras)
        world = PushWorld(specs, sleep_at_rest=config.sleep_at_rest)
        try:
            t0, c0 = time.perf_counter(), time.process_time()
            settled = world.drop(drop_poses(rng, specs))
            poses = [world.poses()]
            timings["physics"] += time.perf_counter() - t0
            timings["physics_cpu"] += time.process_time() - c0
            if settled < 0 or not in_workspace(specs, poses[0]):
                last_reason = "an object left the workspace while settling"
                continue
            t0, c0 = time.perf_counter(), time.process_time()
            observations = [renderer.observe(poses[0])]
            timings["render"] += time.perf_counter() - t0
            timings["render_cpu"] += time.process_time() - c0
            if observations[0].visible_fraction.min() < MIN_VISIBLE_FRACTION:
                last_reason = "an object is less than 40% visible in the front camera"
                continue
            policy = make_policy(config.policy, rng, len(specs), large[0] if large else None)
            policy.reset(poses[0][:, :2])
            decisions, pushes = [], []
            for t in range(config.steps):
                t0, c0 = time.perf_counter(), time.process_time()
                decision = policy.propose(observations[-1].heightmap, poses[-1][:, :2])
                timings["policy"] += time.perf_counter() - t0
                timings["policy_cpu"] += time.process_time() - c0
                if decision is None:
                    raise SceneRejected(f"no valid push at step {t}")
                t0, c0 = time.perf_counter(), time.process_time()
                start, end = world.push(decision.start_xy, decision.direction)
                after = world.poses()
                timings["physics"] += time.perf_counter() - t0
                timings["physics_cpu"] += time.process_time() - c0
                policy.accept(decision, after[:, :2])
                decisions.append(decision)
                pushes.append((start, end))
                poses.append(after)
                t0, c0 = time.perf_counter(), time.process_time()
                observations.append(renderer.observe(after))
                timings["render"] += time.perf_counter() - t0
                timings["render_cpu"] += time.process_time() - c0
        except SceneRejected as exc:
            last_reason = str(exc)
            continue
        finally:
            world.close()
        arrays = _assemble(observations, np.stack(poses), decisions, pushes, renderer)
        meshes = {i: spec.mesh() for i, spec in enumerate(specs)} if config.objects not in ("shapenet", "ycb") else {}
        attrs = sequence_header(
            sequence=name, seed=int(seed), num_steps=config.steps, num_objects=len(specs), object_set=config.objects,
            policy=config.policy, generator_args=config.as_attrs() if generator_args is None else generator_args,
            source="simulation", objects=[spec.identity() for spec in specs], cameras=renderer.cameras,
            versions={"pybullet_version": int(import_pybullet().getAPIVersion())},
            tsdf_image_shape=list(TSDF_IMAGE_SHAPE), scene_attempts=attempt,
            mesh_frames="object frame origin at the centre of mass; poses map object frame -> world",
        )
        return Episode(arrays, attrs, meshes, attempt, timings)
    raise SceneRejected(f"{name}: no usable scene in {MAX_SCENE_ATTEMPTS} attempts (last: {last_reason})")


def _assemble(observations, poses: np.ndarray, decisions, pushes, renderer) -> dict[str, np.ndarray]:
    """Stack per-step observations and ground truth into the schema's arrays."""
    steps = len(decisions)
    arrays: dict[str, np.ndarray] = {
        "tsdf": np.stack([o.tsdf for o in observations]),
        "mask_3d": np.stack([o.mask_3d for o in observations]),
        "heightmap": np.stack([o.heightmap for o in observations]),
        "visible_fraction": np.stack([o.visible_fraction for o in observations]).astype(np.float32),
        "object_poses": poses.astype(np.float64),
        "scene_flow_3d": np.zeros((steps, 3) + GRID_SHAPE, dtype=np.float32),
        "action": np.array([[d.direction, *d.start_rc] for d in decisions], dtype=np.int64).reshape(steps, 3),
        "push_start": np.array([p[0] for p in pushes], dtype=np.float64).reshape(steps, 3),
        "push_end": np.array([p[1] for p in pushes], dtype=np.float64).reshape(steps, 3),
        "policy/chosen_object": np.array([d.object_index for d in decisions], dtype=np.int64),
        "policy/object_probs": np.array([d.object_probs for d in decisions], dtype=np.float32),
        "policy/direction_scores": np.array([d.direction_scores for d in decisions],
                                            dtype=np.float32).reshape(steps, 8),
        "policy/direction_probs": np.array([d.direction_probs for d in decisions], dtype=np.float32).reshape(steps, 8),
        "policy/attempts": np.array([d.attempts for d in decisions], dtype=np.int64),
    }
    for t in range(steps):
        rigid_scene_flow_3d(observations[t].mask_3d, poses[t], poses[t + 1], out=arrays["scene_flow_3d"][t])
    for name in renderer.cameras:
        imgs = [o.images[name] for o in observations]
        arrays[f"cameras/{name}/color"] = np.stack([i.color for i in imgs])
        arrays[f"cameras/{name}/depth"] = np.stack([i.depth for i in imgs])
        arrays[f"cameras/{name}/mask"] = np.stack([i.mask for i in imgs])
        arrays[f"cameras/{name}/points"] = np.stack([i.points for i in imgs])
        arrays[f"cameras/{name}/scene_flow_2d"] = np.stack([
            rigid_scene_flow_2d(imgs[t].points, imgs[t].mask, poses[t], poses[t + 1]) for t in range(steps)])
    return arrays


def check_action_consistency(arrays: dict[str, np.ndarray]) -> bool:
    """Whether each stored action's (row, col) is the grid cell of its world push start."""
    cells = world_to_pixel(arrays["push_start"][:, :2])
    return bool(np.array_equal(cells, arrays["action"][:, 1:]))
