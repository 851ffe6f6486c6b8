"""`POST /api/submissions?method=NAME` (Bearer token): a team's predictions, as the body (a tar archive) or as the one
file of a multipart form, streamed to disk under the size limit and the time limit, checked, then stored.

Every byte of the body counts against the upload limit, a form's other fields and headers too; a malformed form
is refused with 400 and one line. The rules are checked when the upload starts (a quick refusal, the body unread)
and again when it is stored, under the team's lock (`db.team_transaction`): the method's name, submissions open
(the phase at the moment it is stored, not when it started; the reveal ends them), the daily quota. The upload may
take `Settings.upload_timeout` seconds in all, and `Settings.idle_timeout` between two chunks.
"""

from __future__ import annotations

import asyncio
import os
import secrets
from collections.abc import AsyncIterator
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, Request
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from dsr_bench.atomic import fsync_path
from dsr_bench.challenge import rules
from dsr_bench.challenge.db import Submission, Team, team_transaction, utcnow
from dsr_bench.challenge.layout import all_sequences
from dsr_bench.challenge.routes.deps import ApiTeam, Context, CtxDep
from dsr_bench.challenge.storage import Received, UploadRefused, check_archive, ensure_disk, receive

router = APIRouter()
META_NAME = "meta.json"
#: the longest method name accepted in the query, before normalisation (`rules.check_name` allows 64 after it)
METHOD_QUERY_LIMIT = 256


@router.post("/api/submissions", status_code=202)
async def upload(request: Request, method: Annotated[str, Query(max_length=METHOD_QUERY_LIMIT)], team: ApiTeam,
                 ctx: CtxDep) -> dict:
    """Receive, check and store a submission; 202 with its id, or one line and nothing stored."""
    cfg = ctx.config()
    method = await run_in_threadpool(_admit, ctx, team, method, cfg)
    limit = int(cfg["max_upload_bytes"])
    declared = request.headers.get("content-length", "")
    length = int(declared) if declared.isdigit() else 0  # 0: streamed without a length (counted as it arrives)
    if length > limit:
        raise HTTPException(413, f"the upload ({length} bytes) is over the limit of {limit} bytes; submit "
                            "fewer or smaller files")
    content_type = request.headers.get("content-type", "")
    body = counted(request.stream(), limit)
    chunks = multipart_chunks(body, content_type) if content_type.startswith("multipart/") else body
    timeout = ctx.settings.upload_timeout
    try:
        # the disk must hold this upload (its declared length; a stream without one, nothing known yet) beside the
        # margin kept; `receive` checks the margin again while it writes, as other uploads fill the disk too
        ensure_disk(ctx.layout.root, ctx.settings.keep_free, needed=length)
        received = await asyncio.wait_for(receive(chunks, ctx.layout.uploads, limit, ctx.settings.idle_timeout,
                                                  keep_free=ctx.settings.keep_free), timeout)
    except UploadRefused as exc:
        raise HTTPException(exc.status, exc.message) from None
    except ClientDisconnect:
        raise HTTPException(400, "the upload was cut off; send it again") from None
    except asyncio.TimeoutError:
        raise HTTPException(408, f"the upload took more than {timeout:g} s; send it again from a faster link") from None
    try:
        sid = await run_in_threadpool(_store, ctx, team, method, received, cfg)
    finally:
        received.path.unlink(missing_ok=True)
    return {"id": sid, "state": "queued", "status_url": f"/api/submissions/{sid}", "page": f"/submissions/{sid}"}


def _admit(ctx: Context, team: Team, method: str, cfg: dict) -> str:
    """The method's name (normalised) when an upload may start: its name, submissions open, the quota left (checked
    again when it is stored); Refused otherwise."""
    with ctx.session_factory() as session:
        now = utcnow()
        method = rules.check_method_name(session, method)
        rules.admit(session, cfg, now)
        rules.check_quota(session, team, cfg, now)
    return method


def _store(ctx: Context, team: Team, method: str, received: Received, cfg: dict) -> str:
    """Check the received archive's members, move it into submissions/ and write its row, under the team's lock:
    the phase open now (`rules.admit`) and the quota (`rules.check_quota`) checked in the same transaction; an
    HTTPException or Refused when refused, and then nothing is kept."""
    allowed = {f"{name}.h5" for name in all_sequences(cfg)} | {META_NAME}
    problems = check_archive(received.path, allowed, int(cfg["max_extracted_bytes"]), float(cfg["max_ratio"]))
    if problems:
        raise HTTPException(400, problems[0])
    sid = secrets.token_hex(16)
    layout = ctx.layout
    layout.submissions.mkdir(parents=True, exist_ok=True)
    target = layout.archive(sid)
    os.rename(received.path, target)
    fsync_path(layout.submissions)
    try:
        with team_transaction(ctx.session_factory, team.id) as (session, locked):
            if locked is None or locked.revoked_at is not None:
                raise HTTPException(401, "invalid or revoked token")
            now = utcnow()
            phase = rules.admit(session, cfg, now)
            rules.check_quota(session, locked, cfg, now)
            session.add(Submission(id=sid, team_id=team.id, method=method, phase=phase, state="queued",
                                   created_at=now, attempts=0, archive_sha256=received.sha256,
                                   archive_bytes=received.size, messages="[]", final=False, rescore=False))
    except BaseException:
        target.unlink(missing_ok=True)
        raise
    return sid


async def counted(stream: AsyncIterator[bytes], limit: int) -> AsyncIterator[bytes]:
    """The request body's chunks, UploadRefused (413) once they add up past `limit` bytes: every byte counts, a
    form's headers and other fields too."""
    total = 0
    async for chunk in stream:
        total += len(chunk)
        if total > limit:
            raise UploadRefused(413, f"the upload is over the limit of {limit} bytes; submit fewer or smaller files")
        yield chunk


async def multipart_chunks(stream: AsyncIterator[bytes], content_type: str) -> AsyncIterator[bytes]:
    """The bytes of the one file of a multipart/form-data body, as they arrive (python-multipart's streaming
    parser, which bounds each part's headers); UploadRefused (400, one line) for a malformed body or unless it
    holds exactly one file."""
    from python_multipart import MultipartParser
    from python_multipart.exceptions import FormParserError
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

    try:
        parser = MultipartParser(boundary, {"on_header_field": header_field, "on_header_value": header_value,
                                            "on_header_end": header_end, "on_part_begin": part_begin,
                                            "on_part_data": part_data, "on_part_end": part_end})
        async for chunk in stream:
            parser.write(chunk)
            while out:
                yield out.pop(0)
        parser.finalize()
    except (FormParserError, ValueError) as exc:
        reason = " ".join(str(exc).split())[:120]
        raise UploadRefused(400, f"the multipart form is malformed ({reason}); send the archive as the request "
                            "body, or as a form's one file") from None
    if state["files"] != 1:
        raise UploadRefused(400, "the form holds no complete file; send the archive as its one file")
