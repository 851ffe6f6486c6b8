"""The planning track's evidence: every planner's final-vs-target IoU on the pinned tasks, paired task by task,
recomputed from the plan files, each replayed in the simulator, and the verified tasks (never read from
results.json).

    python scripts/planning_evidence.py PLANS_DIR [PLANS_DIR ...] [--tasks TASKS ...]
        [--planners random oracle dsr single 3dflow] [--versus 3dflow] [--out docs/evidence/planning.json]
        [--leaderboard leaderboard] [--workers N]

PLANS_DIR/<planner> is the --out of `dsr-bench plan --model <planner> --tasks plan-novel-test`. Each planner's
results are recomputed (`dsr_bench.planning.verify.recompute_results`) from its plan files against the tasks
(--tasks: one task directory or task set name per PLANS_DIR; default: the set results.json names, as
data/<name>); a results.json that differs from its recomputation is named on stderr and in the summary, and the
recomputed values are used. Prints each planner's mean IoU (matched, identity, occupancy) and the paired
differences, task by task, with their standard errors: against not pushing at all (each task's start state),
against the random planner and the oracle, and against each planner of --versus. Several PLANS_DIRs (of different
task sets) pool their tasks (named i:set/task_NNNN): a planner counts only when every directory has it. With
--leaderboard (one PLANS_DIR) each results file joins the leaderboard's planning column (`dsr-bench leaderboard
add`) and the tables are rebuilt.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

from dsr_bench.atomic import check_writable, write_text
from dsr_bench.errors import UserError

METRICS = ("iou", "iou_identity", "iou_occupancy")


def weights_sha256(weights: dict | list) -> str | list:
    """The SHA-256 of a learned planner's weights file, or of each of an ensemble's (a list of records)."""
    return [w["sha256"] for w in weights] if isinstance(weights, list) else weights["sha256"]


def recomputed_runs(plans: list[Path], tasks: list[str | None], planners: list[str],
                    workers: int = 1) -> tuple[dict, dict, dict]:
    """Per planner present in every directory of `plans`: (its recomputed results per directory, each plan replayed
    in `workers` processes; {planner: the results.json fields that differed from the recomputation}, {task set:
    checksum})."""
    from dsr_bench.planning.verify import differences, recompute_results

    runs: dict[str, list[dict]] = {}
    differed: dict[str, list[str]] = {}
    for name in planners:
        missing = [d / name / "results.json" for d in plans if not (d / name / "results.json").is_file()]
        if missing:
            print(f"skipping {name}: no {missing[0]}", file=sys.stderr)
            continue
        runs[name] = []
        for d, t in zip(plans, tasks):
            recomputed = recompute_results(d / name, t, workers=workers)
            diff = differences(recomputed, json.loads((d / name / "results.json").read_text()))
            if diff:
                print(f"warning: {d / name}/results.json differs from its plan files in {', '.join(diff[:8])}; "
                      "the recomputed values are used", file=sys.stderr)
                differed[f"{d.name}/{name}"] = diff
            runs[name].append(recomputed)
    if not runs:
        raise SystemExit("no planner's results in every directory; check the PLANS_DIR and --planners")
    for name, rs in runs.items():  # pooled directories hold one planner under one name: the same weights
        weights = {json.dumps(weights_sha256((r.get("planner") or {}).get("weights") or {"sha256": None}))
                   for r in rs}
        if len(weights) > 1:
            raise SystemExit(f"error: {name} was run with different weights in {', '.join(map(str, plans))}; pool "
                             "runs of one planner only")
    checksums = {r["task_set"]: r["task_checksum"] for r in next(iter(runs.values()))}
    return runs, differed, checksums


def main() -> None:
    from dsr_bench.scoring.compare import paired_difference

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("plans", type=Path, nargs="+")
    parser.add_argument("--tasks", nargs="+", help="The task directory or set name of each PLANS_DIR, in order.")
    parser.add_argument("--planners", nargs="+", default=["random", "oracle", "dsr", "single", "3dflow"])
    parser.add_argument("--versus", nargs="*", default=[], help="Further planners every other is paired with.")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--leaderboard", type=Path)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="Processes replaying the plans (default: one per core).")
    args = parser.parse_args()
    if args.tasks is not None and len(args.tasks) != len(args.plans):
        parser.error(f"--tasks: {len(args.tasks)} given for {len(args.plans)} PLANS_DIRs; give one per PLANS_DIR")
    if args.leaderboard and len(args.plans) != 1:
        parser.error("--leaderboard adds one task set's runs: give one PLANS_DIR")
    if args.out:  # before the work: the results can be written
        check_writable(args.out, "--out", directory=False)
    tasks = args.tasks or [None] * len(args.plans)

    try:
        runs, differed, checksums = recomputed_runs(args.plans, tasks, args.planners, args.workers)
    except UserError as exc:
        raise SystemExit(f"error: {exc}") from None
    pooled = len(args.plans) > 1
    per_task = {name: {(f"{i}:{r['task_set']}/{t}" if pooled else t): v for i, r in enumerate(rs)
                       for t, v in r["per_task"].items()} for name, rs in runs.items()}
    first = next(iter(per_task.values()))
    per_task["no push"] = {task: {m: v[f"start_{m}"] for m in METRICS} for task, v in first.items()}
    if args.leaderboard:
        for name in runs:
            extra = ["--tasks", tasks[0]] if tasks[0] else []
            subprocess.run([sys.executable, "-m", "dsr_bench", "leaderboard", "add",
                            str(args.plans[0] / name / "results.json"), "--plans", str(args.plans[0] / name), *extra,
                            "--root", str(args.leaderboard)], check=True)
    summary = {"command": shlex.join(["python", *sys.argv]), "task_set": " + ".join(checksums),
               "task_checksum": " + ".join(checksums.values()),
               "task_sets": checksums, "recomputed": True, "differed_from_results_json": differed,
               "commands": {name: [r["command"] for r in rs] if pooled else rs[0]["command"]
                            for name, rs in runs.items()},
               "coverage": {name: [r["coverage"] for r in rs] if pooled else rs[0]["coverage"]
                            for name, rs in runs.items()},
               "weights": {name: weights_sha256(rs[0]["planner"]["weights"]) for name, rs in runs.items()
                           if (rs[0].get("planner") or {}).get("weights")},  # a learned planner's weights file(s)
               "means": {name: {m: sum(t[m] for t in rows.values()) / len(rows) for m in METRICS}
                         for name, rows in per_task.items()},
               "pairs": {}}
    for name in runs:
        for reference in ("no push", "random", "oracle", *args.versus):
            if reference != name and reference in per_task:
                summary["pairs"][f"{name} - {reference}"] = {
                    m: paired_difference(per_task[name], per_task[reference], m) for m in METRICS}
    print(f"{summary['task_set']}: mean IoU (matched, identity, occupancy)")
    for name, row in summary["means"].items():
        print(f"{name:>10} " + " ".join(f"{row[m]:.3f}" for m in METRICS))
    print("\npaired differences, task by task (mean ± standard error, n):")
    for key, row in summary["pairs"].items():
        v = row["iou"]
        print(f"{key:>22} {v['mean']:+.3f} ± {v['se']:.3f} (n {v['n']})")
    if args.leaderboard:
        subprocess.run([sys.executable, "-m", "dsr_bench", "leaderboard", "build", "--root", str(args.leaderboard)],
                       check=True)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_text(args.out, json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
