"""The annotation's files in its work directory, state.json and journal.jsonl, bound to their capture and to each
other, and read as files someone else may have written (docs/annotator.md, "State, autosave and resume").

state.json (`write_snapshot`) is the whole `AnnotationState` plus:

    "journal": g                 the generation of the journal that goes with it (1, 2, ... one per snapshot)
    "capture_sha256": D          the capture's digest (`capture_digest`) it was made on
    "folded": S' or null         state_sha256 of the snapshot before it, whose journal's records it holds
    "snapshot": a random token   so that no two snapshots are equal (two fresh states of copies of one capture)

journal.jsonl starts with the header {"format": JOURNAL_FORMAT, "generation": g, "state_sha256": S,
"capture_sha256": D}, S the sha256 of the state.json bytes its records apply on top of; then one record per change
(`AnnotationState.record`), appended and fsync'd (`append_record`: the header is never rewritten, so saving costs
what it cost before the binding).

Reading (`read_saved`): state.json is checked against the capture (name, steps x objects, digest); the journal must
be state.json's own (its S is the digest of this state.json's bytes, its D and g agree), or the previous
snapshot's, left by a crash between writing state.json and starting its journal (its S is state.json's "folded":
ignored, its records are already in state.json). Anything else is refused in one line naming the journal and the
fix (`UserError`): a journal of another state.json or capture (copied, even of the same generation), an empty or
headerless one where state.json expects its journal, one that is a directory or a link, a record that is malformed,
not finite or does not start from the state it is replayed on (`AnnotationState.replay`, the record's number
named). A last record cut short (no newline: a crash mid-write) is left out with a note, as before.

Files written before the binding (state.json without "capture_sha256", a journal header without "state_sha256"):
an unbound journal is replayed only beside an unbound state.json of the same generation, each record checked to
start from the state it applies to; any other pairing is refused. The next snapshot (on that open) binds both.
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
from pathlib import Path
from typing import NamedTuple

from dsr_bench.annotator.state import AnnotationState, StateError
from dsr_bench.atomic import write_text
from dsr_bench.errors import UserError

STATE_FILE = "state.json"
JOURNAL_FILE = "journal.jsonl"
JOURNAL_FORMAT = "dsr-bench-annotation-journal"
#: The capture's files covered by its digest besides the meshes and the step images (truth.json, which the annotator
#: never reads, and the annotation work directory are not).
CAPTURE_FILES = ("capture.json", "calibration.json", "actions.json", "objects.json")


class Saved(NamedTuple):
    """What `read_saved` found: the state (state.json with its journal replayed), its journal generation, the records
    replayed, notes on records left out, whether the journal file is the one of that generation (False: none, or a
    stale one; new records must then go to a fresh journal), the sha256 of the state.json bytes read (the next
    snapshot's "folded") and whether state.json was bound to its capture (False: written before the binding)."""

    state: AnnotationState
    generation: int
    replayed: int
    notes: list[str]
    journal_current: bool
    state_sha256: str = ""
    bound: bool = False


def capture_digest(capture) -> str:
    """sha256 (hex) of everything of a capture (`dsr_bench.dataset.capture.Capture`) the annotator reads: capture.json,
    calibration.json, actions.json, objects.json, each object's mesh file and every step image, in that order, each
    as its name relative to the capture, its length and its bytes. Another capture (of the same name and size too),
    or this one re-imported or edited, has another digest."""
    files = [capture.path / name for name in CAPTURE_FILES] + [obj.mesh_path for obj in capture.objects]
    files += [capture.image_path(step, camera, kind) for step in range(capture.num_observations)
              for camera in capture.cameras for kind in ("color", "depth")]
    digest = hashlib.sha256()
    for path in files:
        data = Path(path).read_bytes()
        try:
            name = str(Path(path).relative_to(capture.path))
        except ValueError:  # a mesh outside the capture: its file name
            name = Path(path).name
        digest.update(f"{name}\0{len(data)}\0".encode())
        digest.update(data)
    return digest.hexdigest()


def check_file(path: Path, what: str) -> bool:
    """Whether `path` exists; UserError when it is there but is not a regular file (a directory, a link, a device):
    the annotator neither reads nor replaces it."""
    if not (path.exists() or path.is_symlink()):
        return False
    if path.is_symlink() or not path.is_file():
        kind = "a link" if path.is_symlink() else "a directory" if path.is_dir() else "not a regular file"
        raise UserError(f"{path} is {kind}, not the annotation's {what} (a file the annotator writes); move it away "
                        "or give another --work directory")
    return True


def _refuse(journal: Path, problem: str) -> UserError:
    return UserError(f"{journal}: {problem}; move it away to resume from {STATE_FILE} alone (its records are then "
                     "lost), or put back the journal that goes with this state.json")


def _header(line: bytes | None) -> dict | None:
    try:
        header = json.loads(line) if line is not None else None
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError):
        return None
    return header if isinstance(header, dict) and header.get("format") == JOURNAL_FORMAT else None


