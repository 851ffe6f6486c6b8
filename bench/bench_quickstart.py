"""Benchmark: how long the README's first command takes, step by step, on a fresh clone.

    python bench/bench_quickstart.py [--repo .] [--keep DIR]

Clones the repository's HEAD into a temporary directory (or --keep DIR), runs `bash scripts/quickstart.sh` there and
prints each step's wall time as the script reports it ("quickstart step: S s: COMMAND"), the total, the total after
set-up (the quickstart's own steps: issue 33's aim is under 2 minutes on 2 idle cores), the CPU and the load average
before and after (the figure depends on what else the machine runs). Set-up installs into the clone's own .venv
from pip's cache and local wheels where it can.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import cpu_name  # noqa: E402

STEP = re.compile(r"^quickstart step: ([0-9.]+) s: (.*)$")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repo", type=Path, default=Path(__file__).resolve().parents[1])
    parser.add_argument("--keep", type=Path, help="Clone into this (new) directory and keep it")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        clone = args.keep or Path(tmp) / "dsr-bench"
        subprocess.run(["git", "clone", "-q", str(args.repo), str(clone)], check=True)
        load_before = os.getloadavg()
        start = time.perf_counter()
        run = subprocess.run(["bash", "scripts/quickstart.sh"], cwd=clone, capture_output=True, text=True)
        total = time.perf_counter() - start
        load_after = os.getloadavg()
    if run.returncode != 0:
        raise SystemExit(f"quickstart failed (exit {run.returncode}):\n{run.stderr[-2000:]}")
    steps = [(float(m[1]), m[2]) for m in map(STEP.match, run.stdout.splitlines()) if m]
    print(f"{os.cpu_count()} cores, {cpu_name()}; load average {load_before[0]:.2f} before, {load_after[0]:.2f} after")
    for seconds, command in steps:
        print(f"{seconds:8.2f} s  {command}")
    setup = sum(s for s, c in steps if c.startswith("bash scripts/setup.sh"))
    print(f"{total:8.2f} s  in all; {total - setup:.2f} s after set-up ({setup:.2f} s)")


if __name__ == "__main__":
    main()
