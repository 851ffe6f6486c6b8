"""The challenge's commands: `dsr-bench challenge ...` (host), `dsr-bench serve`, `dsr-bench submit`.

Registered through the `dsr_bench.commands` entry point; `challenge create`, which runs the simulator, is added to
the same group by `generators.challenge`. Heavy imports (FastAPI, SQLAlchemy, httpx) happen inside the commands.
Every command ends in one line (`dsr_bench.errors.UserError`) where the challenge extra is not installed (naming
`pip install 'dsr-bench[challenge]'`) or where a file cannot be written (a read-only file system, no permission,
no space: the path and the reason): the group's commands through `ChallengeGroup`, `serve` through `one_line`.
"""

from __future__ import annotations

import contextlib
import errno
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Optional

import typer
from typer.core import TyperGroup

from dsr_bench.errors import UserError

#: how to install what the challenge's commands need beyond the toolkit (pyproject.toml's challenge extra)
INSTALL = "pip install 'dsr-bench[challenge]'"
#: the top-level modules of the challenge extra's packages (and of what they bring: starlette, pydantic)
EXTRA_MODULES = frozenset(("fastapi", "starlette", "pydantic", "uvicorn", "sqlalchemy", "alembic", "multipart",
                           "python_multipart", "argon2", "psycopg", "httpx"))
#: the errors of a file that cannot be written, said in one line: read-only file system, no permission, no space
_WRITE_ERRORS = (errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EDQUOT)


def one_line_error(exc: BaseException, command: str) -> UserError | None:
    """What a host or participant can fix, as a one-line UserError (None for anything else): a module of the
    challenge extra missing (naming `INSTALL`), a file `command` cannot write (naming it and why)."""
    module = (exc.name or "").split(".")[0] if isinstance(exc, ImportError) else ""
    if module in EXTRA_MODULES:
        return UserError(f"dsr-bench {command} needs {module}, which is not installed: {INSTALL}")
    if isinstance(exc, OSError) and exc.errno in _WRITE_ERRORS and exc.filename is not None:
        return UserError(f"dsr-bench {command}: cannot write {exc.filename} ({exc.strerror}); choose a directory on "
                         "a writable file system that you may write to (and with space left)")
    return None


@contextlib.contextmanager
def one_line(command: str) -> Iterator[None]:
    """Run the block with `one_line_error`'s errors raised as UserErrors."""
    try:
        yield
    except (ImportError, OSError) as exc:
        error = one_line_error(exc, command)
        if error is None:
            raise
        raise error from None


class ChallengeGroup(TyperGroup):
    """The `challenge` group: each of its commands (`create` too, which `generators.challenge` adds) ends in one
    line on `one_line_error`'s errors."""

    def invoke(self, ctx: Any) -> Any:  # (typer's vendored click.Context)
        try:
            return super().invoke(ctx)
        except (ImportError, OSError) as exc:
            error = one_line_error(exc, f"challenge {ctx.invoked_subcommand or ''}".rstrip())
            if error is None:
                raise
            raise error from None


challenge_app = typer.Typer(help="Host a challenge: a hidden test set, teams, phases, re-scoring.",
                            no_args_is_help=True, cls=ChallengeGroup)

DbOption = typer.Option(None, "--db", help="Database URL (default: DIR/challenge.db, SQLite); e.g. "
                        "postgresql+psycopg://user@host/dbname.")


def _sessions(root: Path, db: Optional[str]):
    """(layout, configuration, session factory) of challenge `root` and its database, once `binding.open_bound`
    accepted them for each other (bound at the first command of a new challenge)."""
    from dsr_bench.challenge.binding import open_bound
    from dsr_bench.challenge.layout import open_challenge

    layout, config = open_challenge(root)
    return layout, config, open_bound(layout, db or layout.default_db_url())[1]


