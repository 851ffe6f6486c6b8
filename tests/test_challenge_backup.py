"""`dsr-bench challenge backup DIR OUT` copies the challenge's database while submissions are being accepted and
scored: the copy opens, passes PRAGMA integrity_check (SQLite) or restores (PostgreSQL, pg_dump / pg_restore), and
holds one moment's state: the submissions 1..k accepted before it and none after, each with its archive, and each
scored one with both of its parts' score rows (none half-recorded)."""

import sqlite3
import subprocess
import threading
import time

import pytest

pytest.importorskip("sqlalchemy")
pytest.importorskip("alembic")
pytest.importorskip("argon2")

from challenge_helpers import DEADLINE, PostgresCluster, copy_challenge, postgres_binaries  # noqa: E402

from dsr_bench.cli import main  # noqa: E402


class Writer(threading.Thread):
    """Accepts submissions 1, 2, ... as the server does (the archive stored, then its row) and scores each as a
    worker does (claim, then both parts' score rows and the state in one transaction), until stopped."""

    def __init__(self, layout, sessions):
        super().__init__(daemon=True)
        self.layout, self.sessions = layout, sessions
        self.stop, self.count, self.error = threading.Event(), 0, None

    def run(self) -> None:
        from dsr_bench.challenge.db import Submission, utcnow
        from dsr_bench.challenge.layout import DEFAULTS
        from dsr_bench.challenge.service import add_team
        from dsr_bench.challenge.worker import Outcome, claim, finish

        try:
            add_team(self.sessions, "writer")
            from sqlalchemy import select

            from dsr_bench.challenge.db import Team

            with self.sessions() as session:
                team_id = session.scalar(select(Team.id).where(Team.name == "writer"))
            self.layout.submissions.mkdir(exist_ok=True)
            outcome = Outcome("scored", parts={p: {"metrics": {"iou_ordered": 0.5}} for p in ("public", "private")},
                              track="3D")
            while not self.stop.is_set():
                sid = f"{self.count + 1:032x}"
                self.layout.archive(sid).write_bytes(b"archive")
                with self.sessions.begin() as session:
                    session.add(Submission(id=sid, team_id=team_id, method="m", state="queued", attempts=0,
                                           created_at=utcnow(), archive_sha256="0" * 64, archive_bytes=7,
                                           messages="[]", final=False, rescore=False))
                self.count += 1
                if self.count % 2 == 0:  # every other one scored at once; the rest stay queued for a while
                    claimed = claim(self.sessions, "w", lease=60)
                    finish(self.sessions, claimed, "w", outcome, DEFAULTS)
        except BaseException as exc:  # noqa: BLE001  (reported by the test)
            self.error = exc

    def wait_for(self, count: int, timeout: float = DEADLINE) -> None:
        end = time.monotonic() + timeout
        while self.count < count and self.error is None and time.monotonic() < end:
            time.sleep(0.02)
        assert self.error is None, self.error
        assert self.count >= count, f"the writer wrote {self.count} submissions, not {count}"


def _check_consistent(rows: list[tuple], scores: list[tuple], layout) -> int:
    """rows: (id, state); scores: (submission id, part, current). The copy holds submissions 1..k, each with its
    archive, each scored one with exactly its public and private current rows and the others none; returns k."""
    ids = sorted(int(sid, 16) for sid, _ in rows if sid != "0" * 32)
    assert ids == list(range(1, len(ids) + 1))  # a prefix: nothing accepted after the copy, no gap
    by_sub: dict[str, list[str]] = {}
    for sid, part, current in scores:
        assert current
        by_sub.setdefault(sid, []).append(part)
    for sid, state in rows:
        assert layout.archive(sid).is_file()
        assert sorted(by_sub.get(sid, [])) == (["private", "public"] if state == "scored" else []), (sid, state)
    assert set(by_sub) <= {sid for sid, _ in rows}
    return len(ids)


