"""The challenge's rules, each in one place: names, when submissions and final choices are open (phases, the end,
the reveal), the daily quota, the number of final choices, one track per submission.

Every rule that counts a team's rows (the quota, the final choices) runs inside `db.team_transaction`, which holds
the team's write lock from the count to the commit (SQLite: `BEGIN IMMEDIATE`; PostgreSQL: the team's row locked
`FOR UPDATE`), so requests sent at once are counted one after the other. A rule that refuses raises `Refused`: a
`UserError` (one line naming the input and the fix) with the HTTP status the server answers with.

- Names (team, method, phase): Unicode NFKC (full-width letters, ligatures, NBSP as a plain space), stripped, runs of
  spaces one space, 1-64 characters, every one printable (no control, format, bidi or zero-width character), with a
  letter or digit; a team name or a method name that reads like another one without being it
  (`dsr_bench.leaderboard.names.confusable_with`: case, look-alike letters of other scripts, spacing and
  punctuation aside) is refused.
- Submissions are open while a phase is open (none defined: always) and until the host reveals the private scores
  (`challenge reveal` ends the challenge); the phase is checked when an upload starts and again when it is stored.
- Final choices can be changed until the last phase has ended or the private scores are revealed.
- Daily quota: the submissions of a UTC day that are queued, running or scored use a try; a refused one (its
  predictions' problems) or a failed one (the server's) gives its try back. Uploads of the day in every state but
  failed are bounded too, at `UPLOADS_PER_TRY` times the quota, so refused uploads cannot keep the workers busy.
- One track per submission: every part is scored on the same track (3D or 2D-only), as `evaluate` requires of one
  folder.
"""

from __future__ import annotations

import datetime as dt
import unicodedata
from collections.abc import Iterable, Mapping

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from dsr_bench.challenge.db import Phase, Submission, Team
from dsr_bench.errors import UserError

#: the longest name, in characters after normalisation
NAME_LIMIT = 64
#: uploads a team may send per UTC day in every state but failed (refused ones included), per try of its quota
UPLOADS_PER_TRY = 4
#: the states that use a try of the daily quota (refused and failed give it back)
TRY_STATES = ("queued", "running", "scored")


class Refused(UserError):
    """A rule refuses a request: one line, and the HTTP status the server answers with."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


# --- names ---------------------------------------------------------------------------------------------------
def check_name(value: str, what: str) -> str:
    """`value` normalised (module doc: NFKC, stripped, spaces collapsed) when it is a usable name, else a Refused
    naming `what` ("team name", "--method") and the character or length at fault."""
    from dsr_bench.leaderboard.names import skeleton

    shown = ascii(str(value)[:80])
    text = unicodedata.normalize("NFKC", str(value))
    bad = next((c for c in text if not c.isprintable() and c != " "), None)
    if bad is not None:
        kind = "a control character" if unicodedata.category(bad) == "Cc" else \
            "an invisible or reordering character"
        raise Refused(f"{what} {shown} holds U+{ord(bad):04X} ({unicodedata.name(bad, 'unnamed')}), {kind}; "
                      "choose a name of visible characters")
    text = " ".join(text.split())
    if not 1 <= len(text) <= NAME_LIMIT:
        raise Refused(f"{what} {shown} is not 1-{NAME_LIMIT} characters; choose another")
    if not skeleton(text):
        raise Refused(f"{what} {shown} has no letter or digit; choose a name with one")
    return text


def _clash(name: str, others: Iterable[str]) -> str | None:
    """The first of `others` that is `name` or reads like it (`names.confusable_with`), or None."""
    from dsr_bench.leaderboard.names import confusable_with

    others = list(others)
    return name if name in others else confusable_with(name, others)


def check_team_name(session: Session, value: str) -> str:
    """A new team's name, normalised (`check_name`); Refused when a team of that name exists or one reads like it."""
    name = check_name(value, "team name")
    clash = _clash(name, session.scalars(select(Team.name)))
    if clash == name:
        raise Refused(f"team {name!r} exists; choose another name (or revoke it and add a new team)")
    if clash is not None:
        raise Refused(f"team name {name!r} reads like team {clash!r} (case, look-alike letters, spacing and "
                      "punctuation aside); choose a name that reads differently")
    return name


def check_method_name(session: Session, value: str) -> str:
    """A submission's method name, normalised (`check_name`); Refused when it reads like a method name already on the
    server without being it (use that one exactly, or another)."""
    name = check_name(value, "method name")
    clash = _clash(name, session.scalars(select(Submission.method).distinct()))
    if clash is not None and clash != name:
        raise Refused(f"method name {name!r} reads like {clash!r}, a method already on the leaderboard (case, "
                      "look-alike letters, spacing and punctuation aside); give that name exactly, or another")
    return name


# --- when submissions and final choices are open ---------------------------------------------------------------
def revealed(config: Mapping) -> bool:
    """Whether the host revealed the private part's scores (`challenge reveal`): the challenge has ended."""
    return bool(config.get("reveal_private"))


def phases(session: Session) -> list[Phase]:
    """Every phase, by start."""
    return list(session.scalars(select(Phase).order_by(Phase.starts_at)))


