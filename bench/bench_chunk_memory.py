"""Benchmark: the peak memory of `dsr-bench evaluate` on one sequence whose prediction is stored in each of
several chunk layouts (the toolkit's own, h5py's automatic chunking, contiguous, one chunk for the whole array,
layouts at the limit `MAX_STEP_CHUNKS` and over it, which the header check refuses).

    python bench/bench_chunk_memory.py [--steps 10] [--scratch DIR]

A synthetic dataset of one sequence is written to a scratch directory, the oracle's prediction is re-stored in
each layout (the same arrays; the layouts over the limit hold no data, as a forged header needs none), and
`dsr-bench evaluate --workers 1` runs on each in a child process; its peak resident memory is what `os.wait4`
reports for that child (ru_maxrss, the largest the process ever was). Linux carries a process's peak across
fork and exec, so the files are written by another child and this process stays small. Every layout that passes
must give the oracle's results (IoU 1, flow error 0), and every one over the limit must be refused with one line
and no results.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import h5py

from dsr_bench.constants import GRID_SHAPE, IMAGE_SHAPE
from dsr_bench.scoring.predictions import MAX_STEP_CHUNKS

NAMES = ("mask", "motion", "motion_2d")


def layouts(steps: int) -> dict[str, dict[str, dict]]:
    """Layout name -> dataset -> h5py create_dataset keywords (chunks, compression); absent: the toolkit's."""
    gzip = {"compression": "gzip", "compression_opts": 1}
    whole = {"mask": (steps,) + GRID_SHAPE, "motion": (steps, 3) + GRID_SHAPE,
             "motion_2d": (steps,) + IMAGE_SHAPE + (3,)}
    # MAX_STEP_CHUNKS (1024) chunks per step: 32 x 32 columns of the grid, 16 x 64 patches of the image
    at_limit = {"mask": (1, 4, 4, 48), "motion": (1, 3, 4, 4, 48), "motion_2d": (1, 15, 5, 3)}
    return {
        "toolkit (write_predictions: one step a chunk, gzip)": {},
        "h5py chunks=True, gzip": {n: {"chunks": True, **gzip} for n in NAMES},
        "contiguous": {n: {"chunks": None} for n in NAMES},
        "one chunk for the whole array, gzip": {n: {"chunks": whole[n], **gzip} for n in NAMES},
        f"{MAX_STEP_CHUNKS} chunks a step, uncompressed": {n: {"chunks": at_limit[n]} for n in NAMES},
        f"{MAX_STEP_CHUNKS} chunks a step, gzip": {n: {"chunks": at_limit[n], **gzip} for n in NAMES},
        "mask (1, 1, 1, 6): refused": {"mask": {"chunks": (1, 1, 1, 6)}},
        "motion_2d (1, 1, 1, 1): refused": {"motion_2d": {"chunks": (1, 1, 1, 1)}},
    }


def restore(src: Path, dst: Path, spec: dict[str, dict], refused: bool) -> None:
    """The prediction file `src` re-stored at `dst`, each dataset with its keywords in `spec` (else as it is);
    a `refused` layout's datasets are declared without data."""
    with h5py.File(src, "r") as f, h5py.File(dst, "w") as g:
        for key, value in f.attrs.items():
            g.attrs[key] = value
        for name in f:
            ds = f[name]
            kwargs = spec.get(name, {"chunks": ds.chunks, "compression": ds.compression,
                                     "compression_opts": ds.compression_opts})
            if refused and name in spec:
                g.create_dataset(name, shape=ds.shape, dtype=ds.dtype, **kwargs)
            else:
                g.create_dataset(name, data=ds[()], **kwargs)


def prepare(scratch: Path, steps: int) -> None:
    """The dataset (scratch/data) and one predictions directory per layout (scratch/pred_<i>)."""
    from dsr_bench.cli import main as cli
    from dsr_bench.testing import write_synthetic_dataset

    data = write_synthetic_dataset(scratch / "data", num_sequences=1, num_steps=steps)
    oracle = scratch / "oracle"
    assert cli(["predict", "--model", "oracle", "--data", str(data), "--out", str(oracle)]) == 0
    for i, (label, spec) in enumerate(layouts(steps).items()):
        pred = Path(shutil.copytree(oracle, scratch / f"pred_{i}"))
        if spec:
            restore(oracle / "seq_0000.h5", pred / "seq_0000.h5", spec, refused=label.endswith("refused"))


def peak_rss_mb(command: list[str]) -> tuple[int, float, str]:
    """Exit code, peak resident memory (MB) and stderr of `command` run in a child process."""
    with tempfile.TemporaryFile() as err:
        child = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(child.pid, 0)
        child.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        return child.returncode, usage.ru_maxrss / 1024, err.read().decode(errors="replace")


def main(argv: list[str] | None = None) -> list[tuple[str, int, float]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--scratch", type=Path, default=None)
    parser.add_argument("--prepare", type=Path, default=None, help=argparse.SUPPRESS)  # the child that writes
    args = parser.parse_args(argv)
    if args.prepare:
        prepare(args.prepare, args.steps)
        return []
    scratch = Path(tempfile.mkdtemp(dir=args.scratch))
    rows = []
    try:
        subprocess.run([sys.executable, __file__, "--steps", str(args.steps), "--prepare", str(scratch)],
                       check=True, stdout=subprocess.DEVNULL)
        print(f"one sequence of {args.steps} steps; peak RSS of `dsr-bench evaluate --workers 1` (MB)")
        for i, label in enumerate(layouts(args.steps)):
            out = scratch / f"results_{i}.json"
            command = [sys.executable, "-m", "dsr_bench.cli", "evaluate", str(scratch / f"pred_{i}"),
                       "--data", str(scratch / "data"), "--workers", "1", "--out", str(out)]
            rc, rss, err = peak_rss_mb(command)
            if out.exists():
                metrics = json.loads(out.read_text())["metrics"]
                assert metrics["iou_unordered"] == 1.0 and metrics["motion_full"] == 0.0, (label, metrics)
                outcome = "scored as the oracle"
            else:
                lines = [line for line in err.splitlines() if "seq_0000.h5:" in line]
                assert rc != 0 and len(lines) == 1, (label, err)
                outcome = "refused: " + lines[0].split("seq_0000.h5: ", 1)[1][:60] + "..."
            print(f"  {label:52} {rss:6.0f}  {outcome}")
            rows.append((label, rc, rss))
        print(f"  (this process, which started each: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f})")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return rows


if __name__ == "__main__":
    main()
