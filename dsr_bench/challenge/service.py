"""What the commands and the routes do to the database: teams, phases, submissions, final choices, the leaderboard.

The rules these apply (names, phases and the end, the quota, final choices) are `rules`' functions, each in one
place. The leaderboard is built from each submission's current scores (the newest run, `worker.finish`): the public
part's aggregates while the challenge runs, and, once the host reveals them (`challenge reveal`), the private
part's, ranking each team by the best of the submissions it selected as final (its newest scored one when it
selected none), by the challenge's ranking metric of the track.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from dsr_bench.challenge import auth, rules
from dsr_bench.challenge.db import Phase, Score, Submission, Team, team_transaction, utcnow
from dsr_bench.errors import UserError
#: each track's columns and those where lower is better: the local leaderboard's (dsr_bench.leaderboard.table)
from dsr_bench.leaderboard.table import LOWER_IS_BETTER, TRACKS as COLUMNS


def add_team(session_factory: sessionmaker, name: str) -> str:
    """Add team `name` (normalised, and refused when it reads like a team's name: `rules.check_team_name`); returns
    its token (shown once: only its argon2 hash is stored)."""
    key, token = auth.new_token()
    token_hash = auth.hash_token(token)
    try:
        with session_factory.begin() as session:
            name = rules.check_team_name(session, name)
            session.add(Team(name=name, key=key, token_hash=token_hash, created_at=utcnow()))
    except IntegrityError:
        raise UserError(f"team {name!r} exists; choose another name (or revoke it and add a new team)") from None
    return token


def revoke_team(session_factory: sessionmaker, name: str) -> None:
    """Revoke team `name`'s token: every later request with it is refused; its submissions stay."""
    with session_factory.begin() as session:
        team = session.scalar(select(Team).where(Team.name == name))
        if team is None:
            raise UserError(f"no team {name!r}; `dsr-bench challenge teams DIR` lists them")
        team.revoked_at = team.revoked_at or utcnow()


def authenticate(session_factory: sessionmaker, token: str) -> Team | None:
    """The team of a valid, unrevoked token, else None (argon2 verified in constant time, a dummy hash when the
    key is unknown)."""
    key = auth.token_key(token)
    with session_factory() as session:
        team = session.scalar(select(Team).where(Team.key == key)) if key else None
    ok = auth.verify_token(token, team.token_hash if team else None)
    return team if ok and team is not None and team.revoked_at is None else None


def parse_time(text: str, option: str) -> dt.datetime:
    """An ISO 8601 date or time (UTC unless it says otherwise) as naive UTC."""
    try:
        value = dt.datetime.fromisoformat(text)
    except ValueError:
        raise UserError(f"{option} {text!r} is not an ISO date or time; e.g. 2027-03-01 or 2027-03-01T12:00") from None
    if value.tzinfo is not None:
        value = value.astimezone(dt.timezone.utc).replace(tzinfo=None)
    return value


def add_phase(session_factory: sessionmaker, name: str, starts: dt.datetime, ends: dt.datetime) -> None:
    """Add a phase accepting submissions from `starts` to `ends` (naive UTC); phases may not overlap."""
    name = rules.check_name(name, "phase name")
    if ends <= starts:
        raise UserError(f"phase {name!r} ends ({ends}) before it starts ({starts}); give --end after --start")
    with session_factory.begin() as session:
        for other in session.scalars(select(Phase)):
            if other.name == name:
                raise UserError(f"phase {name!r} exists; choose another name")
            if starts < other.ends_at and other.starts_at < ends:
                raise UserError(f"phase {name!r} overlaps phase {other.name!r} ({other.starts_at} to {other.ends_at})"
                                "; give dates outside it")
        session.add(Phase(name=name, starts_at=starts, ends_at=ends))


def submission_view(session: Session, sub: Submission, reveal: bool) -> dict[str, Any]:
    """What a submission's status shows: its state, messages and current aggregate scores (the private part's
    only when revealed)."""
    team = session.get(Team, sub.team_id)
    scores = {}
    for score in session.scalars(select(Score).where(Score.submission_id == sub.id, Score.current.is_(True))):
        if score.part.endswith("public") or reveal:
            scores[score.part] = {**json.loads(score.metrics), "scored_at": f"{score.scored_at:%Y-%m-%dT%H:%M:%SZ}"}
    return {"id": sub.id, "team": team.name if team else None, "method": sub.method, "phase": sub.phase,
            "state": sub.state, "track": sub.track, "created": f"{sub.created_at:%Y-%m-%dT%H:%M:%SZ}",
            "messages": json.loads(sub.messages), "final": sub.final, "scores": scores}


def _ranked(table: list[dict], key: str | None) -> list[dict]:
    """`table` sorted best first by metric `key` (rows without it last), then by date."""
    sign = 1 if key in LOWER_IS_BETTER else -1
    return sorted(table, key=lambda r: (r["metrics"].get(key) is None, sign * (r["metrics"].get(key) or 0.0),
                                        r.get("date", "")))


def public_rows(session: Session, config: dict, part: str = "public") -> dict[str, list[dict]]:
    """Per track, the teams' scored submissions with their current scores of `part` ("public", or a further hidden
    set's "real-public"), best first by the track's ranking metric. The host's reference rows are not among them."""
    rows: dict[str, list[dict]] = {}
    query = (select(Submission, Team.name, Score).join(Team, Team.id == Submission.team_id)
             .join(Score, Score.submission_id == Submission.id)
             .where(Score.current.is_(True), Score.part == part, Submission.track.is_not(None),
                    Team.reference.is_(False)))
    for sub, team, score in session.execute(query):
        metrics = json.loads(score.metrics)
        rows.setdefault(sub.track or "", []).append({
            "id": sub.id, "team": team, "method": sub.method, "phase": sub.phase, "final": sub.final,
            "date": f"{score.scored_at:%Y-%m-%d}", "toolkit_version": score.toolkit_version,
            "metrics": metrics["metrics"]})
    return {track: _ranked(table, config["rank_by"].get(track)) for track, table in rows.items()}


def server_references(session: Session, config: dict, part: str = "public") -> dict[str, list[dict]]:
    """Per track, the host's reference rows scored by the server on the hidden set (`challenge add-references`):
    each reference model's newest scored submission with its current scores of `part`, best first."""
    newest: dict[tuple[str, str], tuple[Submission, Score]] = {}
    query = (select(Submission, Score).join(Team, Team.id == Submission.team_id)
             .join(Score, Score.submission_id == Submission.id)
             .where(Score.current.is_(True), Score.part == part, Submission.state == "scored",
                    Team.reference.is_(True)).order_by(Submission.created_at))
    for sub, score in session.execute(query):
        newest[(sub.track or "", sub.method)] = (sub, score)
    rows: dict[str, list[dict]] = {}
    for (track, method), (sub, score) in newest.items():
        rows.setdefault(track, []).append({
            "id": sub.id, "method": method, "date": f"{score.scored_at:%Y-%m-%d}",
            "toolkit_version": score.toolkit_version, "metrics": json.loads(score.metrics)["metrics"]})
    return {track: _ranked(table, config["rank_by"].get(track)) for track, table in rows.items()}


def leaderboard(session: Session, config: dict) -> dict[str, Any]:
    """The leaderboard: per track, the scored submissions' public aggregates (best first by the track's ranking
    metric), and once revealed the final ranking on the private part; the same per further hidden set (real
    captures) under "hidden_sets"; and the reference rows the server scored on each set under
    "hidden_references" ({set: {"public": {track: rows}, and once revealed "private"}})."""
    from dsr_bench.challenge.layout import hidden_sets

    reveal = bool(config.get("reveal_private"))
    sets = hidden_sets(config)
    out: dict[str, Any] = {"rank_by": config["rank_by"], "tracks": public_rows(session, config),
                           "private_revealed": reveal,
                           "phases": [{"name": p.name, "start": f"{p.starts_at:%Y-%m-%dT%H:%M:%SZ}",
                                       "end": f"{p.ends_at:%Y-%m-%dT%H:%M:%SZ}"} for p in rules.phases(session)]}
    if reveal:
        out["final"] = final_ranking(session, config)
    out["hidden_sets"] = {}
    for hset in sets[1:]:
        entry: dict[str, Any] = {"source": hset.source, "sequences": len(hset.sequences),
                                 "tracks": public_rows(session, config, hset.part_key("public"))}
        if reveal:
            entry["final"] = final_ranking(session, config, hset.part_key("private"))
        out["hidden_sets"][hset.name] = entry
    out["hidden_references"] = {
        hset.name: {part: server_references(session, config, hset.part_key(part))
                    for part in ("public", "private") if part == "public" or reveal} for hset in sets}
    return out


def final_ranking(session: Session, config: dict, part: str = "private") -> dict[str, list[dict]]:
    """Per track, each team's best score of `part` (the private part; "real-private" for a further hidden set)
    among the submissions it selected as final (its newest scored submission when it selected none), best
    first."""
    query = (select(Submission, Team.name, Score).join(Team, Team.id == Submission.team_id)
             .join(Score, Score.submission_id == Submission.id)
             .where(Score.current.is_(True), Score.part == part, Submission.state == "scored",
                    Team.reference.is_(False)))
    by_team: dict[tuple[str, str], list[tuple[Submission, Score]]] = {}
    for sub, team, score in session.execute(query):
        by_team.setdefault((sub.track or "", team), []).append((sub, score))
    out: dict[str, list[dict]] = {}
    for (track, team), entries in by_team.items():
        chosen = [e for e in entries if e[0].final] or [max(entries, key=lambda e: e[0].created_at)]
        key = config["rank_by"].get(track)
        sign = 1 if key in LOWER_IS_BETTER else -1
        valid = [e for e in chosen if e[1].rank_value is not None]
        if not valid:
            continue
        sub, score = min(valid, key=lambda e: sign * (e[1].rank_value or 0.0))
        out.setdefault(track, []).append({"team": team, "method": sub.method, "id": sub.id,
                                          "metrics": json.loads(score.metrics)["metrics"]})
    for track, table in out.items():
        key = config["rank_by"].get(track)
        sign = 1 if key in LOWER_IS_BETTER else -1
        table.sort(key=lambda r: sign * r["metrics"][key])
    return out


def select_final(session_factory: sessionmaker, team: Team, sid: str, final: bool, config: dict) -> None:
    """Mark (or unmark) a scored submission of `team` as one of its final ones (`rules.check_final`: at most
    `max_final`, until the end), counted and written under the team's lock (`db.team_transaction`)."""
    with team_transaction(session_factory, team.id) as (session, locked):
        if locked is None or locked.revoked_at is not None:
            raise rules.Refused("invalid or revoked token", 401)
        rules.check_final(session, locked, sid, final, config, utcnow()).final = final


def team_history(session: Session, team: Team, reveal: bool) -> list[dict[str, Any]]:
    """Every submission of `team`, newest first, as `submission_view` shows it (the private part's scores only when
    revealed)."""
    subs = session.scalars(select(Submission).where(Submission.team_id == team.id)
                           .order_by(Submission.created_at.desc()))
    return [submission_view(session, s, reveal) for s in subs]


def reference_rows(leaderboard: str | Path, split: str) -> tuple[str | None, dict[str, list[dict[str, Any]]]]:
    """(the split shown, per track "3D" / "2D" its reference rows): the reference rows (static, push, oracle:
    `scoring.plots.is_reference_method`) of the local leaderboard directory `leaderboard` scored on the pinned
    version of `split` or, where it has none, of the first test split (by name) generated with the same settings
    (objects, steps, objects per scene, policy; e.g. cpu-novel-test, the first 100 sequences of
    procedural-novel-test). Rows in `board.load_rows`'s shape (per-sequence values included, for their intervals)
    and the local table's order; (None, {}) when there are none. Invalid entry files are skipped silently
    (`dsr-bench leaderboard build` names them)."""
    from dsr_bench.dataset.splits import SPLITS
    from dsr_bench.leaderboard.board import _tables, load_rows
    from dsr_bench.scoring.plots import is_reference_method

    if not (Path(leaderboard) / "entries").is_dir():
        return None, {}
    rows = [r for r in load_rows(leaderboard, warn=lambda line: None)
            if r["kind"] == "reproduced" and is_reference_method(r["method"]) and r["split"] in SPLITS]

    def settings(name: str) -> tuple:
        spec = SPLITS[name]
        return spec.objects, spec.steps, spec.objects_per_scene, spec.policy

    candidates = [split] if split in SPLITS else []
    candidates += sorted(n for n, spec in SPLITS.items() if candidates and n != split and spec.role == "test"
                         and settings(n) == settings(split))
    for name in candidates:
        mine = [r for r in rows if r["split"] == name]
        if mine:
            tables = {track: table.to_dict("records") for _, _, track, table, _ in _tables(mine)
                      if track in COLUMNS and track != "planning"}
            return name, {track: table for track, table in tables.items() if table}
    return None, {}


def reference_view(row: dict[str, Any], columns: tuple[str, ...] | list[str]) -> dict[str, Any]:
    """A reference row as the JSON API shows it: its method, split version, toolkit, date and mean values."""
    metrics = {c: row[c] for c in columns if isinstance(row.get(c), float) and not math.isnan(row[c])}
    return {"method": row["method"], "split_checksum": row["checksum"], "toolkit_version": row["toolkit"],
            "date": row["date"], "label": row["label"], "metrics": metrics}


def request_rescore(session_factory: sessionmaker) -> int:
    """Mark every scored or refused submission to be scored again (after a toolkit fix); returns how many. The
    workers score them with the installed toolkit, whose version each new score records."""
    from sqlalchemy import update

    with session_factory.begin() as session:
        result = session.execute(update(Submission).where(Submission.state.in_(("scored", "refused")))
                                 .values(rescore=True))
        return int(result.rowcount)
