"""Where per-sequence jobs run: in this process or local worker processes (`LocalEngine`, `dsr_bench.parallel`), on a
Ray cluster (`RayEngine`, `--ray ADDRESS`) or in a SLURM job array submitted with submitit (`SlurmEngine`, `--slurm`);
`dsr-bench generate` and `dsr-bench evaluate` take either.

Every engine maps a picklable function over a list of jobs and gives back the outcomes in the order of the jobs,
calling `progress(done, total)` once per job as it finishes (`Engine.map`), or yields (position, outcome) pairs as
jobs finish (`Engine.as_finished`): the contract of `dsr_bench.parallel.run_in_order`, so a result is the same
array for array whichever engine computed it. A job that raises on a remote node becomes one `JobFailed` line (a
UserError) naming the job and where its traceback is; the remaining jobs are cancelled.

Remote workers read and write the paths they are given: the data, predictions and output directories must be on a
file system every node sees, under the same path (the engines get absolute paths), and dsr-bench must be installed
on every node. ray and submitit (`pip install 'dsr-bench[cluster]'`) are imported only inside the engines' methods.
"""

from __future__ import annotations

import shutil
import sys
import time
import traceback
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from dsr_bench.errors import UserError
from dsr_bench.memory import keep_freed_memory
from dsr_bench.parallel import as_finished, in_order, run_in_order

INSTALL = "pip install 'dsr-bench[cluster]'"


class JobFailed(UserError):
    """A job failed on a Ray worker or in a SLURM array task: the message names the job, the error and where the
    whole traceback is."""


class Engine(ABC):
    """Maps a function over jobs somewhere; subclasses say where (`as_finished`)."""

    #: how the engine is named in messages and summaries
    label = "engine"

    @abstractmethod
    def as_finished(self, function, jobs: list, describe: Callable[[Any], str] | None = None
                    ) -> Iterator[tuple[int, Any]]:
        """(position, `function(jobs[position])`) for every job, as jobs finish; `describe(job)` names a job in
        the message of a failure."""

    def map(self, function, jobs: list, progress: Callable[[int, int], None] | None = None,
            describe: Callable[[Any], str] | None = None) -> list:
        """`[function(j) for j in jobs]`, in the order of `jobs`; `progress(done, total)` once per job as each
        finishes."""
        return in_order(self.as_finished(function, jobs, describe), len(jobs), progress)


class LocalEngine(Engine):
    """This machine: `workers` processes (here when 1), as `dsr_bench.parallel.run_in_order`."""

    def __init__(self, workers: int = 1, mp_context=None) -> None:
        self.workers, self.mp_context = workers, mp_context
        self.label = f"{workers} local process{'es' if workers > 1 else ''}"

    def as_finished(self, function, jobs, describe=None):
        return as_finished(function, jobs, self.workers, self.mp_context)


# --- running one job on a remote worker ----------------------------------------------------------------------------
def call_job(function, job) -> tuple[bool, object]:
    """(True, function(job)), or (False, 'Type: message') when it raises, its traceback printed on this worker's
    stderr (the task's log): an error comes back as data, whatever the engine does with exceptions."""
    keep_freed_memory()
    try:
        return True, function(job)
    except Exception as exc:  # noqa: BLE001 - any failure of the job is reported by the driver, naming the job
        traceback.print_exc()
        sys.stderr.flush()
        return False, _error_line(exc)


def call_jobs(function, jobs: list, workers: int = 1) -> list[tuple[bool, object]]:
    """`call_job` of each job, in `workers` processes (spawned) when more than one: one SLURM array task."""
    import functools
    import multiprocessing

    return run_in_order(functools.partial(call_job, function), jobs, workers,
                        mp_context=multiprocessing.get_context("spawn"))


def _error_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _name(describe: Callable[[object], str] | None, job, position: int) -> str:
    return describe(job) if describe is not None else f"job {position}"


