"""Evidence that the reference models learn: a short schedule for each model, then evaluation.

    python scripts/short_schedule.py --out runs/short [--device cuda] [--train-sequences 200]
        [--test-split procedural-novel-mini] [--steps-single 2000] [--steps-multi 500] [--models dsr nowarp single]

Generates a small procedural training set (or reuses --train-data), trains each model on the
curriculum's first two stages with few steps (single-step stage, then 10-step windows; SingleStep
and 3DFlow stay single-step), predicts and evaluates the test split, and prints a table; each
results file goes to OUT/results/ and, with --leaderboard, joins the leaderboard labelled
"short schedule: <steps>, <data>" (never mixed with full-schedule rows). The paper's ordering of the
history ablation on ordered IoU is DSR-Net > NoWarp > SingleStep. Meant for a GPU; on a CPU use a
tiny number of steps (it still runs the full 128 x 128 x 48 grid).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path


def run(*args: str) -> None:
    cmd = [sys.executable, "-m", "dsr_bench.cli", *args]
    print("+", " ".join(cmd[2:]), flush=True)
    subprocess.run(cmd, check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--train-data", type=Path)
    parser.add_argument("--train-sequences", type=int, default=200)
    parser.add_argument("--test-split", default="procedural-novel-mini")
    parser.add_argument("--steps-single", type=int, default=2000)
    parser.add_argument("--steps-multi", type=int, default=500)
    parser.add_argument("--batch-size", type=int, default=12)
    parser.add_argument("--workers", type=int, default=8)
    parser.add_argument("--models", nargs="+", default=["dsr", "nowarp", "single", "gtwarp", "3dflow"])
    parser.add_argument("--leaderboard", action="store_true")
    args = parser.parse_args()

    out = args.out
    data = args.train_data or out / "train"
    if args.train_data is None:
        run("generate", "--objects", "procedural", "-n", str(args.train_sequences), "--seed", "777", "--out", str(data),
            "--workers", str(args.workers))
    test = out / args.test_split
    run("generate", "--split", args.test_split, "--out", str(test), "--workers", str(args.workers))
    rows = []
    for model in args.models:
        run_dir = out / "runs" / model
        common = ["--model", model, "--data", str(data), "--device", args.device, "--batch-size", str(args.batch_size),
                  "--workers", str(args.workers)]
        run("train", *common, "--stage", "cube-single", "--out", str(run_dir / "stage1"), "--max-steps",
            str(args.steps_single))
        ckpt = run_dir / "stage1" / "last.pt"
        if model not in ("single", "3dflow"):
            run("train", *common, "--stage", "cube-multi", "--init", str(ckpt), "--out", str(run_dir / "stage2"),
                "--max-steps", str(args.steps_multi))
            ckpt = run_dir / "stage2" / "last.pt"
        pred = out / "predictions" / model
        run("predict", "--model", model, "--checkpoint", str(ckpt), "--data", str(test), "--out", str(pred),
            "--device", args.device)
        results = out / "results" / f"{model}.json"
        run("evaluate", str(pred), "--data", str(test), "--out", str(results))
        r = json.loads(results.read_text())
        rows.append((model, r["metrics"]))
        if args.leaderboard:
            run("leaderboard", "add", str(results), "--label",
                f"short schedule: {args.steps_single}+{args.steps_multi} steps on {args.train_sequences} procedural sequences")
    print(f"\n{'model':10s} {'IoU unord':>10s} {'IoU ord':>10s} {'flow vis':>10s} {'flow full':>10s}")
    for model, m in rows:
        print(f"{model:10s} {m['iou_unordered']:10.3f} {m['iou_ordered']:10.3f} {m['motion_visible']:10.3f} "
              f"{m['motion_full']:10.4f}")
    ordered = {model: m["iou_ordered"] for model, m in rows}
    if {"dsr", "nowarp", "single"} <= set(ordered):
        holds = ordered["dsr"] > ordered["nowarp"] > ordered["single"]
        print(f"paper's ordering DSR-Net > NoWarp > SingleStep on ordered IoU: {'holds' if holds else 'does NOT hold'}")


if __name__ == "__main__":
    main()
