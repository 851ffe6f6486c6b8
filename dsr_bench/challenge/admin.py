"""The host's hand on single submissions and on a lost database: list them (`challenge submissions`), cancel, hide
or score one again (`challenge cancel|hide|rescore DIR ID`), and put a backup back (`challenge restore`).

- Cancel: a queued or running submission becomes `cancelled` (a running one's worker finds its lease gone and drops
  its result); its extracted archive is removed. Its archive and row stay.
- Hide: none of its scores is current any more (so no table, ranking or page shows them) and it is flagged
  `hidden`; the worker keeps a hidden submission's new scores non-current too. `--undo` makes its newest run's
  scores current again.
- Rescore one: a scored or refused submission is marked to be scored again (as `challenge rescore DIR` marks them
  all); a failed or cancelled one is queued again with its attempts reset.
- Restore (SQLite): the backup (`challenge backup`) is checked (integrity, a challenge database, of this DIR:
  `binding`), copied beside the database file and renamed over it; the file it replaces is kept beside it
  (`<name>.replaced-<UTC time>`, with its -wal and -shm), never deleted. PostgreSQL: the pg_dump archive is
  restored with pg_restore into the empty database `--db` names (a new one: `createdb`). Either way no server may be
  serving DIR (`binding.serving_lock`), and the next `serve` moves the archives stored after the backup, which have
  no row in it, aside (`recovery`).
"""

from __future__ import annotations

import datetime as dt
import json
import os
import shutil
import sqlite3
import subprocess
from pathlib import Path

from sqlalchemy import func, select, update
from sqlalchemy.orm import sessionmaker

from dsr_bench.challenge.db import STATES, Score, Submission, Team
from dsr_bench.challenge.layout import Layout
from dsr_bench.errors import UserError


def _get(session, sid: str) -> Submission:
    sub = session.get(Submission, sid)
    if sub is None:
        raise UserError(f"no submission {sid[:40]!r}; `dsr-bench challenge submissions DIR` lists them")
    return sub


def list_submissions(session_factory: sessionmaker, state: str | None = None) -> list[str]:
    """One line per submission, oldest first (only those in `state`, when given): id, state, created, team, method,
    attempts, hidden, and its messages."""
    if state is not None and state not in STATES:
        raise UserError(f"--status {state!r}: give one of {', '.join(STATES)}")
    query = select(Submission, Team.name).join(Team, Team.id == Submission.team_id).order_by(Submission.created_at)
    if state is not None:
        query = query.where(Submission.state == state)
    lines = []
    with session_factory() as session:
        for sub, team in session.execute(query):
            messages = json.loads(sub.messages or "[]")
            extra = "".join((f", attempts {sub.attempts}" if sub.attempts > 1 else "", ", hidden" if sub.hidden else "",
                             f", track {sub.track}" if sub.track else ""))
            said = f": {' | '.join(messages)}" if messages else ""
            lines.append(f"{sub.id} {sub.state:9} {sub.created_at:%Y-%m-%d %H:%M:%S} team {team!r} method "
                         f"{sub.method!r}{extra}{said}")
    return lines


def cancel(layout: Layout, session_factory: sessionmaker, sid: str) -> str:
    """Cancel queued or running submission `sid` (the module's rules); returns one line."""
    from dsr_bench.challenge.recovery import clean_work

    with session_factory.begin() as session:
        sub = _get(session, sid)
        if sub.state not in ("queued", "running"):
            raise UserError(f"submission {sid} is {sub.state}, not queued or running: nothing to cancel (`challenge "
                            "hide` takes a scored one off the tables)")
        messages = json.loads(sub.messages or "[]") + ["cancelled by the host"]
        session.execute(update(Submission).where(Submission.id == sid)
                        .values(state="cancelled", lease_owner=None, lease_until=None, rescore=False,
                                messages=json.dumps(messages)))
    clean_work(layout, sid)
    return f"submission {sid} cancelled"


