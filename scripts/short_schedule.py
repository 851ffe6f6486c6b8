"""Evidence that the reference models learn: a short schedule for each model, then evaluation.

    python scripts/short_schedule.py --out runs/short [--device cuda] [--train-sequences 200]
        [--test-split procedural-novel-mini] [--steps-single 2000] [--steps-multi 200]
        [--models dsr nowarp single gtwarp 3dflow] [--bf16] [--channels-last] [--leaderboard]
        [--minutes-single M] [--minutes-multi M] [--jobs N]

1. Generates a small procedural training set (or reuses --train-data) and the test split (or
   reuses --test-data).
2. Trains each model in two stages: single-step windows for --steps-single batches (constant
   learning rate --lr-single), then 10-step windows for --steps-multi batches (--lr-multi,
   initialised from stage 1). SingleStep and 3DFlow stay single-step in stage 2 and get
   10 x --steps-multi batches, i.e. the same number of optimiser steps and samples. --minutes-single
   and --minutes-multi cap each stage's wall time instead (the batches actually run are reported);
   --jobs N trains N models at once on the one GPU. Constant
   learning rates replace the official per-epoch tables, whose first two epochs at 1e-5 are
   warm-up that a short schedule cannot afford.
3. Predicts and evaluates the test split, prints a table and whether the paper's ordering of the
   history ablation on ordered IoU (DSR-Net > NoWarp > SingleStep) holds, and writes
   OUT/short_schedule.json (command, data, steps, metrics). With --leaderboard each results file
   joins the leaderboard labelled "short schedule: ..." (never mixed with full-schedule rows).
Meant for a GPU (full 128 x 128 x 48 grid); on a CPU only a smoke run with a few steps is practical.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from dsr_bench.atomic import check_writable, write_text

HISTORY_MODELS = ("dsr", "nowarp", "gtwarp")


def run(*args: str) -> None:
    cmd = [sys.executable, "-m", "dsr_bench.cli", *args]
    print("+ dsr-bench", " ".join(shlex.quote(a) for a in args), flush=True)
    subprocess.run(cmd, check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--train-data", type=Path, help="Existing training dataset (default: generate one).")
    parser.add_argument("--train-sequences", type=int, default=200)
    parser.add_argument("--train-seed", type=int, default=777)
    parser.add_argument("--test-data", type=Path, help="Existing test dataset (default: generate --test-split).")
    parser.add_argument("--test-split", default="procedural-novel-mini")
    parser.add_argument("--steps-single", type=int, default=2000)
    parser.add_argument("--steps-multi", type=int, default=200)
    parser.add_argument("--lr-single", type=float, default=1e-3)
    parser.add_argument("--lr-multi", type=float, default=5e-4)
    parser.add_argument("--batch-size", type=int, default=12)
    parser.add_argument("--workers", type=int, default=8)
    parser.add_argument("--models", nargs="+", default=["dsr", "nowarp", "single", "gtwarp", "3dflow"])
    parser.add_argument("--minutes-single", type=float, help="Wall-time cap of stage 1 per model.")
    parser.add_argument("--minutes-multi", type=float, help="Wall-time cap of stage 2 per model.")
    parser.add_argument("--jobs", type=int, default=1, help="Models trained at once (they share the GPU).")
    parser.add_argument("--bf16", action="store_true")
    parser.add_argument("--channels-last", action="store_true")
    parser.add_argument("--leaderboard", action="store_true")
    args = parser.parse_args()

    out = args.out
    check_writable(out, "--out")  # before the work
    out.mkdir(parents=True, exist_ok=True)
    started = time.time()
    data = args.train_data or out / "train"
    if args.train_data is None and not (data / "manifest.json").is_file():
        run("generate", "--objects", "procedural", "-n", str(args.train_sequences), "--seed", str(args.train_seed),
            "--out", str(data), "--workers", str(args.workers))
    test = args.test_data or out / args.test_split
    if args.test_data is None and not (test / "manifest.json").is_file():
        run("generate", "--split", args.test_split, "--out", str(test), "--workers", str(args.workers))
    extra = (["--bf16"] if args.bf16 else []) + (["--channels-last"] if args.channels_last else [])

    def stage(model: str, name: str, lr: float, steps: int, minutes: float | None, run_dir: Path,
              init: Path | None) -> tuple[Path, int]:
        """One training stage; returns its checkpoint and the number of batches it ran."""
        cmd = ["train", "--model", model, "--data", str(data), "--device", args.device, "--batch-size",
               str(args.batch_size), "--workers", str(args.workers), "--epochs", "100000", "--quiet", *extra,
               "--stage", name, "--lr", str(lr), "--out", str(run_dir), "--max-steps", str(steps)]
        cmd += ["--max-minutes", str(minutes)] if minutes else []
        cmd += ["--init", str(init)] if init else []
        run(*cmd)
        lines = (run_dir / "metrics.jsonl").read_text().splitlines()
        return run_dir / "last.pt", max(json.loads(line)["step"] for line in lines)

    def one_model(model: str) -> dict:
        """Train, predict and score one model; returns its metrics and the batches each stage ran."""
        run_dir = out / "runs" / model
        ckpt, single_steps = stage(model, "cube-single", args.lr_single, args.steps_single, args.minutes_single,
                                   run_dir / "stage1", None)
        multi_steps = 0
        if args.steps_multi > 0:
            multi = args.steps_multi if model in HISTORY_MODELS else 10 * args.steps_multi
            ckpt, multi_steps = stage(model, "cube-multi", args.lr_multi, multi, args.minutes_multi,
                                      run_dir / "stage2", ckpt)
        pred = out / "predictions" / model
        run("predict", "--model", model, "--checkpoint", str(ckpt), "--data", str(test), "--out", str(pred),
            "--device", args.device)
        results = out / "results" / f"{model}.json"
        run("evaluate", str(pred), "--data", str(test), "--out", str(results))
        if args.leaderboard:
            window = "10-step" if model in HISTORY_MODELS else "single-step"
            run("leaderboard", "add", str(results), "--predictions", str(pred), "--data", str(test), "--label",
                f"short schedule: {single_steps} single-step + {multi_steps} {window} batches of "
                f"{args.batch_size} on {args.train_sequences if args.train_data is None else data.name} sequences")
        return {"metrics": json.loads(results.read_text())["metrics"], "batches_stage1": single_steps,
                "batches_stage2": multi_steps}

    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        done = dict(zip(args.models, pool.map(one_model, args.models)))
    rows = {model: d["metrics"] for model, d in done.items()}
    keys = ("iou_unordered", "iou_ordered", "motion_visible", "motion_full")
    print(f"\n{'model':10s} " + " ".join(f"{k:>15s}" for k in keys))
    for model, m in rows.items():
        print(f"{model:10s} " + " ".join(f"{m.get(k, float('nan')):15.4f}" for k in keys))
    ordered = {model: m["iou_ordered"] for model, m in rows.items()}
    verdict = None
    if {"dsr", "nowarp", "single"} <= set(ordered):
        verdict = ordered["dsr"] > ordered["nowarp"] > ordered["single"]
        print("paper's ordering DSR-Net > NoWarp > SingleStep on ordered IoU: "
              f"{'holds' if verdict else 'does NOT hold'}")
    summary = {"command": " ".join(shlex.quote(a) for a in sys.argv), "train_data": str(data), "test_data": str(test),
               "test_split": args.test_split, "steps_single": args.steps_single, "steps_multi": args.steps_multi,
               "batch_size": args.batch_size, "lr_single": args.lr_single, "lr_multi": args.lr_multi,
               "device": args.device, "bf16": args.bf16, "channels_last": args.channels_last, "jobs": args.jobs,
               "minutes_single": args.minutes_single, "minutes_multi": args.minutes_multi,
               "seconds": time.time() - started, "metrics": rows,
               "batches": {m: [d["batches_stage1"], d["batches_stage2"]] for m, d in done.items()},
               "ordering_dsr_nowarp_single_holds": verdict}
    write_text(out / "short_schedule.json", json.dumps(summary, indent=1) + "\n")
    print(f"summary: {out / 'short_schedule.json'}")


if __name__ == "__main__":
    main()
