"""Helpers of the challenge tests: a small challenge directory (2 synthetic sequences of 2 pushes, made once per
session and copied), static predictions on its exported inputs, a uvicorn server on a loopback port, crafted tar
archives, a throwaway PostgreSQL cluster, and waiting on events.

Waiting: a test waits for what it needs to happen (a server answering, a submission's state, a file gone), polled
until a generous overall `DEADLINE` (`wait_until`, `wait_for_state`, `wait_until_serving`), never for a fixed time a
loaded machine may exceed (the suite also runs at load 15 on 2 cores); HTTP requests get a per-request timeout
(`REQUEST_TIMEOUT`) long enough that it is never what limits a test (`get` retries until the deadline, `post` sends
once: an upload is not repeated behind the server's back)."""

from __future__ import annotations

import io
import os
import shutil
import socket
import subprocess
import tarfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

_TEMPLATE: dict[str, Path] = {}
T = TypeVar("T")

#: seconds a test waits, at most, for an event (polled): generous, as passing it means the event never came
DEADLINE = 600.0
#: `dsr-bench serve`'s free-disk margin in the tests (MiB; 1024 by default): small, so that the suite's own 1 GiB
#: upload test beside them, or a CI disk of a few GiB, does not make the other servers refuse their uploads (507)
SERVE_KEEP_FREE_MIB = 64
#: seconds one HTTP request may take (httpx's per-request timeout; its default of 5 s is exceeded under load)
REQUEST_TIMEOUT = 300.0
#: the submission states a worker leaves a submission in
FINISHED = ("scored", "refused", "failed")


def serve_args(root: Path, port: int, *args: str) -> list[str]:
    """The arguments of `dsr-bench serve ROOT --port PORT ARGS` as the tests run it: with their free-disk margin
    (`SERVE_KEEP_FREE_MIB`; a --keep-free in ARGS comes later and wins)."""
    return ["serve", str(root), "--port", str(port), "--keep-free", str(SERVE_KEEP_FREE_MIB), *args]


def wait_until(condition: Callable[[], T], what: str, deadline: float = DEADLINE, interval: float = 0.05) -> T:
    """Poll `condition()` until it returns something true (returned) or `deadline` seconds pass (AssertionError
    naming `what` and the last value)."""
    end = time.monotonic() + deadline
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > end:
            raise AssertionError(f"{what}: not within {deadline:.0f} s (last: {value!r})")
        time.sleep(interval)


def get(url: str, deadline: float = DEADLINE, **kwargs: Any):
    """httpx.get with `REQUEST_TIMEOUT`, tried again after a transport error (a refused connection, a timeout)
    until `deadline` seconds pass: a GET changes nothing, so repeating it is safe."""
    import httpx

    kwargs.setdefault("timeout", REQUEST_TIMEOUT)
    end = time.monotonic() + deadline
    while True:
        try:
            return httpx.get(url, **kwargs)
        except httpx.TransportError:
            if time.monotonic() > end:
                raise
            time.sleep(0.2)


def post(url: str, **kwargs: Any):
    """httpx.post with `REQUEST_TIMEOUT`, sent once (an upload repeated after a timeout could be stored twice)."""
    import httpx

    kwargs.setdefault("timeout", REQUEST_TIMEOUT)
    return httpx.post(url, **kwargs)


def wait_for_state(url: str, sid: str, states: tuple[str, ...] = FINISHED, deadline: float = DEADLINE) -> dict:
    """The status JSON of submission `sid` on the server at `url` once its state is one of `states`, polled until
    `deadline` seconds pass."""
    last: dict = {}

    def reached() -> bool:
        last.clear()
        last.update(get(f"{url}/api/submissions/{sid}", deadline=deadline).json())
        return last.get("state") in states

    wait_until(reached, f"submission {sid} in one of {states}", deadline, interval=0.2)
    return dict(last)


def wait_until_serving(url: str, proc: subprocess.Popen | None = None, deadline: float = DEADLINE,
                       log: Callable[[], str] = lambda: "") -> None:
    """Wait until the server at `url` answers /healthz with 200 (connections refused meanwhile: it is starting);
    RuntimeError, with `log()`, if `proc` exits first or `deadline` seconds pass."""
    import httpx

    end = time.monotonic() + deadline
    while True:
        try:
            if httpx.get(f"{url}/healthz", timeout=REQUEST_TIMEOUT).status_code == 200:
                return
        except httpx.TransportError:
            pass
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"the server exited ({proc.returncode}) before it answered: {log()}")
        if time.monotonic() > end:
            raise RuntimeError(f"the server did not answer within {deadline:.0f} s: {log()}")
        time.sleep(0.1)


def challenge_template(base: Path) -> tuple[Path, Path]:
    """(challenge directory, predictions directory of the static model on its inputs), made once under `base`:
    use `copy_challenge` for a directory a test may change."""
    if "root" not in _TEMPLATE:
        from dsr_bench.challenge.host import export_inputs, finish_hidden_set
        from dsr_bench.challenge.layout import HIDDEN_SPLIT, Layout, write_secret_seed
        from dsr_bench.models.predictors import load_predictor, predict_split
        from dsr_bench.testing import write_synthetic_dataset

        root = base / "challenge"
        root.mkdir(mode=0o700)
        layout = Layout(root)
        write_secret_seed(layout, 987654321987654321)
        write_synthetic_dataset(layout.hidden, num_sequences=2, num_steps=2, split=HIDDEN_SPLIT)
        finish_hidden_set(layout, {"split": "synthetic"})
        export_inputs(layout, layout.inputs)
        predictions = base / "predictions"
        predict_split(load_predictor("static"), layout.inputs, ["seq_0000", "seq_0001"], predictions)
        _TEMPLATE.update(root=root, predictions=predictions)
    return _TEMPLATE["root"], _TEMPLATE["predictions"]


