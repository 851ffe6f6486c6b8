"""Evaluation workers beyond the server's machine (issue 43): `dsr-bench challenge worker DIR --db URL` leases jobs
from the same PostgreSQL database as `dsr-bench serve DIR --db URL` and its own worker, reading the archives and
hidden sets from the shared DIR. Started as its own process, killed with SIGKILL while it holds a job and started
again: every job is scored, each scoring recorded once (one score row per part and run), and the killed worker's
extracted archive does not stay in DIR/work."""

from __future__ import annotations

import os
import signal

import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")
pytest.importorskip("argon2")

from challenge_helpers import DEADLINE, copy_challenge, post, wait_until  # noqa: E402
from challenge_served import Served, dsr_bench, owner_pid, postgres_cluster, rows, stop_process  # noqa: E402

from dsr_bench.cli import main  # noqa: E402


@pytest.fixture(scope="module")
def postgres(tmp_path_factory):
    yield from postgres_cluster(tmp_path_factory)


def _held_by(url: str, pid: int) -> list[str]:
    """The jobs the worker process `pid` (of this host) holds now."""
    return [sid for sid, owner in rows(url, "SELECT id, lease_owner FROM submissions WHERE state = 'running'")
            if owner_pid(owner) == pid]


def _stopped_on_a_job(url: str, root, worker, rescored: list[str]) -> str | None:
    """Stop `worker` (SIGSTOP) while it holds a job; that job's id, or None (then, when every job is finished, one is
    queued again with `challenge rescore`, counted in `rescored`, so that the worker gets another)."""
    assert worker.poll() is None, f"the remote worker exited ({worker.returncode})"
    held = _held_by(url, worker.pid)
    if held:
        os.kill(worker.pid, signal.SIGSTOP)
        if held[0] in _held_by(url, worker.pid):
            return held[0]
        os.kill(worker.pid, signal.SIGCONT)
    states = rows(url, "SELECT id, state, rescore FROM submissions ORDER BY created_at")
    # every job finished and none marked for a re-score (one marked stays "scored" until a worker takes it)
    if all(state in ("scored", "refused", "failed") and not again for _, state, again in states):
        assert main(["challenge", "rescore", str(root), states[-1][0], "--db", url]) == 0
        rescored.append(states[-1][0])
    return None


def test_a_remote_worker_killed_and_restarted_scores_each_job_once(tmp_path, tmp_path_factory, postgres, capsys):
    from dsr_bench.challenge.client import pack
    from dsr_bench.challenge.layout import Layout

    root, predictions = copy_challenge(tmp_path_factory, tmp_path)
    layout = Layout(root)
    url = postgres.url("remote")
    capsys.readouterr()
    assert main(["challenge", "add-team", str(root), "team", "--db", url]) == 0
    token = capsys.readouterr().out.strip()
    pack(predictions, tmp_path / "p.tar")
    served = Served(root, tmp_path / "serve.log", "--db", url, "--workers", "1")
    worker = restarted = None
    rescored: list[str] = []
    try:
        ids = []
        for i in range(3):
            reply = post(f"{served.url}/api/submissions", params={"method": f"m{i}"},
                         content=(tmp_path / "p.tar").read_bytes(), headers={"Authorization": f"Bearer {token}"})
            assert reply.status_code == 202, reply.text
            ids.append(reply.json()["id"])
        # the second worker: its own process, as on another machine
        worker = dsr_bench("challenge", "worker", str(root), "--db", url, log=tmp_path / "worker.log")
        killed = wait_until(lambda: _stopped_on_a_job(url, root, worker, rescored), "the remote worker on a job")
        stop_process(worker)  # SIGKILL while it holds the job (stopped: it cannot finish it first)
        assert killed in [sid for sid, _ in rows(url, "SELECT id, 1 FROM submissions WHERE state = 'running'")]
        restarted = dsr_bench("challenge", "worker", str(root), "--db", url, log=tmp_path / "worker.log")

        def finished() -> bool:
            states = dict(rows(url, "SELECT id, state FROM submissions"))
            assert restarted.poll() is None, (tmp_path / "worker.log").read_text()[-2000:]
            return all(states[sid] == "scored" for sid in ids)

        wait_until(finished, "every job scored")
        for sid in ids:
            runs = rows(url, "SELECT part, run FROM scores WHERE submission_id = :sid ORDER BY part, run", sid=sid)
            expected = range(1, rescored.count(sid) + 2)
            assert runs == [("private", r) for r in expected] + [("public", r) for r in expected], sid
        [(attempts,)] = rows(url, "SELECT attempts FROM submissions WHERE id = :sid", sid=killed)
        assert attempts >= 2  # the killed worker's attempt, then the one that scored it
        assert not list(layout.work.glob(f"{killed}-*"))  # the killed worker's extracted archive removed
        os.killpg(restarted.pid, signal.SIGTERM)  # stops after its job
        assert restarted.wait(DEADLINE) == 0
        assert "worker stopped after" in (tmp_path / "worker.log").read_text()
    finally:
        for proc in (worker, restarted):
            if proc is not None:
                stop_process(proc)
        served.stop()
