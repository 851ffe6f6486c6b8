"""The host's routes: the health check (`GET /healthz`, what `dsr-bench serve`'s supervisors and the tests wait
for). The host's commands (`dsr-bench challenge ...`) work on the directory and the database, not through HTTP."""

from __future__ import annotations

from fastapi import APIRouter

router = APIRouter()


@router.get("/healthz")
def health() -> dict:
    """The server answers."""
    return {"ok": True}
