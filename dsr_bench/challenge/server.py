"""The challenge's web server: a FastAPI app (`create_app`) that `dsr-bench serve` runs under uvicorn.

The routes are routers by concern (`dsr_bench.challenge.routes`: uploads, submissions, teams, pages, admin), with
FastAPI dependencies for the database session and the authenticated team (`routes.deps`); the rules they apply
(names, phases and the end, the quota, final choices) are `rules`' functions, each in one place. JSON is under
/api, pages elsewhere, every name shown on a page HTML-escaped:
- `GET /api/inputs`, `GET /api/inputs/{file}`: the participants' inputs and their digests (flat names only).
- `POST /api/submissions?method=NAME` (Bearer token): the tar archive of a team's predictions, as the body or a
  multipart form's one file, streamed to disk under the size and time limits; 202 with the submission's id.
- `GET /api/submissions/{id}`, `GET /api/submissions/{id}/result`: a submission's state, messages and aggregate
  scores; its result file (its id is 128 random bits).
- `POST /api/submissions/{id}/final` (Bearer token, {"final": true|false}): choose the final submissions.
- `GET /api/me/submissions` (Bearer token): the team's history, every state.
- `GET /api/leaderboard`; pages `/`, `/submissions/{id}`, `/teams/{name}`, `/participate`; `/login`, `/me` (a
  team's own history and final choices, by session cookie), `/healthz`. The leaderboard shows, beside the
  submissions, the reference rows (static, push, oracle) of the challenge's split from the local leaderboard folder
  (`Settings.leaderboard`), and every table is rendered by `dsr_bench.leaderboard.table.render_table`, the code
  that renders the local leaderboard's.
A response sent before its request's body was read to the end closes the connection (`CloseUnreadBody`): a
refused upload is not read on. At start the app recovers what a stopped server left (`recovery.recover`: upload
temporaries removed, archives without a row moved aside). Nothing here reads the secret seed, the hidden set or
another team's archive; scores are the aggregates the workers stored.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from dsr_bench.challenge.auth import FailureThrottle
from dsr_bench.challenge.binding import open_bound
from dsr_bench.challenge.layout import open_challenge
from dsr_bench.challenge.recovery import recover
from dsr_bench.challenge.routes import admin, pages, submissions, teams, uploads
from dsr_bench.challenge.routes.deps import Context, Settings
from dsr_bench.challenge.routes.pages import default_leaderboard
from dsr_bench.errors import UserError

__all__ = ["Settings", "create_app", "default_leaderboard", "CloseUnreadBody"]


def create_app(root: str | Path, db_url: str | None = None, settings: Settings | None = None) -> FastAPI:
    """The app serving challenge directory `root` with the database `db_url` (default: root/challenge.db),
    migrated first."""
    layout, _ = open_challenge(root)
    settings = settings or Settings()
    engine, session_factory = open_bound(layout, db_url or layout.default_db_url(), bind_new=False)  # DIR's own
    throttle = FailureThrottle(settings.auth_limit, settings.auth_window, settings.auth_max_delay)
    ctx = Context(layout, settings, session_factory, throttle)

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        await run_in_threadpool(recover, layout, session_factory)  # again after `serve`'s: nothing left to do
        yield
        engine.dispose()

    app = FastAPI(title="dsr-bench challenge", lifespan=lifespan, docs_url=None, redoc_url=None, openapi_url=None)
    app.add_middleware(CloseUnreadBody)
    app.state.context = ctx
    app.state.layout, app.state.session_factory, app.state.throttle = layout, session_factory, throttle

    @app.exception_handler(UserError)
    async def user_error(_request: Request, exc: UserError) -> JSONResponse:
        """A rule's refusal (`rules.Refused`: its status) or another user error (400): one line."""
        return JSONResponse({"detail": str(exc)}, status_code=getattr(exc, "status", 400))

    for module in (uploads, submissions, teams, pages, admin):
        app.include_router(module.router)
    return app


class CloseUnreadBody:
    """ASGI middleware: a response that starts before its request's body was read to the end (an upload refused
    over the limit, for its declared size, its token, the quota or a closed phase) says `Connection: close`, and
    uvicorn then closes the connection after it. Without it uvicorn keeps the connection alive and reads, to
    discard, whatever the client still sends: a 10 GiB body against a 1 GiB limit was read whole (9.6 s here)."""

    def __init__(self, app: Any):
        self.app = app

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope["headers"])
        unread = {"body": b"transfer-encoding" in headers or headers.get(b"content-length", b"0").strip() != b"0"}

        async def receive_body() -> dict:
            message = await receive()
            if message["type"] != "http.request" or not message.get("more_body", False):
                unread["body"] = False
            return message

        async def send_response(message: dict) -> None:
            if message["type"] == "http.response.start" and unread["body"]:
                kept = [(k, v) for k, v in message.get("headers", []) if k.lower() != b"connection"]
                message = {**message, "headers": [*kept, (b"connection", b"close")]}
            await send(message)

        await self.app(scope, receive_body, send_response)
