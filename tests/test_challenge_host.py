"""What a host must never lose or miss (issue 43), on SQLite and on a throwaway PostgreSQL cluster: a challenge
directory is bound to its database (an id in both) and never used with another one (no empty database made for a
directory with submissions, nothing deleted), a challenge of an earlier version is adopted once, archives without a
row are moved aside and never deleted, the host's commands on one submission (list, cancel, hide, rescore), a job
taken again leaves no extracted archive, messages scrubbed of paths only where a path stands whole, and a
database put back from its backup (`challenge restore`)."""

from __future__ import annotations

import gc
import json
import os
import re
import sqlite3
import subprocess
import tarfile
import time

import pytest

pytest.importorskip("sqlalchemy")
pytest.importorskip("alembic")
pytest.importorskip("argon2")

from challenge_helpers import copy_challenge, postgres_binaries  # noqa: E402
from challenge_served import (archives, bound, database_maker, identity, open_db, postgres_cluster,  # noqa: E402
                              store)

from dsr_bench.cli import main  # noqa: E402


@pytest.fixture(scope="module")
def postgres(tmp_path_factory):
    yield from postgres_cluster(tmp_path_factory)


@pytest.fixture(params=["sqlite", "postgresql"])
def backend(request, tmp_path):
    return database_maker(request, tmp_path)


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def test_a_new_challenge_is_bound_to_its_database_at_its_first_command(tmp_path, tmp_path_factory, backend):
    url = backend("first")
    layout, _, _ = bound(tmp_path, tmp_path_factory, url, n=0)
    config = json.loads(layout.config.read_text())
    assert re.fullmatch(r"[0-9a-f]{32}", config["challenge_id"])
    assert identity(url) == config["challenge_id"]
    assert main(["challenge", "teams", str(layout.root), "--db", url]) == 0  # the same pair: accepted


def test_a_directory_is_never_used_with_another_database(tmp_path, tmp_path_factory, backend, capsys):
    url = backend("bound")
    layout, ids, _ = bound(tmp_path, tmp_path_factory, url)
    other_url = backend("other")
    bound(tmp_path / "other", tmp_path_factory, other_url, n=1)
    before = archives(layout)
    capsys.readouterr()

    # the database left out (a PostgreSQL challenge started without --db; a SQLite file moved away): refused, and
    # no empty DIR/challenge.db is made for a challenge that has submissions
    assert main(["challenge", "teams", str(layout.root)]) == 2
    assert "no such database" in _one_line(capsys)
    assert not (layout.root / "challenge.db").exists()

    # a new, empty database (moving to PostgreSQL by hand): refused
    empty = backend("empty")
    open_db(empty)[0].dispose()
    assert main(["challenge", "add-team", str(layout.root), "b", "--db", empty]) == 2
    assert "is not the database of" in _one_line(capsys)

    # another challenge's database: refused
    assert main(["challenge", "add-team", str(layout.root), "b", "--db", other_url]) == 2
    assert "database of another challenge" in _one_line(capsys)

    assert archives(layout) == before  # nothing deleted, nothing moved
    assert main(["challenge", "teams", str(layout.root), "--db", url]) == 0  # its own database still serves


def test_a_challenge_of_an_earlier_version_is_adopted_once(tmp_path, tmp_path_factory, backend, capsys):
    """A directory and database made before binding existed: adopted by the first command when the database's
    submissions are exactly the directory's archives; otherwise refused, naming `challenge adopt`, which binds them
    and moves the archives without a row aside (never deleting one)."""
    from dsr_bench.challenge.layout import Layout

    url = backend("legacy")
    root, _ = copy_challenge(tmp_path_factory, tmp_path)
    layout = Layout(root)
    engine, sessions = open_db(url)  # an earlier version's database: no identity
    ids = store(layout, sessions, 2)
    engine.dispose()
    assert main(["challenge", "teams", str(root), "--db", url]) == 0
    challenge_id = json.loads(layout.config.read_text())["challenge_id"]
    assert identity(url) == challenge_id

    (tmp_path / "second").mkdir()
    root2, _ = copy_challenge(tmp_path_factory, tmp_path / "second")
    layout2 = Layout(root2)
    url2 = backend("legacy2")
    engine, sessions = open_db(url2)
    ids2 = store(layout2, sessions, 2)
    engine.dispose()
    stray = "ab" * 16  # stored by a server killed before it wrote the row
    layout2.archive(stray).write_bytes(b"a stray")
    capsys.readouterr()
    assert main(["challenge", "teams", str(root2), "--db", url2]) == 2
    assert "challenge adopt" in _one_line(capsys)
    assert "challenge_id" not in json.loads(layout2.config.read_text()) and identity(url2) is None
    assert main(["challenge", "adopt", str(root2), "--db", url2]) == 0
    out = capsys.readouterr().out
    assert "moved 1 archives without a row" in out and "bound" in out
    moved = list(layout2.submissions.glob("stray-*/*.tar"))
    assert [p.name for p in moved] == [f"{stray}.tar"] and moved[0].read_bytes() == b"a stray"
    assert sorted(p.stem for p in layout2.submissions.glob("*.tar")) == sorted(ids2)
    assert identity(url2) == json.loads(layout2.config.read_text())["challenge_id"] != challenge_id
    assert main(["challenge", "teams", str(root2), "--db", url2]) == 0
    assert sorted(p.stem for p in layout.submissions.glob("*.tar")) == sorted(ids)


