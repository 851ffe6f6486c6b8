"""The challenge's web server: a FastAPI app (`create_app`) that `dsr-bench serve` runs under uvicorn.

Routes (JSON under /api, pages elsewhere; every name shown on a page is HTML-escaped):
- `GET /api/inputs`, `GET /api/inputs/{file}`: the participants' inputs and their digests (flat names only).
- `POST /api/submissions?method=NAME` (Bearer token): the tar archive of a team's predictions, as the body or a
  multipart form's one file, streamed to disk under the size limit; 202 with the submission's id when stored.
- `GET /api/submissions/{id}`: a submission's state, messages and aggregate scores (its id is 128 random bits).
- `POST /api/submissions/{id}/final` (Bearer token, {"final": true|false}): choose the final submissions.
- `GET /api/me/submissions` (Bearer token): the team's history, every state.
- `GET /api/leaderboard`; pages `/`, `/submissions/{id}`, `/teams/{name}`. The leaderboard shows, beside the
  submissions, the reference rows (static, push, oracle) of the challenge's split from the local leaderboard folder
  (`Settings.leaderboard`), and every table is rendered by `dsr_bench.leaderboard.table.render_table`, the code
  that renders the local leaderboard's.
A response sent before its request's body was read to the end closes the connection (`CloseUnreadBody`): a
refused upload is not read on. Nothing here reads the secret seed, the hidden set or another team's archive; scores
are the aggregates the workers stored.
"""

from __future__ import annotations

import asyncio
import html
import json
import os
import re
import secrets
import shutil
import threading
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fastapi import FastAPI, HTTPException, Query, Request
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse
from sqlalchemy import select
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from dsr_bench.atomic import fsync_path
from dsr_bench.challenge import service
from dsr_bench.challenge.auth import FailureThrottle
from dsr_bench.challenge.db import Submission, Team, open_database, utcnow
from dsr_bench.challenge.layout import FILE_PATTERN, Layout, all_sequences, check_name, open_challenge, part_title
from dsr_bench.challenge.storage import Received, UploadRefused, check_archive, clean_partials, receive
from dsr_bench.errors import UserError
from dsr_bench.leaderboard.table import COLUMN_TITLES, LINKS, ROLE, SORT_SCRIPT, render_table

SUBMISSION_ID = re.compile(r"[0-9a-f]{32}")
META_NAME = "meta.json"
#: bytes of a final-choice request's body read at most ({"final": true} is 15)
FINAL_BODY_LIMIT = 4096


@dataclass
class Settings:
    """Server settings beyond the challenge's configuration: the failed-auth throttle, the upload idle timeout,
    the free disk kept (bytes), the configuration's overrides (e.g. daily_limit, max_upload_bytes), how long
    (seconds) the leaderboard is served from its last computation, and the local leaderboard folder whose reference
    rows of the challenge's split are shown beside the submissions (None: `default_leaderboard()`)."""

    auth_limit: int = 10
    auth_window: float = 900.0
    auth_max_delay: float = 2.0
    idle_timeout: float = 60.0
    keep_free: int = 1 << 30
    overrides: dict | None = None
    board_cache: float = 1.0
    leaderboard: str | Path | None = None


def default_leaderboard() -> Path | None:
    """The leaderboard/ folder of the clone this toolkit runs from, when there is one (an installed wheel has none)."""
    root = Path(__file__).resolve().parents[2] / "leaderboard"
    return root if (root / "entries").is_dir() else None


