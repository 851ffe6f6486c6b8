"""The planning track's evidence: every planner's final-vs-target IoU on the pinned tasks, paired task by task.

    python scripts/planning_evidence.py PLANS_DIR [--planners random oracle dsr single 3dflow]
        [--versus 3dflow] [--out docs/evidence/planning.json] [--leaderboard leaderboard]

PLANS_DIR/<planner>/results.json are written by `dsr-bench plan --model <planner> --tasks plan-novel-test
--out PLANS_DIR/<planner>`. Prints each planner's mean IoU (matched, identity, occupancy) and the paired
differences, task by task, with their standard errors: against not pushing at all (each task's start state),
against the random planner and the oracle, and against each planner of --versus. With --leaderboard each results
file joins the leaderboard's planning column (`dsr-bench leaderboard add`) and the tables are rebuilt.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from dsr_bench.atomic import check_writable, write_text

METRICS = ("iou", "iou_identity", "iou_occupancy")


def weights_sha256(weights: dict | list) -> str | list:
    """The SHA-256 of a learned planner's weights file, or of each of an ensemble's (a list of records)."""
    return [w["sha256"] for w in weights] if isinstance(weights, list) else weights["sha256"]


def main() -> None:
    from dsr_bench.scoring.compare import paired_difference

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("plans", type=Path)
    parser.add_argument("--planners", nargs="+", default=["random", "oracle", "dsr", "single", "3dflow"])
    parser.add_argument("--versus", nargs="*", default=[], help="Further planners every other is paired with.")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--leaderboard", type=Path)
    args = parser.parse_args()
    if args.out:  # before the work: the results can be written
        check_writable(args.out, "--out", directory=False)

    results = {}
    for name in args.planners:
        path = args.plans / name / "results.json"
        if not path.is_file():
            print(f"skipping {name}: no {path}", file=sys.stderr)
            continue
        results[name] = json.loads(path.read_text())
        if args.leaderboard:
            subprocess.run([sys.executable, "-m", "dsr_bench", "leaderboard", "add", str(path), "--plans",
                            str(args.plans / name), "--root", str(args.leaderboard)], check=True)
    per_task = {name: r["per_task"] for name, r in results.items()}
    first = next(iter(results.values()))
    per_task["no push"] = {task: {m: v[f"start_{m}"] for m in METRICS} for task, v in first["per_task"].items()}
    summary = {"task_set": first["task_set"], "task_checksum": first["task_checksum"],
               "commands": {name: r["command"] for name, r in results.items()},
               "coverage": {name: r["coverage"] for name, r in results.items()},
               "weights": {name: weights_sha256(r["planner"]["weights"]) for name, r in results.items()
                           if (r.get("planner") or {}).get("weights")},  # a learned planner's weights file(s)
               "means": {name: {m: sum(t[m] for t in rows.values()) / len(rows) for m in METRICS}
                         for name, rows in per_task.items()},
               "pairs": {}}
    for name in results:
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
