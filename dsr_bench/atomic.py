"""Atomic writes on local and shared file systems: write to a temporary name, then rename.

A file appears under its final name only when complete. Several processes, possibly on several
hosts of a cluster sharing the directory over NFS or Lustre, may write into one directory at the
same time, and a process may be killed (even with SIGKILL) mid-write; a later run then removes the
temporaries that are *provably abandoned*, never a live writer's.

Names. Writing ``DIR/NAME`` creates, next to it, a companion lock file and then the temporary:

    DIR/.NAME.tmp-<host>-<pid>-<token>.lock   created first, locked for the whole write, removed last
    DIR/.NAME.tmp-<host>-<pid>-<token>        the data; renamed to DIR/NAME when complete

(both match ``.NAME.tmp-*``, the pattern older versions and other writers of this toolkit clean).

``<host>`` is this machine's host name (characters other than ``A-Za-z0-9._`` replaced by ``_``),
``<pid>`` the writing process and ``<token>`` random hex, so two writers never share a name, even
with the same pid on two hosts. Host names are assumed unique among the machines sharing a
directory (true on a cluster).

Lock. The writer holds ``fcntl.flock(LOCK_EX)`` on a descriptor of the companion ``.lock`` file that
it keeps open until the temporary is renamed or removed. Not the temporary itself: HDF5 takes its
own ``flock`` on files it opens (which would conflict), and POSIX ``fcntl``/``lockf`` locks are
released when *any* descriptor of the file is closed by the process (e.g. when h5py closes it). A
``flock`` belongs to the open file description, so it survives other descriptors being closed and
conflicts even with another descriptor in the same process. The kernel releases it when the
process dies, however it dies.

On NFS (Linux clients since 2.6.12) ``flock`` is carried out as a whole-file POSIX lock by the
server's lock manager (NLM for v3, the protocol itself for v4), so it excludes writers on other
hosts too; mounted with ``nolock``/``local_lock=all`` it is local to each host. On Lustre it is
cluster-wide with the ``flock`` mount option, host-local with ``localflock``, and fails (ENOSYS)
with ``noflock``. Emulated as a POSIX lock, it also takes on POSIX's per-process semantics there:
clean from a process that is not itself writing (as ``dsr-bench generate`` does, before it starts
writing). Because a lock that is merely *local* elsewhere would look free from here, the
cleaner trusts a free lock at once only for a writer on its own host and adds a grace period for
writers on other hosts; where locking fails the writer still writes (unlocked) and the cleaners
fall back to the rules below.

Cleaning (`clean_temporaries`), for each writer's temporary and/or lock file, removed only if:

1. the writer ran on this host and its lock can be taken now (the kernel released it: the writer
   is gone), or there is no lockable lock file and its pid is not alive;
2. the writer ran on another host, its lock can be taken and the files have not been modified for
   `FOREIGN_GRACE_SECONDS` (a free lock is proof of death where locks are cluster-wide; the grace
   covers file systems where they are not);
3. fallback, when the owner cannot be told (names of older versions such as ``.NAME.tmp-<pid>``,
   or a writer on another host whose lock file is missing or cannot be locked): not modified for
   `STALE_SECONDS` (a day).

Anything else is kept. An abandoned temporary that is kept costs only disk space: resumption never
depends on removing it (complete files are under final names, every writer uses fresh names).

Directories (`atomic_directory`) follow the same scheme: the temporary ``DIR/.NAME.tmp-<owner>`` is a directory
filled by the caller and renamed to ``DIR/NAME``; a directory already there is first renamed aside to another
writer-owned temporary (``.NAME.tmp-<owner'>``, with its own lock) and removed after the new one is in place, so a
run killed in between leaves only temporaries that `clean_temporaries` removes.

Durability. With ``fsync=True`` the temporary's data is flushed to the device before the rename and the directory
after it (a power loss then leaves either the old or the new content under the final name); a killed process
needs no fsync, the kernel completes its writes.
"""

from __future__ import annotations

import errno
import fcntl
import os
import re
import secrets
import shutil
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from dsr_bench.errors import UserError

#: Temporaries of a writer on another host are removed only after this long without modification,
#: even when their lock is free (locks may be host-local on some shared file systems).
FOREIGN_GRACE_SECONDS = 3600.0
#: Temporaries whose writer cannot be identified or checked are removed after this long.
STALE_SECONDS = 24 * 3600.0

_NAME = re.compile(r"^\.(?P<target>.+?)\.tmp-(?P<rest>.+?)(?P<lock>\.lock)?$")
_OWNER = re.compile(r"^(?P<host>.+)-(?P<pid>\d+)-(?P<token>[0-9a-f]{8,})$")