def _need(module: str, option: str):
    """Import `module` (ray, submitit), or one line saying how to install it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise UserError(f"{option} needs {module}, which is not installed: {INSTALL}") from None


# --- Ray --------------------------------------------------------------------------------------------------------------
class RayEngine(Engine):
    """Each job one Ray task (1 CPU) on the cluster at `address` (as `ray.init` takes it: 'auto', 'HOST:PORT',
    'ray://HOST:10001'), or on a Ray started here for the run ('local', with `num_cpus` CPUs, None: all). A Ray
    this process is already connected to is used as it is and left connected; one it connects to is disconnected
    (and a local one stopped) once the jobs are done."""

    def __init__(self, address: str, num_cpus: int | None = None) -> None:
        self.address, self.num_cpus = address, num_cpus
        self.label = f"Ray ({address})"
        _need("ray", f"--ray {address}")
        if address != "local":
            check_reachable(address)  # before any work: Ray itself retries an unreachable address for minutes

    def as_finished(self, function, jobs, describe=None) -> Iterator[tuple[int, Any]]:
        import ray

        if not jobs:  # nothing to do (a resumed run): no connection
            return
        connected = self._connect(ray)
        refs: dict = {}
        try:
            task = ray.remote(num_cpus=1)(call_job)
            refs = {task.remote(function, job): position for position, job in enumerate(jobs)}
            pending = list(refs)
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                position = refs.pop(ready[0])
                yield position, self._outcome(ray, ready[0], _name(describe, jobs[position], position))
        finally:
            for ref in refs:  # the jobs not finished: a failure or an interruption stops the rest
                ray.cancel(ref)
            if connected:
                ray.shutdown()

    def _outcome(self, ray, ref, name: str):
        where = "its traceback is in the Ray worker's log (`ray logs`, or above when the driver shows them)"
        try:
            ok, value = ray.get(ref)
        except ray.exceptions.RayError as exc:  # the worker died, ran out of memory, ...
            raise JobFailed(f"{name} failed on Ray ({self.address}): {_first_line(exc)}; {where}") from None
        if not ok:
            raise JobFailed(f"{name} failed on Ray ({self.address}): {value}; {where}")
        return value

    def _connect(self, ray) -> bool:
        """Connect unless connected already; True when this call connected."""
        if ray.is_initialized():
            return False
        fix = "start one (`ray start --head`) and give its address, or use --ray local"
        try:
            if self.address == "local":
                ray.init(address="local", num_cpus=self.num_cpus, include_dashboard=False, logging_level="WARNING")
            else:
                ray.init(address=self.address, logging_level="WARNING")
        except ConnectionError as exc:
            why = "none runs on this machine and RAY_ADDRESS is not set" if self.address == "auto" else _first_line(exc)
            raise UserError(f"--ray {self.address}: no Ray cluster found ({why}); {fix}") from None
        except ValueError as exc:
            if "ray[client]" in str(exc):
                raise UserError(f"--ray {self.address}: a ray:// address needs Ray's client: "
                                "pip install 'ray[client]'") from None
            raise UserError(f"--ray {self.address}: {_first_line(exc)}; {fix}") from None
        return True


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def check_reachable(address: str, timeout: float = 10.0) -> None:
    """UserError unless something answers on the host and port of a Ray address ('HOST:PORT' or
    'ray://HOST:PORT'; 'auto' and other forms are left to Ray): Ray itself retries an unreachable address for
    minutes."""
    import socket

    rest = address.split("://", 1)[-1]
    host, _, port = rest.rpartition(":")
    if not host or not port.isdigit():
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as exc:
        raise UserError(f"--ray {address}: nothing answers at {host}:{port} ({exc.strerror or exc}); start the "
                        "cluster (`ray start --head`) or give its address (auto, HOST:6379, "
                        "ray://HOST:10001)") from None


# --- SLURM through submitit -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SlurmOptions:
    """A SLURM job array: `tasks` array tasks of `cpus_per_task` CPUs (as many processes), `time_min` minutes each,
    on `partition`; submitit's files and the tasks' logs in `folder` (None: `engine_from_options` puts them in
    slurm-logs/ under the run's output directory); `local`: run the tasks as processes here (submitit's local
    executor) instead of submitting them."""

    folder: Path | None = None
    partition: str | None = None
    time_min: int = 60
    tasks: int = 8
    cpus_per_task: int = 1
    local: bool = False

    def check(self) -> None:
        """Reject options that cannot make an array."""
        if self.tasks < 1:
            raise UserError(f"--slurm-tasks {self.tasks}: must be at least 1")
        if self.time_min < 1:
            raise UserError(f"--slurm-time {self.time_min}: must be at least 1 (minutes)")
        if self.cpus_per_task < 1:
            raise UserError(f"--workers {self.cpus_per_task}: must be at least 1 (the processes of each array task)")
        if not self.local and shutil.which("sbatch") is None:
            raise UserError("--slurm: SLURM's sbatch is not on PATH here; run the command on a SLURM login node, or "
                            "add --slurm-local to run the array's tasks on this machine")


_DEFAULT = SlurmOptions()
#: The folder of a SLURM run's logs in its output directory, unless --slurm-logs names one.
LOGS_NAME = "slurm-logs"
#: The command-line options of the engines, shared by `generate` and `evaluate` (their help texts).
HELP = {
    "ray": "Run the sequences as tasks on a Ray cluster: its address as ray.init takes it (auto, HOST:PORT, "
           "ray://HOST:10001), or local to start Ray on this machine (with --workers CPUs, default all). The "
           "directories must be on a file system every node sees, and dsr-bench installed on every node.",
    "slurm": "Submit the sequences as a SLURM job array (submitit) and wait for it; each task runs its sequences in "
             "--workers processes (default 1). The directories and --slurm-logs must be on a file system every node "
             "sees.",
    "slurm_partition": "SLURM partition of the array (default: the cluster's).",
    "slurm_time": f"Time limit of each array task, in minutes (default {_DEFAULT.time_min}).",
    "slurm_tasks": f"Array tasks (default {_DEFAULT.tasks}): task k runs the sequences at positions k, k + n, ... "
                   "(the --shard k/n rule).",
    "slurm_logs": f"Folder of submitit's job files and the tasks' logs (default: {LOGS_NAME}/ in the output "
                  "directory, generate's --out or evaluate's PRED_DIR, never the current directory).",
    "slurm_local": "Run the array's tasks as processes on this machine (submitit's local executor) instead of "
                   "submitting them: to try a --slurm command without SLURM.",
}


class SlurmEngine(Engine):
    """The jobs split over a SLURM job array (task k: the jobs at positions k, k + n, ...), submitted with
    submitit, each task running its jobs in `cpus_per_task` processes; the driver waits, polling, and yields a
    task's outcomes when it ends. An interrupted driver cancels the array."""

    def __init__(self, options: SlurmOptions, name: str = "dsr-bench") -> None:
        options.check()
        _need("submitit", "--slurm")
        self.options, self.name = options, name
        tasks = f"{options.tasks} task{'s' if options.tasks > 1 else ''}"
        self.label = f"SLURM array of {tasks}{' (local executor)' if options.local else ''}"

    def as_finished(self, function, jobs, describe=None):
        if not jobs:  # nothing to do (a resumed run): no array
            return
        n = min(self.options.tasks, len(jobs))
        chunks = [list(range(len(jobs)))[k::n] for k in range(n)]
        submitted = self._submit(function, [[jobs[p] for p in chunk] for chunk in chunks])
        pending = dict(zip(submitted, enumerate(chunks)))
        poll = 0.5 if self.options.local else 10.0
        try:
            while pending:
                finished = [job for job in pending if job.done()]
                if not finished:
                    time.sleep(poll)
                for job in finished:
                    k, chunk = pending.pop(job)
                    yield from zip(chunk, self._outcomes(job, k, chunk, jobs, describe))
        finally:
            for job in pending:  # a failure or an interruption cancels the tasks still queued or running
                job.cancel(check=False)

    def _submit(self, function, chunks: list[list]) -> list:
        import submitit

        o = self.options
        executor = submitit.AutoExecutor(folder=o.folder or LOGS_NAME, cluster="local" if o.local else "slurm")
        executor.update_parameters(name=self.name, timeout_min=o.time_min, cpus_per_task=o.cpus_per_task,
                                   slurm_partition=o.partition, slurm_array_parallelism=len(chunks))
        try:
            return executor.map_array(call_jobs, [function] * len(chunks), chunks, [o.cpus_per_task] * len(chunks))
        except Exception as exc:  # noqa: BLE001 - sbatch's refusal (a bad partition, a time over the limit, ...)
            raise UserError(f"--slurm: the array was not submitted ({_first_line(exc)}); check --slurm-partition "
                            f"and --slurm-time") from None

    def _outcomes(self, job, k: int, chunk: list[int], jobs: list, describe) -> list:
        try:
            results = job.result()
        except Exception as exc:  # noqa: BLE001 - submitit's UncompletedJobError: killed, timed out, node failure
            names = ", ".join(_name(describe, jobs[p], p) for p in chunk[:4]) + (", ..." if len(chunk) > 4 else "")
            raise JobFailed(f"SLURM array task {k} ({names}) did not finish: {_first_line(exc)}; its log: "
                            f"{job.paths.stderr} (a longer --slurm-time?)") from None
        for position, (ok, value) in zip(chunk, results):
            if not ok:
                raise JobFailed(f"{_name(describe, jobs[position], position)} failed in SLURM array task {k}: "
                                f"{value}; its traceback: {job.paths.stderr}")
        return [value for _, value in results]


