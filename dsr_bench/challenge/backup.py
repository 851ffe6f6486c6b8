"""A consistent copy of a challenge's database while the server runs (`dsr-bench challenge backup DIR OUT`).

SQLite: SQLite's online backup API (`sqlite3.Connection.backup`) copies every page in one step inside one read
transaction, so the copy is the database as of one commit: in WAL mode the server's writers go on meanwhile and
none of their later commits is in it, none half. The copy is written to a temporary name beside OUT (0600: it holds
the token hashes), switched to a plain rollback journal (one self-contained file, no -wal beside it), checked with
`PRAGMA integrity_check`, flushed and renamed to OUT. PostgreSQL: `pg_dump --format=custom` (one snapshot
transaction), run when it is on PATH, into a temporary name renamed to OUT; restore it with `pg_restore`.

The submissions' archives (DIR/submissions) are not in the database: an archive is stored before its row is
committed and never changed after, so copying DIR/submissions after the database gives every copied row its archive.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
from pathlib import Path

from dsr_bench.atomic import atomic_path
from dsr_bench.errors import UserError


def backup_database(url: str, out: str | Path) -> str:
    """Copy the database at SQLAlchemy `url` to the new file `out`, consistently while it is written to; returns
    one line saying what was written. SQLite: a database file (the online backup API); PostgreSQL: a pg_dump
    archive (custom format). UserError for an existing `out`, a missing database or another backend."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    out = Path(out)
    if out.exists() or out.is_symlink():
        raise UserError(f"{out} exists; give a new file name for the copy (or delete it)")
    if not out.parent.is_dir():
        raise UserError(f"{out.parent} is not a directory; give OUT in an existing directory")
    try:
        parsed = make_url(url)
    except ArgumentError:
        raise UserError(f"--db {url!r} is not a database URL; e.g. sqlite:///DIR/challenge.db") from None
    backend = parsed.get_backend_name()
    if backend == "sqlite":
        return _backup_sqlite(parsed.database or "", out)
    if backend == "postgresql":
        return _backup_postgresql(parsed, out)
    raise UserError(f"--db {parsed.render_as_string(hide_password=True)}: no backup for {backend} databases; "
                    "use the database's own dump tool")


def _create_private(tmp: Path) -> None:
    """Create `tmp` (an `atomic_path` temporary) empty, readable by its owner only: the copy holds the token hashes."""
    os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))


def _backup_sqlite(database: str, out: Path) -> str:
    if not database or database == ":memory:" or not Path(database).is_file():
        raise UserError(f"{database or '(no file)'}: no SQLite database file there; give the challenge DIR whose "
                        "server has run (or --db sqlite:///PATH)")
    try:
        with atomic_path(out, fsync=True) as tmp:
            _create_private(tmp)
            source = sqlite3.connect(database, timeout=30)
            try:
                source.execute("PRAGMA busy_timeout=30000")
                copy = sqlite3.connect(tmp)
                try:
                    source.backup(copy)  # pages=-1: every page in one step, one read transaction: one commit's state
                    copy.execute("PRAGMA journal_mode=DELETE")  # one self-contained file
                    found = [row[0] for row in copy.execute("PRAGMA integrity_check")]
                    tables = copy.execute("SELECT count(*) FROM sqlite_master WHERE type='table'").fetchone()[0]
                finally:
                    copy.close()
            finally:
                source.close()
            if found != ["ok"]:
                raise UserError(f"the copy of {database} fails its integrity check ({found[0][:120]}); the "
                                "database itself may be damaged: run `sqlite3 DB 'PRAGMA integrity_check'`")
    except sqlite3.DatabaseError as exc:
        raise UserError(f"{database}: cannot be copied ({exc}); check that it is the challenge's database") from None
    return f"copied {database} to {out} ({out.stat().st_size} bytes, {tables} tables, integrity ok)"


def _backup_postgresql(parsed, out: Path) -> str:
    shown = parsed.render_as_string(hide_password=True)
    pg_dump = shutil.which("pg_dump")
    if pg_dump is None:
        raise UserError(f"{shown}: pg_dump is the tool for a PostgreSQL database and it is not on PATH; install "
                        "PostgreSQL's client (Debian: apt-get install postgresql-client) or run pg_dump "
                        "--format=custom --file OUT yourself")
    libpq = parsed.set(drivername="postgresql", password=None).render_as_string(hide_password=False)
    env = dict(os.environ)
    if parsed.password:
        env["PGPASSWORD"] = str(parsed.password)  # not on the command line (ps shows it)
    with atomic_path(out, fsync=True) as tmp:
        _create_private(tmp)
        done = subprocess.run([pg_dump, "--format=custom", "--no-owner", f"--file={tmp}", f"--dbname={libpq}"],
                              capture_output=True, text=True, env=env, timeout=3600)
        if done.returncode != 0:
            first = (done.stderr.strip().splitlines() or ["no message"])[0]
            raise UserError(f"pg_dump of {shown} failed: {first[:200]}; check --db")
    return f"dumped {shown} to {out} with pg_dump ({out.stat().st_size} bytes; restore with pg_restore)"
