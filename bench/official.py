"""Helpers for benchmarks that run the authors' code (columbia-ai-robotics/dsr) beside ours.

The rule: a figure that compares with the authors' code is measured against the authors' code,
side by side in one run, the runs alternated (A, B, A, B, ...), medians reported. The authors' code
is never copied into this repository: a benchmark loads it from a checkout the user names with
`--official-repo PATH`.

- `add_official_args(parser)`: `--official-repo`, `--official-python`, `--official-env`, `--no-venv`.
- `check_official_repo(path, needs)`: a one-line `UserError` unless `path` is a checkout holding `needs`.
- `official_env(repo, scratch_dir, python)`: the interpreter of a separate virtual environment with
  the authors' dependencies (/work/shared/notes/official-release.md), built once and cached outside
  the toolkit's environment (default ~/.cache/dsr-bench/official-env).
- `load_official_functions(repo, names, source)`: just the named functions of one of their files
  (and the imports those use), extracted with `ast`, so that their other imports (their model
  needs cupy) are never run.
- `alternate(runs, repeats)`: the sides run A, B, A, B, ...; `report(...)`: medians and ratios.
"""

from __future__ import annotations

import argparse
import ast
import json
import shutil
import statistics
import subprocess
import sys
import symtable
import time
from pathlib import Path
from typing import Callable

from dsr_bench.errors import UserError, one_line

OFFICIAL_REPOSITORY = "columbia-ai-robotics/dsr"
# The authors' generator's environment (official-release.md, "Running the authors' code beside ours").
OFFICIAL_REQUIREMENTS = ("numpy==1.23.5", "numba==0.57.1", "pybullet==3.2.7", "opencv-python-headless",
                         "scikit-image<0.22", "h5py<3.12", "trimesh", "dominate", "tqdm")
DEFAULT_ENV_DIR = Path("~/.cache/dsr-bench/official-env")
NEWEST_PYTHON = (3, 11)  # numpy 1.23.5 and numba 0.57.1 have no wheels for later versions


def add_official_args(parser: argparse.ArgumentParser, needs_env: bool = True) -> None:
    """Add `--official-repo PATH` (and, for benchmarks that run the authors' scripts in their own
    environment, `--official-python`, `--official-env`, `--no-venv`)."""
    parser.add_argument("--official-repo", type=Path, metavar="PATH",
                        help=f"a checkout of {OFFICIAL_REPOSITORY}: run the authors' code beside ours, alternated "
                             "(without it only our side is measured and no comparison is made)")
    if not needs_env:
        return
    parser.add_argument("--official-python", type=Path, metavar="PATH",
                        help="interpreter to build the authors' environment with (Python 3.8-3.11; default: this "
                             "one); with --no-venv, the interpreter that runs their code as is")
    parser.add_argument("--official-env", type=Path, metavar="DIR", default=DEFAULT_ENV_DIR,
                        help=f"where the authors' environment is built and cached (default {DEFAULT_ENV_DIR})")
    parser.add_argument("--no-venv", action="store_true",
                        help="build no environment: run the authors' code with --official-python as it is "
                             "(an environment you made yourself)")


def check_official_repo(path: str | Path | None, needs: tuple[str, ...] = ("data_generation.py",)) -> Path:
    """The checkout's path, or a one-line UserError naming what is missing."""
    if path is None:
        raise UserError("--official-repo: no path given")
    path = Path(path).expanduser()
    if not path.is_dir():
        raise UserError(f"--official-repo {path}: not a directory; pass a checkout of {OFFICIAL_REPOSITORY}")
    missing = [name for name in needs if not (path / name).is_file()]
    if missing:
        raise UserError(f"--official-repo {path}: not a checkout of {OFFICIAL_REPOSITORY} "
                        f"({', '.join(missing)} missing)")
    return path.resolve()


def _python_version(python: Path) -> tuple[int, int]:
    try:
        out = subprocess.run([str(python), "-c", "import sys; print(*sys.version_info[:2])"], capture_output=True,
                             text=True, check=True, timeout=60).stdout.split()
    except (OSError, subprocess.SubprocessError) as exc:
        raise UserError(f"--official-python {python}: cannot run it ({one_line(exc)})") from None
    return int(out[0]), int(out[1])