def create_app(root: str | Path, db_url: str | None = None, settings: Settings | None = None) -> FastAPI:
    """The app serving challenge directory `root` with the database `db_url` (default: root/challenge.db),
    migrated first."""
    layout, _ = open_challenge(root)
    settings = settings or Settings()
    engine, session_factory = open_database(db_url or layout.default_db_url())
    throttle = FailureThrottle(settings.auth_limit, settings.auth_window, settings.auth_max_delay)

    loaded: dict[str, Any] = {"mtime": None, "config": {}}

    def config() -> dict:  # challenge.json, read again only when the host changed it
        mtime = layout.config.stat().st_mtime_ns
        if mtime != loaded["mtime"]:
            loaded.update(mtime=mtime, config={**open_challenge(layout.root)[1], **(settings.overrides or {})})
        return loaded["config"]

    @asynccontextmanager
    async def lifespan(_app: FastAPI):
        await run_in_threadpool(_recover, layout, session_factory)
        yield
        engine.dispose()

    app = FastAPI(title="dsr-bench challenge", lifespan=lifespan, docs_url=None, redoc_url=None, openapi_url=None)
    app.add_middleware(CloseUnreadBody)
    app.state.layout, app.state.session_factory, app.state.throttle = layout, session_factory, throttle

    async def team_of(request: Request) -> Team:
        address = request.client.host if request.client else "?"
        wait = throttle.blocked(address)
        if wait:
            raise HTTPException(429, "too many failed token checks from this address; try again later",
                                headers={"Retry-After": str(int(wait) + 1)})
        header = request.headers.get("authorization", "")
        token = header[7:].strip() if header.lower().startswith("bearer ") else ""
        team = await run_in_threadpool(service.authenticate, session_factory, token) if token else None
        if team is None:
            await asyncio.sleep(throttle.failed(address))
            raise HTTPException(401, "invalid or revoked token; give the token the host sent your team (--token)",
                                headers={"WWW-Authenticate": "Bearer"})
        return team

    @app.exception_handler(UserError)
    async def user_error(_request: Request, exc: UserError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=400)

    @app.get("/api/inputs")
    def inputs_index() -> dict:
        return {"split": "challenge", "files": _input_digests(layout)}

    @app.get("/api/inputs/{name}")
    def input_file(name: str) -> FileResponse:
        digests = _input_digests(layout)
        if not FILE_PATTERN.fullmatch(name) or name not in digests:
            raise HTTPException(404, "no such input file; GET /api/inputs lists them")
        return FileResponse(layout.inputs / name, media_type="application/x-hdf5", filename=name)

    @app.post("/api/submissions", status_code=202)
    async def upload(request: Request, method: str = Query(..., max_length=64)) -> dict:
        team = await team_of(request)
        try:
            method = check_name(method, "method name")
        except UserError as exc:
            raise HTTPException(400, str(exc)) from None
        cfg = config()
        phase = await run_in_threadpool(_admit, session_factory, team, cfg)
        limit = int(cfg["max_upload_bytes"])
        declared = request.headers.get("content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            raise HTTPException(413, f"the upload ({declared} bytes) is over the limit of {limit} bytes; submit "
                                "fewer or smaller files")
        if shutil.disk_usage(layout.root).free < limit + settings.keep_free:
            raise HTTPException(507, "the server's disk is full; try again later (the host is told)")
        content_type = request.headers.get("content-type", "")
        chunks = (_multipart_chunks(request.stream(), content_type) if content_type.startswith("multipart/")
                  else request.stream())
        try:
            received = await receive(chunks, layout.uploads, limit, settings.idle_timeout)
        except UploadRefused as exc:
            raise HTTPException(exc.status, exc.message) from None
        except ClientDisconnect:
            raise HTTPException(400, "the upload was cut off; send it again") from None
        try:
            sid = await run_in_threadpool(_store, layout, session_factory, team, method, phase, received, cfg)
        finally:
            received.path.unlink(missing_ok=True)
        return {"id": sid, "state": "queued", "status_url": f"/api/submissions/{sid}", "page": f"/submissions/{sid}"}

    def load_submission(sid: str) -> dict:
        if not SUBMISSION_ID.fullmatch(sid):
            raise HTTPException(404, "no such submission")
        with session_factory() as session:
            sub = session.get(Submission, sid)
            if sub is None:
                raise HTTPException(404, "no such submission")
            return service.submission_view(session, sub, bool(config().get("reveal_private")))

    @app.get("/api/submissions/{sid}")
    def submission_status(sid: str) -> dict:
        return load_submission(sid)

    @app.post("/api/submissions/{sid}/final")
    async def choose_final(sid: str, request: Request) -> dict:
        team = await team_of(request)
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
        await run_in_threadpool(service.select_final, session_factory, team, sid, final, int(config()["max_final"]))
        return load_submission(sid)

    @app.get("/api/me/submissions")
    async def history(request: Request) -> dict:
        team = await team_of(request)

        def rows() -> list[dict]:
            reveal = bool(config().get("reveal_private"))
            with session_factory() as session:
                subs = session.scalars(select(Submission).where(Submission.team_id == team.id)
                                       .order_by(Submission.created_at.desc()))
                return [service.submission_view(session, s, reveal) for s in subs]

        return {"team": team.name, "submissions": await run_in_threadpool(rows)}

    cache: dict[str, Any] = {"until": 0.0}
    cache_lock = threading.Lock()
    board_root = Path(settings.leaderboard) if settings.leaderboard is not None else default_leaderboard()
    refs: dict[str, Any] = {"key": None, "rows": (None, {})}

    def references(split: str) -> tuple[str | None, dict[str, list[dict]]]:
        """The local leaderboard's reference rows for `split` (`service.reference_rows`), read again only when its
        entries change."""
        if board_root is None or not split:
            return None, {}
        try:
            files = sorted((p.name, p.stat().st_mtime_ns) for p in (board_root / "entries").glob("*.json"))
        except OSError:
            files = []
        key = (split, tuple(files))
        if key != refs["key"]:
            refs.update(key=key, rows=service.reference_rows(board_root, split))
        return refs["rows"]

    def board() -> tuple[dict, str]:
        """The leaderboard's JSON and page, computed at most once per `settings.board_cache` seconds (however many
        readers ask)."""
        with cache_lock:
            if time.monotonic() >= cache["until"]:
                cfg = config()
                with session_factory() as session:
                    data = service.leaderboard(session, cfg)
                    data["open"] = service.open_phase(session, utcnow())
                shown, rows = references(str(cfg.get("split", "")))
                page = render_leaderboard(data, cfg, rows, shown)
                data.pop("open")
                data["reference_split"] = shown
                data["reference_rows"] = {track: [service.reference_view(r, service.COLUMNS[track]) for r in table]
                                          for track, table in rows.items()}
                cache.update(until=time.monotonic() + settings.board_cache, data=data, page=page)
            return cache["data"], cache["page"]

    @app.get("/api/leaderboard")
    def leaderboard_json() -> dict:
        return board()[0]

    @app.get("/", response_class=HTMLResponse)
    def leaderboard_page() -> str:
        return board()[1]

    @app.get("/submissions/{sid}", response_class=HTMLResponse)
    def submission_page(sid: str) -> str:
        return render_submission(load_submission(sid))

    @app.get("/teams/{name:path}", response_class=HTMLResponse)
    def team_page(name: str) -> str:
        with session_factory() as session:
            team = session.scalar(select(Team).where(Team.name == name, Team.reference.is_(False)))
            if team is None:
                raise HTTPException(404, "no such team")
            subs = session.scalars(select(Submission).where(Submission.team_id == team.id,
                                                            Submission.state == "scored")
                                   .order_by(Submission.created_at.desc()))
            views = [service.submission_view(session, s, bool(config().get("reveal_private"))) for s in subs]
        return render_team(team.name, views)

    @app.get("/healthz")
    def health() -> dict:
        return {"ok": True}

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