def copy_challenge(tmp_path_factory, dest: Path) -> tuple[Path, Path]:
    """A fresh copy of the template challenge and its predictions under `dest` (the template is made once per
    session, in the session's base temporary directory)."""
    base = tmp_path_factory.getbasetemp() / "challenge-template"
    base.mkdir(exist_ok=True)
    root, predictions = challenge_template(base)
    shutil.copytree(root, dest / "challenge")
    shutil.copytree(predictions, dest / "predictions")
    return dest / "challenge", dest / "predictions"


class LiveServer:
    """A FastAPI app served by uvicorn on 127.0.0.1 (a free port) in a thread; `url` once entered."""

    def __init__(self, app):
        import uvicorn

        self.server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning"))
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.url = ""

    def __enter__(self) -> LiveServer:
        self.thread.start()
        wait_until(lambda: self.server.started or not self.thread.is_alive(), "the test server starting")
        if not self.server.started:
            raise RuntimeError("the test server did not start")
        port = self.server.servers[0].sockets[0].getsockname()[1]
        self.url = f"http://127.0.0.1:{port}"
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(DEADLINE)


def tar_bytes(members: list[tuple[tarfile.TarInfo, bytes | None]], mode: str = "w") -> bytes:
    """A tar archive (mode "w" or "w:gz") of crafted members: (header, data or None)."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode=mode) as tar:
        for info, data in members:
            if data is not None:
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
            else:
                tar.addfile(info)
    return buffer.getvalue()


def member(name: str, kind: bytes = tarfile.REGTYPE, link: str = "") -> tarfile.TarInfo:
    """A tar header: a regular file by default, or a link, device, FIFO or directory (`kind`)."""
    info = tarfile.TarInfo(name)
    info.type = kind
    info.linkname = link
    return info


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def postgres_binaries() -> Path | None:
    """The directory of PostgreSQL's initdb and pg_ctl (Debian's /usr/lib/postgresql/<v>/bin or PATH), or None."""
    for candidate in sorted(Path("/usr/lib/postgresql").glob("*/bin"), reverse=True):
        if (candidate / "initdb").exists() and (candidate / "pg_ctl").exists():
            return candidate
    found = shutil.which("initdb")
    return Path(found).resolve().parent if found and shutil.which("pg_ctl") else None


class PostgresCluster:
    """A throwaway PostgreSQL cluster in `base` listening on a Unix socket only (run as the `postgres` user when
    this process is root, as initdb refuses root); `url(db)` is a SQLAlchemy URL of a fresh database."""

    def __init__(self, base: Path, bin_dir: Path):
        self.base, self.bin = base, bin_dir
        self.data, self.socket_dir = base / "data", base / "sock"
        self.as_root = os.geteuid() == 0
        self.user = "postgres" if self.as_root else os.environ.get("USER", "postgres")
        self.port = free_port()

    def _run(self, *args: str) -> subprocess.CompletedProcess:
        command = [*(["runuser", "-u", "postgres", "--"] if self.as_root else []), *args]
        return subprocess.run(command, capture_output=True, text=True, timeout=DEADLINE, check=True)

    def start(self) -> PostgresCluster:
        self.base.mkdir(parents=True, exist_ok=True)
        self.socket_dir.mkdir()
        if self.as_root:
            shutil.chown(self.base, "postgres")
            shutil.chown(self.socket_dir, "postgres")
            os.chmod(self.base, 0o755)
            parent = self.base.parent
            while parent != parent.parent:  # the postgres user must reach the directory
                os.chmod(parent, os.stat(parent).st_mode | 0o011)
                parent = parent.parent
        self._run(str(self.bin / "initdb"), "-D", str(self.data), "-A", "trust", "-U", self.user, "--no-sync")
        self._run(str(self.bin / "pg_ctl"), "-D", str(self.data), "-w", "-l", str(self.base / "log"), "-o",
                  f"-c listen_addresses='' -k {self.socket_dir} -p {self.port} -c fsync=off", "start")
        return self

    def url(self, database: str) -> str:
        self._run(str(self.bin / "createdb"), "-h", str(self.socket_dir), "-p", str(self.port), "-U", self.user,
                  database)
        return f"postgresql+psycopg://{self.user}@/{database}?host={self.socket_dir}&port={self.port}"

    def stop(self) -> None:
        self._run(str(self.bin / "pg_ctl"), "-D", str(self.data), "-m", "immediate", "stop")


def challenge_with_teams(tmp_path_factory, tmp_path, teams=("alpha", "beta")):
    """A fresh copy of the module's challenge with `teams` added, yielded as (layout, session factory, {team: token},
    predictions directory); its database closed after (a module's `challenge` fixture: `yield from` it)."""
    from dsr_bench.challenge.db import open_database
    from dsr_bench.challenge.layout import Layout
    from dsr_bench.challenge.service import add_team

    root, predictions = copy_challenge(tmp_path_factory, tmp_path)
    layout = Layout(root)
    engine, sessions = open_database(layout.default_db_url())
    tokens = {name: add_team(sessions, name) for name in teams}
    yield layout, sessions, tokens, predictions
    engine.dispose()
