"""A team in the browser: `GET/POST /login` (the token in a form, throttled like every token check), the session
cookie (`auth.SessionSigner`: HttpOnly, SameSite=Strict, Secure over HTTPS), `GET /me` (the team's own history),
`POST /me/final` (a final choice) and `POST /logout`, both with the session's CSRF token and refused from another
origin; and `GET /teams/{name}`, a team's public page (scored submissions, public scores).
"""

from __future__ import annotations

from urllib.parse import parse_qs

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from sqlalchemy import func, select
from starlette.concurrency import run_in_threadpool

from dsr_bench.challenge import pages, rules, service, team_pages
from dsr_bench.challenge.auth import SessionSigner
from dsr_bench.challenge.db import Submission, Team, utcnow
from dsr_bench.challenge.routes.deps import BrowserTeam, Context, CtxDep, DbDep, check_token, client_address

router = APIRouter()
#: bytes of a form's body read at most (a token is 74 characters)
FORM_LIMIT = 4096
#: headers of the pages a signed-in team sees: never framed (its buttons cannot be overlaid), never cached
PRIVATE_HEADERS = {"X-Frame-Options": "DENY", "Content-Security-Policy": "frame-ancestors 'none'",
                   "Cache-Control": "no-store"}


async def read_form(request: Request) -> dict[str, str]:
    """The fields of a small urlencoded form (413 past `FORM_LIMIT` bytes); 403 when the request comes from another
    origin (its Origin header names another site)."""
    origin = request.headers.get("origin")
    own = f"{request.url.scheme}://{request.headers.get('host', '')}"
    if origin is not None and origin != own:
        raise HTTPException(403, "a form from another site; use this server's own pages")
    raw = bytearray()
    async for chunk in request.stream():
        raw += chunk
        if len(raw) > FORM_LIMIT:
            raise HTTPException(413, f"the form is over {FORM_LIMIT} bytes")
    fields = parse_qs(bytes(raw).decode("utf-8", "replace"), max_num_fields=8)
    return {key: values[0] for key, values in fields.items()}


def _private(content: str, status: int = 200) -> HTMLResponse:
    return HTMLResponse(content, status_code=status, headers=PRIVATE_HEADERS)


@router.get("/login", response_class=HTMLResponse)
def login_page() -> HTMLResponse:
    """The sign-in form."""
    return _private(team_pages.render_login())


@router.post("/login")
async def login(request: Request, ctx: CtxDep) -> Response:
    """Check the form's token (throttled as every token check) and set the session cookie; 303 to /me."""
    try:
        form = await read_form(request)
        team = await check_token(ctx, client_address(request), form.get("token", "").strip())
    except HTTPException as exc:
        return _private(team_pages.render_login(str(exc.detail)), exc.status_code)
    reply = RedirectResponse("/me", status_code=303, headers=PRIVATE_HEADERS)
    reply.set_cookie(SessionSigner.COOKIE, ctx.signer.issue(team.id, team.key), max_age=SessionSigner.LIFETIME,
                     httponly=True, samesite="strict", secure=request.url.scheme == "https", path="/")
    return reply


async def _signed_in(request: Request, ctx: Context, team: Team | None) -> tuple[Team, str]:
    """(the signed-in team, the session cookie) of a form's request whose CSRF token is right; HTTPException
    otherwise."""
    form = await read_form(request)
    cookie = request.cookies.get(SessionSigner.COOKIE, "")
    if team is None:
        raise HTTPException(401, "not signed in; sign in on /login")
    if not ctx.signer.csrf_ok(cookie, form.get("csrf", "")):
        raise HTTPException(403, "the form's CSRF token is missing or stale; reload the page and try again")
    request.state.form = form
    return team, cookie


@router.post("/logout")
async def logout(request: Request, team: BrowserTeam,
                 ctx: CtxDep) -> Response:
    """End the session: the cookie is removed; 303 to the leaderboard."""
    await _signed_in(request, ctx, team)
    reply = RedirectResponse("/", status_code=303)
    reply.delete_cookie(SessionSigner.COOKIE, path="/", httponly=True, samesite="strict")
    return reply


def _history_page(ctx: Context, team: Team, cookie: str, error: str = "", status: int = 200) -> HTMLResponse:
    cfg = ctx.config()
    now = utcnow()
    with ctx.session_factory() as session:
        views = service.team_history(session, team, rules.revealed(cfg))
        finals = session.scalar(select(func.count()).select_from(Submission).where(
            Submission.team_id == team.id, Submission.final.is_(True))) or 0
        summary = {"tries": rules.tries_used(session, team.id, now), "daily_limit": cfg["daily_limit"],
                   "finals": finals, "max_final": cfg["max_final"], "rank_by": cfg["rank_by"],
                   "revealed": rules.revealed(cfg), "submissions_closed": rules.submission_window(session, cfg, now)[1],
                   "finals_closed": rules.finals_closed(session, cfg, now)}
    html = team_pages.render_history(team.name, views, summary, ctx.signer.csrf_token(cookie), error)
    return _private(html, status)


@router.get("/me", response_class=HTMLResponse)
async def my_page(request: Request, team: BrowserTeam,
                  ctx: CtxDep) -> Response:
    """The signed-in team's history; 303 to /login without a session."""
    if team is None:
        return RedirectResponse("/login", status_code=303)
    return await run_in_threadpool(_history_page, ctx, team, request.cookies.get(SessionSigner.COOKIE, ""))


@router.post("/me/final")
async def my_final(request: Request, team: BrowserTeam,
                   ctx: CtxDep) -> Response:
    """Choose (final=1) or unselect (final=0) one of the signed-in team's final submissions; 303 to /me, or the page
    again with the rule's one line."""
    team, cookie = await _signed_in(request, ctx, team)
    form = request.state.form
    try:
        await run_in_threadpool(service.select_final, ctx.session_factory, team, form.get("sid", "")[:64],
                                form.get("final") == "1", ctx.config())
    except rules.Refused as exc:
        return await run_in_threadpool(_history_page, ctx, team, cookie, str(exc), exc.status)
    return RedirectResponse("/me", status_code=303)


@router.get("/teams/{name:path}", response_class=HTMLResponse)
def team_page(name: str, session: DbDep, ctx: CtxDep) -> str:
    """A team's public page: its scored submissions and their public scores."""
    team = session.scalar(select(Team).where(Team.name == name, Team.reference.is_(False)))
    if team is None:
        raise HTTPException(404, "no such team")
    subs = session.scalars(select(Submission).where(Submission.team_id == team.id, Submission.state == "scored",
                                                    Submission.hidden.is_(False))  # hidden by the host: no page
                           .order_by(Submission.created_at.desc()))
    views = [service.submission_view(session, s, rules.revealed(ctx.config())) for s in subs]
    return pages.render_team(team.name, views)