def hide(session_factory: sessionmaker, sid: str, undo: bool = False) -> str:
    """Take submission `sid` off every table, or (`undo`) show its newest scores again; returns one line."""
    with session_factory.begin() as session:
        sub = _get(session, sid)
        if sub.hidden != undo:
            return f"submission {sid} is {'hidden' if sub.hidden else 'shown'} already"
        sub.hidden = not undo
        session.execute(update(Score).where(Score.submission_id == sid).values(current=False))
        if undo:
            last = session.scalar(select(func.max(Score.run)).where(Score.submission_id == sid))
            if last is not None:
                session.execute(update(Score).where(Score.submission_id == sid, Score.run == last)
                                .values(current=True))
    return f"submission {sid} " + ("shown again" if undo else "hidden: no table or page shows its scores")


def rescore_one(session_factory: sessionmaker, sid: str) -> str:
    """Have the workers score submission `sid` again (the module's rules); returns one line."""
    with session_factory.begin() as session:
        sub = _get(session, sid)
        if sub.state in ("queued", "running") or sub.rescore:
            raise UserError(f"submission {sid} is {sub.state}{' and marked for a re-score' if sub.rescore else ''}: "
                            "the workers score it already")
        if sub.state in ("scored", "refused"):
            sub.rescore = True
        else:
            sub.state, sub.attempts, sub.lease_owner, sub.lease_until = "queued", 0, None, None
    return f"submission {sid} queued to be scored again by the workers"


def _stamp() -> str:
    return f"{dt.datetime.now(dt.timezone.utc):%Y%m%dT%H%M%SZ}"


def _check_sqlite_backup(backup: Path) -> tuple[str | None, set[str]]:
    """(its challenge id, its submission ids) of a SQLite challenge database that passes its integrity check."""
    try:
        copy = sqlite3.connect(f"file:{backup}?mode=ro", uri=True)
        try:
            found = [row[0] for row in copy.execute("PRAGMA integrity_check")]
            if found != ["ok"]:
                raise UserError(f"{backup} fails its integrity check ({found[0][:120]}); give another backup")
            tables = {row[0] for row in copy.execute("SELECT name FROM sqlite_master WHERE type='table'")}
            if "submissions" not in tables:
                raise UserError(f"{backup} is not a challenge database (no submissions table); give a file "
                                "`dsr-bench challenge backup` wrote")
            ids = {row[0] for row in copy.execute("SELECT id FROM submissions")}
            identity = (copy.execute("SELECT challenge_id FROM challenge_identity").fetchone()
                        if "challenge_identity" in tables else None)
        finally:
            copy.close()
    except sqlite3.DatabaseError as exc:
        raise UserError(f"{backup} is not a SQLite database ({exc}); give a file `dsr-bench challenge backup` "
                        "wrote (a PostgreSQL backup is restored with --db URL)") from None
    return (identity[0] if identity else None), ids


def _check_belongs(layout: Layout, backup: Path, backup_id: str | None, ids: set[str]) -> None:
    """A UserError unless the backup is of DIR's database: the same challenge id, or (a backup made before binding
    existed) every one of its submissions has its archive in DIR."""
    from dsr_bench.challenge.binding import ID_KEY, archive_ids

    dir_id = json.loads(layout.config.read_text()).get(ID_KEY)
    if backup_id is not None and dir_id is not None and backup_id != dir_id:
        raise UserError(f"{backup} is a backup of another challenge ({backup_id}), not of {layout.root} ({dir_id}); "
                        "give a backup of this challenge's database")
    missing = ids - archive_ids(layout)
    if backup_id is None and missing:
        raise UserError(f"{backup}: {len(missing)} of its submissions have no archive in {layout.submissions}: not "
                        "a backup of this challenge's database; give another backup")


