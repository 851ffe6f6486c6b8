"""The challenge's rules hold against a script, on SQLite and on a throwaway PostgreSQL cluster: twenty uploads sent
at once use exactly the daily quota, six final choices at once keep the limit, the end freezes final choices and
the reveal closes submissions, the phase is checked when an upload is stored (and an upload's time is bounded),
X-Forwarded-For is trusted only from a proxy the host names, every byte of a multipart body counts and a malformed
one is one line, names are normalised and look-alikes refused, and a submission's parts share one track."""

from __future__ import annotations

import datetime as dt
import json
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")
pytest.importorskip("argon2")

import httpx  # noqa: E402
from challenge_helpers import (DEADLINE, LiveServer, copy_challenge, free_port, get, post, serve_args,  # noqa: E402
                               wait_for_state, wait_until, wait_until_serving)
from challenge_served import postgres_cluster  # noqa: E402

from dsr_bench.errors import UserError  # noqa: E402


@pytest.fixture(scope="module")
def postgres(tmp_path_factory):
    yield from postgres_cluster(tmp_path_factory)


@pytest.fixture(params=["sqlite", "postgresql"])
def challenge(request, tmp_path, tmp_path_factory):
    """(layout, session factory, {team: token}, predictions, database URL) of a fresh challenge on each database."""
    from dsr_bench.challenge.db import open_database
    from dsr_bench.challenge.layout import Layout
    from dsr_bench.challenge.service import add_team

    root, predictions = copy_challenge(tmp_path_factory, tmp_path)
    layout = Layout(root)
    url = (layout.default_db_url() if request.param == "sqlite"
           else request.getfixturevalue("postgres").url(f"t{time.monotonic_ns()}"))
    engine, sessions = open_database(url)
    tokens = {name: add_team(sessions, name) for name in ("alpha", "beta")}
    yield layout, sessions, tokens, predictions, url
    engine.dispose()


def _serve(layout, url, settings=None, **overrides) -> LiveServer:
    from dsr_bench.challenge.server import Settings, create_app

    settings = settings or Settings(keep_free=0, auth_max_delay=0.01, board_cache=0.0)
    settings.overrides = overrides or None
    return LiveServer(create_app(layout.root, url, settings))


def _archive(predictions: Path, tmp_path: Path) -> bytes:
    from dsr_bench.challenge.client import pack

    pack(predictions, tmp_path / "p.tar")
    return (tmp_path / "p.tar").read_bytes()


def _upload(url: str, token: str, body, method: str = "static") -> httpx.Response:
    return post(f"{url}/api/submissions", params={"method": method}, content=body,
                headers={"Authorization": f"Bearer {token}"})


def _rows(sessions, team: str | None = None) -> list:
    from sqlalchemy import select

    from dsr_bench.challenge.db import Submission, Team

    with sessions() as session:
        query = select(Submission).join(Team, Team.id == Submission.team_id)
        return list(session.scalars(query.where(Team.name == team) if team else query))


def _at_once(n: int, call) -> list:
    """`call(i)` in `n` threads released together; their results in order."""
    barrier = threading.Barrier(n)
    results: list = [None] * n

    def run(i: int) -> None:
        barrier.wait()
        results[i] = call(i)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(DEADLINE)
    return results


def _scored(sessions, team: str, private: list[float]) -> list[str]:
    """Scored submissions of `team` written straight to the database, one per private IoU (public 0.5 each)."""
    import secrets

    from sqlalchemy import select

    from dsr_bench.challenge.db import Score, Submission, Team, utcnow

    ids = []
    with sessions.begin() as session:
        team_id = session.scalar(select(Team.id).where(Team.name == team))
        for i, value in enumerate(private):
            sid = secrets.token_hex(16)
            ids.append(sid)
            session.add(Submission(id=sid, team_id=team_id, method=f"m{i}", state="scored", attempts=1,
                                   created_at=utcnow() - dt.timedelta(minutes=len(private) - i), track="3D",
                                   archive_sha256="0" * 64, archive_bytes=1, messages="[]", final=False,
                                   rescore=False))
            session.flush()
            for part, iou in (("public", 0.5), ("private", value)):
                session.add(Score(submission_id=sid, part=part, run=1, current=True, rank_value=iou,
                                  metrics=json.dumps({"metrics": {"iou_ordered": iou}}), toolkit_version="test"))
    return ids


def _final(url: str, token: str, sid: str, final: bool = True) -> httpx.Response:
    return post(f"{url}/api/submissions/{sid}/final", json={"final": final},
                headers={"Authorization": f"Bearer {token}"})