def _input_digests(layout: Layout) -> dict[str, str]:
    try:
        return json.loads((layout.inputs / "digests.json").read_text())
    except (OSError, ValueError):
        return {}


def _admit(session_factory, team: Team, cfg: dict) -> str | None:
    """The open phase (None when no phase is defined), or an HTTPException: closed, or the daily quota used."""
    with session_factory() as session:
        now = utcnow()
        phase, closed = service.open_phase(session, now)
        if closed:
            raise HTTPException(403, closed)
        used = service.used_today(session, team.id, now)
    if used >= int(cfg["daily_limit"]):
        raise HTTPException(429, f"team {team.name!r} has used its {cfg['daily_limit']} submissions of today (UTC); "
                            "submit again after 00:00 UTC")
    return phase


def _store(layout: Layout, session_factory, team: Team, method: str, phase: str | None, received: Received,
           cfg: dict) -> str:
    """Check the received archive's members, move it into submissions/ and write its row (the quota checked again
    in the same transaction); an HTTPException when refused, and then nothing is kept."""
    allowed = {f"{name}.h5" for name in all_sequences(cfg)} | {META_NAME}
    problems = check_archive(received.path, allowed, int(cfg["max_extracted_bytes"]), float(cfg["max_ratio"]))
    if problems:
        raise HTTPException(400, problems[0])
    sid = secrets.token_hex(16)
    layout.submissions.mkdir(parents=True, exist_ok=True)
    target = layout.archive(sid)
    os.rename(received.path, target)
    fsync_path(layout.submissions)
    try:
        with session_factory.begin() as session:
            locked = session.scalar(select(Team).where(Team.id == team.id).with_for_update())  # serialises a team
            if locked is None or locked.revoked_at is not None:
                raise HTTPException(401, "invalid or revoked token")
            if service.used_today(session, team.id, utcnow()) >= int(cfg["daily_limit"]):
                raise HTTPException(429, f"team {team.name!r} has used its {cfg['daily_limit']} submissions of today "
                                    "(UTC); submit again after 00:00 UTC")
            session.add(Submission(id=sid, team_id=team.id, method=method, phase=phase, state="queued",
                                   created_at=utcnow(), attempts=0, archive_sha256=received.sha256,
                                   archive_bytes=received.size, messages="[]", final=False, rescore=False))
    except BaseException:
        target.unlink(missing_ok=True)
        raise
    return sid