def open_phase(session: Session, now: dt.datetime) -> tuple[str | None, str | None]:
    """(the phase open at `now` or None, why submissions are closed or None). No phase defined: always open."""
    defined = phases(session)
    if not defined:
        return None, None
    for phase in defined:
        if phase.starts_at <= now < phase.ends_at:
            return phase.name, None
    upcoming = [p for p in defined if p.starts_at > now]
    if not upcoming:
        return None, "submissions are closed: the challenge's last phase has ended"
    opens = upcoming[0].starts_at.strftime("%Y-%m-%d %H:%M")
    return None, f"submissions are closed; the next phase, {upcoming[0].name}, opens {opens} UTC"


def submission_window(session: Session, config: Mapping, now: dt.datetime) -> tuple[str | None, str | None]:
    """(the open phase or None, why submissions are closed or None): closed outside every phase and once the
    private scores are revealed."""
    if revealed(config):
        return None, "submissions are closed: the challenge has ended and its private scores are revealed"
    return open_phase(session, now)


def admit(session: Session, config: Mapping, now: dt.datetime) -> str | None:
    """The phase an upload arriving (or stored) at `now` belongs to (None: no phase defined); Refused (403) when
    submissions are closed."""
    phase, closed = submission_window(session, config, now)
    if closed:
        raise Refused(closed, 403)
    return phase


def finals_closed(session: Session, config: Mapping, now: dt.datetime) -> str | None:
    """Why final choices can no longer change at `now` (the private scores revealed, the last phase ended), or
    None."""
    if revealed(config):
        return "final choices are closed: the challenge has ended and its private scores are revealed"
    defined = phases(session)
    if defined and max(p.ends_at for p in defined) <= now:
        return "final choices are closed: the challenge's last phase has ended"
    return None


# --- the daily quota -------------------------------------------------------------------------------------------
def day_start(now: dt.datetime) -> dt.datetime:
    """The start of `now`'s UTC day."""
    return now.replace(hour=0, minute=0, second=0, microsecond=0)


def tries_used(session: Session, team_id: int, now: dt.datetime) -> int:
    """The team's submissions since the start of `now`'s UTC day that use a try (`TRY_STATES`)."""
    return session.scalar(select(func.count()).select_from(Submission).where(
        Submission.team_id == team_id, Submission.created_at >= day_start(now),
        Submission.state.in_(TRY_STATES))) or 0


def check_quota(session: Session, team: Team, config: Mapping, now: dt.datetime) -> None:
    """Refused (429) when `team` has used its daily tries, or sent `UPLOADS_PER_TRY` times as many uploads today
    (refused ones included). Counted inside `db.team_transaction` when a submission is stored."""
    limit = int(config["daily_limit"])
    if tries_used(session, team.id, now) >= limit:
        raise Refused(f"team {team.name!r} has used its {limit} submissions of today (UTC); submit again after "
                      "00:00 UTC", 429)
    uploads = session.scalar(select(func.count()).select_from(Submission).where(
        Submission.team_id == team.id, Submission.created_at >= day_start(now), Submission.state != "failed")) or 0
    if uploads >= UPLOADS_PER_TRY * limit:
        raise Refused(f"team {team.name!r} has sent {uploads} uploads today (UTC), refused ones included, the most "
                      f"allowed ({UPLOADS_PER_TRY} per submission of its quota); check predictions with `dsr-bench "
                      "evaluate` first, and submit again after 00:00 UTC", 429)


# --- final choices ---------------------------------------------------------------------------------------------
def check_final(session: Session, team: Team, sid: str, final: bool, config: Mapping,
                now: dt.datetime) -> Submission:
    """Submission `sid` when `team` may mark (`final`) or unmark it as one of its final ones now: its own, scored,
    within the `max_final` allowed, while final choices are open; else Refused. Counted inside
    `db.team_transaction`."""
    sub = session.get(Submission, sid)
    if sub is None or sub.team_id != team.id:
        raise Refused(f"no submission {sid[:40]!r} of team {team.name!r}; `dsr-bench challenge final --server URL` "
                      "lists yours")
    closed = finals_closed(session, config, now)
    if closed:
        raise Refused(closed, 403)
    if final and sub.state != "scored":
        raise Refused(f"submission {sub.id} is {sub.state}, not scored: only a scored submission can be final")
    if final and not sub.final:
        limit = int(config["max_final"])
        chosen = session.scalar(select(func.count()).select_from(Submission).where(
            Submission.team_id == team.id, Submission.final.is_(True))) or 0
        if chosen >= limit:
            raise Refused(f"team {team.name!r} has selected {chosen} final submissions, the most allowed; unselect "
                          "one first")
    return sub


# --- one track per submission ----------------------------------------------------------------------------------
def track_of(parts: Mapping[str, Mapping]) -> tuple[str | None, str | None]:
    """(the track, a problem or None) of a submission's scored parts ({part key: results with "metrics"}): "3D"
    when a part was scored on the 3D track, "2D" when every part was 2D-only; a mix is a problem, as `evaluate`
    refuses 3D and 2D-only predictions in one folder."""
    kinds = {key: "3D" if "motion_full" in part.get("metrics", {}) else "2D" for key, part in sorted(parts.items())}
    if len(set(kinds.values())) > 1:
        three = next(k for k, v in kinds.items() if v == "3D")
        two = next(k for k, v in kinds.items() if v == "2D")
        return None, (f"mixed submission: the {three} part's files hold mask and motion (3D) but the {two} part's "
                      "hold motion_2d alone (2D-only); write every sequence the same way (all with mask and motion, "
                      "or all with motion_2d alone)")
    return next(iter(kinds.values()), None), None
