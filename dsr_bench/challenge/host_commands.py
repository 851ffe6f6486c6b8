"""The host's commands on single submissions, on the binding of DIR and its database, on a lost database, and the
evaluation worker of another machine: `dsr-bench challenge submissions | cancel | hide | restore | adopt | worker`
(`challenge rescore DIR [ID]` is in `cli`). Added to the `challenge` group by `cli.register`; heavy imports happen
inside the commands."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dsr_bench.challenge.cli import DbOption, _sessions, challenge_app
from dsr_bench.errors import UserError

SubmissionId = typer.Argument(..., help="The submission's id (32 hex digits; `challenge submissions DIR` lists them).")


@challenge_app.command("submissions")
def submissions(root: Path = typer.Argument(..., help="Challenge directory."),
                status: Optional[str] = typer.Option(None, "--status", help="Only those in this state: queued, "
                                                     "running, scored, refused, failed or cancelled."),
                db: Optional[str] = DbOption) -> None:
    """List the submissions, oldest first: id, state, time, team, method, attempts, and their messages (a failed
    one's reason and traceback are in the server's log)."""
    from dsr_bench.challenge.admin import list_submissions

    _, _, sessions = _sessions(root, db)
    lines = list_submissions(sessions, status)
    for line in lines:
        typer.echo(line)
    if not lines:
        typer.echo("no submission" + (f" is {status}" if status else " yet"), err=True)


@challenge_app.command("cancel")
def cancel(root: Path = typer.Argument(..., help="Challenge directory."), sid: str = SubmissionId,
           db: Optional[str] = DbOption) -> None:
    """Cancel a queued or running submission: it is never scored (a worker scoring it drops its result); its archive
    and row stay."""
    from dsr_bench.challenge.admin import cancel as run

    layout, _, sessions = _sessions(root, db)
    typer.echo(run(layout, sessions, sid))


@challenge_app.command("hide")
def hide(root: Path = typer.Argument(..., help="Challenge directory."), sid: str = SubmissionId,
         undo: bool = typer.Option(False, "--undo", help="Show it again (its newest scores)."),
         db: Optional[str] = DbOption) -> None:
    """Take a submission off the leaderboard, the final ranking and every page's scores (or, with --undo, put it
    back); its row, archive and scores stay."""
    from dsr_bench.challenge.admin import hide as run

    _, _, sessions = _sessions(root, db)
    typer.echo(run(sessions, sid, undo))


@challenge_app.command("restore")
def restore(root: Path = typer.Argument(..., help="Challenge directory (its server stopped)."),
            backup: Path = typer.Argument(..., help="The file `dsr-bench challenge backup` wrote."),
            db: Optional[str] = DbOption) -> None:
    """Put a backup of the challenge's database back: SQLite, the database file replaced (the old one kept beside
    it); PostgreSQL, pg_restore into the new, empty database --db names. The backup must be this challenge's; the
    next `serve` moves archives newer than the backup aside."""
    from dsr_bench.challenge.admin import restore as run
    from dsr_bench.challenge.layout import open_challenge

    layout, _ = open_challenge(root)
    for line in run(layout, db or layout.default_db_url(), backup):
        typer.echo(line)
    typer.echo(f"next: dsr-bench serve {root}" + (" --db URL" if db else ""))


@challenge_app.command("adopt")
def adopt(root: Path = typer.Argument(..., help="Challenge directory."), db: Optional[str] = DbOption) -> None:
    """Bind a challenge directory and its database that `serve` would not bind by itself (made before binding
    existed, and they differ: archives without a row are moved aside to DIR/submissions/stray-<time>/, never
    deleted), or a directory holding no submission to a new database."""
    from dsr_bench.challenge.binding import adopt as run
    from dsr_bench.challenge.layout import open_challenge

    layout, _ = open_challenge(root)
    for line in run(layout, db or layout.default_db_url()):
        typer.echo(line)


@challenge_app.command("worker")
def worker(root: Path = typer.Argument(..., help="Challenge directory, as this machine reaches it (shared with the "
                                       "server's: its hidden sets, pins and submissions)."),
           db: Optional[str] = DbOption,
           lease: float = typer.Option(60.0, "--lease", help="Seconds a job stays this worker's without a renewal "
                                       "(renewed every third of it while it runs).")) -> None:
    """Run one evaluation worker here, beside the server's: it takes queued submissions from the challenge's
    database (PostgreSQL, --db, for another machine), scores them on DIR's hidden sets and records the scores.
    SIGTERM or Ctrl-C stops it after its job; killed, its job is taken again when its lease expires (at once by
    a worker started again on this machine)."""
    import signal
    import threading

    from dsr_bench.challenge.cli import one_line

    with one_line("challenge worker"):
        from dsr_bench.challenge.layout import open_challenge
        from dsr_bench.challenge.worker import log_to_stderr, run_worker

    if lease < 3:
        raise UserError(f"--lease {lease:g}: give at least 3 seconds (a lease is renewed every third of it)")
    layout, _ = open_challenge(root)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    log_to_stderr()
    done = run_worker(str(root), db or layout.default_db_url(), lease=lease, stop=stop)
    typer.echo(f"worker stopped after {done} jobs", err=True)