def _recover(layout: Layout, session_factory) -> None:
    """At start: remove upload temporaries and stored archives that no submission row names (a server killed
    between the two), and work directories of evaluations that stopped."""
    clean_partials(layout.uploads)
    if layout.work.is_dir():
        shutil.rmtree(layout.work, ignore_errors=True)
    if layout.submissions.is_dir():
        with session_factory() as session:
            known = set(session.scalars(select(Submission.id)))
        for path in layout.submissions.glob("*.tar"):
            if path.stem not in known:
                path.unlink(missing_ok=True)


async def _multipart_chunks(stream: AsyncIterator[bytes], content_type: str) -> AsyncIterator[bytes]:
    """The bytes of the one file of a multipart/form-data body, as they arrive (python-multipart's streaming
    parser); UploadRefused unless the body holds exactly one file."""
    from python_multipart import MultipartParser
    from python_multipart.multipart import parse_options_header

    _, options = parse_options_header(content_type)
    boundary = options.get(b"boundary")
    if not boundary:
        raise UploadRefused(400, "a multipart upload without a boundary; send the archive as the request body")
    out: list[bytes] = []
    state: dict[str, Any] = {"field": b"", "value": b"", "file": False, "files": 0}

    def header_field(data: bytes, start: int, end: int) -> None:
        state["field"] += data[start:end]

    def header_value(data: bytes, start: int, end: int) -> None:
        state["value"] += data[start:end]

    def header_end() -> None:
        if state["field"].lower() == b"content-disposition" and b"filename=" in state["value"]:
            state["file"] = True
        state["field"], state["value"] = b"", b""

    def part_begin() -> None:
        state["file"] = False

    def part_data(data: bytes, start: int, end: int) -> None:
        if state["file"]:
            if state["files"]:
                raise UploadRefused(400, "the form holds more than one file; send one archive")
            out.append(bytes(data[start:end]))

    def part_end() -> None:
        state["files"] += bool(state["file"])

    parser = MultipartParser(boundary, {"on_header_field": header_field, "on_header_value": header_value,
                                        "on_header_end": header_end, "on_part_begin": part_begin,
                                        "on_part_data": part_data, "on_part_end": part_end})
    async for chunk in stream:
        parser.write(chunk)
        while out:
            yield out.pop(0)
    parser.finalize()
    if state["files"] != 1:
        raise UploadRefused(400, "the form holds no complete file; send the archive as its one file")


# --- pages ---------------------------------------------------------------------------------------------------
_STYLE = ("body{font-family:sans-serif;margin:2em;max-width:70em}table{border-collapse:collapse;margin:1em 0}"
          "td,th{border:1px solid #bbb;padding:.3em .6em;text-align:right}td{white-space:nowrap}"
          "td:not([data-v]),th:first-child{text-align:left}th{cursor:pointer;background:#f4f4f4}.best{font-weight:bold}"
          ".worse{color:#a00}.note{color:#555}.state{font-weight:bold}")