def _scored(sessions, sid: str, value: float = 0.5) -> None:
    """Score submission `sid` as a worker does (claim, then both parts' rows and the state in one transaction)."""
    from dsr_bench.challenge.layout import DEFAULTS
    from dsr_bench.challenge.worker import Outcome, claim, finish

    owner = f"scorer-{sid[:6]}"
    while (claimed := claim(sessions, owner, lease=60)) != sid:
        assert claimed is not None, f"{sid} is not claimable"
        finish(sessions, claimed, owner, Outcome("refused", ["not this one"]), DEFAULTS)
    outcome = Outcome("scored", parts={p: {"metrics": {"iou_ordered": value}} for p in ("public", "private")},
                      track="3D")
    finish(sessions, sid, owner, outcome, DEFAULTS)


def _board(url: str, layout) -> list[str]:
    from dsr_bench.challenge.layout import open_challenge
    from dsr_bench.challenge.service import leaderboard

    engine, sessions = open_db(url)
    try:
        with sessions() as session:
            board = leaderboard(session, {**open_challenge(layout.root)[1], "reveal_private": True})
        return sorted(r["id"] for rows in board["tracks"].values() for r in rows)
    finally:
        engine.dispose()


def test_the_host_lists_cancels_hides_and_rescores_one_submission(tmp_path, tmp_path_factory, backend, capsys):
    from sqlalchemy import select

    from dsr_bench.challenge.db import Score, Submission
    from dsr_bench.challenge.worker import claim

    url = backend("commands")
    layout, (scored, refused, failed, queued), _ = bound(tmp_path, tmp_path_factory, url, n=4)
    engine, sessions = open_db(url)
    _scored(sessions, scored)
    with sessions.begin() as session:
        session.get(Submission, refused).state = "refused"
        sub = session.get(Submission, failed)
        sub.state, sub.attempts, sub.messages = "failed", 4, json.dumps(["the server failed while scoring"])
    root = str(layout.root)
    capsys.readouterr()

    assert main(["challenge", "submissions", root, "--db", url]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[:2] for line in lines] == [[scored, "scored"], [refused, "refused"], [failed, "failed"],
                                                     [queued, "queued"]]
    assert main(["challenge", "submissions", root, "--status", "failed", "--db", url]) == 0
    assert capsys.readouterr().out.splitlines() == [line for line in lines if line.startswith(failed)]
    assert "the server failed while scoring" in lines[2] and "attempts 4" in lines[2]
    assert main(["challenge", "submissions", root, "--status", "lost", "--db", url]) == 2
    assert "--status 'lost'" in _one_line(capsys)

    # cancel: a queued one is never scored, and its extracted archive (a worker's) is removed
    (layout.work / f"{queued}-0badcafe" / "all").mkdir(parents=True)
    assert main(["challenge", "cancel", root, queued, "--db", url]) == 0
    assert claim(sessions, "w", lease=60) is None
    assert not list(layout.work.glob(f"{queued}-*"))
    assert main(["challenge", "cancel", root, scored, "--db", url]) == 2
    assert "is scored, not queued or running" in _one_line(capsys)
    assert main(["challenge", "cancel", root, "f" * 32, "--db", url]) == 2
    assert "no submission" in _one_line(capsys)

    # hide: off every table, its scores kept; --undo puts its newest scores back
    assert _board(url, layout) == [scored]
    assert main(["challenge", "hide", root, scored, "--db", url]) == 0
    assert _board(url, layout) == []
    with sessions() as session:
        assert session.get(Submission, scored).hidden
        scores = session.scalars(select(Score).where(Score.submission_id == scored)).all()
        assert sorted(s.current for s in scores) == [False, False]
    # a hidden submission scored again stays off the tables
    assert main(["challenge", "rescore", root, scored, "--db", url]) == 0
    assert main(["challenge", "rescore", root, scored, "--db", url]) == 2
    assert "score it already" in _one_line(capsys)
    _scored(sessions, scored, 0.75)
    assert _board(url, layout) == []
    assert main(["challenge", "hide", root, scored, "--undo", "--db", url]) == 0
    assert _board(url, layout) == [scored]
    with sessions() as session:
        current = session.scalars(select(Score).where(Score.submission_id == scored, Score.current.is_(True))).all()
        assert sorted((s.part, s.run) for s in current) == [("private", 2), ("public", 2)]

    # rescore one: a failed one is queued again, its attempts reset
    assert main(["challenge", "rescore", root, failed, "--db", url]) == 0
    with sessions() as session:
        sub = session.get(Submission, failed)
        assert (sub.state, sub.attempts) == ("queued", 0)
    assert claim(sessions, "w", lease=60) == failed
    engine.dispose()


