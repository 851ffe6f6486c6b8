"""What every route depends on: the app's `Context` (made once by `server.create_app`) and the FastAPI dependencies
of the database session and of the authenticated team (a Bearer token for the API, a session cookie for the
team's pages).

Failed token checks are slowed and, past the limit, refused per client address (`auth.FailureThrottle`); the
address is the connection's peer, or the proxy's forwarded one only where the host named its proxy
(`dsr-bench serve --forwarded-allow-ips`).
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request
from sqlalchemy.orm import Session, sessionmaker
from starlette.concurrency import run_in_threadpool

from dsr_bench.challenge import service
from dsr_bench.challenge.auth import FailureThrottle, SessionSigner
from dsr_bench.challenge.db import Team
from dsr_bench.challenge.layout import Layout, open_challenge


@dataclass
class Settings:
    """Server settings beyond the challenge's configuration: the failed-auth throttle, the upload idle timeout and
    the longest an upload may take in all (seconds), the free disk kept (bytes), the configuration's overrides (e.g.
    daily_limit, max_upload_bytes), how long (seconds) the leaderboard is served from its last computation, and the
    local leaderboard folder whose reference rows of the challenge's split are shown beside the submissions (None:
    `server.default_leaderboard()`)."""

    auth_limit: int = 10
    auth_window: float = 900.0
    auth_max_delay: float = 2.0
    idle_timeout: float = 60.0
    upload_timeout: float = 3600.0
    keep_free: int = 1 << 30
    overrides: dict | None = None
    board_cache: float = 1.0
    leaderboard: str | Path | None = None


@dataclass
class Context:
    """The app's state: the challenge's layout, the server's settings, the database's session factory, the
    failed-auth throttle, the session signer, and caches (the configuration, the leaderboard)."""

    layout: Layout
    settings: Settings
    session_factory: sessionmaker
    throttle: FailureThrottle
    signer: SessionSigner = field(default_factory=SessionSigner)
    cache: dict[str, Any] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def config(self) -> dict:
        """challenge.json with the settings' overrides, read again only when the host changed it."""
        mtime = self.layout.config.stat().st_mtime_ns
        if mtime != self.cache.get("config_mtime"):
            config = {**open_challenge(self.layout.root)[1], **(self.settings.overrides or {})}
            self.cache.update(config_mtime=mtime, config=config)
        return self.cache["config"]


def context(request: Request) -> Context:
    """The app's context."""
    return request.app.state.context


#: the app's context, as a route's parameter
CtxDep = Annotated[Context, Depends(context)]


def db_session(ctx: CtxDep) -> Iterator[Session]:
    """A database session for one request, closed after it."""
    with ctx.session_factory() as session:
        yield session


def client_address(request: Request) -> str:
    """The client's address: the connection's peer (a proxy's forwarded address only where `serve` trusts it)."""
    return request.client.host if request.client else "?"


async def check_token(ctx: Context, address: str, token: str) -> Team:
    """The team of a valid, unrevoked `token`; HTTPException 429 while `address` is refused for its failures, 401
    (after the throttle's delay) for a bad token."""
    wait = ctx.throttle.blocked(address)
    if wait:
        raise HTTPException(429, "too many failed token checks from this address; try again later",
                            headers={"Retry-After": str(int(wait) + 1)})
    team = await run_in_threadpool(service.authenticate, ctx.session_factory, token) if token else None
    if team is None:
        await asyncio.sleep(ctx.throttle.failed(address))
        raise HTTPException(401, "invalid or revoked token; give the token the host sent your team (--token)",
                            headers={"WWW-Authenticate": "Bearer"})
    return team


async def api_team(request: Request, ctx: CtxDep) -> Team:
    """The team of the request's Bearer token (the API's routes); 401 or 429 otherwise."""
    header = request.headers.get("authorization", "")
    token = header[7:].strip() if header.lower().startswith("bearer ") else ""
    return await check_token(ctx, client_address(request), token)


def _cookie_team(ctx: Context, cookie: str) -> Team | None:
    claim = ctx.signer.read(cookie)
    if claim is None:
        return None
    with ctx.session_factory() as session:
        team = session.get(Team, claim[0])
    return team if team is not None and team.key == claim[1] and team.revoked_at is None else None


async def browser_team(request: Request, ctx: CtxDep) -> Team | None:
    """The team signed in by the request's session cookie (`auth.SessionSigner`), None without a valid one (or
    once the team is revoked)."""
    cookie = request.cookies.get(SessionSigner.COOKIE, "")
    return await run_in_threadpool(_cookie_team, ctx, cookie) if cookie else None


#: a route's parameters: a database session for the request, the team of its Bearer token, the signed-in team
DbDep = Annotated[Session, Depends(db_session)]
ApiTeam = Annotated[Team, Depends(api_team)]
BrowserTeam = Annotated["Team | None", Depends(browser_team)]