def test_twenty_uploads_at_once_use_exactly_the_daily_quota(challenge, tmp_path):
    layout, sessions, tokens, predictions, url = challenge
    body = _archive(predictions, tmp_path)
    with _serve(layout, url, daily_limit=5) as live:
        replies = _at_once(20, lambda i: _upload(live.url, tokens["alpha"], body, f"try {i}"))
    codes = sorted(r.status_code for r in replies)
    assert codes == [202] * 5 + [429] * 15, codes
    assert all("5 submissions of today" in r.json()["detail"] for r in replies if r.status_code == 429)
    assert len(_rows(sessions, "alpha")) == 5
    assert len(list(layout.submissions.glob("*.tar"))) == 5  # the refused ones' archives are not kept


def test_six_final_choices_at_once_keep_the_limit(challenge):
    layout, sessions, tokens, _, url = challenge
    ids = _scored(sessions, "alpha", [0.1] * 6)
    with _serve(layout, url, max_final=2) as live:
        replies = _at_once(6, lambda i: _final(live.url, tokens["alpha"], ids[i]))
    assert sorted(r.status_code for r in replies) == [200] * 2 + [400] * 4
    assert sum(s.final for s in _rows(sessions, "alpha")) == 2


def test_the_end_freezes_final_choices_and_the_reveal_closes_submissions(challenge, tmp_path):
    from dsr_bench.challenge.db import utcnow
    from dsr_bench.challenge.layout import open_challenge, write_config
    from dsr_bench.challenge.service import add_phase

    layout, sessions, tokens, predictions, url = challenge
    low, high = _scored(sessions, "alpha", [0.0, 0.1685])
    now = utcnow()
    with _serve(layout, url) as live:
        assert _final(live.url, tokens["alpha"], low).status_code == 200
        add_phase(sessions, "only", now - dt.timedelta(days=2), now - dt.timedelta(days=1))  # it has ended
        mine = get(f"{live.url}/api/me/submissions", headers={"Authorization": f"Bearer {tokens['alpha']}"}).json()
        assert all(set(s["scores"]) == {"public"} for s in mine["submissions"])  # private scores: not before reveal
        for sid, final in ((high, True), (low, False)):
            swap = _final(live.url, tokens["alpha"], sid, final)
            assert swap.status_code == 403 and "last phase has ended" in swap.json()["detail"], swap.text
        write_config(layout, {**open_challenge(layout.root)[1], "reveal_private": True})
        swap = _final(live.url, tokens["alpha"], high)
        assert swap.status_code == 403 and "revealed" in swap.json()["detail"]
        ranking = get(f"{live.url}/api/leaderboard").json()["final"]["3D"]
        assert [(r["id"], r["metrics"]["iou_ordered"]) for r in ranking] == [(low, 0.0)]


def test_the_reveal_ends_the_challenge_without_phases(challenge, tmp_path):
    from dsr_bench.challenge.layout import open_challenge, write_config

    layout, sessions, tokens, predictions, url = challenge
    sid = _scored(sessions, "alpha", [0.2])[0]
    body = _archive(predictions, tmp_path)
    write_config(layout, {**open_challenge(layout.root)[1], "reveal_private": True})
    with _serve(layout, url) as live:
        late = _upload(live.url, tokens["beta"], body)
        assert late.status_code == 403 and "revealed" in late.json()["detail"], late.text
        assert _final(live.url, tokens["alpha"], sid).status_code == 403
        assert "revealed" in get(live.url + "/").text
    assert _rows(sessions, "beta") == []


def test_an_upload_still_arriving_when_its_phase_ends_is_refused(challenge, tmp_path):
    from sqlalchemy import update

    from dsr_bench.challenge.db import Phase, utcnow
    from dsr_bench.challenge.service import add_phase

    layout, sessions, tokens, predictions, url = challenge
    now = utcnow()
    add_phase(sessions, "only", now - dt.timedelta(hours=1), now + dt.timedelta(hours=1))
    body = _archive(predictions, tmp_path)

    def trickled() -> Iterator[bytes]:
        yield body[:1000]  # begun while the phase is open
        wait_until(lambda: list(layout.uploads.glob(".part-*")), "the server receiving the upload")
        with sessions.begin() as session:  # the phase ends while the rest is on its way
            session.execute(update(Phase).values(ends_at=utcnow() - dt.timedelta(seconds=1)))
        yield body[1000:]

    with _serve(layout, url) as live:
        reply = _upload(live.url, tokens["alpha"], trickled())
    assert reply.status_code == 403 and "last phase has ended" in reply.json()["detail"], reply.text
    assert _rows(sessions) == [] and not list(layout.submissions.glob("*.tar"))


