"""Generation and evaluation beyond one machine (issue 19): on a Ray cluster (`--ray`, here a local Ray each test
starts and stops) and as a SLURM job array through submitit (`--slurm`, here submitit's local executor,
`--slurm-local`). Every HDF5 array of every sequence, the manifest's digests and the split checksum equal a
single-process run's, and the results JSON's numbers an evaluation's in one process; the engines give outcomes in
the order of the jobs with progress per job, and name a failed remote job in one line; the users' errors (two
engines, --shard with one, an unreachable address, no SLURM, ray not installed) are one line each; and neither ray
nor submitit is imported unless an engine is asked for."""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
import socket
import sys
from pathlib import Path

import pytest

from dsr_bench.cli import main
from helpers import assert_same_dataset

REPO = Path(__file__).resolve().parents[1]
ARGS = ["generate", "--objects", "cube", "-n", "4", "--steps", "2", "--seed", "5"]

needs_simulator = pytest.mark.skipif(importlib.util.find_spec("pybullet") is None, reason="needs pybullet (sim extra)")


def _generate(out: Path, *extra: str) -> Path:
    assert main([*ARGS, "--out", str(out), *extra]) == 0
    return out


def _error(capsys) -> str:
    """The one line a failed command printed on stderr."""
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, lines
    return lines[0]


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --- the same dataset, the same results ---------------------------------------------------------------------------
@needs_simulator
def test_generate_on_a_local_ray_equals_one_process(tmp_path):
    pytest.importorskip("ray")
    plain = _generate(tmp_path / "plain")
    assert_same_dataset(_generate(tmp_path / "ray", "--ray", "local", "--workers", "2"), plain)


@needs_simulator
def test_generate_as_a_submitit_array_equals_one_process(tmp_path):
    pytest.importorskip("submitit")
    plain = _generate(tmp_path / "plain")
    logs = tmp_path / "logs"
    got = _generate(tmp_path / "slurm", "--slurm", "--slurm-local", "--slurm-tasks", "2", "--slurm-logs", str(logs))
    assert_same_dataset(got, plain)
    assert len(list(logs.glob("*_result.pkl"))) == 2  # two array tasks ran
    _generate(got, "--slurm", "--slurm-local", "--slurm-logs", str(logs))  # complete: resumed, nothing submitted
    assert len(list(logs.glob("*_result.pkl"))) == 2


def test_evaluate_on_ray_and_as_a_submitit_array_equals_one_process(tmp_path):
    pytest.importorskip("ray")
    pytest.importorskip("submitit")
    from dsr_bench.testing import write_synthetic_dataset

    data = write_synthetic_dataset(tmp_path / "data", num_sequences=3, num_steps=2)
    pred = tmp_path / "pred"
    assert main(["predict", "--model", "push", "--data", str(data), "--out", str(pred)]) == 0
    engines = {"plain": [], "ray": ["--ray", "local", "--workers", "2"],
               "slurm": ["--slurm", "--slurm-local", "--slurm-tasks", "2", "--slurm-logs", str(tmp_path / "logs")]}
    results = {}
    for name, extra in engines.items():
        out = tmp_path / f"{name}.json"
        assert main(["evaluate", str(pred), "--data", str(data), "--out", str(out), *extra]) == 0
        found = json.loads(out.read_text())
        assert found["coverage"]["scored"] == 3
        found.pop("date")
        results[name] = json.dumps(found, sort_keys=True)  # text: NaN equals NaN, every float to the last bit
    assert results["ray"] == results["plain"] and results["slurm"] == results["plain"]


def test_slurm_logs_go_in_the_output_directory_unless_named(tmp_path, monkeypatch):
    """--slurm without --slurm-logs writes submitit's files in slurm-logs/ of the run's output directory (evaluate:
    PRED_DIR, which the nodes share anyway), nothing in the current directory; --slurm-logs DIR puts them there."""
    pytest.importorskip("submitit")
    from dsr_bench.engines import engine_from_options, slurm_options_given
    from dsr_bench.testing import write_synthetic_dataset

    data = write_synthetic_dataset(tmp_path / "data", num_sequences=1, num_steps=1)
    pred = tmp_path / "pred"
    assert main(["predict", "--model", "static", "--data", str(data), "--out", str(pred)]) == 0
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    assert main(["evaluate", str(pred), "--slurm", "--slurm-local", "--slurm-tasks", "1"]) == 0
    assert list(here.iterdir()) == [] and len(list((pred / "slurm-logs").glob("*_result.pkl"))) == 1
    local = slurm_options_given(None, None, None, None, True)
    engine = engine_from_options(slurm=True, slurm_options=local, output=Path("data/out"))
    assert engine.options.folder == here / "data" / "out" / "slurm-logs"  # generate: in its --out
    named = slurm_options_given(None, None, None, Path("logs"), True)
    assert engine_from_options(slurm=True, slurm_options=named, output=Path("x")).options.folder == here / "logs"