def last_line(text: str) -> str:
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[-1] if lines else "no output"


def official_env(repo: str | Path, scratch_dir: str | Path | None = None, python: str | Path | None = None,
                 requirements: tuple[str, ...] = OFFICIAL_REQUIREMENTS, log: Callable[[str], None] = print) -> Path:
    """The Python interpreter of a virtual environment holding the authors' dependencies.

    Built once with `python` (default: this interpreter) under `scratch_dir` (default
    ~/.cache/dsr-bench/official-env), one environment per Python version, and reused while its
    requirements are unchanged. It must lie outside the toolkit's own environment. A failing pip
    is reported in one line with the log's path and the way out (--official-python, --no-venv)."""
    repo = Path(repo)
    scratch = Path(scratch_dir or DEFAULT_ENV_DIR).expanduser().resolve()
    if scratch.is_relative_to(Path(sys.prefix).resolve()):
        raise UserError(f"--official-env {scratch}: inside the toolkit's environment {sys.prefix}; "
                        "pass a directory outside it")
    python = Path(python or sys.executable)
    major, minor = _python_version(python)
    if (major, minor) > NEWEST_PYTHON:
        raise UserError(f"--official-python {python} is Python {major}.{minor}: numpy 1.23.5 and numba 0.57.1 have "
                        "no wheels for it; pass --official-python PATH of a Python 3.8-3.11")
    env = scratch / f"venv-py{major}.{minor}"
    env_python = env / "bin" / "python"
    marker = env / "dsr-bench-official-env.json"
    wanted = {"requirements": list(requirements), "python": f"{major}.{minor}", "repo": str(repo)}
    if marker.exists() and env_python.exists():
        try:
            if json.loads(marker.read_text())["requirements"] == wanted["requirements"]:
                return env_python
        except (ValueError, KeyError):
            pass
    scratch.mkdir(parents=True, exist_ok=True)
    if env.exists():
        shutil.rmtree(env)
    logfile = scratch / f"pip-py{major}.{minor}.log"
    log(f"building the authors' environment in {env} with {python} (once; log: {logfile})")
    steps = [[str(python), "-m", "venv", str(env)],
             [str(env_python), "-m", "pip", "install", "--upgrade", "pip"],
             [str(env_python), "-m", "pip", "install", "--prefer-binary", *requirements]]
    with open(logfile, "w") as fh:
        for cmd in steps:
            fh.write(f"$ {' '.join(cmd)}\n")
            fh.flush()
            proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT)
            if proc.returncode != 0:
                shutil.rmtree(env, ignore_errors=True)
                raise UserError(f"building the authors' environment failed: `{' '.join(cmd[1:4])} ...` exited "
                                f"{proc.returncode} ({last_line(logfile.read_text())}; log: {logfile}); pass "
                                "--official-python PATH of a Python 3.8-3.11 with wheels for numpy 1.23.5, or "
                                "--no-venv --official-python PATH of an environment you built")
    marker.write_text(json.dumps(wanted, indent=1))
    return env_python


def official_python(args: argparse.Namespace, repo: Path, log: Callable[[str], None] = print) -> Path:
    """The interpreter that runs the authors' scripts, from the options `add_official_args` adds."""
    if args.no_venv:
        python = Path(args.official_python or sys.executable)
        _python_version(python)  # runs at all
        return python
    return official_env(repo, args.official_env, args.official_python, log=log)


def _global_names(table: symtable.SymbolTable) -> set[str]:
    """Names a function (and the scopes nested in it) looks up in the module or the builtins."""
    names = {s.get_name() for s in table.get_symbols() if s.is_global()}
    for child in table.get_children():
        names |= _global_names(child)
    return names


def _bound_names(node: ast.stmt) -> set[str]:
    if isinstance(node, (ast.Import, ast.ImportFrom)):
        return {(a.asname or a.name.split(".")[0]) for a in node.names}
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return {node.name}
    if isinstance(node, (ast.Assign, ast.AnnAssign)):
        targets = node.targets if isinstance(node, ast.Assign) else [node.target]
        return {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}
    return set()


