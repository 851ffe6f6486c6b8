"""Benchmark: seconds per 10-step cube sequence and bytes on disk per step, the authors' generator against ours,
side by side.

    python bench/bench_generate_official.py [--official-repo PATH] [--repeats 3] [--steps 10]
                                            [--official-python PATH] [--official-env DIR] [--no-venv]

Alternates (A, B, A, B, ...), each run a fresh process that pays its imports and writes one
sequence to a fresh directory:
- the authors' generator, only with `--official-repo PATH` (a checkout of columbia-ai-robotics/dsr):
  `python data_generation.py --data_path DIR --object_type cube --train_num 1 --test_num 0`, run
  from their repository root in their own environment (built once with their dependencies, see
  bench/official.py; --no-venv runs it with --official-python as is). It is unseeded;
- ours: `dsr-bench generate --objects cube -n 1 --workers 1 --seed K --out DIR`, K = --seed + run;
- ours with `--sleep-at-rest` (every object asleep through each push until touched), the same seeds.
Prints each side's median wall seconds and median process CPU seconds per sequence (user + system time of
the process and everything it waited for, all threads: the authors' generator steps its physics in a
free-running thread and waits on fixed sleeps and polling, so on a loaded machine its wall time says more about
the load than about the work), the ratios of the medians, each side's median bytes on disk per step (every file
the run wrote, over its steps; the authors' files hold one step each) and their ratio, and one markdown table
row (date, cores, load, both medians and ranges, ratios) to quote. Without `--official-repo` only our side is
run and no comparison is made. Both generators are single-process.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from official import (add_official_args, alternate, check_official_repo, last_line,  # noqa: E402
                      official_python, report, run_main)

from dsr_bench.errors import UserError  # noqa: E402

THEIRS = "authors' data_generation.py"
OURS = "dsr-bench generate"
OURS_ASLEEP = "dsr-bench generate --sleep-at-rest"


def our_command(out: Path, seed: int, steps: int, sleep_at_rest: bool = False) -> list[str]:
    """`dsr-bench generate` for one cube sequence (the CLI of this environment)."""
    exe = Path(sys.executable).with_name("dsr-bench")
    if not exe.exists():
        found = shutil.which("dsr-bench")
        if found is None:
            raise UserError("dsr-bench: command not found next to this Python or on PATH; install the toolkit "
                            "(pip install -e .[sim]) in this environment")
        exe = Path(found)
    cmd = [str(exe), "generate", "--objects", "cube", "-n", "1", "--workers", "1", "--seed", str(seed),
           "--out", str(out)]
    return cmd + (["--steps", str(steps)] if steps != 10 else []) + (["--sleep-at-rest"] if sleep_at_rest
                                                                   else [])


def official_command(python: Path, out: Path, steps: int) -> list[str]:
    """The authors' generator for one cube sequence (run from their repository root)."""
    cmd = [str(python), "data_generation.py", "--data_path", str(out), "--object_type", "cube", "--train_num", "1",
           "--test_num", "0"]
    return cmd + (["--max_path_length", str(steps)] if steps != 10 else [])


def bytes_on_disk(out: Path) -> int:
    """Bytes of every file under `out` (what a run wrote)."""
    return sum(p.stat().st_size for p in out.rglob("*") if p.is_file())


