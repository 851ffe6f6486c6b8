"""Scores of the track, per task, of the final full state (the true amodal masks after the last push) against the
target's:

- `iou` (the headline, the leaderboard's planning IoU): the mean voxel IoU over objects under the best one-to-one
  matching of final and target objects (Hungarian on IoU), as the benchmark's mask IoU and the cost match;
- `iou_identity`: object i against object i (the simulator knows the ids): a swap of two objects counts 0;
- `iou_occupancy`: the occupied voxels (any object) against the target's;
- the same three for the start state (`start_iou`, ...): what not pushing at all would score.

The results JSON ("dsr-bench-plan-results") has the means, per-task values, the task set's checksum and whether it
matches the pin, the plans' checksum and the exact command (`build_results`); the leaderboard's planning rows are
made from it by `dsr_bench.leaderboard.board.planning_rows`.
"""

from __future__ import annotations

import datetime as dt
import hashlib
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from dsr_bench import __version__
from dsr_bench.planning.cost import matched_iou, object_iou, occupancy_iou

RESULTS_FORMAT = "dsr-bench-plan-results"


def score_plan(final: np.ndarray, start: np.ndarray, target: np.ndarray, num_objects: int) -> dict:
    """Scores of one plan: final and start states (Y, X, Z) uint8 against the target (object ids 1..N)."""
    per_object = object_iou(final, target, num_objects)
    return {"iou": matched_iou(final, target, num_objects), "iou_identity": float(per_object.mean()),
            "iou_occupancy": occupancy_iou(final, target), "start_iou": matched_iou(start, target, num_objects),
            "start_iou_identity": float(object_iou(start, target, num_objects).mean()),
            "start_iou_occupancy": occupancy_iou(start, target), "iou_per_object": per_object.tolist()}


def plans_checksum(paths: list[Path]) -> str:
    """SHA-256 over the sorted plan files' names and SHA-256s."""
    from dsr_bench.dataset.manifest import file_sha256

    h = hashlib.sha256()
    for p in sorted(paths, key=lambda p: p.name):
        h.update(f"{p.stem}:{file_sha256(p)}\n".encode())
    return h.hexdigest()


def build_results(per_task: Mapping[str, dict], planner: Mapping, manifest: Mapping, expected: int,
                  plan_paths: list[Path], command: str | None, parameters: Mapping) -> dict:
    """The results JSON of a planning run (`dsr-bench plan`): means over the tasks scored (in name order), per task
    values. `manifest`: {"task_set", "checksum"}, the checksum recomputed from the task files
    (`dsr_bench.planning.verify.verify_tasks`), never a tasks.json's; `pinned` is whether it is this toolkit's pin."""
    from dsr_bench.planning.tasks import pinned_checksums

    keys = ("iou", "iou_identity", "iou_occupancy", "start_iou", "start_iou_identity", "start_iou_occupancy")
    ordered = [per_task[name] for name in sorted(per_task)]  # one order of summation, wherever it is recomputed
    metrics: dict[str, float | None] = {k: float(np.mean([t[k] for t in ordered])) if per_task else float("nan")
                                        for k in keys}
    seconds = [t["seconds"] for t in ordered if "seconds" in t]
    metrics["planning_iou"] = metrics["iou"]
    metrics["tasks_per_minute"] = 60.0 * len(seconds) / sum(seconds) if seconds and sum(seconds) > 0 else None
    name = manifest["task_set"]
    pinned = pinned_checksums().get(name)
    return {
        "format": RESULTS_FORMAT, "version": 1, "method": planner["name"], "planner": dict(planner),
        "task_set": name, "split": name, "task_checksum": manifest["checksum"], "split_checksum": manifest["checksum"],
        "pinned": pinned is not None and pinned == manifest["checksum"],
        "plans_checksum": plans_checksum(plan_paths), "parameters": dict(parameters), "command": command,
        "toolkit_version": __version__, "date": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "coverage": {"scored": len(per_task), "expected": expected, "partial": len(per_task) < expected},
        "metrics": metrics, "per_task": {k: dict(v) for k, v in sorted(per_task.items())},
    }