@challenge_app.command("export-inputs")
def export_inputs(
    root: Path = typer.Argument(..., help="Challenge directory."),
    out: Path = typer.Argument(..., help="New directory to write the participants' inputs into."),
) -> None:
    """Write what participants may have: per hidden sequence its TSDF, depth, colour, camera parameters and actions
    (no masks, flow, poses, objects or 2D ground truth), splits/challenge.txt, and digests.json (SHA-256 per file);
    OUT appears complete or not at all."""
    from dsr_bench.challenge.host import export_inputs as run
    from dsr_bench.challenge.layout import open_challenge

    layout, _ = open_challenge(root)
    run(layout, out)
    typer.echo(f"wrote the inputs to {out}")


@challenge_app.command("add-team")
def add_team(root: Path = typer.Argument(..., help="Challenge directory."),
             name: str = typer.Argument(..., help="Team name (1-64 visible characters, NFKC-normalised; one that reads "
                                       "like a team's name is refused)."),
             db: Optional[str] = DbOption) -> None:
    """Add a team and print its token once (only its argon2 hash is stored: a lost token is revoked and the team
    added again under another name)."""
    from dsr_bench.challenge.rules import check_name
    from dsr_bench.challenge.service import add_team as run

    _, _, sessions = _sessions(root, db)
    token = run(sessions, name)
    typer.echo(token)
    typer.echo(f"team {check_name(name, 'team name')!r} added (the name as stored); give it the token above (shown "
               "once)", err=True)


@challenge_app.command("revoke-team")
def revoke_team(root: Path = typer.Argument(..., help="Challenge directory."),
                name: str = typer.Argument(..., help="Team name."), db: Optional[str] = DbOption) -> None:
    """Revoke a team's token: every later request with it is refused; its submissions and scores stay."""
    from dsr_bench.challenge.service import revoke_team as run

    _, _, sessions = _sessions(root, db)
    run(sessions, name)
    typer.echo(f"team {name!r} revoked")


@challenge_app.command("teams")
def teams(root: Path = typer.Argument(..., help="Challenge directory."), db: Optional[str] = DbOption) -> None:
    """List the teams (name, added, revoked)."""
    from sqlalchemy import select

    from dsr_bench.challenge.db import Team

    _, _, sessions = _sessions(root, db)
    with sessions() as session:
        for team in session.scalars(select(Team).order_by(Team.id)):
            revoked = f", revoked {team.revoked_at:%Y-%m-%d %H:%M}" if team.revoked_at else ""
            typer.echo(f"{team.name!r}: added {team.created_at:%Y-%m-%d %H:%M}{revoked}")


@challenge_app.command("add-phase")
def add_phase(root: Path = typer.Argument(..., help="Challenge directory."),
              name: str = typer.Argument(..., help="Phase name, e.g. development or final."),
              start: str = typer.Option(..., "--start", help="Opens at (ISO date or time, UTC)."),
              end: str = typer.Option(..., "--end", help="Closes at (ISO date or time, UTC)."),
              db: Optional[str] = DbOption) -> None:
    """Add a phase: submissions are accepted only while a phase is open (none defined: always)."""
    from dsr_bench.challenge.service import add_phase as run, parse_time

    _, _, sessions = _sessions(root, db)
    run(sessions, name, parse_time(start, "--start"), parse_time(end, "--end"))
    typer.echo(f"phase {name!r} added")


@challenge_app.command("rescore")
def rescore(root: Path = typer.Argument(..., help="Challenge directory."),
            sid: Optional[str] = typer.Argument(None, help="Only this submission (a failed or cancelled one is "
                                                "queued again)."),
            db: Optional[str] = DbOption) -> None:
    """Score every scored or refused submission again with the installed toolkit (after a fix), or only submission
    ID; the running server's workers do it, and each new score records the toolkit version."""
    from dsr_bench.challenge.admin import rescore_one
    from dsr_bench.challenge.service import request_rescore

    _, _, sessions = _sessions(root, db)
    if sid is not None:
        typer.echo(rescore_one(sessions, sid))
        return
    typer.echo(f"{request_rescore(sessions)} submissions queued to be scored again")


