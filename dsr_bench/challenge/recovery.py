"""What a start recovers and what a job leaves behind; nothing stored is ever deleted.

- `recover` (run by `serve` after `binding.open_bound` accepted DIR and its database, before its workers start and
  before it accepts an upload): upload temporaries removed (never accepted); archives without a row moved aside to
  DIR/submissions/stray-<UTC time>/ (a server killed between storing an archive and writing its row, or a database
  restored from a backup older than the archives: kept for the host to look at); jobs whose worker ran on this host
  and is dead put back in the queue at once (not when their lease runs out); the work directories of jobs that no
  live worker holds removed.
- `clean_work`: a job's extracted archive (DIR/work/<id>-<random>) removed when the job ends, when it is taken
  again after its worker died (by the worker taking it), and when the host cancels it.
- `release_dead_leases`: a running job whose worker's process is gone from this host (its owner names host and pid,
  `worker.worker_owner`) goes back to the queue; a worker on another host keeps its lease until it expires.
"""

from __future__ import annotations

import datetime as dt
import shutil

from sqlalchemy import select, update
from sqlalchemy.orm import sessionmaker

from dsr_bench.challenge.binding import ARCHIVE, archive_ids
from dsr_bench.challenge.db import Submission, utcnow
from dsr_bench.challenge.layout import Layout


def owner_process(owner: str | None) -> tuple[str, int] | None:
    """(host, pid) of a worker's lease owner `<host>-<pid>-<random>` (None for another form)."""
    host, _, rest = (owner or "").rpartition("-")
    host, _, pid = host.rpartition("-")
    return (host, int(pid)) if host and pid.isdigit() and rest else None


def release_dead_leases(session_factory: sessionmaker) -> list[str]:
    """Put the running jobs of this host's dead workers back in the queue; returns their ids."""
    from dsr_bench.atomic import host_name, pid_alive

    here = host_name()[:32]
    with session_factory() as session:
        running = session.execute(select(Submission.id, Submission.lease_owner)
                                  .where(Submission.state == "running")).all()
    released = []
    for sid, owner in running:
        process = owner_process(owner)
        if process is None or process[0] != here or pid_alive(process[1]):
            continue
        with session_factory.begin() as session:
            done = session.execute(update(Submission).where(Submission.id == sid, Submission.lease_owner == owner,
                                                            Submission.state == "running")
                                   .values(state="queued", lease_owner=None, lease_until=None))
            if done.rowcount == 1:
                released.append(sid)
    return released


def release(session_factory: sessionmaker, sid: str, owner: str) -> bool:
    """Give job `sid` back to the queue while `owner` holds it, its attempt not counted (the worker stops, not
    because of the job: its server is gone); True when it was given back."""
    with session_factory.begin() as session:
        done = session.execute(update(Submission).where(Submission.id == sid, Submission.lease_owner == owner,
                                                        Submission.state == "running")
                               .values(state="queued", lease_owner=None, lease_until=None,
                                       attempts=Submission.attempts - 1))
        return done.rowcount == 1


def clean_work(layout: Layout, sid: str) -> None:
    """Remove what an evaluation of `sid` extracted (every DIR/work/<sid>-* directory)."""
    if ARCHIVE.fullmatch(sid) and layout.work.is_dir():
        for path in layout.work.glob(f"{sid}-*"):
            shutil.rmtree(path, ignore_errors=True)


def move_strays(layout: Layout, known: set[str]) -> tuple[str, int]:
    """Move DIR/submissions' archives whose id is not in `known` to a new DIR/submissions/stray-<UTC time>/;
    returns (that folder, how many)."""
    from dsr_bench.atomic import fsync_path

    strays = sorted(archive_ids(layout) - known)
    if not strays:
        return "", 0
    folder = layout.submissions / f"stray-{dt.datetime.now(dt.timezone.utc):%Y%m%dT%H%M%S%fZ}"
    folder.mkdir(mode=0o700)
    for sid in strays:
        layout.archive(sid).rename(folder / f"{sid}.tar")
    fsync_path(folder)
    fsync_path(layout.submissions)
    return str(folder), len(strays)


def recover(layout: Layout, session_factory: sessionmaker) -> list[str]:
    """Recover what a stopped server and its workers left (the module's list); returns lines saying what was done
    (none when there was nothing to do)."""
    from dsr_bench.challenge.storage import clean_partials

    lines = []
    removed = clean_partials(layout.uploads)
    if removed:
        lines.append(f"removed {removed} upload temporaries of a stopped server (never accepted)")
    released = release_dead_leases(session_factory)
    if released:
        lines.append(f"put {len(released)} jobs of stopped workers back in the queue: {', '.join(released)}")
    with session_factory() as session:
        known = set(session.scalars(select(Submission.id)))
        active = set(session.scalars(select(Submission.id).where(Submission.state == "running",
                                                                 Submission.lease_until >= utcnow())))
    folder, moved = move_strays(layout, known)
    if moved:
        lines.append(f"moved {moved} archives without a row in the database to {folder} (kept, never deleted)")
    if layout.work.is_dir():
        for path in layout.work.iterdir():
            if path.name.split("-")[0] in active:
                continue
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink(missing_ok=True)
    return lines
