"""The plan file: one HDF5 file per task (format "dsr-bench-plan", version 1), everything a plan did.

  states/tsdf (S+1, Y, X, Z) f4          the front camera's TSDF at the start and after each push
  states/mask_3d (S+1, Y, X, Z) u1       the true amodal state (object ids) at the start and after each push
  states/object_poses (S+1, N, 7) f8     the object poses (x, y, z, qx, qy, qz, qw), world metres
  states/color (S+1, H, W, 3) u1         the front camera's image (when the world renders one)
  target/mask_3d (Y, X, Z) u1, target/object_poses (N, 7) f8   the task's target (a copy)
  actions (S, 3) i8                      the executed pushes (d, row, col)
  candidates (S, C, 3) i8, costs (S, C) f8, chosen (S,) i8      every candidate, its cost, the one executed
  clear (S, C) bool                      whether each candidate is a clear push (touches nothing seen)
  cost_position_mse (S, C, N) f8 (cm^2), cost_iou (S, C, N) f8  each candidate's terms per target object
  planner_masks (S, Y, X, Z) u1          the planner's masks of the current state (what it sampled around)
  predicted (S, Y, X, Z) u1              the executed candidate's predicted next masks
  seconds (S,) f8                        planning time per step (simulation of the push excluded)

Root attributes: format, version, task, task_file, task_ground_truth_sha256, planner, description, candidates,
seed, lambda, margin, clear (clear candidates per step), toolkit_version, and the scores
(`dsr_bench.planning.results.score_plan`): iou, iou_occupancy, iou_identity, start_iou, start_iou_identity,
start_iou_occupancy, iou_per_object (JSON), seconds. The stored scores are a record for people, never read back: a
rerun and `dsr_bench.planning.verify` recompute them from states/mask_3d[-1] and the verified task.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from dsr_bench.atomic import atomic_path
from dsr_bench.errors import UserError
from dsr_bench.planning.runner import PlanRecord
from dsr_bench.planning.tasks import Task

PLAN_FORMAT, PLAN_VERSION = "dsr-bench-plan", 1


def plan_arrays(task: Task, record: PlanRecord) -> dict[str, np.ndarray]:
    """The plan file's arrays of a record."""
    arrays: dict[str, np.ndarray] = {
        "states/tsdf": np.stack([s.tsdf for s in record.states]).astype(np.float32),
        "states/mask_3d": np.stack([s.mask_3d for s in record.states]).astype(np.uint8),
        "states/object_poses": np.stack([s.object_poses for s in record.states]).astype(np.float64),
        "target/mask_3d": task.target_mask, "target/object_poses": task.arrays["target/object_poses"],
        "actions": np.stack(record.actions).astype(np.int64),
        "candidates": _pad(record.candidates, 3, 0).astype(np.int64),
        "costs": _pad(record.costs, None, np.nan),
        "cost_position_mse": _pad(record.position_mse, task.num_objects, np.nan),
        "cost_iou": _pad(record.object_iou, task.num_objects, np.nan),
        "chosen": np.array(record.chosen, np.int64),
        "clear": _pad(record.clear, None, 0).astype(bool),
        "planner_masks": np.stack(record.planner_masks).astype(np.uint8),
        "predicted": np.stack(record.predicted).astype(np.uint8),
        "seconds": np.array(record.seconds, np.float64),
    }
    colors = [s.color for s in record.states if s.color is not None]
    if len(colors) == len(record.states):
        arrays["states/color"] = np.stack(colors).astype(np.uint8)
    return arrays


def _pad(rows: list[np.ndarray], width: int | None, fill) -> np.ndarray:
    """Stack per-step arrays of different candidate counts, padded with `fill` to the largest."""
    c = max(len(r) for r in rows)
    shape = (len(rows), c) + (() if width is None else (width,))
    out = np.full(shape, fill, dtype=np.float64 if fill is not None and isinstance(fill, float) else np.int64)
    for i, r in enumerate(rows):
        out[i, : len(r)] = r
    return out


def write_plan(path: str | Path, arrays: Mapping[str, np.ndarray], attrs: Mapping) -> Path:
    """Write a plan file atomically (`dsr_bench.atomic`)."""
    import h5py

    path = Path(path)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        for name, value in arrays.items():
            a = np.ascontiguousarray(value)
            big = a.size > 4096
            f.create_dataset(name, data=a, compression="gzip" if big else None,
                             compression_opts=4 if big else None)
        for key, value in {**attrs, "format": PLAN_FORMAT, "version": PLAN_VERSION}.items():
            f.attrs[key] = json.dumps(value) if isinstance(value, (dict, list)) else value
    return path


def read_plan_attrs(path: str | Path) -> dict:
    """A plan file's root attributes (JSON ones decoded); UserError naming the file and the fix if it is not a plan."""
    import h5py

    path = Path(path)
    fix = "rerun `dsr-bench plan` for its task (delete the file first)"
    try:
        with h5py.File(path, "r") as f:
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    except Exception as exc:  # noqa: BLE001 - whatever h5py raises on a damaged file
        raise UserError(f"{path}: unreadable plan file ({type(exc).__name__}); {fix}") from None
    if attrs.get("format") != PLAN_FORMAT or attrs.get("version") != PLAN_VERSION:
        raise UserError(f"{path}: not a dsr-bench plan file of version {PLAN_VERSION}; {fix}")
    for key in ("iou_per_object",):
        if isinstance(attrs.get(key), str):
            attrs[key] = json.loads(attrs[key])
    return attrs


def read_plan(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """A plan file's arrays and attributes."""
    import h5py

    attrs = read_plan_attrs(path)
    arrays: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: arrays.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return arrays, attrs