def test_an_upload_may_take_a_bounded_time_in_all(challenge, tmp_path):
    from dsr_bench.challenge.server import Settings

    layout, sessions, tokens, predictions, url = challenge
    settings = Settings(keep_free=0, auth_max_delay=0.01, idle_timeout=60.0, upload_timeout=1.0)

    def trickled() -> Iterator[bytes]:  # a byte at a time, never idle for long, until the server gives up
        seen: list[Path] = []
        while True:
            yield b"\0"
            parts = list(layout.uploads.glob(".part-*"))
            seen.extend(parts)
            if seen and not parts:
                return
            time.sleep(0.05)

    with _serve(layout, url, settings) as live:
        try:
            reply = _upload(live.url, tokens["alpha"], trickled())
            assert reply.status_code == 408 and "took more than 1 s" in reply.json()["detail"], reply.text
        except httpx.TransportError:
            pass  # closed while the client still sent: refused all the same
    assert _rows(sessions) == []


def _serve_process(root: Path, url: str, log: Path, *args: str) -> tuple[subprocess.Popen, str]:
    port = free_port()
    with open(log, "ab") as out:
        proc = subprocess.Popen([sys.executable, "-m", "dsr_bench", *serve_args(root, port, "--workers", "1", "--db",
                                                                                url, *args)],
                                stdout=out, stderr=subprocess.STDOUT)
    server = f"http://127.0.0.1:{port}"
    wait_until_serving(server, proc, log=lambda: log.read_text()[-2000:])
    return proc, server


def _stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(DEADLINE)
    except subprocess.TimeoutExpired:
        proc.kill()


def test_x_forwarded_for_is_trusted_only_from_a_named_proxy(challenge, tmp_path):
    """`dsr-bench serve` trusts no proxy header by default: a client rotating X-Forwarded-For is still one address
    to the failed-token throttle (10 failures, then 429); with --forwarded-allow-ips naming the proxy, it is."""
    layout, sessions, tokens, _, url = challenge

    def failures(server: str) -> list[int]:
        return [get(f"{server}/api/me/submissions", headers={"Authorization": "Bearer dsrc_000000000000_" + "x" * 43,
                                                             "X-Forwarded-For": f"10.0.{i}.1"}).status_code
                for i in range(11)]

    proc, server = _serve_process(layout.root, url, tmp_path / "serve.log")
    try:
        assert failures(server) == [401] * 10 + [429]
    finally:
        _stop(proc)
    if url.startswith("sqlite"):  # the option itself (the database plays no part)
        proc, server = _serve_process(layout.root, url, tmp_path / "proxied.log", "--forwarded-allow-ips",
                                      "127.0.0.1")
        try:
            assert failures(server) == [401] * 11  # each forwarded address failed once
        finally:
            _stop(proc)


