"""The participant's side: `dsr-bench submit` (pack a predictions directory, upload it to a challenge server,
follow it to its score), `dsr-bench challenge final` (list the team's submissions, choose the final ones) and
`dsr-bench challenge download` (the inputs).

The archive is an uncompressed tar of the directory's `*.h5` files and meta.json, flat (the prediction files are
compressed already), written to a temporary file and streamed from it. The client then polls the submission's
status until it is scored, refused (each problem printed as `dsr-bench evaluate` prints it) or failed. Every
network error (unreachable, a timeout) is one line (`UserError`). Timeouts: 30 s to connect; a read may wait
`READ_TIMEOUT` s (the server checks a whole archive before it answers an upload; a large input file may stall on a
busy server) before the command stops.
"""

from __future__ import annotations

import json
import tarfile
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from dsr_bench.errors import UserError

FINISHED = ("scored", "refused", "failed", "cancelled")
#: seconds a read (an answer, or the next bytes of a download) may take before the command stops with one line
READ_TIMEOUT = 600.0


def _timeout():
    """The participant commands' timeouts: 30 s to connect, `READ_TIMEOUT` to read or write."""
    import httpx

    return httpx.Timeout(READ_TIMEOUT, connect=30.0)


def _network_error(server: str, what: str, exc: Exception) -> UserError:
    """One line for a network error while doing `what`."""
    reason = " ".join(str(exc).split())[:200]
    return UserError(f"--server {server}: {what} failed ({type(exc).__name__}{': ' + reason if reason else ''}); "
                     "check the URL and that the server runs, then try again")


def pack(pred_dir: Path, out: Path) -> list[str]:
    """Write the tar of `pred_dir`'s regular *.h5 files and meta.json to `out`; returns the member names."""
    from dsr_bench.scoring.evaluate import require_predictions_dir

    require_predictions_dir(pred_dir)
    names = sorted(p.name for p in pred_dir.glob("*.h5") if p.is_file() and not p.is_symlink())
    if not names:
        raise UserError(f"{pred_dir} holds no .h5 prediction file; write them with `dsr-bench predict --out "
                        f"{pred_dir}`")
    if (pred_dir / "meta.json").is_file():
        names.append("meta.json")
    with tarfile.open(out, "w", format=tarfile.PAX_FORMAT) as tar:
        for name in names:
            info = tar.gettarinfo(str(pred_dir / name), arcname=name)
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            info.mode = 0o644
            with open(pred_dir / name, "rb") as f:
                tar.addfile(info, f)
    return names


def _chunks(path: Path, size: int = 1 << 20) -> Iterator[bytes]:
    with open(path, "rb") as f:
        yield from iter(lambda: f.read(size), b"")


def _detail(response) -> str:
    try:
        detail = response.json().get("detail")
    except ValueError:
        detail = None
    return " ".join(str(detail or response.text or response.reason_phrase).split())[:500]


def submit(pred_dir: Path, server: str, token: str, method: str, echo: Callable[[str], None],
           poll: float = 2.0, timeout: float = 3600.0, follow: bool = True) -> tuple[str, dict]:
    """Upload `pred_dir` as `method` and (with `follow`) wait for its outcome; returns (state, status JSON).
    `echo` prints one line. UserError for what the user can fix (an unreachable server, a refused upload)."""
    import httpx

    server = server.rstrip("/")
    with tempfile.TemporaryDirectory(prefix="dsr-submit-") as tmp:
        archive = Path(tmp) / "predictions.tar"
        names = pack(pred_dir, archive)
        size = archive.stat().st_size
        echo(f"uploading {len(names)} files ({size / 1e6:.1f} MB) to {server} as {method!r}")
        try:
            with httpx.Client(timeout=_timeout()) as client:
                response = client.post(f"{server}/api/submissions", params={"method": method},
                                       headers={"Authorization": f"Bearer {token}", "Content-Length": str(size),
                                                "Content-Type": "application/x-tar"},
                                       content=_chunks(archive))
        except httpx.HTTPError as exc:
            raise _network_error(server, "the upload", exc) from None
    if response.status_code != 202:
        raise UserError(f"upload refused ({response.status_code}): {_detail(response)}")
    sid = response.json()["id"]
    echo(f"submission {sid}: queued; status page {server}/submissions/{sid}")
    status: dict = {"state": "queued", "id": sid}
    if not follow:
        return "queued", status
    end, last = time.monotonic() + timeout, "queued"
    with httpx.Client(timeout=30.0) as client:
        while True:
            try:
                reply = client.get(f"{server}/api/submissions/{sid}")
            except httpx.HTTPError as exc:
                echo(f"status not reachable ({type(exc).__name__}); trying again")
                reply = None
            if reply is not None and reply.status_code == 200:
                status = reply.json()
                if status["state"] != last:
                    last = status["state"]
                    echo(f"submission {sid}: {last}")
                if last in FINISHED:
                    return last, status
            if time.monotonic() > end:
                raise UserError(f"submission {sid} is still {last} after {timeout:.0f} s; follow it at "
                                f"{server}/submissions/{sid}")
            time.sleep(poll)


