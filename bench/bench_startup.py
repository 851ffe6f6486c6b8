"""Benchmark: start-up of the command line (issue 20): what `dsr-bench` imports, and how long it takes.

    python bench/bench_startup.py [--runs 5]
    PYTHONPATH=/tmp/head python bench/bench_startup.py   # another tree (e.g. `git archive HEAD`), same venv

Prints the median wall seconds over --runs fresh processes of
  - `dsr-bench --help` (the console script of this interpreter's environment; `python -m dsr_bench`
    where there is none),
  - `python -c "import dsr_bench"`,
  - a one-sequence cube run (`generate --objects cube -n 1 --steps 1`): the whole run, and its imports
    (`python -X importtime`, the top-level cumulative times summed). pybullet's own line is hidden, as
    `generators.physics.import_pybullet` sends stderr to /dev/null while pybullet prints its build banner,
    so pybullet alone (`python -X importtime -c "import pybullet"`) is printed beside it;
and which heavy libraries (HEAVY, then a few notable others) each command leaves in sys.modules.
Every process runs in a scratch directory, so that `python -c` and `-m` (which put the working directory
first on sys.path) import the installed tree, or PYTHONPATH's. Timings on a shared machine are noisy: compare
medians taken on the same machine at the same time.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: Libraries that `dsr-bench --help` must not import (tests/test_startup.py): 0.1 to 1 s each to import.
HEAVY: tuple[str, ...] = ("torch", "open3d", "trimesh", "plotly", "dash", "pybullet", "rerun", "scipy",
                          "matplotlib")
#: Also reported, not asserted anywhere.
NOTABLE: tuple[str, ...] = ("pandas", "skimage", "PIL", "networkx", "h5py", "numpy", "isal")
#: A one-sequence, one-push cube run (add --out DIR).
CUBE_RUN: tuple[str, ...] = ("generate", "--objects", "cube", "-n", "1", "--steps", "1")

#: Run `dsr-bench` in-process for each argv of a JSON list (argv[1]) and write, per argv, its exit code and
#: the modules of `names` (argv[2]) then in sys.modules, as JSON to the file argv[3]. Output is discarded.
_PROBE = """
import contextlib, io, json, sys
runs, names, report = json.loads(sys.argv[1]), json.loads(sys.argv[2]), []
from dsr_bench.cli import main
for argv in runs:
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        rc = main(argv)
    report.append({"argv": argv, "rc": rc, "loaded": [n for n in names if n in sys.modules]})
report.append({"dsr_bench": sys.modules["dsr_bench"].__file__})
with open(sys.argv[3], "w") as f:
    json.dump(report, f)
"""


def probe(runs: list[list[str]], names=HEAVY, cwd: Path | None = None) -> list[dict]:
    """Run `dsr-bench` with each argv of `runs` in turn, in one fresh interpreter; per argv: {"argv", "rc",
    "loaded": the modules of `names` in sys.modules after it (and after the argvs before it)}. The last entry
    is {"dsr_bench": the file of the dsr_bench package that ran}. Runs in `cwd` (default: a scratch directory)."""
    with tempfile.TemporaryDirectory(prefix="dsr-bench-probe-") as tmp:
        out = Path(tmp) / "report.json"
        done = subprocess.run([sys.executable, "-c", _PROBE, json.dumps(runs), json.dumps(list(names)), str(out)],
                              capture_output=True, text=True, cwd=cwd or tmp, check=False)
        if done.returncode != 0 or not out.is_file():
            raise RuntimeError(f"probe failed (exit {done.returncode}): {done.stderr.strip()[-2000:]}")
        return json.loads(out.read_text())


def help_commands(cwd: Path) -> list[list[str]]:
    """`--help` of the app and of every registered subcommand, as argvs (asked of a fresh interpreter)."""
    code = ("import json; from dsr_bench.cli import app; "
            "print(json.dumps([c.name for c in app.registered_commands]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=cwd, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"listing the commands failed (exit {done.returncode}): {done.stderr.strip()[-2000:]}")
    return [["--help"]] + [[name, "--help"] for name in json.loads(done.stdout)]


def _cli() -> list[str]:
    script = Path(sys.executable).parent / "dsr-bench"
    if script.is_file():
        return [str(script)]
    found = shutil.which("dsr-bench")
    return [found] if found else [sys.executable, "-m", "dsr_bench"]


def _wall(command: list[str], cwd: Path) -> tuple[float, subprocess.CompletedProcess]:
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, cwd=cwd, check=False)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed (exit {done.returncode}): {done.stderr.strip()[-2000:]}")
    return seconds, done


def import_seconds(importtime: str) -> float:
    """Seconds of the top-level imports in `python -X importtime` output (cumulative, summed)."""
    total = 0
    for line in importtime.splitlines():
        if not line.startswith("import time:") or "|" not in line:
            continue
        _, cumulative, name = line.split("|", 2)
        if name.startswith(" ") and not name.startswith("  ") and cumulative.strip().isdigit():
            total += int(cumulative)
    return total / 1e6


def _median(values: list[float]) -> str:
    return f"{statistics.median(values):6.3f} s  (min {min(values):.3f}, max {max(values):.3f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=5, help="fresh processes per figure (the median is printed)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="dsr-bench-startup-") as tmp:
        here = Path(tmp)
        helps = help_commands(here)
        report = probe(helps + [[*CUBE_RUN, "--out", str(here / "probe")]], HEAVY + NOTABLE, cwd=here)
        help_loaded = sorted({n for r in report[:len(helps)] for n in r["loaded"]})
        cube_loaded = report[len(helps)]["loaded"]
        cli_help, import_only, cube_wall, cube_imports, pybullet = [], [], [], [], []
        for i in range(args.runs):
            cli_help.append(_wall([*_cli(), "--help"], here)[0])
            import_only.append(_wall([sys.executable, "-c", "import dsr_bench"], here)[0])
            seconds, done = _wall([sys.executable, "-X", "importtime", "-m", "dsr_bench", *CUBE_RUN,
                                   "--out", str(here / f"run{i}")], here)
            cube_wall.append(seconds)
            cube_imports.append(import_seconds(done.stderr))
            alone = _wall([sys.executable, "-X", "importtime", "-c", "import pybullet"], here)[1]
            pybullet.append(import_seconds(alone.stderr))

    cube = " ".join(CUBE_RUN)
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}; python {sys.version.split()[0]}; "
          f"dsr_bench from {Path(report[-1]['dsr_bench']).parent}")
    print(f"medians of {args.runs} fresh processes:")
    print(f"  dsr-bench --help                                {_median(cli_help)}")
    print(f"  python -c 'import dsr_bench'                    {_median(import_only)}")
    print(f"  {cube}          {_median(cube_wall)}")
    print(f"    its imports (-X importtime, top level summed) {_median(cube_imports)}  (pybullet's line hidden)")
    print(f"    pybullet alone (-X importtime)                {_median(pybullet)}")
    print(f"heavy libraries ({', '.join(HEAVY)}) and notable others ({', '.join(NOTABLE)}) imported:")
    print(f"  by --help of the app and of its {len(helps) - 1} commands: {', '.join(help_loaded) or 'none'}")
    print(f"  by the cube run: {', '.join(cube_loaded) or 'none'}")


if __name__ == "__main__":
    main()