def _raw_upload(url: str, token: str, content_type: str, chunks: Iterator[bytes]) -> tuple[int, dict]:
    """POST a chunked body from `chunks` on a raw socket, sent by a thread while the answer is read: (status, JSON
    body), however early the server answers and closes."""
    host, port = url.removeprefix("http://").split(":")
    sock = socket.create_connection((host, int(port)), timeout=DEADLINE)
    sock.sendall(f"POST /api/submissions?method=m HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n"
                 f"Content-Type: {content_type}\r\nTransfer-Encoding: chunked\r\n\r\n".encode())

    def send() -> None:
        try:
            for chunk in chunks:
                sock.sendall(f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n")
            sock.sendall(b"0\r\n\r\n")
        except OSError:
            pass  # the server answered and closed

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    data = b""
    while b"\r\n\r\n" not in data:
        data += sock.recv(65536)
    head, _, rest = data.partition(b"\r\n\r\n")
    lines = head.split(b"\r\n")
    length = int(next(line.split(b":")[1] for line in lines if line.lower().startswith(b"content-length")))
    while len(rest) < length:
        more = sock.recv(65536)
        if not more:
            break
        rest += more
    sock.close()
    return int(head.split()[1]), json.loads(rest[:length])


def test_every_byte_of_a_multipart_body_counts_and_a_malformed_one_is_one_line(challenge, tmp_path):
    layout, sessions, tokens, predictions, url = challenge
    archive = _archive(predictions, tmp_path)
    boundary = "b0undary"
    form = f"multipart/form-data; boundary={boundary}"

    def field_then_file() -> Iterator[bytes]:  # a 20 MiB text field, then the archive as the file
        yield f'--{boundary}\r\nContent-Disposition: form-data; name="note"\r\n\r\n'.encode()
        for _ in range(20):
            yield b"x" * (1 << 20)
        yield (f'\r\n--{boundary}\r\nContent-Disposition: form-data; name="f"; filename="p.tar"\r\n'
               "Content-Type: application/x-tar\r\n\r\n").encode() + archive + f"\r\n--{boundary}--\r\n".encode()

    def huge_header() -> Iterator[bytes]:  # a part header of 150 MiB
        yield f'--{boundary}\r\nContent-Disposition: form-data; name="f"; filename="p.tar"\r\nX-Pad: '.encode()
        for _ in range(150):
            yield b"a" * (1 << 20)

    with _serve(layout, url, max_upload_bytes=2 << 20) as live:
        status, reply = _raw_upload(live.url, tokens["alpha"], form, field_then_file())
        assert status == 413 and "over the limit of 2097152 bytes" in reply["detail"]
        for body in (iter([b"this is not a form at all\r\n"]), huge_header()):
            status, reply = _raw_upload(live.url, tokens["alpha"], form, body)
            assert status == 400 and "the multipart form is malformed" in reply["detail"], reply
            assert "\n" not in reply["detail"]
        ok = post(f"{live.url}/api/submissions", params={"method": "form"}, files={"f": ("p.tar", archive)},
                  headers={"Authorization": f"Bearer {tokens['alpha']}"})
        assert ok.status_code == 202, ok.text
    assert len(_rows(sessions)) == 1


def test_names_are_normalised_and_look_alikes_refused(challenge, tmp_path):
    from dsr_bench.challenge.service import add_team

    layout, sessions, tokens, predictions, url = challenge
    add_team(sessions, "team one")
    for name, message in (("team\u202eeno", "U+202E"), ("team\u200bthree", "U+200B"), ("team\tfour", "U+0009"),
                          ("team\u00a0one", "exists"),  # NBSP reads as a space
                          ("t\u0435am one", "reads like team 'team one'"),  # Cyrillic e
                          ("TEAM ONE", "reads like team 'team one'"), ("Team-One", "reads like"),
                          ("!!!", "no letter or digit"), ("x" * 65, "1-64")):
        with pytest.raises(UserError, match=re.escape(message)):
            add_team(sessions, name)
    add_team(sessions, "\uff54\uff45\uff41\uff4d two")  # full-width letters: stored as they read
    names = sorted(t.name for t in _team_rows(sessions))
    assert names == ["alpha", "beta", "team one", "team two"]
    body = _archive(predictions, tmp_path)
    with _serve(layout, url) as live:
        assert _upload(live.url, tokens["alpha"], body, "static").status_code == 202
        for method, message in (("\u0455tatic", "reads like 'static'"), ("Static", "reads like 'static'"),
                                ("my\u202emethod", "U+202E"), ("a\u200bb", "U+200B")):
            reply = _upload(live.url, tokens["beta"], body, method)
            assert reply.status_code == 400 and message in reply.json()["detail"], (method, reply.text)
        assert _upload(live.url, tokens["beta"], body, "static").status_code == 202  # the same name exactly
    assert sorted(s.method for s in _rows(sessions)) == ["static", "static"]


def _team_rows(sessions) -> list:
    from sqlalchemy import select

    from dsr_bench.challenge.db import Team

    with sessions() as session:
        return list(session.scalars(select(Team)))


def test_parts_scored_on_different_tracks_are_refused(challenge, tmp_path):
    """Public files 3D, private files 2D-only: refused as `evaluate` refuses the same mix in one folder, not scored
    as 2D."""
    import h5py
    import numpy as np

    from dsr_bench.challenge.client import pack
    from dsr_bench.challenge.layout import open_challenge
    from dsr_bench.challenge.worker import run_worker
    from dsr_bench.scoring.predictions import write_predictions

    layout, sessions, tokens, predictions, url = challenge
    config = open_challenge(layout.root)[1]
    for name in config["private"]:
        with h5py.File(predictions / f"{name}.h5") as f:
            steps = f["motion"].shape[0]
        (predictions / f"{name}.h5").unlink()
        write_predictions(predictions / f"{name}.h5", motion_2d=np.zeros((steps, 240, 320, 3), np.float32))
    pack(predictions, tmp_path / "mixed.tar")
    with _serve(layout, url) as live:
        sid = _upload(live.url, tokens["alpha"], (tmp_path / "mixed.tar").read_bytes()).json()["id"]
        assert run_worker(str(layout.root), url, once=True) == 1
        status = wait_for_state(live.url, sid)
        board = get(f"{live.url}/api/leaderboard").json()
    assert status["state"] == "refused", status
    assert any("mixed submission" in m for m in status["messages"]), status["messages"]
    assert board["tracks"] == {}  # not on the 2D table, nor the 3D one
