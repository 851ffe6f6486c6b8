"""Benchmark: planning tasks per minute (one process) of the random, oracle and dsr planners.

    python bench/bench_plan.py [--tasks DIR] [--num-tasks 2] [--candidates 100] [--planners random,oracle,dsr]

A planner is a name, or name:masks for a learned one (e.g. 3dflow:observed, `dsr-bench plan --masks`); each runs
with its own margin (`dsr-bench plan`'s default).

Without --tasks it generates the first --num-tasks tasks of plan-novel-mini in a temporary directory. Each
planner runs once over the tasks in this process (`dsr_bench.planning.runner.run_plan` in
`generators.planning.SimEnvironment`; the dsr planner with the shipped CPU-track weights), after a warm-up task
that pays the imports and the model's loading. Prints wall and process-CPU seconds per task (CPU seconds are the
per-core cost, the figure to compare on a shared machine), tasks per minute (wall), the share of planning
(sampling, prediction, cost) in the wall time, and the mean final IoU.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", type=Path, help="A task directory (default: plan-novel-mini, generated)")
    parser.add_argument("--num-tasks", type=int, default=2)
    parser.add_argument("--candidates", type=int, default=100)
    parser.add_argument("--planners", default="random,oracle,dsr")
    args = parser.parse_args()

    import numpy as np
    import torch

    from dsr_bench.planning.planners import make_planner
    from dsr_bench.planning.runner import run_plan
    from dsr_bench.planning.results import score_plan
    from dsr_bench.planning.tasks import load_manifest, read_task
    from dsr_bench.generators.planning import SimEnvironment, generate_tasks

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        task_dir = args.tasks
        if task_dir is None:
            task_dir = Path(tmp) / "tasks"
            generate_tasks("plan-novel-mini", task_dir, num_tasks=args.num_tasks)
        entries = load_manifest(task_dir)["tasks"][: args.num_tasks]
        tasks = [read_task(task_dir / e["file"]) for e in entries]
        print(f"{len(tasks)} tasks of {task_dir}, {args.candidates} candidates per step, 1 process, "
              f"torch threads {torch.get_num_threads()}")
        print(f"{'planner':<16} {'s/task wall':>12} {'s/task CPU':>11} {'tasks/min':>10} {'planning %':>11} {'IoU':>7}")
        for name in args.planners.split(","):
            env = SimEnvironment()
            model, _, masks = name.partition(":")
            planner = make_planner(model, (env.current_mask, env.simulate)) if model == "oracle" else \
                make_planner(model, masks=masks or "model")
            run_plan(tasks[0], planner, env, min(args.candidates, 4), steps=1)  # warm-up
            wall0, cpu0, planning, ious = time.perf_counter(), time.process_time(), 0.0, []
            for task in tasks:
                record = run_plan(task, planner, env, args.candidates, margin=planner.margin)
                planning += sum(record.seconds)
                ious.append(score_plan(record.states[-1].mask_3d, record.states[0].mask_3d, task.target_mask,
                                       task.num_objects)["iou"])
            wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
            env.close()
            n = len(tasks)
            print(f"{name:<16} {wall / n:>12.2f} {cpu / n:>11.2f} {60 * n / wall:>10.2f} "
                  f"{100 * planning / wall:>10.0f}% {float(np.mean(ious)):>7.3f}")


if __name__ == "__main__":
    main()