def _dead_pid() -> int:
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


def test_a_job_taken_again_leaves_no_extracted_archive(tmp_path, tmp_path_factory, backend):
    """A worker killed mid-job left its extracted archive in work/: the worker that takes the job again removes it,
    and a job that ends leaves nothing there."""
    from dsr_bench.atomic import host_name
    from dsr_bench.challenge.client import pack
    from dsr_bench.challenge.db import Submission
    from dsr_bench.challenge.worker import claim, run_worker

    url = backend("reclaim")
    layout, _, predictions = bound(tmp_path, tmp_path_factory, url, n=0)
    engine, sessions = open_db(url)
    sid = os.urandom(16).hex()
    pack(predictions, layout.archive(sid))
    from dsr_bench.challenge.db import Team, utcnow

    with sessions.begin() as session:
        team = session.query(Team).one()
        session.add(Submission(id=sid, team_id=team.id, method="m", state="queued", attempts=0, created_at=utcnow(),
                               archive_sha256="0" * 64, archive_bytes=1, messages="[]", final=False, rescore=False))
    dead = f"{host_name()[:32]}-{_dead_pid()}-0badcafe"  # a worker of this host whose process is gone
    assert claim(sessions, dead, lease=3600) == sid
    left = layout.work / f"{sid}-0badcafe" / "all"
    left.mkdir(parents=True)
    (left / "seq_0000.h5").write_bytes(b"x" * 1000)
    assert run_worker(str(layout.root), url, once=True) == 1  # its job taken again at once: its worker is dead
    with sessions() as session:
        sub = session.get(Submission, sid)
        assert (sub.state, sub.attempts) == ("scored", 2)
    assert list(layout.work.iterdir()) == []
    engine.dispose()


def test_paths_are_scrubbed_from_messages_only_where_they_stand_whole(tmp_path, tmp_path_factory, monkeypatch):
    """With DIR `ch` (relative), h5py's "Unable to synchronously open file" stays whole (it was "Unable to
    syn<challenge>ronously open file"), while a path under DIR is still hidden."""
    import io

    from dsr_bench.challenge.host import load_pins
    from dsr_bench.challenge.layout import open_challenge
    from dsr_bench.challenge.worker import _sanitize, evaluate_submission

    root, predictions = copy_challenge(tmp_path_factory, tmp_path)
    root.rename(tmp_path / "ch")
    monkeypatch.chdir(tmp_path)
    layout, config = open_challenge("ch")
    layout.submissions.mkdir(exist_ok=True)
    sid = "c" * 32
    with tarfile.open(layout.archive(sid), "w") as tar:
        for path in sorted(predictions.iterdir()):
            if path.name == "seq_0000.h5":  # not HDF5: h5py's message names the file
                info = tarfile.TarInfo(path.name)
                info.size = 700
                tar.addfile(info, io.BytesIO(b"garbage" * 100))
            else:
                tar.add(path, arcname=path.name)
    outcome = evaluate_submission(layout, config, load_pins(layout), sid)
    assert outcome.state == "refused"
    assert outcome.messages == ["seq_0000.h5: unreadable HDF5 file (OSError: Unable to synchronously open file "
                                "(file signature not found))"]
    hide = {"ch": "<challenge>", "ch/hidden": "<hidden>", str(tmp_path / "ch"): "<challenge>"}
    assert _sanitize(f"open ch/hidden/seq_0000.h5 and {tmp_path}/ch/pins.json in ch.", hide) == \
        "open <hidden>/seq_0000.h5 and <challenge>/pins.json in <challenge>."
    assert _sanitize("which ch.h5 is in arch/ch_x or rich/ch", hide) == "which ch.h5 is in arch/ch_x or rich/ch"