@challenge_app.command("reveal")
def reveal(root: Path = typer.Argument(..., help="Challenge directory."),
           hide: bool = typer.Option(False, "--hide", help="Hide the private part's scores again.")) -> None:
    """Show the private part's scores and the final ranking on the leaderboard (at the challenge's end)."""
    from dsr_bench.challenge.layout import open_challenge, write_config

    layout, config = open_challenge(root)
    config["reveal_private"] = not hide
    write_config(layout, config)
    typer.echo("private scores " + ("hidden" if hide else "shown: the final ranking is on the leaderboard"))


@challenge_app.command("backup")
def backup(root: Path = typer.Argument(..., help="Challenge directory."),
           out: Path = typer.Argument(..., help="New file for the copy (SQLite: a database file; PostgreSQL: a "
                                      "pg_dump archive)."),
           db: Optional[str] = DbOption) -> None:
    """Copy the challenge's database consistently while the server runs: SQLite through its online backup API (one
    commit's state, checked with PRAGMA integrity_check), PostgreSQL with pg_dump; OUT appears complete or not at
    all. Copy DIR/submissions after it: every row of the copy then has its archive."""
    from dsr_bench.challenge.backup import backup_database
    from dsr_bench.challenge.layout import open_challenge

    layout, _ = open_challenge(root)
    typer.echo(backup_database(db or layout.default_db_url(), out))


@challenge_app.command("add-references")
def add_references(
    root: Path = typer.Argument(..., help="Challenge directory."),
    models: str = typer.Option("static", "--models", help="Comma-separated reference models: static (predicting "
                               "no motion), push, and learned models with shipped CPU-track weights (e.g. dsr)."),
    db: Optional[str] = DbOption,
) -> None:
    """Predict with reference models on the challenge's inputs (every hidden set's) and queue them for the server's
    workers, which score them as they score the teams' submissions; the leaderboard shows them as reference rows
    (public part; private part once revealed)."""
    from dsr_bench.challenge.references import add_references as run

    layout, config, sessions = _sessions(root, db)
    queued = run(layout, config, sessions, models.split(","), typer.echo)
    for model, sid in queued.items():
        typer.echo(f"{model}: queued as submission {sid}")
    typer.echo("the running server's workers score them (`dsr-bench serve`); they appear as reference rows")


@challenge_app.command("add-hidden-set")
def add_hidden_set(
    root: Path = typer.Argument(..., help="Challenge directory."),
    source: Path = typer.Argument(..., help="Folder of annotated sequences (`dsr-bench annotate --export` files)."),
    name: str = typer.Option("real", "--name", help="The set's name (1-8 lower-case letters or digits): its "
                             "sequences become seq_NAME_0000, ... and its tables are titled by it."),
    public_fraction: float = typer.Option(0.5, "--public-fraction", help="Share of its sequences in the public "
                                          "part."),
) -> None:
    """Add real annotated captures as a further hidden set: copied into DIR, pinned, split into a public and a
    private part, their inputs exported beside the simulated ones (DIR/inputs is written again); submissions that
    hold its predictions are scored on it separately, in its own leaderboard tables."""
    from dsr_bench.challenge.host import add_hidden_set as run
    from dsr_bench.challenge.layout import open_challenge

    layout, _ = open_challenge(root)
    entry = run(layout, source, name, public_fraction)
    typer.echo(f"hidden set {name!r} added: {len(entry['sequences'])} annotated sequences ({len(entry['public'])} "
               f"public, {len(entry['private'])} private) as {entry['sequences'][0]} ...; inputs written again to "
               f"{layout.inputs}")


@challenge_app.command("download")
def download(out: Path = typer.Argument(..., help="New directory for the inputs."),
             server: str = typer.Option(..., "--server", help="The challenge server's URL.")) -> None:
    """Download a challenge's inputs (each file checked against its digest), ready for `dsr-bench predict --data
    OUT`."""
    from dsr_bench.challenge.client import download_inputs

    download_inputs(server, out, typer.echo)
    typer.echo(f"inputs written to {out}; next: dsr-bench predict --model MODEL --data {out} --out PREDICTIONS")


