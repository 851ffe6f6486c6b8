"""A CPU-track model trained towards the paper's length, in resumable chunks (docs/models.md, "The CPU track at the
paper's length").

    python scripts/train_cpu_long.py --model dsr --data data/cpu-train-4k --runs runs/long --until 1000000 \
        [--chunk 1000] [--from dsr_bench/models/weights/cpu-track] [--multi-lr 5e-4] [--threads 1]
    python scripts/train_cpu_long.py --model dsr --data data/cpu-train-4k --runs runs/long \
        --schedule 488000:5e-4,608000:1e-4,728000:5e-5 [--chunk 500] ...

Each chunk is one `dsr-bench train --track cpu --model M --data DATA --init RUNS/M.pt --multi-batches CHUNK --out
RUNS/M.pt`: CHUNK more windows of stage 2 (8 windows of 10 pushes a batch: CHUNK x 80 sample-steps), written
atomically over the file, so the script can be stopped at any moment and run again with the same arguments to
go on from the last chunk written. The first chunk starts from the shipped weights of --from (their file name
recorded). It stops once the file has trained on --until sample-steps (`cpu_track.sample_steps`, counted from
the file's own stage records), and appends one line per chunk to RUNS/M.log.jsonl (the chunk's sample-steps
reached, its starting learning rate, seconds, its loss in the first and last tenth).

--schedule UNTIL:RATE,... replaces --until and --multi-lr with a learning-rate schedule: chunks at each RATE until
the file has trained on its UNTIL sample-steps, each in turn (UNTIL increasing); a stage the file has already passed
is skipped, so the whole schedule is one command, resumable like the rest.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path


def trained(path: Path) -> tuple[int, dict]:
    """(sample-steps, the last stage record) of a CPU-track weights file."""
    from dsr_bench.models.registry import VOXEL
    from dsr_bench.models.training.checkpoints import read_weights
    from dsr_bench.models.training.cpu_track import sample_steps

    state = read_weights(path, kind=VOXEL, role="weights")
    stages = state["stages"]
    last = (stages.get("continued") or [stages.get("multi") or stages["single"]])[-1]
    return sample_steps(stages, int(state["recipe"].get("batch_size", 8))), last


def parse_schedule(text: str) -> list[tuple[int, float]]:
    """[(until sample-steps, learning rate), ...] of --schedule "UNTIL:RATE,..." (UNTIL increasing, RATE finite and
    positive); argparse.ArgumentTypeError naming the bad part otherwise (argparse's one line, exit 2)."""
    stages: list[tuple[int, float]] = []
    for part in text.split(","):
        until, _, rate = part.strip().partition(":")
        try:
            stage = int(until), float(rate)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{part!r} is not UNTIL:RATE (e.g. 608000:1e-4)") from None
        if not (math.isfinite(stage[1]) and stage[1] > 0) or (stages and stage[0] <= stages[-1][0]):
            raise argparse.ArgumentTypeError(f"at {part!r}: rates must be positive numbers and the sample-steps "
                                             "increasing")
        stages.append(stage)
    return stages


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--runs", type=Path, required=True)
    goal = parser.add_mutually_exclusive_group(required=True)
    goal.add_argument("--until", type=int, help="Sample-steps to reach (at --multi-lr).")
    goal.add_argument("--schedule", type=parse_schedule,
                      help="UNTIL:RATE,... : chunks at each rate until its sample-steps, in turn (instead of --until).")
    parser.add_argument("--chunk", type=int, default=1000, help="Stage-2 batches per chunk.")
    parser.add_argument("--from", dest="start", type=Path,
                        default=Path(__file__).resolve().parents[1] / "dsr_bench/models/weights/cpu-track")
    parser.add_argument("--multi-lr", type=float,
                        help="Each chunk's starting learning rate with --until (default 5e-4; Adam restarted; halved "
                             "at 50%% and 75%% of the chunk).")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of each chunk's process.")
    args = parser.parse_args()
    if args.schedule and args.multi_lr is not None:
        parser.error("--multi-lr goes with --until; --schedule gives each stage's rate")
    schedule = args.schedule or [(args.until, 5e-4 if args.multi_lr is None else args.multi_lr)]
    args.runs.mkdir(parents=True, exist_ok=True)
    weights, log = args.runs / f"{args.model}.pt", args.runs / f"{args.model}.log.jsonl"
    if not weights.is_file():
        shutil.copy2(args.start / f"{args.model}.pt", weights)
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
    for until, rate in schedule:
        while (done := trained(weights)[0]) < until:
            train_chunk(args, weights, log, rate, env)
    print(f"{args.model}: {done} sample-steps, done", flush=True)


def train_chunk(args: argparse.Namespace, weights: Path, log: Path, rate: float, env: dict) -> None:
    """One chunk of `args.chunk` stage-2 batches at `rate`, written over `weights`, and its line in `log`."""
    start = time.time()
    command = [sys.executable, "-m", "dsr_bench", "train", "--track", "cpu", "--model", args.model, "--data",
               str(args.data), "--init", str(weights), "--multi-batches", str(args.chunk), "--multi-lr", str(rate),
               "--out", str(weights)]
    subprocess.run(command, check=True, env=env)
    reached, last = trained(weights)
    line = {"model": args.model, "sample_steps": reached, "lr": last.get("lr"),
            "seconds": round(time.time() - start, 1),
            "loss_first_tenth": last.get("loss_first_tenth"), "loss_last_tenth": last.get("loss_last_tenth"),
            "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    with open(log, "a") as fh:
        fh.write(json.dumps(line) + "\n")
    print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
