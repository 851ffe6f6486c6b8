"""scripts/train_cpu_long.py, the CPU track's long runs in resumable chunks, end to end at toy size: the run starts
from the shipped file of --from, trains chunk after chunk until the file's own records count --until sample-steps,
logs each chunk (its sample-steps and rate), and run again with the same arguments it has nothing left to do; a
--schedule of rates goes on from there, skipping the stages the file has passed."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from dsr_bench.models.predictors import SHIPPED_WEIGHTS
from dsr_bench.models.training.cpu_track import sample_steps
from dsr_bench.testing import write_synthetic_dataset

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import train_cpu_long  # noqa: E402


def _steps(path: Path) -> int:
    state = torch.load(path, weights_only=True)
    return sample_steps(state["stages"], int(state["recipe"]["batch_size"]))


def test_a_long_run_goes_on_chunk_by_chunk_until_its_sample_steps(tmp_path):
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=2, num_steps=10, split="train")
    shipped = SHIPPED_WEIGHTS / "single.pt"
    start, runs = _steps(shipped), tmp_path / "runs"
    # a chunk of one stage-2 batch: SingleStep has no history, so 10 single-step batches of 8 (80 sample-steps)
    command = [sys.executable, str(ROOT / "scripts" / "train_cpu_long.py"), "--model", "single", "--data", str(data),
               "--runs", str(runs), "--until", str(start + 150), "--chunk", "1", "--multi-lr", "1e-4"]
    env = {**os.environ, "DSR_BENCH_CACHE": str(tmp_path / "cache")}
    done = subprocess.run(command, capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in (runs / "single.log.jsonl").read_text().splitlines()]
    assert [line["sample_steps"] for line in lines] == [start + 80, start + 160]  # whole chunks, past --until
    assert all(line["model"] == "single" and line["lr"] == 1e-4 for line in lines)
    assert _steps(runs / "single.pt") == start + 160
    chunks = torch.load(runs / "single.pt", weights_only=True)["stages"]["continued"]
    shipped_chunks = torch.load(shipped, weights_only=True)["stages"]["continued"]
    assert len(chunks) == len(shipped_chunks) + 2 and chunks[-1]["data"]["sequences"] == 2
    assert chunks[len(shipped_chunks)]["from"] == "single.pt"  # the shipped file it started from
    again = subprocess.run(command, capture_output=True, text=True, env=env)
    assert again.returncode == 0 and f"{start + 160} sample-steps, done" in again.stdout
    assert len((runs / "single.log.jsonl").read_text().splitlines()) == 2  # nothing more trained

    # a schedule: its first stage is passed already (skipped), its second trains at its own rate until its steps
    schedule = command[:command.index("--until")] + ["--schedule", f"{start + 160}:1e-4,{start + 240}:5e-5",
                                                    "--chunk", "1"]
    done = subprocess.run(schedule, capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in (runs / "single.log.jsonl").read_text().splitlines()]
    assert [(line["sample_steps"], line["lr"]) for line in lines[2:]] == [(start + 240, 5e-5)]
    assert f"{start + 240} sample-steps, done" in done.stdout


def test_a_schedule_is_whole_and_increasing_and_takes_no_other_rate(tmp_path):
    assert train_cpu_long.parse_schedule("488000:5e-4, 608000:1e-4") == [(488000, 5e-4), (608000, 1e-4)]
    for bad, why in (("608000", "is not UNTIL:RATE"), ("608000:fast", "is not UNTIL:RATE"),
                     ("608000:1e-4,528000:5e-5", "increasing"), ("608000:0", "positive"), ("608000:nan", "positive"),
                     ("608000:inf", "positive")):
        with pytest.raises(argparse.ArgumentTypeError, match=why):
            train_cpu_long.parse_schedule(bad)
    both = subprocess.run([sys.executable, str(ROOT / "scripts" / "train_cpu_long.py"), "--model", "single", "--data",
                           str(tmp_path), "--runs", str(tmp_path / "runs"), "--schedule", "608000:1e-4",
                           "--multi-lr", "5e-5"], capture_output=True, text=True)
    assert both.returncode == 2 and "--multi-lr goes with --until" in both.stderr
    assert not (tmp_path / "runs").exists()  # refused before anything was written
