"""A submission's status and result file (anyone with its id: 128 random bits), the final choice and the team's
history (Bearer token). The private part's scores are in none of them before the host reveals them.
"""

from __future__ import annotations

import json
import re

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import Response
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from dsr_bench.challenge import rules, service
from dsr_bench.challenge.db import Submission, Team
from dsr_bench.challenge.routes.deps import ApiTeam, Context, CtxDep, DbDep

router = APIRouter()
SUBMISSION_ID = re.compile(r"[0-9a-f]{32}")
#: bytes of a final-choice request's body read at most ({"final": true} is 15)
FINAL_BODY_LIMIT = 4096
#: the result file's format name
RESULT_FORMAT = "dsr-bench-challenge-result"


def load_submission(session: Session, ctx: Context, sid: str) -> dict:
    """Submission `sid`'s view (`service.submission_view`), 404 when there is none."""
    sub = session.get(Submission, sid) if SUBMISSION_ID.fullmatch(sid) else None
    if sub is None:
        raise HTTPException(404, "no such submission")
    return service.submission_view(session, sub, rules.revealed(ctx.config()))


@router.get("/api/submissions/{sid}")
def submission_status(sid: str, session: DbDep, ctx: CtxDep) -> dict:
    """A submission's state, messages and aggregate scores."""
    return load_submission(session, ctx, sid)


@router.get("/api/submissions/{sid}/result")
def submission_result(sid: str, session: DbDep, ctx: CtxDep) -> Response:
    """A submission's result file (JSON, as an attachment): its state and messages and, per part shown, the
    aggregate metrics, breakdowns, coverage, toolkit version and predictions' checksum."""
    view = load_submission(session, ctx, sid)
    body = json.dumps({"format": RESULT_FORMAT, **view}, indent=1, sort_keys=True) + "\n"
    return Response(body, media_type="application/json",
                    headers={"Content-Disposition": f'attachment; filename="submission-{view["id"]}.json"'})


@router.post("/api/submissions/{sid}/final")
async def choose_final(sid: str, request: Request, team: ApiTeam,
                       ctx: CtxDep) -> dict:
    """Mark (`{"final": true}`) or unmark one of the team's final submissions (`rules.check_final`)."""
    raw = bytearray()
    async for chunk in request.stream():  # a few bytes are expected: never hold more than FINAL_BODY_LIMIT
        raw += chunk
        if len(raw) > FINAL_BODY_LIMIT:
            raise HTTPException(413, f'send {{"final": true}} or {{"final": false}} (at most {FINAL_BODY_LIMIT} '
                                'bytes)')
    try:
        body = json.loads(bytes(raw))
    except ValueError:
        raise HTTPException(400, 'send {"final": true} or {"final": false}') from None
    final = body.get("final") if isinstance(body, dict) else None
    if not isinstance(final, bool):
        raise HTTPException(400, 'send {"final": true} or {"final": false}')
    if not SUBMISSION_ID.fullmatch(sid):
        raise HTTPException(404, "no such submission")
    return await run_in_threadpool(set_final, ctx, team, sid, final)


def set_final(ctx: Context, team: Team, sid: str, final: bool) -> dict:
    """Record the team's final choice (`service.select_final`) and return the submission's view."""
    service.select_final(ctx.session_factory, team, sid, final, ctx.config())
    with ctx.session_factory() as session:
        return load_submission(session, ctx, sid)


@router.get("/api/me/submissions")
def history(team: ApiTeam, session: DbDep,
            ctx: CtxDep) -> dict:
    """The team's own submissions, every state, newest first."""
    return {"team": team.name, "submissions": service.team_history(session, team, rules.revealed(ctx.config()))}
