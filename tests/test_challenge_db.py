"""The challenge database on SQLite and on a real PostgreSQL server (a throwaway cluster started here): migrations,
unique team names, job claims that never hand one submission to two workers, results recorded once, leases that
expire after a worker dies."""

import json
import threading
import time

import pytest

pytest.importorskip("sqlalchemy")
pytest.importorskip("alembic")
pytest.importorskip("argon2")

from challenge_served import postgres_cluster  # noqa: E402

from dsr_bench.errors import UserError  # noqa: E402


@pytest.fixture(scope="module")
def postgres(tmp_path_factory):
    yield from postgres_cluster(tmp_path_factory)


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request, tmp_path):
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'challenge.db'}"
    cluster = request.getfixturevalue("postgres")
    return cluster.url(f"t{time.monotonic_ns()}")


def _submission(session_factory, team_id: int, n: int) -> list[str]:
    from dsr_bench.challenge.db import Submission, utcnow

    ids = [f"{i:032x}" for i in range(1, n + 1)]
    with session_factory.begin() as session:
        for sid in ids:
            session.add(Submission(id=sid, team_id=team_id, method="m", state="queued", attempts=0,
                                   created_at=utcnow(), archive_sha256="0" * 64, archive_bytes=1, messages="[]",
                                   final=False, rescore=False))
    return ids


def _team(session_factory) -> int:
    from sqlalchemy import select

    from dsr_bench.challenge.db import Team
    from dsr_bench.challenge.service import add_team

    add_team(session_factory, "team a")
    with session_factory() as session:
        return session.scalar(select(Team.id))


def test_migrations_teams_and_tokens(db_url):
    from sqlalchemy import select

    from dsr_bench.challenge.db import Team, open_database
    from dsr_bench.challenge.service import add_team, authenticate, revoke_team

    engine, sessions = open_database(db_url)
    open_database(db_url)  # migrating again is a no-op
    token = add_team(sessions, "team a")
    with pytest.raises(UserError, match="exists"):
        add_team(sessions, "team a")
    with sessions() as session:
        stored = session.scalar(select(Team.token_hash))
    assert stored.startswith("$argon2id$") and token not in stored
    assert authenticate(sessions, token).name == "team a"
    assert authenticate(sessions, token[:-1] + ("A" if token[-1] != "A" else "B")) is None
    revoke_team(sessions, "team a")
    assert authenticate(sessions, token) is None
    engine.dispose()


def test_claims_are_exclusive_and_results_recorded_once(db_url):
    from sqlalchemy import func, select

    from dsr_bench.challenge.db import Score, Submission, open_database
    from dsr_bench.challenge.layout import DEFAULTS
    from dsr_bench.challenge.worker import Outcome, _Lost, claim, finish

    engine, sessions = open_database(db_url)
    ids = _submission(sessions, _team(sessions), 24)
    claimed: dict[str, list[str]] = {}
    lock = threading.Lock()

    def worker(owner: str) -> None:
        while (sid := claim(sessions, owner, lease=60)) is not None:
            with lock:
                claimed.setdefault(sid, []).append(owner)

    threads = [threading.Thread(target=worker, args=(f"w{i}",)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(claimed) == ids and all(len(owners) == 1 for owners in claimed.values())
    sid, owner = ids[0], claimed[ids[0]][0]
    outcome = Outcome("scored", parts={"public": {"metrics": {"iou_ordered": 0.5}}}, track="3D")
    finish(sessions, sid, owner, outcome, DEFAULTS)
    with pytest.raises(_Lost):  # a second result for the same job is dropped
        finish(sessions, sid, owner, outcome, DEFAULTS)
    with pytest.raises(_Lost):  # and so is another worker's
        finish(sessions, ids[1], "not-the-owner", outcome, DEFAULTS)
    with sessions() as session:
        assert session.scalar(select(func.count()).select_from(Score)) == 1
        sub = session.get(Submission, sid)
        assert sub.state == "scored" and sub.lease_owner is None
        assert json.loads(session.scalar(select(Score.metrics)))["metrics"]["iou_ordered"] == 0.5
    engine.dispose()


def test_an_expired_lease_is_taken_again(db_url):
    import datetime as dt

    from sqlalchemy import update

    from dsr_bench.challenge.db import Submission, open_database, utcnow
    from dsr_bench.challenge.worker import claim, renew

    engine, sessions = open_database(db_url)
    sid = _submission(sessions, _team(sessions), 1)[0]
    assert claim(sessions, "dead", lease=3600) == sid
    assert claim(sessions, "alive", lease=60) is None  # leased: nobody else takes it
    # the dead worker's lease runs out: its end moved a second into the past (no sleep that a loaded machine could
    # make outlast a short lease before the check above)
    with sessions.begin() as session:
        session.execute(update(Submission).where(Submission.id == sid)
                        .values(lease_until=utcnow() - dt.timedelta(seconds=1)))
    assert claim(sessions, "alive", lease=60) == sid  # the dead worker's lease expired
    assert not renew(sessions, sid, "dead", 60)  # the dead worker cannot take it back
    with sessions() as session:
        assert session.get(Submission, sid).attempts == 2
    engine.dispose()


def test_a_database_of_the_first_schema_is_upgraded_with_its_rows(db_url):
    """A challenge database made before the reference team existed (migration 0001), holding a team and its
    submission, is brought to the newest schema by opening it: rows kept, the team not a reference team."""
    from alembic import command
    from alembic.config import Config
    from sqlalchemy import select, text

    from dsr_bench.challenge.db import MIGRATIONS, Team, make_engine, open_database

    engine = make_engine(db_url)
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    with engine.begin() as connection:
        config.attributes["connection"] = connection
        command.upgrade(config, "0001")
    with engine.begin() as connection:
        connection.execute(text("INSERT INTO teams (id, name, key, token_hash, created_at) "
                                "VALUES (1, 'old team', 'k', 'h', '2026-01-01')"))
        connection.execute(text("INSERT INTO submissions (id, team_id, method, state, created_at, attempts, "
                                "archive_sha256, archive_bytes, messages, final, rescore) VALUES "
                                "('x', 1, 'm', 'scored', '2026-01-01', 1, '0', 1, '[]', false, false)"))
    engine.dispose()
    engine, sessions = open_database(db_url)
    with sessions() as session:
        team = session.scalar(select(Team))
        assert (team.name, team.reference) == ("old team", False)
        assert session.execute(text("SELECT count(*) FROM submissions")).scalar() == 1
    engine.dispose()