def load_official_functions(repo: str | Path, names: tuple[str, ...] = ("calc_iou_unordered", "calc_iou_ordered"),
                            source: str = "test.py") -> dict[str, Callable]:
    """The named top-level functions of `repo/source`, run in a fresh namespace: only their
    definitions, the top-level functions, classes and constants they use, and the imports those
    need are executed (their `test.py` imports their model, which needs cupy: never run here)."""
    path = check_official_repo(repo, (source,)) / source
    text = path.read_text()
    try:
        tree = ast.parse(text, filename=str(path))
        table = symtable.symtable(text, str(path), "exec")
    except SyntaxError as exc:
        raise UserError(f"{path}: cannot be parsed by this Python ({one_line(exc)})") from None
    top = {name: node for node in tree.body for name in _bound_names(node)}
    scopes = {child.get_name(): child for child in table.get_children()}
    missing = [n for n in names if not isinstance(top.get(n), (ast.FunctionDef, ast.AsyncFunctionDef))]
    if missing:
        raise UserError(f"{path} defines no function {', '.join(missing)}: not the authors' {source}?")
    keep: set[int] = set()
    todo = list(names)
    seen: set[str] = set()
    while todo:
        name = todo.pop()
        if name in seen or name not in top:
            continue  # a builtin, or a name the file never binds at the top level
        seen.add(name)
        node = top[name]
        keep.add(id(node))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and name in scopes:
            todo += _global_names(scopes[name])
            # decorators, defaults and annotations are evaluated at module level
            header = [*node.decorator_list, *getattr(getattr(node, "args", None), "defaults", [])]
            todo += [n.id for h in header for n in ast.walk(h) if isinstance(n, ast.Name)]
        elif not isinstance(node, (ast.Import, ast.ImportFrom)):
            todo += [n.id for n in ast.walk(node) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)]
    body = [node for node in tree.body if id(node) in keep
            or (isinstance(node, ast.ImportFrom) and node.module == "__future__")]
    namespace: dict = {"__name__": f"official_{path.stem}", "__file__": str(path)}
    module = ast.Module(body=body, type_ignores=[])
    try:
        exec(compile(module, str(path), "exec"), namespace)
    except ImportError as exc:
        raise UserError(f"{path}: {', '.join(names)} need a module this Python lacks ({one_line(exc)})") from None
    return {name: namespace[name] for name in names}


def alternate(runs: dict[str, Callable[[], float | None]], repeats: int) -> dict[str, list[float]]:
    """Run the sides in turn, A, B, A, B, ..., `repeats` times each; seconds per run per side.

    A side returns the seconds it measured itself (e.g. only the calls under test), or None to be
    timed as a whole."""
    if repeats < 1:
        raise UserError(f"--repeats {repeats}: must be at least 1")
    timings: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run in runs.items():
            t0 = time.perf_counter()
            seconds = run()
            timings[name].append(float(time.perf_counter() - t0 if seconds is None else seconds))
    return timings


def report(timings: dict[str, list[float]], ratios: list[tuple[str, str]] = (), per: int = 1,
           unit: str = "sequence", out: Callable[[str], None] = print) -> dict[str, float]:
    """Print each side's median (and per `unit`, over `per` units), and for each (slower, faster)
    pair the ratio of their medians; returns {side: median seconds per unit, "A / B": ratio}."""
    width = max(len(name) for name in timings) + 2
    out(f"{'':{width}s}{'runs':>5s}{'median s':>11s}{f's/{unit}':>14s}{'min s':>10s}{'max s':>10s}")
    result: dict[str, float] = {}
    for name, values in timings.items():
        median = statistics.median(values)
        result[name] = median / per
        out(f"{name:{width}s}{len(values):5d}{median:11.3f}{median / per:14.3f}{min(values):10.3f}{max(values):10.3f}")
    for slower, faster in ratios:
        ratio = statistics.median(timings[slower]) / statistics.median(timings[faster])
        result[f"{slower} / {faster}"] = ratio
        out(f"{slower} / {faster}: {ratio:.1f}x (medians of runs alternated side by side)")
    return result


def run_main(main: Callable[[list[str] | None], None], argv: list[str] | None = None) -> None:
    """Run a benchmark's main: a UserError is printed as one line and exits 2 (as the CLI does)."""
    try:
        main(argv)
    except UserError as exc:
        print(f"error: {one_line(exc)}", file=sys.stderr)
        raise SystemExit(2) from None