def describe(status: dict, pred_dir: Path) -> list[str]:
    """The outcome's lines: the aggregate scores of each part shown, or each problem as `evaluate` prints it."""
    lines = []
    if status["state"] == "scored":
        for part, score in sorted(status.get("scores", {}).items()):
            values = ", ".join(f"{k} {v:.4g}" for k, v in sorted(score["metrics"].items())
                               if isinstance(v, (int, float)))
            lines.append(f"{part} part: {values}")
    else:
        problems = status.get("messages") or []
        if status["state"] == "refused":
            lines.append(f"{len(problems)} problems in {pred_dir}:")
        lines += [f"  {pred_dir / m if m.split(':', 1)[0].endswith(('.h5', '.json')) else m}" for m in problems]
        lines.append("no score: fix the problems above" if status["state"] == "refused" else
                     "no score: the server failed while scoring; the host is told, submit again later")
    return lines


def download_inputs(server: str, out: Path, echo: Callable[[str], None]) -> Path:
    """Download the challenge's inputs into the new directory `out`, each file checked against its digest, and
    write splits/challenge.txt; built in a temporary directory renamed when complete (`atomic_directory`): a
    network error or a timeout is one line and keeps nothing."""
    import httpx

    from dsr_bench.atomic import atomic_directory
    from dsr_bench.challenge.layout import INPUTS_SPLIT

    if out.exists():
        raise UserError(f"{out} exists; give a new directory to download the inputs into")
    server = server.rstrip("/")
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_directory(out) as tmp, httpx.Client(timeout=_timeout()) as client:
        try:
            files = _download_files(client, server, tmp, echo)
        except httpx.HTTPError as exc:  # a timeout, a reset: nothing is kept (the temporary directory is removed)
            raise _network_error(server, "the download", exc) from None
        (tmp / "splits").mkdir()
        names = sorted(n[:-3] for n in files if n.endswith(".h5"))
        (tmp / "splits" / f"{INPUTS_SPLIT}.txt").write_text("".join(f"{n}\n" for n in names))
        (tmp / "digests.json").write_text(json.dumps(files, indent=1, sort_keys=True) + "\n")
    return out


def _download_files(client, server: str, into: Path, echo: Callable[[str], None]) -> dict[str, str]:
    """Download every input file the server lists into `into`, each checked against its digest; returns the list."""
    import hashlib

    from dsr_bench.challenge.layout import FILE_PATTERN

    index = client.get(f"{server}/api/inputs")
    if index.status_code != 200:
        raise UserError(f"--server {server}: no inputs ({index.status_code}: {_detail(index)})")
    files = index.json()["files"]
    for name, digest in sorted(files.items()):
        if not FILE_PATTERN.fullmatch(name):
            raise UserError(f"--server {server} lists an input named {name[:80]!r}; refusing it")
        h = hashlib.sha256()
        with client.stream("GET", f"{server}/api/inputs/{name}") as reply, open(into / name, "wb") as f:
            if reply.status_code != 200:
                raise UserError(f"--server {server}: {name}: {reply.status_code}")
            for chunk in reply.iter_bytes(1 << 20):
                h.update(chunk)
                f.write(chunk)
        if h.hexdigest() != digest:
            raise UserError(f"{name}: its digest differs from the server's list; download again")
        echo(f"{name}: ok")
    return files


def _api(server: str, token: str, method: str, path: str, **kwargs) -> dict:
    """A JSON request to the server's API with the team's token; UserError (one line) for a network error or a
    refusal (the server's one line)."""
    import httpx

    server = server.rstrip("/")
    try:
        with httpx.Client(timeout=_timeout()) as client:
            reply = client.request(method, f"{server}{path}", headers={"Authorization": f"Bearer {token}"}, **kwargs)
    except httpx.HTTPError as exc:
        raise _network_error(server, f"{method} {path}", exc) from None
    if reply.status_code != 200:
        raise UserError(f"refused ({reply.status_code}): {_detail(reply)}")
    return reply.json()


def my_submissions(server: str, token: str) -> dict:
    """The team's history as the server gives it: {"team": name, "submissions": [status, ...]}, newest first."""
    return _api(server, token, "GET", "/api/me/submissions")


def choose_final(server: str, token: str, sid: str, final: bool = True) -> dict:
    """Mark (or, with `final` False, unmark) submission `sid` as one of the team's final ones; its status."""
    return _api(server, token, "POST", f"/api/submissions/{sid}/final", json={"final": final})


def history_lines(history: dict) -> list[str]:
    """The team's submissions, one line each: id, time, state, method, the public part's scores, final."""
    lines = [f"team {history['team']!r}: {len(history['submissions'])} submissions, newest first"]
    for sub in history["submissions"]:
        scores = sub.get("scores", {}).get("public", {}).get("metrics", {})
        values = ", ".join(f"{k} {v:.4g}" for k, v in sorted(scores.items()) if isinstance(v, (int, float)))
        lines.append(f"{sub['id']}  {sub['created']}  {sub['state']:<8}  {sub['method']!r}"
                     + (f"  public: {values}" if values else "") + ("  FINAL" if sub.get("final") else ""))
    return lines