def test_backup_of_a_sqlite_database_being_written(tmp_path, tmp_path_factory, capsys):
    from dsr_bench.challenge.db import open_database
    from dsr_bench.challenge.layout import Layout

    root, _ = copy_challenge(tmp_path_factory, tmp_path)
    layout = Layout(root)
    engine, sessions = open_database(layout.default_db_url())
    writer = Writer(layout, sessions)
    writer.start()
    try:
        writer.wait_for(20)
        out = tmp_path / "copy.db"
        assert main(["challenge", "backup", str(root), str(out)]) == 0
        assert "integrity ok" in capsys.readouterr().out
        copy = sqlite3.connect(out)
        assert [r[0] for r in copy.execute("PRAGMA integrity_check")] == ["ok"]
        assert copy.execute("PRAGMA journal_mode").fetchone()[0] == "delete"  # one file, no -wal beside it
        rows = copy.execute("SELECT id, state FROM submissions").fetchall()
        scores = copy.execute("SELECT submission_id, part, current FROM scores").fetchall()
        copy.close()
        k = _check_consistent(rows, scores, layout)
        assert k >= 20 and not (tmp_path / "copy.db-wal").exists()
        writer.wait_for(k + 10)  # the server's writes went on past the copy
    finally:
        writer.stop.set()
        writer.join(DEADLINE)
    assert writer.error is None
    with sessions() as session:
        from sqlalchemy import func, select

        from dsr_bench.challenge.db import Submission

        assert session.scalar(select(func.count()).select_from(Submission)) > k
    engine.dispose()
    # the copy is a challenge database the server can run on (migrated: nothing to do)
    engine, copied = open_database(f"sqlite:///{out}")
    with copied() as session:
        assert session.scalar(select(func.count()).select_from(Submission)) == k
    engine.dispose()


def test_backup_refuses_bad_input(tmp_path, tmp_path_factory, capsys):
    root, _ = copy_challenge(tmp_path_factory, tmp_path)
    assert main(["challenge", "backup", str(root), str(tmp_path / "copy.db")]) == 2  # no server has run
    assert "no SQLite database file there" in capsys.readouterr().err
    from dsr_bench.challenge.db import open_database
    from dsr_bench.challenge.layout import Layout

    open_database(Layout(root).default_db_url())[0].dispose()
    (tmp_path / "taken.db").write_text("x")
    assert main(["challenge", "backup", str(root), str(tmp_path / "taken.db")]) == 2
    assert "exists; give a new file name" in capsys.readouterr().err
    assert (tmp_path / "taken.db").read_text() == "x"
    assert main(["challenge", "backup", str(root), str(tmp_path / "no" / "copy.db")]) == 2
    assert "not a directory" in capsys.readouterr().err
    assert main(["challenge", "backup", str(tmp_path), str(tmp_path / "c.db")]) == 2
    assert "not a challenge directory" in capsys.readouterr().err
    assert not list(tmp_path.glob(".*.tmp-*"))  # nothing half-written left


def test_backup_of_a_postgresql_database_being_written(tmp_path, tmp_path_factory, monkeypatch, capsys):
    bin_dir = postgres_binaries()
    if bin_dir is None or not (bin_dir / "pg_dump").exists():
        pytest.skip("PostgreSQL's initdb, pg_ctl and pg_dump are not installed (Debian: apt-get install postgresql)")
    pytest.importorskip("psycopg")
    from sqlalchemy import create_engine, text

    from dsr_bench.challenge.db import open_database
    from dsr_bench.challenge.layout import Layout

    monkeypatch.setenv("PATH", f"{bin_dir}:{__import__('os').environ['PATH']}")  # the server's own pg_dump
    cluster = PostgresCluster(tmp_path_factory.mktemp("pg"), bin_dir).start()
    try:
        root, _ = copy_challenge(tmp_path_factory, tmp_path)
        layout = Layout(root)
        url = cluster.url("live")
        engine, sessions = open_database(url)
        writer = Writer(layout, sessions)
        writer.start()
        try:
            writer.wait_for(20)
            out = tmp_path / "copy.dump"
            assert main(["challenge", "backup", str(root), str(out), "--db", url]) == 0
            assert "with pg_dump" in capsys.readouterr().out
            writer.wait_for(writer.count + 10)
        finally:
            writer.stop.set()
            writer.join(DEADLINE)
        assert writer.error is None
        engine.dispose()
        restored = cluster.url("restored")
        libpq = restored.replace("postgresql+psycopg://", "postgresql://")
        subprocess.run([str(bin_dir / "pg_restore"), "--no-owner", f"--dbname={libpq}", str(out)], check=True,
                       capture_output=True, timeout=DEADLINE)
        check = create_engine(restored)
        with check.connect() as connection:
            rows = connection.execute(text("SELECT id, state FROM submissions")).all()
            scores = connection.execute(text("SELECT submission_id, part, current FROM scores")).all()
            live_count = writer.count
        check.dispose()
        k = _check_consistent([tuple(r) for r in rows], [tuple(s) for s in scores], layout)
        assert 20 <= k < live_count
    finally:
        cluster.stop()
