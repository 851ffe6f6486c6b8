"""Uploads: streamed to disk under a size limit, and archives checked member by member before use.

An upload is written to `uploads/.part-<random>` as it arrives, counting bytes: past the limit, after an idle
gap of `idle_timeout` seconds (a slow client) or on a broken stream the temporary is removed and nothing else is
written. An accepted upload is renamed into `submissions/<id>.tar` only after its archive passed
`check_archive`, and its database row is written after that: a submission is visible whole or not at all
(`clean_partials` removes, at start, what a killed server left: temporaries and archives without a row).

An archive (tar, optionally gzip/bzip2/xz) may hold only regular files with flat names of this challenge
(`seq_0000.h5`, ..., `meta.json`): an absolute path, `..`, a directory, a link, a device or FIFO, a repeated
name, members whose bytes add up past `max_extracted` or past `max_ratio` times the archive's size (a
compression bomb), or a truncated stream refuse it, each with one line. Members are read as a stream (never
seeked, never held in memory whole) and, when extracting, written with O_EXCL | O_NOFOLLOW into a fresh directory.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import os
import secrets
import shutil
import tarfile
import zlib
from collections.abc import AsyncIterator, Collection
from dataclasses import dataclass
from pathlib import Path

from dsr_bench.challenge.layout import FILE_PATTERN

CHUNK = 1 << 20
#: how often (bytes written) an upload checks that the disk still keeps the server's free margin
DISK_CHECK_BYTES = 16 << 20
DISK_FULL = "the server's disk is full; try again later (the host is told)"
log = logging.getLogger("dsr_bench.challenge.storage")
#: below this many extracted bytes the ratio is not judged (small archives of zeros compress far)
RATIO_FLOOR = 16 << 20


class UploadRefused(Exception):
    """An upload that is not stored: `status` (HTTP) and a one-line `message`."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status, self.message = status, message


@dataclass
class Received:
    """A complete upload on disk under a temporary name."""

    path: Path
    size: int
    sha256: str


def new_partial(uploads: Path) -> Path:
    """A fresh temporary name in `uploads` (created empty, 0600)."""
    uploads.mkdir(parents=True, exist_ok=True)
    path = uploads / f".part-{secrets.token_hex(16)}"
    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    return path


def ensure_disk(path: Path, keep_free: int, needed: int = 0, written: int = 0) -> None:
    """UploadRefused (507, one line) unless the disk under `path` has `needed` bytes free beside the `keep_free`
    bytes the server keeps (`serve --keep-free`); the refusal is logged for the host, with the upload's `written`
    bytes so far."""
    free = shutil.disk_usage(path).free
    if free < needed + keep_free:
        log.error("an upload was refused (%d bytes needed, %d written): %d bytes free under %s, the %d kept free "
                  "included (serve --keep-free); free disk space", needed, written, free, path, keep_free)
        raise UploadRefused(507, DISK_FULL)


async def receive(chunks: AsyncIterator[bytes], uploads: Path, limit: int, idle_timeout: float = 60.0,
                  keep_free: int = 0) -> Received:
    """Write the byte chunks of an upload to a temporary in `uploads`, enforcing `limit` bytes while they arrive,
    at most `idle_timeout` seconds between chunks and at least `keep_free` bytes of free disk (checked every
    `DISK_CHECK_BYTES` written); UploadRefused (the temporary removed) otherwise."""
    path = new_partial(uploads)
    h, size, checked = hashlib.sha256(), 0, 0
    try:
        with open(path, "wb") as f:
            iterator = chunks.__aiter__()
            while True:
                try:
                    chunk = await asyncio.wait_for(iterator.__anext__(), idle_timeout)
                except StopAsyncIteration:
                    break
                except asyncio.TimeoutError:
                    raise UploadRefused(408, f"the upload stalled for {idle_timeout:g} s; send it again") from None
                size += len(chunk)
                if size > limit:
                    raise UploadRefused(413, f"the upload is over the limit of {limit} bytes; submit fewer or "
                                        "smaller files")
                h.update(chunk)
                f.write(chunk)
                if keep_free and size - checked >= DISK_CHECK_BYTES:
                    checked = size
                    ensure_disk(uploads, keep_free, written=size)
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    if size == 0:
        path.unlink(missing_ok=True)
        raise UploadRefused(400, "the upload is empty; send the tar archive of your predictions")
    return Received(path, size, h.hexdigest())


