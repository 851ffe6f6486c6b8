"""What binds a challenge directory to its database, so that no start loses what either holds.

A bound pair holds one random id twice: DIR/challenge.json's `challenge_id` (with `database`, the URL it was bound
to, password hidden, for messages) and the database's one `challenge_identity` row (`db.Identity`). Every host
command, `serve` and `challenge worker` open the database through `open_bound`, which checks the pair before anything
is written to either (`serve` then moves strays aside, `recovery.recover`, and deletes no archive):

- both hold an id: the same one, go on; another one: refused (DIR is served only with its own database);
- the database holds one, DIR none: refused (the database belongs to another directory);
- DIR holds one, the database none: refused (not DIR's database: e.g. a PostgreSQL challenge started without
  `--db`, or a SQLite file lost), except when it is the database DIR was being bound to when a command was killed
  between its two writes (the URL challenge.json records, empty, DIR without submissions): the binding is finished;
- neither (a new challenge, or one made before binding existed): bound when the database is empty and DIR holds no
  archive (new), or adopted at once when the database's submissions are exactly DIR's archives (a challenge of an
  earlier version, served with its own database); anything else is refused, naming `challenge adopt`, which binds
  such a pair explicitly and moves DIR's archives without a row aside (`adopt`).

A SQLite database file that does not exist is never created for a DIR that is bound or holds archives (the one-line
refusal names the database DIR was served with, or `challenge restore` when that file is what was lost).
`serving_lock` keeps a second `serve` (and `challenge restore`) off a DIR that is being served.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
from collections.abc import Iterator

from sqlalchemy import func, select
from sqlalchemy.engine import Engine
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import sessionmaker

from dsr_bench.challenge.db import Identity, Phase, Submission, Team, open_database, utcnow
from dsr_bench.challenge.layout import Layout, open_challenge, write_config
from dsr_bench.errors import UserError

ID_KEY, URL_KEY = "challenge_id", "database"
ARCHIVE = re.compile(r"[0-9a-f]{32}")
LOCK_NAME = ".serve.lock"


def shown_url(url: str) -> str:
    """`url` with its password hidden (what messages and challenge.json show)."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        return make_url(url).render_as_string(hide_password=True)
    except ArgumentError:
        raise UserError(f"--db {url!r} is not a database URL; e.g. postgresql+psycopg://user@host/dbname") from None


def sqlite_file(url: str) -> str | None:
    """The file of a SQLite URL (None for another backend or an in-memory database)."""
    from sqlalchemy.engine import make_url

    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite" or not parsed.database or parsed.database == ":memory:":
        return None
    return parsed.database


def archive_ids(layout: Layout) -> set[str]:
    """The ids of the archives stored in DIR/submissions (strays moved aside are not among them)."""
    if not layout.submissions.is_dir():
        return set()
    return {p.stem for p in layout.submissions.glob("*.tar") if ARCHIVE.fullmatch(p.stem)}


def read_identity(session_factory: sessionmaker) -> Identity | None:
    with session_factory() as session:
        return session.scalar(select(Identity))


def _contents(session_factory: sessionmaker) -> tuple[set[str], int]:
    """(the database's submission ids, how many teams and phases it holds)."""
    with session_factory() as session:
        subs = set(session.scalars(select(Submission.id)))
        others = (session.scalar(select(func.count()).select_from(Team)) or 0) + \
            (session.scalar(select(func.count()).select_from(Phase)) or 0)
    return subs, others


def _raw_config(layout: Layout) -> dict:
    """challenge.json as written (without the defaults `open_challenge` adds)."""
    open_challenge(layout.root)  # its one-line refusals
    return json.loads(layout.config.read_text())


def write_identity(session_factory: sessionmaker, layout: Layout, challenge_id: str) -> str:
    """Insert the database's identity row; returns the id it holds (another binder's, when one was faster)."""
    try:
        with session_factory.begin() as session:
            session.add(Identity(slot=1, challenge_id=challenge_id, bound_at=utcnow(),
                                 directory=str(layout.root.absolute())))
    except IntegrityError:
        found = read_identity(session_factory)
        if found is None:
            raise
        return found.challenge_id
    return challenge_id


