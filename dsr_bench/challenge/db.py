"""The challenge's database: teams, phases, submissions and their aggregate scores (SQLAlchemy 2).

SQLite by default (one file, WAL journal, FULL sync: a commit is on disk when it returns), PostgreSQL by URL
(`postgresql+psycopg://...`). The schema is made and upgraded by the Alembic migrations beside this module
(`migrate`, run by `dsr-bench serve` and every host command at start). Times are naive UTC.
Scores hold aggregates only: the metrics and breakdowns of a whole part (public, private), never a sequence's or
a step's value. `team_transaction` serialises the writes that count a team's rows (its quota, its final choices).
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from sqlalchemy import (BigInteger, Boolean, DateTime, Float, ForeignKey, Integer, String, Text, UniqueConstraint,
                        create_engine, event, false)
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, sessionmaker

MIGRATIONS = Path(__file__).resolve().parent / "migrations"
#: a submission's states: queued -> running -> scored | refused (its predictions' problems) | failed (the server's) |
#: cancelled (by the host: `challenge cancel`)
STATES = ("queued", "running", "scored", "refused", "failed", "cancelled")


def utcnow() -> dt.datetime:
    """Now, naive UTC (what every column holds)."""
    return dt.datetime.now(dt.timezone.utc).replace(tzinfo=None)


class Base(DeclarativeBase):
    pass


class Team(Base):
    __tablename__ = "teams"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    key: Mapped[str] = mapped_column(String(12), unique=True)  # the token's lookup key (not secret)
    token_hash: Mapped[str] = mapped_column(String(200))  # argon2id PHC string
    created_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    revoked_at: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)
    #: the host's reference rows (`challenge add-references`): no usable token, never ranked, shown as reference rows
    reference: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())


class Phase(Base):
    __tablename__ = "phases"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    starts_at: Mapped[dt.datetime] = mapped_column(DateTime)
    ends_at: Mapped[dt.datetime] = mapped_column(DateTime)


class Submission(Base):
    __tablename__ = "submissions"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)  # 128 random bits, hex: also its status page's URL
    team_id: Mapped[int] = mapped_column(ForeignKey("teams.id"), index=True)
    method: Mapped[str] = mapped_column(String(64))
    phase: Mapped[str | None] = mapped_column(String(64), nullable=True)
    state: Mapped[str] = mapped_column(String(16), index=True, default="queued")
    created_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow, index=True)
    started_at: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)
    finished_at: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    lease_owner: Mapped[str | None] = mapped_column(String(64), nullable=True)
    lease_until: Mapped[dt.datetime | None] = mapped_column(DateTime, nullable=True)
    archive_sha256: Mapped[str] = mapped_column(String(64))
    archive_bytes: Mapped[int] = mapped_column(BigInteger)
    messages: Mapped[str] = mapped_column(Text, default="[]")  # JSON list of one-line messages
    final: Mapped[bool] = mapped_column(Boolean, default=False)
    rescore: Mapped[bool] = mapped_column(Boolean, default=False)  # the host asked for it to be scored again
    track: Mapped[str | None] = mapped_column(String(8), nullable=True)  # "3D" or "2D", once scored
    #: hidden by the host (`challenge hide`): none of its scores is current, so no table shows it
    hidden: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())


class Score(Base):
    __tablename__ = "scores"
    __table_args__ = (UniqueConstraint("submission_id", "part", "run"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    submission_id: Mapped[str] = mapped_column(ForeignKey("submissions.id"), index=True)
    part: Mapped[str] = mapped_column(String(16))  # "public" | "private"
    run: Mapped[int] = mapped_column(Integer)  # 1 for the first scoring, +1 per re-score
    current: Mapped[bool] = mapped_column(Boolean, default=True)
    metrics: Mapped[str] = mapped_column(Text)  # JSON: the aggregate metrics and breakdowns of the part
    rank_value: Mapped[float | None] = mapped_column(Float, nullable=True)
    toolkit_version: Mapped[str] = mapped_column(String(32))
    scored_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)


class Identity(Base):
    """The challenge this database belongs to (`binding`): one row, whose `challenge_id` is also in the challenge
    directory's challenge.json; a directory is served only with the database of its id."""

    __tablename__ = "challenge_identity"
    slot: Mapped[int] = mapped_column(Integer, primary_key=True)  # always 1: a second row cannot be inserted
    challenge_id: Mapped[str] = mapped_column(String(32), unique=True)
    bound_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    directory: Mapped[str] = mapped_column(Text)  # the directory's path when bound (shown in messages only)


def _sqlite_pragmas(dbapi_connection, _record) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA synchronous=FULL")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute("PRAGMA busy_timeout=30000")
    cursor.close()


def make_engine(url: str) -> Engine:
    """An engine for `url`: SQLite files in WAL mode with a 30 s busy timeout, or any SQLAlchemy URL
    (postgresql+psycopg://user@host/db)."""
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"timeout": 30, "check_same_thread": False})
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    return create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=20)


def migrate(engine: Engine) -> None:
    """Bring the database's schema to the newest migration (Alembic `upgrade head`), on `engine`'s connection."""
    from alembic import command
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    with engine.begin() as connection:
        config.attributes["connection"] = connection
        command.upgrade(config, "head")


def open_database(url: str) -> tuple[Engine, sessionmaker]:
    """(engine, session factory) of a migrated database."""
    from dsr_bench.errors import UserError
    from sqlalchemy.exc import OperationalError

    engine = make_engine(url)
    try:
        migrate(engine)
    except OperationalError as exc:
        raise UserError(f"database {engine.url.render_as_string(hide_password=True)}: cannot be opened "
                        f"({' '.join(str(exc.orig).split())[:200]}); check --db") from None
    return engine, sessionmaker(engine, expire_on_commit=False)


@contextmanager
def team_transaction(session_factory: sessionmaker, team_id: int) -> Iterator[tuple[Session, Team | None]]:
    """A write transaction holding team `team_id`'s lock from its first statement to its commit: (session, the team
    or None). Requests of one team that count its rows and then write (the daily quota, the final choices) run one
    after the other. SQLite: `BEGIN IMMEDIATE`, the database's write lock taken before the count (pysqlite would
    begin a transaction only at the first write, after the count: twenty uploads at once were all counted before
    any was stored); PostgreSQL: the team's row locked `FOR UPDATE` (each later statement of the transaction sees
    what the previous holder committed). Committed when the block ends, rolled back when it raises."""
    from sqlalchemy import select

    with session_factory() as session:
        connection = session.connection()
        if connection.dialect.name == "sqlite":
            connection.exec_driver_sql("BEGIN IMMEDIATE")
            team = session.get(Team, team_id)
        else:
            team = session.scalar(select(Team).where(Team.id == team_id).with_for_update())
        try:
            yield session, team
        except BaseException:
            session.rollback()
            raise
        session.commit()