def _page(title: str, body: str, refresh: bool = False) -> str:
    meta = '<meta http-equiv="refresh" content="2">' if refresh else ""
    return (f'<!doctype html><html lang="en"><head><meta charset="utf-8">{meta}<title>{html.escape(title)}</title>'
            f"<style>{_STYLE}</style></head><body>{body}<script>{SORT_SCRIPT}</script></body></html>")


#: the leaderboard table's columns before the method: the rank and the team (linked to its page)
LEAD = (("#", "rank"), ("team", "team"))


def _columns(track: str, rows: list[dict]) -> list[str]:
    """The track's columns (the local leaderboard's) that some row of the table has a value of."""
    return [c for c in service.COLUMNS.get(track, ()) if any(_has_value(r.get(c)) for r in rows)]


def _has_value(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value == value


def _table(rows: list[dict], track: str, lead: tuple[tuple[str, str], ...] = ()) -> str:
    """An HTML table of rows in `dsr_bench.leaderboard.table`'s shape, rendered by its `render_table`: the very code
    that renders the local leaderboard's tables (every text cell escaped)."""
    return render_table(rows, track, _columns(track, rows), lead=lead).html("board")


def _submission_row(row: dict, rank: int | None = None) -> dict:
    """A scored submission (`service.leaderboard` or `final_ranking` row) as a table row: no model grid or split
    checksum (the hidden set's are not shown); its phase and final choice as the note."""
    note = ", ".join(n for n in (f"phase {row['phase']}" if row.get("phase") else "",
                                 "final" if row.get("final") else "") if n)
    return {**row["metrics"], "rank": "" if rank is None else str(rank), "team": row.get("team", ""),
            "method": row["method"], "grid": "-", "label": note, "toolkit": row.get("toolkit_version") or "",
            "date": row.get("date", ""), "checksum": "", ROLE: "submission",
            LINKS: {"team": f"/teams/{_quote(str(row.get('team', '')))}", "method": f"/submissions/{row['id']}"}}


def _quote(text: str) -> str:
    from urllib.parse import quote

    return quote(text, safe="")


def _server_reference_row(row: dict) -> dict:
    """A reference row the server scored on the hidden set (`service.server_references`) as a table row: marked
    among the server's reference rows only (its own role), linked to its submission's page."""
    return {**row["metrics"], "rank": "", "team": "", "method": row["method"], "grid": "-",
            "label": "reference, scored by this server on the hidden set", "toolkit": row.get("toolkit_version") or "",
            "date": row.get("date", ""), "checksum": "", ROLE: "hidden-reference",
            LINKS: {"method": f"/submissions/{row['id']}"}}


def _hidden_references(data: dict, name: str, part: str) -> dict[str, list[dict]]:
    """Per track, the table rows of the reference rows the server scored on hidden set `name`'s `part`."""
    found = (data.get("hidden_references") or {}).get(name, {}).get(part, {})
    return {track: [_server_reference_row(r) for r in rows] for track, rows in found.items()}


def _reference_note(shown: str, split: str) -> str:
    same = "" if shown == split else f" (generated with the same settings as {html.escape(split)})"
    return (f"<p class=note>Reference rows (unranked, below the submissions): the local leaderboard's static, push "
            f"and oracle rows of {html.escape(shown)}{same}, scored by <code>dsr-bench evaluate</code> on that "
            "split's pinned public sequences, not on this challenge's hidden ones (drawn with the split's objects "
            "and policy from a secret seed): a yardstick, not a paired comparison. Bold and &#9660; mark the "
            "reference rows among themselves, as on the local leaderboard; submissions, ranked by #, are never "
            "marked against them.</p>")


def render_leaderboard(data: dict, config: dict, references: dict[str, list[dict]] | None = None,
                       reference_split: str | None = None) -> str:
    """The leaderboard page: per track the public part's table with the `references` rows per track (of
    `reference_split`: `service.reference_rows`) beside the submissions, the final ranking once revealed, the
    phases."""
    references = references or {}
    parts = [f"<h1>{html.escape(str(config.get('title') or 'DSR benchmark challenge'))}</h1>"]
    phase, closed = data.get("open") or (None, None)
    parts.append(f"<p>{html.escape(closed or (f'phase {phase} is open' if phase else 'submissions are open'))}; "
                 f"{html.escape(str(config['daily_limit']))} submissions per team per day.</p>")
    if references:
        parts.append(_reference_note(str(reference_split), str(config.get("split", ""))))
    if any(rows for by_part in (data.get("hidden_references") or {}).values() for rows in by_part.values()):
        parts.append("<p class=note>Rows noted <i>scored by this server on the hidden set</i> are the host's "
                     "reference models (<code>dsr-bench challenge add-references</code>), predicted on the same "
                     "inputs as the submissions and scored by the same workers; bold and &#9660; mark them among "
                     "themselves.</p>")
    sets = [("simulated", "", data)] + [(name, f", hidden set {name} ({entry.get('source') or 'further'} sequences)",
                                         entry) for name, entry in sorted((data.get("hidden_sets") or {}).items())]
    for name, title, entry in sets:
        local = references if name == "simulated" else {}
        if entry.get("final"):
            private = _hidden_references(data, name, "private")
            for track, rows in sorted(entry["final"].items()):
                parts.append(f"<h2>Final ranking, {html.escape(track)} track{html.escape(title)} (private part)</h2>")
                parts.append(_table([_submission_row(r, i) for i, r in enumerate(rows, 1)] + private.get(track, [])
                                    + local.get(track, []), track, LEAD))
        public = _hidden_references(data, name, "public")
        for track in sorted(set(entry["tracks"]) | set(local) | set(public)):
            rows = entry["tracks"].get(track, [])
            parts.append(f"<h2>{html.escape(track)} track{html.escape(title)} (public part), ranked by "
                         f"{html.escape(COLUMN_TITLES.get(config['rank_by'].get(track, ''), ''))}</h2>")
            parts.append(_table([_submission_row(r, i) for i, r in enumerate(rows, 1)] + public.get(track, [])
                                + local.get(track, []), track, LEAD))
    if not data["tracks"]:
        parts.append("<p>No scored submission yet.</p>")
    if data.get("phases"):
        items = "".join(f"<li>{html.escape(p['name'])}: {html.escape(p['start'])} to {html.escape(p['end'])}</li>"
                        for p in data["phases"])
        parts.append(f"<h2>Phases</h2><ul>{items}</ul>")
    return _page("Leaderboard", "".join(parts))


def render_submission(view: dict) -> str:
    """A submission's status page; it reloads itself every 2 s until the submission is scored, refused or failed."""
    waiting = view["state"] in ("queued", "running")
    parts = [f"<h1>Submission {html.escape(view['id'])}</h1>",
             f"<p>team {html.escape(str(view['team']))}, method {html.escape(view['method'])}, "
             f"submitted {html.escape(view['created'])}</p>",
             f'<p>state: <span class="state" id="state">{html.escape(view["state"])}</span></p>']
    if view["messages"]:
        parts.append("<ul>" + "".join(f"<li>{html.escape(m)}</li>" for m in view["messages"]) + "</ul>")
    for part, score in sorted(view["scores"].items(), key=lambda item: ("-" in item[0], item[0])):
        parts.append(f"<h2>{html.escape(part_title(part))}</h2>")
        row = {**score.get("metrics", {}), "method": view["method"], "grid": "-", "label": part_title(part),
               "date": str(score.get("scored_at", ""))[:10], ROLE: "submission"}
        parts.append(_table([row], view.get("track") or "3D"))
    return _page(f"Submission {view['id']}", "".join(parts), refresh=waiting)


def render_team(name: str, views: list[dict]) -> str:
    """A team's public page: its scored submissions and their public aggregate scores."""
    rows = [{**v["scores"].get("public", {}).get("metrics", {}), "method": v["method"], "grid": "-",
             "label": "final" if v["final"] else "", "date": v["created"][:10], ROLE: "submission",
             LINKS: {"method": f"/submissions/{v['id']}"}} for v in views]
    body = [f"<h1>Team {html.escape(name)}</h1>",
            _table(rows, views[0].get("track") or "3D") if rows else "<p>No scored submission yet.</p>",
            '<p><a href="/">leaderboard</a></p>']
    return _page(f"Team {name}", "".join(body))