def children_cpu_seconds() -> float:
    """User + system CPU seconds of every child process this one has waited for so far (all their threads)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_process(what: str, cmd: list[str], out: Path, cwd: Path | None, logs: Path, timeout: float,
                env: dict | None = None, sizes: list[int] | None = None, cpu: list[float] | None = None) -> float:
    """Wall seconds of one fresh process writing into `out` (removed afterwards; the bytes it wrote appended to
    `sizes`, its process CPU seconds to `cpu`); a failure, or a run that wrote nothing, is a one-line UserError
    with the last line of its output."""
    log = logs / ("theirs.log" if what == THEIRS else "ours-asleep.log" if what == OURS_ASLEEP else "ours.log")
    with open(log, "w") as fh:
        c0 = children_cpu_seconds()
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, cwd=cwd, stdout=fh, stderr=subprocess.STDOUT, timeout=timeout, env=env)
        except subprocess.TimeoutExpired:
            raise UserError(f"{what}: still running after {timeout:.0f} s (--timeout); output in {log}") from None
        seconds = time.perf_counter() - t0
        if cpu is not None:
            cpu.append(children_cpu_seconds() - c0)
    if proc.returncode != 0:
        raise UserError(f"{what} failed: `{' '.join(cmd)}` exited {proc.returncode} "
                        f"({last_line(log.read_text())}; output in {log})")
    if not out.is_dir() or not any(p.is_file() for p in out.rglob("*")):
        raise UserError(f"{what} wrote nothing under {out} (`{' '.join(cmd)}`; output in {log})")
    if sizes is not None:
        sizes.append(bytes_on_disk(out))
    shutil.rmtree(out)
    return seconds


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3, help="runs of each side, alternated (default 3)")
    parser.add_argument("--steps", type=int, default=10, help="pushes per sequence (default 10, the authors')")
    parser.add_argument("--seed", type=int, default=0, help="our base seed; run i uses seed + i")
    parser.add_argument("--timeout", type=float, default=900, help="seconds one run may take (default 900)")
    add_official_args(parser)
    args = parser.parse_args(argv)

    repo = python = None
    if args.official_repo is not None:
        repo = check_official_repo(args.official_repo, ("data_generation.py",))
        python = official_python(args, repo)
    work = Path(tempfile.mkdtemp(prefix="dsr-bench-generate-official-"))
    logs = Path(tempfile.mkdtemp(prefix="dsr-bench-generate-logs-"))  # kept when a run fails
    try:
        count = {OURS: 0, OURS_ASLEEP: 0, "theirs": 0}
        sizes: dict[str, list[int]] = {OURS: [], OURS_ASLEEP: [], THEIRS: []}
        cpu: dict[str, list[float]] = {THEIRS: [], OURS: [], OURS_ASLEEP: []}

        def our_side(side: str) -> float:
            seed = args.seed + count[side]
            count[side] += 1
            out = work / f"{'asleep' if side == OURS_ASLEEP else 'ours'}-{seed}"
            return run_process(side, our_command(out, seed, args.steps, side == OURS_ASLEEP), out, None, logs,
                               args.timeout, sizes=sizes[side], cpu=cpu[side])

        def ours() -> float:
            return our_side(OURS)

        def ours_asleep() -> float:
            return our_side(OURS_ASLEEP)

        def theirs() -> float:
            count["theirs"] += 1
            out = work / f"theirs-{count['theirs']}"
            env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
            return run_process(THEIRS, official_command(python, out, args.steps), out, repo, logs, args.timeout, env,
                               sizes[THEIRS], cpu[THEIRS])

        runs = {THEIRS: theirs} if repo else {}
        runs.update({OURS: ours, OURS_ASLEEP: ours_asleep})
        pairs = [(THEIRS, OURS), (THEIRS, OURS_ASLEEP), (OURS, OURS_ASLEEP)] if repo else [(OURS, OURS_ASLEEP)]
        load_before = os.getloadavg()[0]
        timings = alternate(runs, args.repeats)
        load_after = os.getloadavg()[0]
        shutil.rmtree(logs)
        cpu = {side: values for side, values in cpu.items() if values}
        print(f"one {args.steps}-step cube sequence per run, a fresh process each; {os.cpu_count()} cores, load "
              f"average {load_before:.1f} before and {load_after:.1f} after; {args.repeats} runs of each side"
              + (", alternated" if repo else ""))
        print("wall seconds:")
        figures = report(timings, pairs, per=1, unit="sequence")
        print("process CPU seconds (user + system, all threads):")
        cpu_figures = report(cpu, pairs, per=1, unit="sequence")
        figures.update({f"CPU {key}": value for key, value in cpu_figures.items()})
        per_step = {side: statistics.median(b) / args.steps / 1e6 for side, b in sizes.items() if b}
        for side, mb in per_step.items():
            print(f"{side}: {mb:.3f} MB on disk per step (median of {len(sizes[side])} runs)")
        if THEIRS in per_step:
            figures["MB per step"] = per_step
            print(f"bytes per step, {THEIRS} / {OURS}: {per_step[THEIRS] / per_step[OURS]:.2f}x")
        if not repo:
            print("no comparison with the authors' code was made: pass --official-repo PATH (a checkout of "
                  "columbia-ai-robotics/dsr) to run their data_generation.py beside ours")
            return {"timings": timings, "cpu": cpu, "figures": figures}
        date = dt.date.today().isoformat()

        def cell(values: list[float], digits: int) -> str:
            return f"{statistics.median(values):.{digits}f} ({min(values):.{digits}f}-{max(values):.{digits}f})"

        print("\n| date | machine | CPU s/sequence, theirs | CPU s/sequence, ours | CPU ratio | ours, asleep | "
              "CPU ratio, asleep | wall s, theirs | wall s, ours | wall ratio | wall, asleep | wall ratio, asleep | "
              "MB/step, theirs | MB/step, ours | ratio | runs |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        print(f"| {date} | {os.cpu_count()} cores, load {load_before:.1f}-{load_after:.1f} | {cell(cpu[THEIRS], 1)} | "
              f"{cell(cpu[OURS], 2)} | {figures[f'CPU {THEIRS} / {OURS}']:.1f}x | {cell(cpu[OURS_ASLEEP], 2)} | "
              f"{figures[f'CPU {THEIRS} / {OURS_ASLEEP}']:.1f}x | {cell(timings[THEIRS], 1)} | "
              f"{cell(timings[OURS], 2)} | {figures[f'{THEIRS} / {OURS}']:.1f}x | {cell(timings[OURS_ASLEEP], 2)} | "
              f"{figures[f'{THEIRS} / {OURS_ASLEEP}']:.1f}x | {per_step[THEIRS]:.2f} | "
              f"{per_step[OURS]:.2f} | {per_step[THEIRS] / per_step[OURS]:.1f}x | "
              f"{args.repeats} of each side, alternated, medians (ranges) |")
        return {"timings": timings, "cpu": cpu, "figures": figures}
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    run_main(main)