def host_name() -> str:
    """This machine's host name as used in temporary names (no '/' or odd characters)."""
    return re.sub(r"[^A-Za-z0-9._]", "_", socket.gethostname() or "unknown")


def _names(path: Path, token: str) -> tuple[Path, Path]:
    owner = f"{host_name()}-{os.getpid()}-{token}"
    tmp = path.with_name(f".{path.name}.tmp-{owner}")
    return tmp, tmp.with_name(f"{tmp.name}.lock")


def _create_lock(path: Path) -> tuple[Path, Path, int | None]:
    """(temporary, lock file, its open descriptor: locked, or unlocked where the file system has no locks)."""
    while True:
        tmp, lock = _names(path, secrets.token_hex(6))
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):  # a cleaner took the fresh file
                os.close(fd)
                continue
            # no locks on this file system: write unlocked, cleaners fall back to pid and age
            os.write(fd, f"{host_name()} {os.getpid()} unlocked\n".encode())
            return tmp, lock, fd
        try:  # a cleaner may have removed the file between open and lock: then start again
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            os.write(fd, f"{host_name()} {os.getpid()}\n".encode())
            return tmp, lock, fd
        os.close(fd)


def fsync_path(path: Path) -> None:
    """Flush `path` (a file or a directory) to its device."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _release(lock: Path, fd: int | None) -> None:
    try:
        lock.unlink(missing_ok=True)
    finally:
        if fd is not None:
            os.close(fd)


def _rename_into_place(tmp: Path, path: Path) -> None:
    try:
        os.replace(tmp, path)
    except FileNotFoundError:
        raise UserError(f"{tmp} was removed by another process while being written (an older dsr-bench "
                        f"sharing {path.parent}?); rerun the same command to finish") from None


def _remove_tree(path: Path) -> None:
    """Remove a file or a directory tree at `path` (nothing if absent)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