def serve(
    root: Path = typer.Argument(..., help="Challenge directory (`dsr-bench challenge create`)."),
    host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on."),
    port: int = typer.Option(8000, "--port", help="Port to listen on."),
    db: Optional[str] = DbOption,
    workers: int = typer.Option(1, "--workers", "-w", help="Evaluation worker processes (0: none here, workers on "
                                "other machines: `dsr-bench challenge worker`)."),
    leaderboard: Optional[Path] = typer.Option(
        None, "--leaderboard", help="Local leaderboard folder whose reference rows (static, push, oracle) of the "
        "challenge's split are shown beside the submissions [default: the clone's leaderboard/, if any]."),
    keep_free: int = typer.Option(
        1024, "--keep-free", help="Free disk (MiB) the server keeps under DIR: an upload that would leave less is "
        "refused (507, the host told in this log), checked before it is read and while it is written."),
    forwarded_allow_ips: Optional[str] = typer.Option(
        None, "--forwarded-allow-ips", help="Your reverse proxy's addresses (comma-separated, or *): only requests "
        "from them may name the client's address (X-Forwarded-For) and scheme; default: trust no proxy header, the "
        "connection's peer is the client (the failed-token throttle counts per client address)."),
) -> None:
    """Run the challenge's web server (leaderboard, uploads, status) and its evaluation workers; the database is
    migrated and checked to be DIR's first (docs/challenge.md, "What binds DIR and its database"), what a stopped
    server left is recovered (nothing stored is deleted), then the server starts, and its workers once it serves
    (they end with it). Ctrl-C stops both."""
    import multiprocessing as mp
    import os

    with one_line("serve"):
        import uvicorn

        from dsr_bench.challenge.binding import open_bound, serving_lock
        from dsr_bench.challenge.layout import open_challenge
        from dsr_bench.challenge.recovery import recover
        from dsr_bench.challenge.server import Settings, create_app
        from dsr_bench.challenge.worker import worker_main

    if workers < 0:
        raise UserError(f"--workers {workers}: give 0 or more evaluation workers")
    if keep_free < 0:
        raise UserError(f"--keep-free {keep_free}: give the free disk to keep in MiB, 0 or more (default 1024)")
    if leaderboard is not None and not (leaderboard / "entries").is_dir():
        raise UserError(f"--leaderboard {leaderboard}: not a leaderboard folder (no entries/); give the folder "
                        "`dsr-bench leaderboard build` writes, e.g. leaderboard")
    layout, _ = open_challenge(root)
    url = db or layout.default_db_url()
    with serving_lock(layout), one_line("serve"):
        engine, sessions = open_bound(layout, url)  # a mismatch is refused before anything is touched
        try:
            for line in recover(layout, sessions):  # before the workers start and before any upload
                typer.echo(line, err=True)
        finally:
            engine.dispose()
        app = create_app(root, url, Settings(leaderboard=leaderboard, keep_free=keep_free << 20))
        server = uvicorn.Server(uvicorn.Config(app, host=host, port=port, log_level="info",
                                               proxy_headers=bool(forwarded_allow_ips),
                                               forwarded_allow_ips=forwarded_allow_ips or ""))
        context = mp.get_context("spawn")
        stopping = threading.Event()
        args = (str(root), url, os.getpid())  # the worker ends when this process is gone (worker._watch_parent)
        procs = [context.Process(target=worker_main, args=args, daemon=True) for _ in range(workers)]

        def supervise() -> None:  # a worker that died (killed, crashed) is replaced; its job goes back to the queue
            while not server.started and not stopping.wait(0.1):
                pass  # the app's start-up ran first
            for p in procs:
                if not stopping.is_set():
                    p.start()
            while not stopping.wait(1.0):
                for i, p in enumerate(procs):
                    if p.pid is not None and not p.is_alive() and not stopping.is_set():
                        procs[i] = context.Process(target=worker_main, args=args, daemon=True)
                        procs[i].start()

        supervisor = threading.Thread(target=supervise, daemon=True)
        supervisor.start()
        try:
            server.run()
        except KeyboardInterrupt:
            pass
        finally:
            stopping.set()
            supervisor.join()
            for p in procs:
                if p.pid is not None:
                    p.terminate()
            for p in procs:
                if p.pid is not None:
                    p.join(10)
    if not server.started:
        raise typer.Exit(3)  # uvicorn said why (e.g. the port is taken)


