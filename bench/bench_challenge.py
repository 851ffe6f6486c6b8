"""Benchmark: the challenge server under load, on loopback only, bounded in time.

    python bench/bench_challenge.py [--teams 50] [--readers 200] [--seconds 60] [--workers 1] [--db URL]

Makes a small challenge (2 synthetic hidden sequences of 2 pushes, static predictions on its inputs: an upload of
about 0.5 MB), adds `--teams` teams, starts `dsr-bench serve` on a free 127.0.0.1 port with `--workers` evaluation
processes, then for `--seconds` runs `--teams` uploaders (each uploads, waits for its submission to be scored or
refused, uploads again) and `--readers` page readers (each GETs the leaderboard page, the leaderboard JSON and a
submission's status page in turn, without pause), all async in this process (httpx). Prints uploads accepted and
submissions scored per minute, p50/p99 latency of the readers' requests and of the uploads, errors, and the peak
resident memory (VmHWM) of the server process and of its workers. Nothing leaves the loopback interface; every
loop stops at the deadline.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _make_challenge(base: Path, teams: int, db: str | None) -> tuple[Path, Path, list[str]]:
    from dsr_bench.challenge.client import pack
    from dsr_bench.challenge.db import open_database
    from dsr_bench.challenge.host import export_inputs, finish_hidden_set
    from dsr_bench.challenge.layout import HIDDEN_SPLIT, Layout, open_challenge, write_config, write_secret_seed
    from dsr_bench.challenge.service import add_team
    from dsr_bench.models.predictors import load_predictor, predict_split
    from dsr_bench.testing import write_synthetic_dataset

    root = base / "challenge"
    root.mkdir(mode=0o700)
    layout = Layout(root)
    write_secret_seed(layout, 1)
    write_synthetic_dataset(layout.hidden, num_sequences=2, num_steps=2, split=HIDDEN_SPLIT)
    finish_hidden_set(layout, {"split": "synthetic"})
    export_inputs(layout, layout.inputs)
    write_config(layout, {**open_challenge(root)[1], "daily_limit": 100_000})
    predict_split(load_predictor("static"), layout.inputs, ["seq_0000", "seq_0001"], base / "predictions")
    pack(base / "predictions", base / "upload.tar")
    _, sessions = open_database(db or layout.default_db_url())
    tokens = [add_team(sessions, f"team {i:03d}") for i in range(teams)]
    return root, base / "upload.tar", tokens


def _peak_kib(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def _children(pid: int) -> list[int]:
    """The child processes of `pid` (started by any of its threads), but multiprocessing's resource tracker."""
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found += [int(p) for p in (task / "children").read_text().split()]
        except OSError:
            pass
    return [p for p in found if "resource_tracker" not in _cmdline(p)]


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