def _journal_lines(path: Path, d: dict, state_sha256: str, generation: int) -> tuple[list[bytes], list[str], bool]:
    """The journal's complete record lines, notes (a last line cut short by a crash) and whether it is state.json's
    current journal (False with no records: none, or the previous snapshot's); UserError for anything else."""
    if not check_file(path, "journal"):
        return [], [], False
    try:
        lines = path.read_bytes().split(b"\n")
    except OSError as exc:
        raise _refuse(path, f"unreadable ({exc.strerror or exc})") from None
    tail = lines.pop()  # b"" when the file ends with a newline; else a record cut short
    header = _header(lines[0] if lines else None)
    if header is None:
        what = "empty" if not lines and not tail else "has no journal header (not an annotation journal)"
        raise _refuse(path, f"{what}, but {STATE_FILE} (generation {generation}) is followed by its journal, which "
                            "holds the changes saved since: they are lost or the file was replaced")
    notes = [f"{path.name}: ignored its last record, cut short ({len(tail)} bytes; a crash mid-write)"] if tail else []
    bound = isinstance(d.get("capture_sha256"), str)
    if "state_sha256" in header:
        if header["state_sha256"] == state_sha256 and bound and header.get("capture_sha256") == d["capture_sha256"] \
                and header.get("generation") == generation:
            return lines[1:], notes, True
        if bound and header["state_sha256"] == d.get("folded"):
            return [], [], False  # the previous snapshot's: its records are in state.json (a crash before the new one)
        raise _refuse(path, f"written on top of another state.json (generation {header.get('generation')!r}; this "
                            f"one is generation {generation}): a journal copied from another capture or work "
                            "directory, or one whose state.json was replaced")
    # a journal written before journals were bound to their state (no state_sha256)
    if bound:
        raise _refuse(path, f"carries no binding to its state.json (written by an older annotator, or by hand) but "
                            f"{STATE_FILE} is bound to its journal: it is not this state's journal")
    if header.get("generation") != generation:
        raise _refuse(path, f"generation {header.get('generation')!r} does not go with {STATE_FILE}'s {generation}, "
                            "and neither file says which capture it was written for (both written before journals "
                            "were bound): its records may be another capture's or already in state.json")
    return lines[1:], notes, True


def read_saved(work_dir: str | Path, capture=None, digest: str | None = None) -> Saved:
    """The annotation state saved in a work directory: state.json with its journal's records replayed (see `Saved`
    and the module docstring). `capture`: the `Capture` it must belong to (name, steps x objects, digest), checked
    when given; `digest`: its `capture_digest` when already computed. Raises StateError (or a JSON / OS error)
    when state.json is unreadable, UserError (one line naming the file and the fix) when it belongs to another
    capture or the journal is not its own or is malformed."""
    work = Path(work_dir)
    state_path = work / STATE_FILE
    check_file(state_path, "state")
    raw = state_path.read_bytes()
    d = json.loads(raw)
    state = AnnotationState.from_dict(d)
    if capture is not None:
        _check_capture(state_path, d, state, capture, digest or capture_digest(capture))
    generation = d.get("journal", 0) if type(d.get("journal", 0)) is int else 0
    state_sha256 = hashlib.sha256(raw).hexdigest()
    bound = isinstance(d.get("capture_sha256"), str)
    journal = work / JOURNAL_FILE
    lines, notes, current = _journal_lines(journal, d, state_sha256, generation)
    for k, line in enumerate(lines):
        try:
            state.replay(json.loads(line))
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError, StateError) as exc:
            text = str(exc).removeprefix("journal: ") if isinstance(exc, StateError) else f"unreadable JSON ({exc})"
            raise _refuse(journal, f"record {k + 1} of {len(lines)} (line {k + 2}): {text}") from None
    return Saved(state, generation, len(lines), notes, current, state_sha256, bound)


def _check_capture(state_path: Path, d: dict, state: AnnotationState, capture, digest: str) -> None:
    """UserError unless the state read from `state_path` (its dict `d`) is an annotation of `capture` (its
    `capture_digest` is `digest`)."""
    if state.capture != capture.name:
        raise UserError(f"{state_path} belongs to capture {state.capture!r}, not {capture.name!r}; give another "
                        f"--work directory for {capture.name!r}")
    if (state.num_steps, state.num_objects) != (capture.num_steps, capture.num_objects):
        raise UserError(f"{state_path} has {state.num_steps} pushes x {state.num_objects} objects but capture "
                        f"{capture.name!r} has {capture.num_steps} x {capture.num_objects}; give another "
                        "--work directory")
    made_on = d.get("capture_sha256")
    if made_on is not None and made_on != digest:
        raise UserError(f"{state_path} was made on another capture's content than {capture.path} (capture digest "
                        f"{str(made_on)[:12]}..., this one {digest[:12]}...: another capture named "
                        f"{capture.name!r}, or this one re-imported or edited since, so its poses do not hold); give "
                        f"another --work directory for {capture.path}")