def submit(
    predictions: Path = typer.Argument(..., help="Predictions directory: one SEQUENCE.h5 per sequence of the "
                                     "split and meta.json, nothing else (regular files, no links)."),
    server: str = typer.Option(..., "--server", help="The challenge server's URL, e.g. http://127.0.0.1:8000."),
    token: str = typer.Option(..., "--token", envvar="DSR_BENCH_TOKEN", help="Your team's token (or "
                              "$DSR_BENCH_TOKEN)."),
    method: str = typer.Option(..., "--method", help="Your method's name, shown on the leaderboard."),
    no_wait: bool = typer.Option(False, "--no-wait", help="Upload and return; do not follow the submission."),
    timeout: float = typer.Option(3600.0, "--timeout", help="Seconds to follow the submission before giving up."),
    final: bool = typer.Option(False, "--final", help="Once scored, choose it as one of your team's final "
                               "submissions (`dsr-bench challenge final` changes the choice)."),
) -> None:
    """Upload predictions to a challenge server and follow them until scored.

    Exit 0: scored (and, with --final, chosen); 1: stored but refused or failed (each problem on one line as
    `dsr-bench evaluate` prints it; a refused one does not use a daily try); 2: one line, nothing scored: the upload
    refused (token, daily quota, phase closed, too large, archive, method name), the server unreachable, no outcome
    within --timeout, or the final choice refused."""
    from dsr_bench.challenge.client import choose_final, describe, submit as run

    if no_wait and final:
        raise UserError("--final needs the score: drop --no-wait, or choose later with `dsr-bench challenge final`")
    with one_line("submit"):  # without httpx or SQLAlchemy (the challenge extra): one line naming it
        from dsr_bench.challenge.rules import check_name

        state, status = run(predictions, server, token, check_name(method, "--method"), typer.echo, timeout=timeout,
                            follow=not no_wait)
    if no_wait:
        return
    for line in describe(status, predictions):
        typer.echo(line, err=state != "scored")
    if state != "scored":
        raise typer.Exit(1)
    if final:
        choose_final(server, token, status["id"])
        typer.echo(f"submission {status['id']}: chosen as one of your final submissions")


@challenge_app.command("final")
def final_choice(
    submission: Optional[str] = typer.Argument(None, help="The submission to choose (its id, 32 hex digits); none: "
                                               "list your team's submissions."),
    server: str = typer.Option(..., "--server", help="The challenge server's URL, e.g. http://127.0.0.1:8000."),
    token: str = typer.Option(..., "--token", envvar="DSR_BENCH_TOKEN", help="Your team's token (or "
                              "$DSR_BENCH_TOKEN)."),
    undo: bool = typer.Option(False, "--undo", help="Unselect SUBMISSION instead."),
) -> None:
    """(Participant) Choose one of your team's final submissions, or list them.

    The best of the final submissions by the private part ranks the team (none chosen: its newest scored one);
    --undo unselects SUBMISSION; without SUBMISSION, the team's submissions are listed (id, time, state, method,
    public scores, FINAL). A refusal (not yours, not scored, too many, the challenge ended) is one line, exit 2."""
    from dsr_bench.challenge.client import choose_final, history_lines, my_submissions

    if submission is None:
        if undo:
            raise UserError("--undo needs the SUBMISSION to unselect; run without --undo to list yours")
        for line in history_lines(my_submissions(server, token)):
            typer.echo(line)
        return
    status = choose_final(server, token, submission.strip(), final=not undo)
    typer.echo(f"submission {status['id']} ({status['method']!r}): "
               + ("chosen as one of your final submissions" if status["final"] else "not a final submission"))


def register(app: typer.Typer) -> None:
    from dsr_bench.challenge import host_commands  # noqa: F401  (adds the host's further commands to the group)

    app.add_typer(challenge_app, name="challenge")
    app.command("serve")(serve)
    app.command("submit")(submit)
