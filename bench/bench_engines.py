"""Benchmark: seconds to generate the same sequences in one process, in local worker processes, on a local Ray and
as a submitit job array run by its local executor (issue 19), and whether every array is the same.

    python bench/bench_engines.py [--objects cube] [--num-sequences 8] [--steps 10] [--cpus 2] [--keep DIR]

Runs `dsr-bench generate` in a fresh interpreter for each of: 1 worker; --workers CPUS; --ray local --workers CPUS
(a Ray of CPUS CPUs, started and stopped by the command); --slurm --slurm-local --slurm-tasks CPUS (CPUS array
tasks of one process each), each into a fresh directory, timed wall to wall (interpreter start-up, Ray's start,
the tasks' submission and polling included: what a user waits for). Prints seconds, the speed-up over 1 worker,
and whether every array of every sequence, the manifest's digests and the split checksum equal the 1-worker run's.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np


def _arrays(path: Path) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def same_dataset(got: Path, want: Path) -> bool:
    """Every array of every sequence equal (dtype and values, NaN equal to NaN), the same sequences' digests and
    split checksum in the manifests."""
    from dsr_bench.dataset.manifest import load_manifest, split_digest

    names = sorted(p.name for p in want.glob("seq_*.h5"))
    if sorted(p.name for p in got.glob("seq_*.h5")) != names:
        return False
    for name in names:
        a, b = _arrays(got / name), _arrays(want / name)
        if sorted(a) != sorted(b):
            return False
        for key, value in b.items():
            nan = value.dtype.kind in "fc"
            if a[key].dtype != value.dtype or not np.array_equal(a[key], value, equal_nan=nan):
                return False
    ma, mb = load_manifest(got), load_manifest(want)
    return ([(s["name"], s["content_sha256"]) for s in ma["sequences"]] ==
            [(s["name"], s["content_sha256"]) for s in mb["sequences"]] and
            split_digest(ma, "all") == split_digest(mb, "all"))


def generate(out: Path, args: argparse.Namespace, extra: list[str]) -> float:
    """Seconds a `dsr-bench generate` command takes, wall to wall."""
    cmd = [sys.executable, "-m", "dsr_bench.cli", "generate", "--objects", args.objects, "-n",
           str(args.num_sequences), "--steps", str(args.steps), "--seed", "0", "--out", str(out), *extra]
    start = time.perf_counter()
    done = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, check=False)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{done.stderr[-3000:]}")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", default="cube")
    parser.add_argument("--num-sequences", "-n", type=int, default=8)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--cpus", type=int, default=2, help="workers, Ray CPUs and array tasks")
    parser.add_argument("--keep", type=Path, help="write the datasets here and keep them (default: a temporary "
                        "directory, removed at the end)")
    args = parser.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="bench-engines-"))
    c = str(args.cpus)
    runs = {
        "1 worker": [],
        f"--workers {c}": ["--workers", c],
        f"--ray local --workers {c}": ["--ray", "local", "--workers", c],
        f"--slurm --slurm-local --slurm-tasks {c}": ["--slurm", "--slurm-local", "--slurm-tasks", c,
                                                     "--slurm-logs", str(root / "slurm-logs")],
    }
    print(f"{args.num_sequences} {args.objects} sequences x {args.steps} pushes; {os.cpu_count()} cores here; "
          f"load average {', '.join(f'{x:.1f}' for x in os.getloadavg())} at the start")
    seconds: dict[str, float] = {}
    for i, (label, extra) in enumerate(runs.items()):
        seconds[label] = generate(root / f"run{i}", args, extra)
    reference = root / "run0"
    print(f"{'run':44s} {'seconds':>8s} {'speed-up':>9s}  arrays equal to 1 worker's")
    for i, label in enumerate(runs):
        equal = "-" if i == 0 else ("yes" if same_dataset(root / f"run{i}", reference) else "NO")
        print(f"{label:44s} {seconds[label]:8.1f} {seconds['1 worker'] / seconds[label]:8.2f}x  {equal}")
    print(f"load average {', '.join(f'{x:.1f}' for x in os.getloadavg())} at the end")
    if args.keep is None:
        shutil.rmtree(root)


if __name__ == "__main__":
    main()