def bind(layout: Layout, session_factory: sessionmaker, url: str, challenge_id: str | None = None) -> str:
    """Bind DIR and the database: challenge.json first (with the URL), then the database's row (a command killed
    between the two is finished by the next, `check`); returns the id."""
    challenge_id = challenge_id or secrets.token_hex(16)
    config = _raw_config(layout)
    write_config(layout, {**config, ID_KEY: challenge_id, URL_KEY: shown_url(url)})
    held = write_identity(session_factory, layout, challenge_id)
    if held != challenge_id:  # two first starts at once: the database's row decides
        write_config(layout, {**_raw_config(layout), ID_KEY: held, URL_KEY: shown_url(url)})
    return held


def _count(n: int, what: str) -> str:
    return f"{n} {what}" + ("" if n == 1 else "s")


def _refuse_missing_file(layout: Layout, config: dict, url: str) -> None:
    """A UserError, before the file is created, when SQLite `url` names no file and DIR is bound or holds archives."""
    path = sqlite_file(url)
    if path is None or os.path.exists(path):
        return
    archives = archive_ids(layout)
    bound, root = config.get(URL_KEY), layout.root
    if bound and bound != shown_url(url):
        raise UserError(f"{path}: no such database, and {root} is served with {bound}: give --db {bound} (no empty "
                        "database is made for a challenge that has one)")
    if bound:
        held = f" (it holds {_count(len(archives), 'submission')})" if archives else ""
        raise UserError(f"{path}: the database of {root}{held} is missing; restore its backup (`dsr-bench "
                        f"challenge restore {root} BACKUP`)")
    if archives:
        raise UserError(f"{path}: no such database, and {root} holds {_count(len(archives), 'submission')}: give "
                        "--db URL of the database it was served with, or restore its backup (`dsr-bench challenge "
                        f"restore {root} BACKUP`); no empty database is made for a challenge with submissions")


def check(layout: Layout, session_factory: sessionmaker, url: str, bind_new: bool = True) -> str | None:
    """Check (and with `bind_new`, make or finish) the binding of DIR and the database at `url` (the module's
    rules); returns the challenge's id (None: neither is bound and `bind_new` is off, an unbound pair a worker
    may still serve)."""
    config = _raw_config(layout)
    dir_id = config.get(ID_KEY)
    found = read_identity(session_factory)
    db_id = found.challenge_id if found else None
    where = found.directory if found else ""
    shown, root = shown_url(url), layout.root
    if dir_id and db_id:
        if dir_id != db_id:
            raise UserError(f"{shown} is the database of another challenge ({db_id}, bound to {where}), "
                            f"not of {root} ({dir_id}); give --db {config.get(URL_KEY) or 'URL of its database'}")
        return dir_id
    if db_id:
        raise UserError(f"{shown} is the database of the challenge in {where} ({db_id}), not of {root}; "
                        "give that directory, or the --db of this one")
    subs, others = _contents(session_factory)
    archives = archive_ids(layout)
    if dir_id:
        if bind_new and config.get(URL_KEY) == shown and not subs and not others and not archives:
            return bind(layout, session_factory, url, dir_id)  # the binding a killed command began
        held = f" (it holds {_count(len(archives), 'submission')})" if archives else ""
        raise UserError(f"{shown} is not the database of {root}{held}: give --db {config.get(URL_KEY)}; if that "
                        f"database is lost, restore its backup (`dsr-bench challenge restore {root} BACKUP`)")
    if not bind_new:
        return None
    if not subs and not others and not archives:
        return bind(layout, session_factory, url)  # a new challenge
    if (subs and subs == archives) or (not subs and not archives):
        return bind(layout, session_factory, url)  # made before binding existed: its own database
    if not subs:
        raise UserError(f"{shown} holds no submission but {root} holds {_count(len(archives), 'archive')}: it is "
                        f"not this challenge's database; give the --db {root} was served with")
    raise UserError(f"{shown} and {root} do not match: {len(archives - subs)} archives without a row, "
                    f"{len(subs - archives)} rows without an archive; give the --db {root} was served with, or bind "
                    f"them anyway with `dsr-bench challenge adopt {root} --db URL` (archives without a row are moved "
                    "aside)")


