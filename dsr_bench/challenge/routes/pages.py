"""The public pages and downloads: the leaderboard (`/`, `/api/leaderboard`: computed at most once per
`Settings.board_cache` seconds however many readers ask), a submission's page, the participants' guide
(`/participate`) and the inputs (`/api/inputs`, `/api/inputs/{file}`: flat names listed in digests.json only).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import FileResponse, HTMLResponse

from dsr_bench.challenge import pages, rules, service, team_pages
from dsr_bench.challenge.db import utcnow
from dsr_bench.challenge.layout import FILE_PATTERN, Layout, hidden_sets
from dsr_bench.challenge.routes.deps import Context, CtxDep, DbDep
from dsr_bench.challenge.routes.submissions import load_submission

router = APIRouter()


def default_leaderboard() -> Path | None:
    """The leaderboard/ folder of the clone this toolkit runs from, when there is one (an installed wheel has none)."""
    root = Path(__file__).resolve().parents[3] / "leaderboard"
    return root if (root / "entries").is_dir() else None


def _references(ctx: Context, split: str) -> tuple[str | None, dict[str, list[dict]]]:
    """The local leaderboard's reference rows for `split` (`service.reference_rows`), read again only when its
    entries change."""
    setting = ctx.settings.leaderboard
    board_root = Path(setting) if setting is not None else default_leaderboard()
    if board_root is None or not split:
        return None, {}
    try:
        files = sorted((p.name, p.stat().st_mtime_ns) for p in (board_root / "entries").glob("*.json"))
    except OSError:
        files = []
    key = (str(board_root), split, tuple(files))
    if key != ctx.cache.get("refs_key"):
        ctx.cache.update(refs_key=key, refs=service.reference_rows(board_root, split))
    return ctx.cache["refs"]


def board(ctx: Context) -> tuple[dict, str]:
    """The leaderboard's JSON and page, computed at most once per `Settings.board_cache` seconds."""
    with ctx.lock:
        if time.monotonic() >= ctx.cache.get("board_until", 0.0):
            cfg = ctx.config()
            with ctx.session_factory() as session:
                data = service.leaderboard(session, cfg)
                data["open"] = rules.submission_window(session, cfg, utcnow())
            shown, rows = _references(ctx, str(cfg.get("split", "")))
            page = pages.render_leaderboard(data, cfg, rows, shown)
            data.pop("open")
            data["reference_split"] = shown
            data["reference_rows"] = {track: [service.reference_view(r, service.COLUMNS[track]) for r in table]
                                      for track, table in rows.items()}
            ctx.cache.update(board_until=time.monotonic() + ctx.settings.board_cache, board=(data, page))
        return ctx.cache["board"]


@router.get("/api/leaderboard")
def leaderboard_json(ctx: CtxDep) -> dict:
    """The leaderboard as JSON."""
    return board(ctx)[0]


@router.get("/", response_class=HTMLResponse)
def leaderboard_page(ctx: CtxDep) -> str:
    """The leaderboard page."""
    return board(ctx)[1]


def part_checksums(ctx: Context, view: dict) -> dict[str, str]:
    """Per part of a submission's scores, the split checksum of the hidden part it was scored on (the first 12 hex
    digits of the pinned ground truth's `ground_truth_sha256`, which the worker checked), as the local leaderboard
    shows a split's; pins.json is read again only when it changes."""
    from dsr_bench.challenge.host import expected_truth_checksum, load_pins

    layout: Layout = ctx.layout
    try:
        mtime = layout.pins.stat().st_mtime_ns
    except OSError:
        return {}
    if mtime != ctx.cache.get("pins_mtime"):
        ctx.cache.update(pins_mtime=mtime, pins=load_pins(layout))
    pins: dict[str, Any] = ctx.cache["pins"]
    parts = {hset.part_key(part): list(hset.part(part)) for hset in hidden_sets(ctx.config())
             for part in ("public", "private")}
    out = {}
    for key, score in view["scores"].items():
        names = parts.get(key)
        if names and all(n in pins for n in names):
            out[key] = expected_truth_checksum(pins, names, score.get("metrics", {}))[:12]
    return out


@router.get("/submissions/{sid}", response_class=HTMLResponse)
def submission_page(sid: str, session: DbDep, ctx: CtxDep) -> str:
    """A submission's page."""
    view = load_submission(session, ctx, sid)
    return pages.render_submission(view, part_checksums(ctx, view))


@router.get("/participate", response_class=HTMLResponse)
def participate(request: Request, session: DbDep, ctx: CtxDep) -> str:
    """The participants' guide, with this server's URL and this challenge's numbers."""
    cfg = ctx.config()
    phases = [{"name": p.name, "start": f"{p.starts_at:%Y-%m-%d %H:%M}", "end": f"{p.ends_at:%Y-%m-%d %H:%M}"}
              for p in rules.phases(session)]
    closed = rules.submission_window(session, cfg, utcnow())[1]
    return team_pages.render_participate(str(request.base_url).rstrip("/"), cfg, phases, closed)


def _input_digests(layout: Layout) -> dict[str, str]:
    try:
        return json.loads((layout.inputs / "digests.json").read_text())
    except (OSError, ValueError):
        return {}


@router.get("/api/inputs")
def inputs_index(ctx: CtxDep) -> dict:
    """The participants' input files and their digests."""
    return {"split": "challenge", "files": _input_digests(ctx.layout)}


@router.get("/api/inputs/{name}")
def input_file(name: str, ctx: CtxDep) -> FileResponse:
    """One input file (flat names listed in digests.json only)."""
    digests = _input_digests(ctx.layout)
    if not FILE_PATTERN.fullmatch(name) or name not in digests:
        raise HTTPException(404, "no such input file; GET /api/inputs lists them")
    return FileResponse(ctx.layout.inputs / name, media_type="application/x-hdf5", filename=name)