# --- the engines' contract ------------------------------------------------------------------------------------------
JOBS = [5, 3, 0, 7, 1]


def _check_engine(engine) -> None:
    """Outcomes in the order of the jobs, progress once per job; a job that raises is named in one line."""
    from dsr_bench.engines import JobFailed

    calls: list[tuple[int, int]] = []
    assert engine.map(math.factorial, JOBS, progress=lambda done, total: calls.append((done, total))) == [
        math.factorial(j) for j in JOBS]
    assert calls == [(done, len(JOBS)) for done in range(1, len(JOBS) + 1)]
    with pytest.raises(JobFailed) as failed:
        engine.map(math.sqrt, [4.0, -1.0, 9.0], describe=lambda job: f"sqrt({job})")
    message = str(failed.value)
    assert "sqrt(-1.0) failed" in message and "ValueError: math domain error" in message and "\n" not in message


def test_ray_engine_keeps_order_and_names_a_failed_job():
    ray = pytest.importorskip("ray")
    from dsr_bench.engines import RayEngine

    ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING")
    try:
        _check_engine(RayEngine("auto"))
        assert ray.is_initialized()  # a Ray the caller connected to is left connected
    finally:
        ray.shutdown()


def test_submitit_engine_keeps_order_and_names_a_failed_job(tmp_path):
    pytest.importorskip("submitit")
    from dsr_bench.engines import SlurmEngine, SlurmOptions

    engine = SlurmEngine(SlurmOptions(folder=tmp_path / "logs", tasks=2, time_min=5, local=True))
    _check_engine(engine)
    failed = [p for p in (tmp_path / "logs").glob("*_log.err") if "math domain error" in p.read_text()]
    assert len(failed) == 1  # the traceback is in the failed task's log


# --- the users' errors ------------------------------------------------------------------------------------------------
def test_engine_options_refused_with_one_line(tmp_path, capsys, monkeypatch):
    out = str(tmp_path / "out")
    cases = [
        (["--ray", "local", "--slurm"], "--ray and --slurm both given"),
        (["--ray", "local", "--shard", "0/2"],
         "--shard 0/2 with --ray: the engine splits the run itself; drop --shard"),
        (["--slurm", "--slurm-local", "--shard", "1/2"], "drop --shard"),
        (["--slurm-partition", "gpu"], "need --slurm"),
        (["--slurm", "--slurm-local", "--slurm-tasks", "0"], "--slurm-tasks 0: must be at least 1"),
    ]
    if importlib.util.find_spec("submitit") and not shutil.which("sbatch"):
        cases.append((["--slurm"], "sbatch is not on PATH here"))
    for extra, expected in cases:
        assert main([*ARGS, "--out", out, *extra]) == 2, extra
        assert expected in _error(capsys), extra
    monkeypatch.setitem(sys.modules, "ray", None)  # as if ray were not installed
    assert main([*ARGS, "--out", out, "--ray", "auto"]) == 2
    assert "pip install 'dsr-bench[cluster]'" in _error(capsys)
    assert not Path(out).exists()  # refused before anything was written


@needs_simulator
def test_an_unreachable_ray_address_is_one_line(tmp_path, capsys):
    pytest.importorskip("ray")
    address = f"127.0.0.1:{_closed_port()}"
    assert main([*ARGS, "--out", str(tmp_path / "out"), "--ray", address]) == 2
    line = _error(capsys)
    assert f"--ray {address}: nothing answers" in line and "ray start --head" in line
    assert not (tmp_path / "out").exists()  # refused before anything was written


def test_help_and_a_plain_run_import_neither_ray_nor_submitit(tmp_path):
    sys.path.insert(0, str(REPO / "bench"))
    import bench_startup

    runs = [["generate", "--help"], ["evaluate", "--help"]]
    if importlib.util.find_spec("pybullet"):
        runs.append([*bench_startup.CUBE_RUN, "--out", str(tmp_path / "cubes")])
    report = bench_startup.probe(runs, ("ray", "submitit"), cwd=REPO)
    for entry in report[:-1]:
        assert entry["rc"] == 0 and entry["loaded"] == [], entry
