"""Replay every planning task's own reference pushes in the planning world and compare with its target.

    python scripts/replay_plan_tasks.py TASKS_DIR [--json OUT]

TASKS_DIR holds the tasks of a set (`dsr-bench generate-plan-tasks --tasks plan-novel-test --out TASKS_DIR`). Each
task's start is restored in a fresh `generators.planning.SimEnvironment` (the world plans run in), its three
reference pushes are executed, and the final state is compared with the task's target: the matched IoU the planning
track scores (`dsr_bench.planning.results.score_plan`) and whether the object poses are the target's bit for bit.
The planning world is the generator's (every push starts from a world built afresh at the rest poses), so every
task should reach IoU 1.0 with identical poses; the script exits 1 naming each task that does not.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("tasks", type=Path)
    parser.add_argument("--json", type=Path, help="write the per-task figures here")
    args = parser.parse_args()

    from dsr_bench.atomic import write_text
    from dsr_bench.planning.results import score_plan
    from dsr_bench.planning.tasks import read_task
    from dsr_bench.generators.planning import SimEnvironment

    paths = sorted(args.tasks.glob("task_*.h5"))
    if not paths:
        print(f"{args.tasks}: no task_*.h5 files; generate them with `dsr-bench generate-plan-tasks`", file=sys.stderr)
        return 2
    rows = {}
    for path in paths:
        task = read_task(path)
        env = SimEnvironment()
        try:
            start = env.reset(task)
            for action in task.arrays["reference/action"]:
                env.step(action)
            final = env.current_mask()
            identical = bool(np.array_equal(env.world.poses(), task.arrays["target/object_poses"]))
        finally:
            env.close()
        scores = score_plan(final, start.mask_3d, task.target_mask, task.num_objects)
        rows[task.name] = {"iou": float(scores["iou"]), "poses_identical": identical}
    ious = np.array([r["iou"] for r in rows.values()])
    off = [name for name, r in rows.items() if r["iou"] < 1.0 or not r["poses_identical"]]
    print(f"{len(rows)} tasks of {args.tasks}: replayed IoU mean {ious.mean():.4f}, min {ious.min():.4f}; "
          f"poses identical in {sum(r['poses_identical'] for r in rows.values())}")
    for name in off:
        print(f"  {name}: IoU {rows[name]['iou']:.4f}, poses identical: {rows[name]['poses_identical']}")
    if args.json:
        write_text(args.json, json.dumps({"tasks": str(args.tasks), "per_task": rows}, indent=1) + "\n")
    return 1 if off else 0


if __name__ == "__main__":
    sys.exit(main())