async def _run(url: str, archive: bytes, tokens: list[str], readers: int, seconds: float) -> dict:
    import httpx

    deadline = time.monotonic() + seconds
    stats: dict[str, list] = {"read": [], "upload": [], "accepted": [], "scored": [], "refused": [], "errors": []}
    known: list[str] = []
    limits = httpx.Limits(max_connections=len(tokens) + readers + 10)
    async with httpx.AsyncClient(base_url=url, timeout=60.0, limits=limits) as client:
        async def uploader(token: str) -> None:
            while time.monotonic() < deadline:
                start = time.perf_counter()
                try:
                    reply = await client.post("/api/submissions", params={"method": "static"}, content=archive,
                                              headers={"Authorization": f"Bearer {token}"})
                except httpx.HTTPError as exc:
                    stats["errors"].append(f"upload {type(exc).__name__}")
                    continue
                stats["upload"].append(time.perf_counter() - start)
                if reply.status_code != 202:
                    stats["errors"].append(f"upload {reply.status_code}")
                    await asyncio.sleep(1.0)
                    continue
                sid = reply.json()["id"]
                stats["accepted"].append(time.monotonic())
                known.append(sid)
                while time.monotonic() < deadline:
                    await asyncio.sleep(1.0)
                    try:
                        state = (await client.get(f"/api/submissions/{sid}")).json()["state"]
                    except (httpx.HTTPError, ValueError):
                        continue
                    if state in ("scored", "refused", "failed"):
                        stats["scored" if state == "scored" else "refused"].append(time.monotonic())
                        break

        async def reader(i: int) -> None:
            pages = ["/", "/api/leaderboard", None]
            k = i
            while time.monotonic() < deadline:
                page = pages[k % 3] or (f"/submissions/{known[k % len(known)]}" if known else "/")
                k += 1
                start = time.perf_counter()
                try:
                    reply = await client.get(page)
                    if reply.status_code != 200:
                        stats["errors"].append(f"read {reply.status_code}")
                except httpx.HTTPError as exc:
                    stats["errors"].append(f"read {type(exc).__name__}")
                    continue
                stats["read"].append(time.perf_counter() - start)

        await asyncio.gather(*[uploader(t) for t in tokens], *[reader(i) for i in range(readers)])
    return stats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--teams", type=int, default=50)
    parser.add_argument("--readers", type=int, default=200)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--db", default=None, help="A database URL instead of the challenge's SQLite file.")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-challenge-") as tmp:
        t0 = time.perf_counter()
        root, archive, tokens = _make_challenge(Path(tmp), args.teams, args.db)
        print(f"challenge made in {time.perf_counter() - t0:.1f} s: {args.teams} teams, upload "
              f"{archive.stat().st_size / 1e6:.2f} MB", flush=True)
        port = _port()
        command = [sys.executable, "-m", "dsr_bench", "serve", str(root), "--port", str(port), "--workers",
                   str(args.workers), *(["--db", args.db] if args.db else [])]
        server = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        url = f"http://127.0.0.1:{port}"
        try:
            import httpx

            for _ in range(300):
                try:
                    if httpx.get(f"{url}/healthz").status_code == 200:
                        break
                except httpx.TransportError:
                    time.sleep(0.1)
            start = time.monotonic()
            stats = asyncio.run(_run(url, archive.read_bytes(), tokens, args.readers, args.seconds))
            elapsed = time.monotonic() - start
            workers = _children(server.pid)
            server_peak, worker_peaks = _peak_kib(server.pid), [_peak_kib(p) for p in workers]
        finally:
            server.send_signal(signal.SIGINT)
            try:
                server.wait(30)
            except subprocess.TimeoutExpired:
                server.kill()
    minutes = elapsed / 60
    reads, uploads = np.array(stats["read"]) * 1e3, np.array(stats["upload"]) * 1e3
    print(f"{args.teams} uploading teams, {args.readers} readers, {elapsed:.0f} s on 127.0.0.1, {args.workers} "
          f"worker(s), {os.cpu_count()} CPUs, database {'--db' if args.db else 'SQLite (WAL)'}")
    print(f"uploads accepted: {len(stats['accepted'])} ({len(stats['accepted']) / minutes:.1f}/min); scored: "
          f"{len(stats['scored'])} ({len(stats['scored']) / minutes:.1f}/min); refused or failed: "
          f"{len(stats['refused'])}")
    if len(reads):
        print(f"page reads: {len(reads)} ({len(reads) / elapsed:.0f}/s), latency p50 {np.percentile(reads, 50):.0f} "
              f"ms, p99 {np.percentile(reads, 99):.0f} ms")
    if len(uploads):
        print(f"uploads: latency p50 {np.percentile(uploads, 50):.0f} ms, p99 {np.percentile(uploads, 99):.0f} ms")
    errors: dict[str, int] = {}
    for e in stats["errors"]:
        errors[e] = errors.get(e, 0) + 1
    print(f"errors: {errors or 'none'}")
    print(f"peak memory (VmHWM): server {server_peak / 1024:.0f} MiB, workers "
          f"{', '.join(f'{p / 1024:.0f}' for p in worker_peaks) or '-'} MiB")


if __name__ == "__main__":
    main()