def test_a_sqlite_database_is_restored_from_its_backup(tmp_path, tmp_path_factory, capsys):
    """backup, damage, restore: the scores are back, the damaged file is kept beside, a backup of another challenge
    and a restore under a running server are refused."""
    from dsr_bench.challenge.binding import serving_lock

    layout, ids, _ = bound(tmp_path, tmp_path_factory, f"sqlite:///{tmp_path / 'challenge' / 'challenge.db'}", n=2)
    url = layout.default_db_url()
    engine, sessions = open_db(url)
    _scored(sessions, ids[0])
    engine.dispose()
    root, db_file = str(layout.root), layout.root / "challenge.db"
    copy = tmp_path / "copy.db"
    assert main(["challenge", "backup", root, str(copy)]) == 0
    engine, sessions = open_db(url)
    newer = store(layout, sessions, 1)[0]  # accepted after the backup
    engine.dispose()
    gc.collect()  # the engines of the commands run in this process are closed: none writes to the new file
    db_file.unlink()
    db_file.write_bytes(b"damaged" * 1000)
    capsys.readouterr()
    assert main(["challenge", "teams", root]) == 2
    assert "damaged" in (line := _one_line(capsys)) and "challenge restore" in line

    with serving_lock(layout):  # a server on DIR: its database is not replaced under it
        assert main(["challenge", "restore", root, str(copy)]) == 2
        assert "is being served" in _one_line(capsys)
    (tmp_path / "other").mkdir()
    other, _, _ = bound(tmp_path / "other", tmp_path_factory, f"sqlite:///{tmp_path / 'other.db'}", n=0)
    assert main(["challenge", "backup", str(other.root), str(tmp_path / "other-copy.db"), "--db",
                 f"sqlite:///{tmp_path / 'other.db'}"]) == 0
    capsys.readouterr()
    assert main(["challenge", "restore", root, str(tmp_path / "other-copy.db")]) == 2
    assert "backup of another challenge" in _one_line(capsys)

    assert main(["challenge", "restore", root, str(copy)]) == 0
    out = capsys.readouterr().out
    assert "restored" in out and "1 archives" in out and "newer than the backup" in out
    kept = list(layout.root.glob("challenge.db.replaced-*"))
    assert [p.read_bytes() for p in kept if p.name.endswith(tuple("0123456789Z"))] == [b"damaged" * 1000]
    assert _board(url, layout) == [ids[0]]
    assert sqlite3.connect(db_file).execute("SELECT count(*) FROM submissions").fetchone()[0] == 2
    assert main(["challenge", "teams", root]) == 0
    assert layout.archive(newer).is_file()  # kept: the next serve moves it aside


def test_a_postgresql_database_is_restored_from_its_backup(tmp_path, tmp_path_factory, postgres, monkeypatch,
                                                           capsys):
    bin_dir = postgres_binaries()
    if not (bin_dir / "pg_dump").exists() or not (bin_dir / "pg_restore").exists():
        pytest.skip("PostgreSQL's pg_dump and pg_restore are not installed")
    monkeypatch.setenv("PATH", f"{bin_dir}:{os.environ['PATH']}")
    url = postgres.url(f"live{time.monotonic_ns()}")
    layout, ids, _ = bound(tmp_path, tmp_path_factory, url, n=2)
    engine, sessions = open_db(url)
    _scored(sessions, ids[1])
    engine.dispose()
    root, dump = str(layout.root), tmp_path / "copy.dump"
    assert main(["challenge", "backup", root, str(dump), "--db", url]) == 0
    engine, sessions = open_db(url)
    from sqlalchemy import text

    with sessions.begin() as session:  # damaged: the scores lost
        session.execute(text("DELETE FROM scores"))
    engine.dispose()
    assert _board(url, layout) == []
    capsys.readouterr()
    assert main(["challenge", "restore", root, str(dump), "--db", url]) == 2  # not into a database holding tables
    assert "not empty" in _one_line(capsys)
    restored = postgres.url(f"restored{time.monotonic_ns()}")
    assert main(["challenge", "restore", root, str(dump), "--db", restored]) == 0
    assert "with pg_restore (2 submissions)" in capsys.readouterr().out
    assert _board(restored, layout) == [ids[1]]
    assert identity(restored) == json.loads(layout.config.read_text())["challenge_id"]
    assert main(["challenge", "teams", root, "--db", restored]) == 0