def open_bound(layout: Layout, url: str, bind_new: bool = True) -> tuple[Engine, sessionmaker]:
    """(engine, session factory) of the database at `url`, migrated, once `check` accepts it for DIR (a UserError
    otherwise, and then a missing SQLite file is not created)."""
    from sqlalchemy.exc import DatabaseError

    config = _raw_config(layout)
    _refuse_missing_file(layout, config, url)
    try:
        engine, session_factory = open_database(url)
    except DatabaseError as exc:  # not a database (a damaged file): open_database says the rest in one line
        raise UserError(f"{shown_url(url)}: damaged ({' '.join(str(exc.orig).split())[:160]}); restore its backup "
                        f"(`dsr-bench challenge restore {layout.root} BACKUP`)") from None
    try:
        check(layout, session_factory, url, bind_new)
    except BaseException:
        engine.dispose()
        raise
    return engine, session_factory


def adopt(layout: Layout, url: str) -> list[str]:
    """Bind DIR and the database at `url` explicitly (`challenge adopt`): a pair neither of which is bound (the
    archives of DIR without a row are moved aside, never deleted), or a bound DIR that holds no submission with a
    new database (a new id: its old database is refused from then on). Returns lines saying what was done."""
    from dsr_bench.challenge.recovery import move_strays

    config = _raw_config(layout)
    engine, session_factory = open_database(url)
    try:
        found = read_identity(session_factory)
        dir_id, shown = config.get(ID_KEY), shown_url(url)
        if found is not None:
            if found.challenge_id == dir_id:
                return [f"{layout.root} and {shown} are bound already ({dir_id})"]
            raise UserError(f"{shown} is the database of the challenge in {found.directory} ({found.challenge_id}); "
                            "it cannot be bound to another directory: give another --db")
        archives = archive_ids(layout)
        if dir_id and archives:
            raise UserError(f"{layout.root} holds {len(archives)} submissions of its database {config.get(URL_KEY)}; "
                            "give --db of that one (or restore its backup with `dsr-bench challenge restore`)")
        subs, _ = _contents(session_factory)
        lines = []
        folder, moved = move_strays(layout, subs)
        if moved:
            lines.append(f"moved {moved} archives without a row in {shown} to {folder}")
        if subs - archives:
            lines.append(f"{len(subs - archives)} submissions of {shown} have no archive in {layout.submissions}: "
                         "their workers fail them; `dsr-bench challenge submissions` lists them")
        challenge_id = bind(layout, session_factory, url)
        return [*lines, f"bound {layout.root} and {shown} (challenge {challenge_id})"]
    finally:
        engine.dispose()


def _lock_holder(fd: int) -> str:
    os.lseek(fd, 0, os.SEEK_SET)
    return os.read(fd, 200).decode(errors="replace").strip() or "another process"


@contextlib.contextmanager
def serving_lock(layout: Layout) -> Iterator[None]:
    """Hold DIR/.serve.lock (flock) while serving: a second `serve` of DIR is refused in one line (its start would
    take the first one's upload in flight for a stray), and so is `challenge restore`. The kernel releases it when
    the server dies, however it dies."""
    import fcntl

    from dsr_bench.atomic import host_name

    fd = os.open(layout.root / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise UserError(f"{layout.root} is being served ({_lock_holder(fd)}); stop that server first") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"dsr-bench serve, pid {os.getpid()} on {host_name()}\n".encode())
        yield
    finally:
        os.close(fd)


def refuse_if_served(layout: Layout, what: str) -> None:
    """A UserError when a server holds DIR's `serving_lock` (`what`: the command refused)."""
    import fcntl

    path = layout.root / LOCK_NAME
    if not path.exists():
        return
    fd = os.open(path, os.O_RDWR)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise UserError(f"{layout.root} is being served ({_lock_holder(fd)}); stop that server before "
                            f"{what}") from None
    finally:
        os.close(fd)