# --- from the command line --------------------------------------------------------------------------------------------
def engine_from_options(ray: str | None = None, slurm: bool = False, workers: int | None = None,
                        slurm_options: SlurmOptions | None = None, name: str = "dsr-bench",
                        output: Path | None = None) -> Engine | None:
    """The engine that --ray / --slurm ask for, None for neither (the command's own processes). `workers`: the CPUs
    of a `--ray local` Ray (None or 0: all), the processes of each SLURM array task (None or 0: 1). The other
    --slurm-* options (`slurm_options`, None: not given) need --slurm. `output`: the run's output directory, on the
    file system the nodes share; SLURM's logs go in its slurm-logs/ unless --slurm-logs names a folder."""
    if ray is not None and slurm:
        raise UserError("--ray and --slurm both given: choose one engine")
    if workers is not None and workers < 0:
        raise UserError(f"--workers {workers}: must be at least 0")
    if slurm_options is not None and not slurm:
        raise UserError("--slurm-partition, --slurm-time, --slurm-tasks, --slurm-logs and --slurm-local need --slurm")
    if ray is not None:
        if not ray.strip():
            raise UserError("--ray '': give an address (auto, HOST:PORT, ray://HOST:10001) or local")
        return RayEngine(ray.strip(), num_cpus=workers or None)
    if slurm:
        options = replace(slurm_options or SlurmOptions(), cpus_per_task=workers or 1)
        folder = options.folder if options.folder is not None else Path(output or ".") / LOGS_NAME
        return SlurmEngine(replace(options, folder=Path(folder).absolute()), name=name)
    return None


def slurm_options_given(partition: str | None, time_min: int | None, tasks: int | None, logs: Path | None,
                        local: bool) -> SlurmOptions | None:
    """SlurmOptions from the --slurm-* options, their defaults where not given; None when none was given."""
    if partition is None and time_min is None and tasks is None and logs is None and not local:
        return None
    return SlurmOptions(folder=logs, partition=partition,
                        time_min=_DEFAULT.time_min if time_min is None else time_min,
                        tasks=_DEFAULT.tasks if tasks is None else tasks, local=local)