def write_snapshot(work_dir: Path, state: AnnotationState, generation: int, capture_sha256: str,
                   folded: str | None) -> str:
    """Write state.json (atomic: temporary file, fsync, rename) of `state` under journal generation `generation`,
    bound to the capture digest `capture_sha256`, with `folded` (the previous snapshot's state_sha256, or None); then
    that generation's journal holding only its header (atomic too). Returns the new state.json's state_sha256. A
    crash between the two leaves the previous snapshot's journal, which `read_saved` ignores (its records are in
    this state.json)."""
    work_dir.mkdir(parents=True, exist_ok=True)
    d = state.to_dict()
    d.update({"journal": generation, "capture_sha256": capture_sha256, "folded": folded,
              "snapshot": secrets.token_hex(16)})  # unique: two equal states (fresh ones) still have other journals
    text = json.dumps(d, separators=(",", ":"))
    write_text(work_dir / STATE_FILE, text, fsync=True)
    state_sha256 = hashlib.sha256(text.encode()).hexdigest()
    header = {"format": JOURNAL_FORMAT, "generation": generation, "state_sha256": state_sha256,
              "capture_sha256": capture_sha256}
    write_text(work_dir / JOURNAL_FILE, json.dumps(header) + "\n", fsync=True)
    return state_sha256


def append_record(journal: Path, record: dict) -> None:
    """Append one record to the journal and fsync it (a few hundred bytes, whatever the history's length)."""
    line = json.dumps(record, separators=(",", ":")) + "\n"
    with open(journal, "a", encoding="utf-8") as f:
        f.write(line)
        f.flush()
        os.fsync(f.fileno())


# --- the write lock ---------------------------------------------------------------------------------------------------
#: The lock file in the work directory: held (flock, exclusive) by the one process that may change the annotation; it
#: names its holder (pid, host, command, since when). The kernel releases it when that process ends, however it ends.
LOCK_FILE = "lock"
#: Locks this process holds: the lock file's resolved path -> [file descriptor, sessions sharing it]. Sessions of one
#: process share the lock (the API's caller orders its own calls); another process is refused.
_HELD: dict[str, list[int]] = {}


def _holder(fd: int) -> str:
    """Who holds a lock, from what its holder wrote into the lock file."""
    try:
        d = json.loads(os.pread(fd, 4096, 0).decode("utf-8") or "{}")
    except (OSError, ValueError):
        d = {}
    if not isinstance(d, dict) or "pid" not in d:
        return "another process (it has not written its name yet)"
    return (f"pid {d.get('pid')} on {d.get('host', '?')} (`{str(d.get('command', '?'))[:120]}`, since "
            f"{d.get('since', '?')})")


def acquire_lock(work_dir: Path) -> str:
    """Take the write lock of the annotation in `work_dir` (created if missing) for this process; returns its key for
    `release_lock` (and `name_holder`). Another process holding it: a one-line UserError naming the holder (as it
    wrote itself into the file) and what to do."""
    import fcntl

    work_dir = Path(work_dir)
    try:
        work_dir.mkdir(parents=True, exist_ok=True)
        path = work_dir / LOCK_FILE
        key = str(path.resolve())
        if key in _HELD:
            _HELD[key][1] += 1
            return key
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise UserError(f"{work_dir}: cannot create the annotation's lock file ({exc.strerror}); give a --work "
                        "directory you can write to") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = _holder(fd)
        os.close(fd)
        raise UserError(f"{work_dir}: this annotation is open for changes by {holder}; close that window or let that "
                        "command finish, then try again (--status, --export and --bop read it without changing it)"
                        ) from None
    _HELD[key] = [fd, 1]
    return key


def name_holder(key: str) -> None:
    """Write this process (pid, host, command, time) into a lock it holds, for a refused process to name it. Done
    once the session has opened, so that an open refused for another reason leaves the work directory as it was."""
    import sys
    import time

    from dsr_bench.atomic import host_name

    fd = _HELD[key][0]
    me = {"pid": os.getpid(), "host": host_name(), "command": " ".join(os.path.basename(a) if i == 0 else a
                                                                        for i, a in enumerate(sys.argv)),
          "since": time.strftime("%Y-%m-%d %H:%M:%S")}
    data = json.dumps(me).encode("utf-8")
    if os.pread(fd, 4096, 0) != data:
        os.ftruncate(fd, 0)
        os.pwrite(fd, data, 0)


def release_lock(key: str) -> None:
    """Give back one session's share of a lock taken by `acquire_lock`; the last share unlocks it (the file stays)."""
    import fcntl

    held = _HELD.get(key)
    if held is None:
        return
    held[1] -= 1
    if held[1] <= 0:
        del _HELD[key]
        try:
            fcntl.flock(held[0], fcntl.LOCK_UN)
        finally:
            os.close(held[0])