def _member_problem(member: tarfile.TarInfo, seen: set[str], allowed: Collection[str]) -> str | None:
    """Why an archive member may not be used (None: a regular file of an allowed flat name, first seen)."""
    raw = member.name
    name = raw[2:] if raw.startswith("./") else raw
    shown = repr(raw[:80])
    if raw.startswith("/") or (len(raw) > 1 and raw[1] == ":"):
        return f"member {shown}: an absolute path; archive the files themselves, with plain names"
    if ".." in name.split("/") or "\\" in name:
        return f"member {shown}: a path that leaves the archive ('..'); archive the files with plain names"
    if member.issym() or member.islnk():
        return f"member {shown}: a link; archive regular files only"
    if member.ischr() or member.isblk() or member.isfifo():
        return f"member {shown}: a device or FIFO; archive regular files only"
    if member.isdir():
        return None if name in (".", "") else f"member {shown}: a directory; archive the files flat, no folders"
    if not member.isreg():
        return f"member {shown}: not a regular file; archive regular files only"
    if "/" in name or not FILE_PATTERN.fullmatch(name):
        return f"member {shown}: not a plain file name; archive the files flat (seq_0000.h5, ..., meta.json)"
    if name not in allowed:
        return f"member {shown}: not a file of this challenge (its sequences' .h5 files and meta.json)"
    if name in seen:
        return f"member {shown}: appears twice; archive each file once"
    return None


def check_archive(path: Path, allowed: Collection[str], max_extracted: int, max_ratio: float,
                  extract_to: Path | None = None) -> list[str]:
    """Problems of the archive at `path` (empty: usable), reading every member as a stream; with `extract_to` (a
    new directory) the members are written there as they are read. The first problem stops the reading."""
    compressed = max(1, path.stat().st_size)
    total = 0
    seen: set[str] = set()
    if extract_to is not None:
        extract_to.mkdir(mode=0o700)
    try:
        with tarfile.open(path, "r|*") as tar:
            for member in tar:
                problem = _member_problem(member, seen, allowed)
                if problem:
                    return [f"archive: {problem}"]
                if member.isdir():
                    continue
                name = member.name[2:] if member.name.startswith("./") else member.name
                seen.add(name)
                if total + member.size > max_extracted:
                    return [f"archive: its files add up to more than {max_extracted} bytes (a compression bomb?); "
                            "submit only the predictions"]
                source = tar.extractfile(member)
                if source is None:
                    return [f"archive: member {name!r} cannot be read; archive regular files only"]
                fd = None
                if extract_to is not None:
                    fd = os.open(extract_to / name, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
                try:
                    while block := source.read(CHUNK):
                        total += len(block)
                        if total > RATIO_FLOOR and total > max_ratio * compressed:
                            return [f"archive: expands more than {max_ratio:g} times (a compression bomb?); send "
                                    "an uncompressed tar of the predictions"]
                        if fd is not None:
                            os.write(fd, block)
                finally:
                    if fd is not None:
                        os.close(fd)
    except (tarfile.TarError, EOFError, zlib.error, OSError, ValueError) as exc:
        kind = "truncated or damaged" if seen else "not a readable tar archive"
        return [f"archive: {kind} ({type(exc).__name__}); pack it again with `dsr-bench submit`"]
    if not seen:
        return ["archive: holds no file; archive the predictions' .h5 files and meta.json"]
    return []


def clean_partials(uploads: Path) -> int:
    """Remove the upload temporaries a stopped server left; returns how many."""
    removed = 0
    if uploads.is_dir():
        for path in uploads.glob(".part-*"):
            path.unlink(missing_ok=True)
            removed += 1
    return removed