@contextmanager
def atomic_path(path: str | Path, fsync: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to `path` to write; rename it to `path` when the block succeeds,
    remove it when the block raises. The writer's lock is held throughout (see the module doc).
    `fsync`: flush the data before the rename and the directory after it.

    >>> with atomic_path("out/seq_0000.h5") as tmp:
    ...     with h5py.File(tmp, "w") as f: ...
    """
    path = Path(path)
    tmp, lock, fd = _create_lock(path)
    try:
        yield tmp
        if fsync:
            fsync_path(tmp)
        _rename_into_place(tmp, path)
        if fsync:
            fsync_path(path.parent)
    finally:
        try:
            tmp.unlink(missing_ok=True)
        finally:
            _release(lock, fd)


@contextmanager
def atomic_directory(path: str | Path, fsync: bool = False) -> Iterator[Path]:
    """Yield a new, empty temporary directory next to `path` to fill; when the block succeeds it is renamed
    to `path` (replacing a file or directory already there, renamed aside first and then removed), when the
    block raises it is removed. Names, locks and cleaning as for `atomic_path` (see the module doc).
    `fsync`: flush the parent directory after the renames (the files inside are the caller's to flush)."""
    path = Path(path)
    tmp, lock, fd = _create_lock(path)
    try:
        tmp.mkdir()
        yield tmp
        if not (path.exists() or path.is_symlink()):
            _rename_into_place(tmp, path)
        else:
            old, old_lock, old_fd = _create_lock(path)  # the replaced one, a temporary of this writer until removed
            try:
                os.replace(path, old)
                try:
                    _rename_into_place(tmp, path)
                except BaseException:
                    os.replace(old, path)  # put the replaced one back
                    raise
                _remove_tree(old)
            finally:
                _release(old_lock, old_fd)
        if fsync:
            fsync_path(path.parent)
    finally:
        try:
            if tmp.exists() or tmp.is_symlink():
                _remove_tree(tmp)
        finally:
            _release(lock, fd)


def write_text(path: str | Path, text: str, fsync: bool = False) -> Path:
    """Write `text` to `path` atomically (see `atomic_path`)."""
    path = Path(path)
    with atomic_path(path, fsync=fsync) as tmp:
        tmp.write_text(text)
    return path


def write_bytes(path: str | Path, data: bytes, fsync: bool = False) -> Path:
    """Write `data` to `path` atomically (see `atomic_path`)."""
    path = Path(path)
    with atomic_path(path, fsync=fsync) as tmp:
        tmp.write_bytes(data)
    return path


def check_writable(path: str | Path, option: str = "--out", directory: bool = True) -> None:
    """Raise a one-line UserError unless the output `path` can be written, before any work is done.

    `directory`: `path` is a directory the command fills (files must be creatable in it, or, where it does not
    exist yet, in its nearest existing parent); otherwise a file the command writes atomically (a temporary
    beside it, renamed over it: its directory must take new files, and a file already there must not be
    immutable or a directory). A probe file is created and removed; nothing else is written. `option` names
    the path in the message (`--out`, `--root`, ...)."""
    target = Path(path)
    here = target if directory else target.parent if str(target.parent) else Path(".")
    while True:
        try:
            if here.exists():
                break
        except OSError as exc:  # e.g. a parent without search permission
            raise UserError(f"{option} {target}: cannot look into {here.parent} ({exc.strerror}); choose another "
                            f"{option} or fix its permissions") from None
        if here.parent == here:
            break
        here = here.parent
    if not here.is_dir():
        what = option if here == target else f"{option} {target}: its parent"
        raise UserError(f"{what} {here} exists and is not a directory; choose another {option} or move the file away")
    probe = here / f".dsr-bench-write-probe-{host_name()}-{os.getpid()}-{secrets.token_hex(4)}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as exc:
        where = "cannot create files in it" if here == target else f"cannot create files in {here}"
        raise UserError(f"{option} {target}: {where} ({exc.strerror or exc}); choose a writable {option} or give "
                        f"write permission on {here}") from None
    os.close(fd)
    probe.unlink(missing_ok=True)
    if directory or not (target.exists() or target.is_symlink()):
        return
    if target.is_dir():
        raise UserError(f"{option} {target} is a directory; give a file name (for example {target / 'out.json'})")
    try:  # an immutable or append-only file refuses to be opened for writing (and to be renamed over)
        os.close(os.open(target, os.O_WRONLY))
    except OSError as exc:
        raise UserError(f"{option} {target}: cannot be replaced ({exc.strerror or exc}); choose another {option} "
                        "or make the file writable (chattr -i)") from None


# --- cleaning ---------------------------------------------------------------------------------------
def pid_alive(pid: int) -> bool:
    """Whether process `pid` exists on this host (a zombie counts as alive)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _try_lock(lock: Path) -> tuple[str, int | None]:
    """('taken', fd) holding the lock; 'held' by another; 'missing'; or 'unsupported'."""
    fd = None
    for flags in (os.O_RDWR, os.O_RDONLY):  # never O_CREAT: a new inode would prove nothing
        try:
            fd = os.open(lock, flags)
            break
        except FileNotFoundError:
            return "missing", None
        except OSError:  # e.g. another user's file: flock works on a read-only descriptor too
            continue
    if fd is None:
        return "unsupported", None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        return ("held" if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES) else "unsupported"), None
    return "taken", fd


def _age(paths: list[Path]) -> float:
    """Seconds since the most recent modification of any of `paths` (inf if none exists)."""
    times = []
    for p in paths:
        try:
            times.append(p.stat().st_mtime)
        except FileNotFoundError:
            pass
    return time.time() - max(times) if times else float("inf")


def _remove(paths: list[Path]) -> list[Path]:
    """Remove `paths` (the temporary, a file or a directory of `atomic_directory`, first; the lock file last);
    return those removed."""
    removed = []
    for p in paths:
        try:
            _remove_tree(p)
        except FileNotFoundError:
            continue
        except OSError:  # e.g. no permission: keep it, it only costs disk space
            break
        removed.append(p)
    return removed


def clean_temporaries(directory: str | Path, pattern: str = "*") -> list[Path]:
    """Remove the abandoned temporaries (and lock files) of targets matching `pattern` (a glob of
    final names, e.g. 'seq_*.h5') in `directory`; keep every live or undecidable writer's. Returns
    the paths removed. Rules in the module doc."""
    directory = Path(directory)
    writers: dict[tuple[str, str], dict[str, Path]] = {}
    for p in directory.glob(f".{pattern}.tmp-*"):
        m = _NAME.match(p.name)
        if m:
            writers.setdefault((m["target"], m["rest"]), {})["lock" if m["lock"] else "tmp"] = p
    here = host_name()
    removed: list[Path] = []
    for (target, rest), files in sorted(writers.items()):
        owner = _OWNER.match(rest)
        paths = [files[k] for k in ("tmp", "lock") if k in files]
        lock = directory / f".{target}.tmp-{rest}.lock"
        if owner is None:  # not this module's naming (an older version's): age only
            if _age(paths) > STALE_SECONDS:
                removed += _remove(paths)
            continue
        state, fd = _try_lock(lock)
        try:
            if state == "held":
                continue
            if owner["host"] == here:
                abandoned = state == "taken" or not pid_alive(int(owner["pid"]))
            elif state == "taken":
                abandoned = _age(paths) > FOREIGN_GRACE_SECONDS
            else:
                abandoned = _age(paths) > STALE_SECONDS
            if abandoned:
                removed += _remove(paths)
        finally:
            if fd is not None:
                os.close(fd)
    return removed
