"""Helpers of the tests of what a host must never lose or miss and of remote workers: the challenge's real processes
(`dsr-bench serve`, `dsr-bench challenge worker`) in their own process groups (their logs in files), the server's
worker processes found by parent pid, a database read straight, a submission's state waited for; the fixtures of a
throwaway PostgreSQL cluster and of new databases of either backend; challenges bound to a database holding
submissions stored as the server stores them. Test modules import the fixtures (`postgres`, `backend`) by name."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from challenge_helpers import (DEADLINE, PostgresCluster, copy_challenge, free_port, postgres_binaries, serve_args,
                               wait_until, wait_until_serving)


def dsr_bench(*args: str, log: Path, **kwargs) -> subprocess.Popen:
    """`python -m dsr_bench ARGS` in its own session (process group), stdout and stderr appended to `log`."""
    with open(log, "ab") as out:
        return subprocess.Popen([sys.executable, "-m", "dsr_bench", *args], stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True, **kwargs)


class Served:
    """`dsr-bench serve ROOT [ARGS]` on a free loopback port; with `wait`, returns once it answers /healthz."""

    def __init__(self, root: Path, log: Path, *args: str, wait: bool = True):
        self.root, self.log = root, log
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc = dsr_bench(*serve_args(root, self.port, *args), log=log)
        self.group = self.proc.pid
        if wait:
            try:
                wait_until_serving(self.url, self.proc, log=self.tail)
            except RuntimeError:
                self.kill()
                raise

    def tail(self) -> str:
        return self.log.read_text(errors="replace")[-3000:] if self.log.exists() else ""

    def outcome(self) -> int | None:
        """Wait until the server exits (its exit status) or answers /healthz (None)."""
        import httpx

        def settled():
            if self.proc.poll() is not None:
                return ("exited",)
            try:
                return ("serving",) if httpx.get(f"{self.url}/healthz", timeout=5).status_code == 200 else None
            except httpx.TransportError:
                return None

        return self.proc.returncode if wait_until(settled, "the server exiting or serving")[0] == "exited" else None

    def workers(self) -> list[int]:
        """The pids of the server's evaluation worker processes (multiprocessing's spawned children)."""
        return children(self.proc.pid, "spawn_main")

    def kill_server_only(self) -> None:
        """SIGKILL the server process alone (its workers are left as a crash leaves them)."""
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
        self.proc.wait(DEADLINE)

    def kill(self) -> None:
        """SIGKILL the server and everything in its process group."""
        try:
            os.killpg(self.group, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait(DEADLINE)

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.group, signal.SIGINT)
            try:
                self.proc.wait(DEADLINE)
            except subprocess.TimeoutExpired:
                pass
        self.kill()


def children(parent: int, marker: str = "") -> list[int]:
    """The pids of `parent`'s living child processes whose command line holds `marker`."""
    found = []
    for status in Path("/proc").glob("[0-9]*/status"):
        try:
            fields = dict(line.split(":\t", 1) for line in status.read_text().splitlines() if ":\t" in line)
            cmdline = (status.parent / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if int(fields.get("PPid", "0").strip()) == parent and marker in cmdline and \
                not fields.get("State", "").startswith("Z"):
            found.append(int(status.parent.name))
    return found


def alive(pid: int) -> bool:
    """Whether `pid` is a living process (a zombie is not)."""
    try:
        state = Path(f"/proc/{pid}/status").read_text().split("State:\t", 1)[1][0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def owner_pid(owner: str | None) -> int:
    """The pid in a worker's lease owner `<host>-<pid>-<random>` (0 for another form)."""
    parts = (owner or "").rsplit("-", 2)
    return int(parts[1]) if len(parts) == 3 and parts[1].isdigit() else 0


def rows(url: str, sql: str, **params) -> list[tuple]:
    """The rows of `sql` on the database at `url` (read straight, no binding check)."""
    from sqlalchemy import text

    from dsr_bench.challenge.db import make_engine

    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            return [tuple(r) for r in connection.execute(text(sql), params)]
    finally:
        engine.dispose()


def wait_state(url: str, sid: str, states: tuple[str, ...]) -> str:
    """Poll the database at `url` until submission `sid` is in one of `states`; returns it."""
    def state():
        found = rows(url, "SELECT state FROM submissions WHERE id = :sid", sid=sid)
        return found[0][0] if found and found[0][0] in states else None

    return wait_until(state, f"submission {sid} in one of {states}", interval=0.1)


def stop_process(proc: subprocess.Popen) -> None:
    """SIGKILL `proc`'s process group (if still there) and reap it."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait(DEADLINE)


def wait_exit(proc: subprocess.Popen) -> int:
    wait_until(lambda: proc.poll() is not None, "the process exiting")
    return proc.returncode


def postgres_cluster(tmp_path_factory):
    """A throwaway PostgreSQL cluster, yielded (a module's `postgres` fixture: `yield from postgres_cluster(...)`);
    skipped, saying why, without its binaries."""
    bin_dir = postgres_binaries()
    if bin_dir is None:
        pytest.skip("PostgreSQL's initdb and pg_ctl are not installed (Debian: apt-get install postgresql)")
    pytest.importorskip("psycopg")
    cluster = PostgresCluster(tmp_path_factory.mktemp("pg"), bin_dir).start()
    yield cluster
    cluster.stop()


def database_maker(request, tmp_path):
    """A function making a new, empty database (by name) of the backend `request.param` names (a module's `backend`
    fixture, parametrised "sqlite" / "postgresql"): a SQLite file beside the challenge (not DIR/challenge.db), or a
    database of the module's `postgres` cluster."""
    def make(name: str) -> str:
        if request.param == "sqlite":
            return f"sqlite:///{tmp_path / f'{name}.db'}"
        return request.getfixturevalue("postgres").url(f"{name}{time.monotonic_ns()}")

    return make


def open_db(url: str):
    from dsr_bench.challenge.db import open_database

    return open_database(url)


def store(layout, sessions, n: int, team: str = "team a", states: tuple[str, ...] = ()) -> list[str]:
    """`n` submissions of `team` as the server stores them (the archive, then its row), in `states` (queued)."""
    from sqlalchemy import select

    from dsr_bench.challenge.db import Submission, Team, utcnow
    from dsr_bench.challenge.service import add_team

    with sessions() as session:
        team_id = session.scalar(select(Team.id).where(Team.name == team))
    if team_id is None:
        add_team(sessions, team)
        with sessions() as session:
            team_id = session.scalar(select(Team.id).where(Team.name == team))
    layout.submissions.mkdir(exist_ok=True)
    ids = []
    for i in range(n):
        sid = os.urandom(16).hex()
        layout.archive(sid).write_bytes(f"archive {sid}".encode())
        with sessions.begin() as session:
            session.add(Submission(id=sid, team_id=team_id, method=f"m{i}", state=(states or ("queued",) * n)[i],
                                   attempts=0, created_at=utcnow(), archive_sha256="0" * 64, archive_bytes=7,
                                   messages="[]", final=False, rescore=False))
        ids.append(sid)
    return ids


def archives(layout) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(layout.submissions.rglob("*.tar"))}


def identity(url: str) -> str | None:
    from dsr_bench.challenge.binding import read_identity

    engine, sessions = open_db(url)
    try:
        found = read_identity(sessions)
        return found.challenge_id if found else None
    finally:
        engine.dispose()


def bound(tmp_path, tmp_path_factory, url: str, n: int = 3):
    """A challenge (under `tmp_path`) bound to the database at `url` by its first command, holding `n` queued
    submissions; (layout, their ids, the static model's predictions)."""
    from dsr_bench.challenge.layout import Layout
    from dsr_bench.cli import main

    tmp_path.mkdir(parents=True, exist_ok=True)
    root, predictions = copy_challenge(tmp_path_factory, tmp_path)
    assert main(["challenge", "add-team", str(root), "team a", "--db", url]) == 0
    engine, sessions = open_db(url)
    ids = store(Layout(root), sessions, n)
    engine.dispose()
    return Layout(root), ids, predictions