def restore(layout: Layout, url: str, backup: str | Path) -> list[str]:
    """Put backup `backup` back as the database at `url` (the module's rules); returns lines saying what was done."""
    from dsr_bench.challenge.binding import refuse_if_served, shown_url, sqlite_file

    backup = Path(backup)
    if not backup.is_file():
        raise UserError(f"{backup}: no such file; give the file `dsr-bench challenge backup` wrote")
    refuse_if_served(layout, "restoring its database")
    target = sqlite_file(url)
    if target is None:
        if not url.startswith("postgresql"):
            raise UserError(f"--db {shown_url(url)}: restore works for SQLite and PostgreSQL databases only")
        return _restore_postgresql(layout, url, backup)
    backup_id, ids = _check_sqlite_backup(backup)
    _check_belongs(layout, backup, backup_id, ids)
    path = Path(target)
    lines = []
    from dsr_bench.atomic import atomic_path, fsync_path

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path, fsync=True) as tmp:
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))  # token hashes: the owner's only
        source, copy = sqlite3.connect(f"file:{backup}?mode=ro", uri=True), sqlite3.connect(tmp)
        try:
            source.backup(copy)
            copy.execute("PRAGMA journal_mode=DELETE")
        finally:
            copy.close()
            source.close()
        aside = path.with_name(f"{path.name}.replaced-{_stamp()}")
        for suffix in ("", "-wal", "-shm", "-journal"):  # the old file with its journal: openable where it lies
            old = Path(f"{path}{suffix}")
            if old.exists():
                old.rename(Path(f"{aside}{suffix}"))
                if not suffix:
                    lines.append(f"kept the database it replaces as {aside}")
    fsync_path(path.parent)
    lines.append(f"restored {backup} as {path} ({len(ids)} submissions)")
    return lines + _after_restore(layout, url, ids)


def _after_restore(layout: Layout, url: str, ids: set[str]) -> list[str]:
    """Bind a restored backup made before binding existed; say what the next start does with DIR's other archives."""
    from dsr_bench.challenge.binding import ID_KEY, archive_ids, read_identity, write_identity
    from dsr_bench.challenge.db import open_database

    engine, session_factory = open_database(url)  # migrated: a backup of an older version is brought up to date
    try:
        dir_id = json.loads(layout.config.read_text()).get(ID_KEY)
        if dir_id is not None and read_identity(session_factory) is None:
            write_identity(session_factory, layout, dir_id)
    finally:
        engine.dispose()
    newer = archive_ids(layout) - ids
    if not newer:
        return []
    return [f"{len(newer)} archives in {layout.submissions} are newer than the backup (no row in it): the next "
            "`dsr-bench serve` moves them aside to submissions/stray-<time>/"]


def _restore_postgresql(layout: Layout, url: str, backup: Path) -> list[str]:
    from sqlalchemy import create_engine, inspect
    from sqlalchemy.engine import make_url

    from dsr_bench.challenge.binding import shown_url

    parsed = make_url(url)
    shown = shown_url(url)
    pg_restore = shutil.which("pg_restore")
    if pg_restore is None:
        raise UserError(f"{shown}: pg_restore restores a PostgreSQL backup and it is not on PATH; install "
                        "PostgreSQL's client (Debian: apt-get install postgresql-client)")
    engine = create_engine(url)
    try:
        with engine.connect() as connection:
            tables = inspect(connection).get_table_names()
    except Exception as exc:  # noqa: BLE001  (any driver error: one line)
        raise UserError(f"{shown}: cannot be opened ({' '.join(str(exc).split())[:160]}); create it first "
                        "(createdb) and give its URL") from None
    finally:
        engine.dispose()
    if tables:
        raise UserError(f"{shown} is not empty ({len(tables)} tables); restore into a new database (createdb NAME) "
                        "and serve with --db of that one")
    libpq = parsed.set(drivername="postgresql", password=None).render_as_string(hide_password=False)
    env = dict(os.environ)
    if parsed.password:
        env["PGPASSWORD"] = str(parsed.password)
    done = subprocess.run([pg_restore, "--no-owner", "--single-transaction", "--exit-on-error", f"--dbname={libpq}",
                           str(backup)], capture_output=True, text=True, env=env, timeout=3600)
    if done.returncode != 0:
        first = (done.stderr.strip().splitlines() or ["no message"])[0]
        raise UserError(f"pg_restore of {backup} into {shown} failed: {first[:200]}; give a file `dsr-bench "
                        "challenge backup --db` wrote")
    from dsr_bench.challenge.db import open_database

    engine, session_factory = open_database(url)
    try:
        with session_factory() as session:
            ids = set(session.scalars(select(Submission.id)))
        from dsr_bench.challenge.binding import read_identity

        found = read_identity(session_factory)
    finally:
        engine.dispose()
    try:
        _check_belongs(layout, backup, found.challenge_id if found else None, ids)
    except UserError as exc:
        raise UserError(f"{exc} (it was restored into {shown}: drop that database)") from None
    return [f"restored {backup} into {shown} with pg_restore ({len(ids)} submissions)",
            *_after_restore(layout, url, ids)]
