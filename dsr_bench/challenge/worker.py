"""Evaluation workers: processes that claim queued submissions, score them with the toolkit's `evaluate` on the
hidden ground truth, and record aggregate scores.

A claim is one conditional UPDATE (queued, or running with an expired lease, or scored and marked for a re-score
-> running, owned by this worker, leased for `lease` seconds), so two workers never take one job; a thread renews
the lease while the job runs. A worker killed mid-evaluation (SIGKILL) stops renewing: once its lease expires
another worker (or the restarted one) takes the job again. The result is written by one transaction that
requires the lease to still be this worker's, so a job is scored once whatever happens. A job that three workers
died on is marked failed.

A worker started by `dsr-bench serve` ends with its server: a thread polls its parent's pid, and when the server is
gone (killed, even with SIGKILL) the worker gives its job back to the queue, removes its work directory and exits,
so no orphan keeps scoring beside a restarted server with the old code. `dsr-bench challenge worker DIR --db URL`
runs one worker on its own (another machine that reaches the same PostgreSQL database and DIR, shared). A job
that ends, and one taken again after its worker died, leaves no extracted archive in DIR/work
(`recovery.clean_work`). Every outcome is logged (to stderr: the server's log); a failed job with the reason and,
for an exception, its traceback.

Each part (public, private) is scored by `dsr_bench.scoring.evaluate.evaluate` on a directory of hard links to the
submission's files for that part; its ground truth is recomputed while read and compared with the challenge's
pins (`host.expected_truth_checksum`). Only the aggregate metrics and breakdowns are kept: per-step and
per-sequence values are dropped here, never stored. Messages name the submission's files, never a path of the
server: a path is replaced only where it stands as a whole path (`_sanitize`), never inside a word.
"""

from __future__ import annotations

import json
import logging
import os
import re
import secrets
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from sqlalchemy import and_, func, or_, select, update
from sqlalchemy.orm import sessionmaker

from dsr_bench.challenge.db import Score, Submission, utcnow
from dsr_bench.challenge.host import expected_truth_checksum, load_pins
from dsr_bench.challenge.layout import PARTS, SIMULATED, Layout, all_sequences, hidden_sets, open_challenge
from dsr_bench.challenge.rules import track_of

MAX_ATTEMPTS = 3
META_NAME = "meta.json"
#: seconds between two checks that a served worker's server is alive
PARENT_POLL = 0.5
log = logging.getLogger("dsr_bench.challenge.worker")


@dataclass
class Outcome:
    """A scored or refused submission: its state, one-line messages, and per part its aggregate results."""

    state: str
    messages: list[str] = field(default_factory=list)
    parts: dict[str, dict] = field(default_factory=dict)
    track: str | None = None
    #: for the host's log only: why it failed, and the exception (its traceback is logged)
    reason: str = ""
    error: BaseException | None = None


def worker_owner() -> str:
    """A worker's lease owner: `<host>-<pid>-<random>` (`recovery.owner_process` reads host and pid back)."""
    from dsr_bench.atomic import host_name

    return f"{host_name()[:32]}-{os.getpid()}-{secrets.token_hex(4)}"


def _claimable(now):
    """The condition of a submission a worker may take at `now`."""
    return or_(Submission.state == "queued",
               and_(Submission.state == "running", Submission.lease_until < now),
               and_(Submission.state.in_(("scored", "refused")), Submission.rescore.is_(True)))


def claim(session_factory: sessionmaker, owner: str, lease: float) -> str | None:
    """Take the oldest claimable submission for `owner` (None: nothing to do)."""
    import datetime as dt

    now = utcnow()
    with session_factory() as session:
        candidates = session.scalars(select(Submission.id).where(_claimable(now))
                                     .order_by(Submission.created_at).limit(8)).all()
        for sid in candidates:
            result = session.execute(
                update(Submission).where(Submission.id == sid, _claimable(now))
                .values(state="running", lease_owner=owner, lease_until=now + dt.timedelta(seconds=lease),
                        started_at=now, attempts=Submission.attempts + 1))
            session.commit()
            if result.rowcount == 1:
                return sid
    return None


def renew(session_factory: sessionmaker, sid: str, owner: str, lease: float) -> bool:
    """Extend this worker's lease on `sid`; False when it is no longer this worker's."""
    import datetime as dt

    with session_factory() as session:
        result = session.execute(update(Submission).where(Submission.id == sid, Submission.lease_owner == owner,
                                                          Submission.state == "running")
                                 .values(lease_until=utcnow() + dt.timedelta(seconds=lease)))
        session.commit()
        return result.rowcount == 1


def finish(session_factory: sessionmaker, sid: str, owner: str, outcome: Outcome, config: dict) -> bool:
    """Record `outcome` for `sid` in one transaction, only while `owner` holds its lease; True when recorded."""
    from dsr_bench import __version__

    with session_factory() as session, session.begin():
        result = session.execute(
            update(Submission).where(Submission.id == sid, Submission.lease_owner == owner,
                                     Submission.state == "running")
            .values(state=outcome.state, messages=json.dumps(outcome.messages), finished_at=utcnow(),
                    lease_owner=None, lease_until=None, rescore=False, track=outcome.track))
        if result.rowcount != 1:
            raise _Lost()
        hidden = bool(session.scalar(select(Submission.hidden).where(Submission.id == sid)))
        last = session.scalar(select(func.max(Score.run)).where(Score.submission_id == sid)) or 0
        session.execute(update(Score).where(Score.submission_id == sid).values(current=False))
        rank_key = config["rank_by"].get(outcome.track or "", None)
        for part, metrics in outcome.parts.items():
            value = metrics["metrics"].get(rank_key) if rank_key else None
            session.add(Score(submission_id=sid, part=part, run=last + 1, current=not hidden,
                              metrics=json.dumps(metrics),
                              rank_value=value if isinstance(value, float) and value == value else None,
                              toolkit_version=__version__))
    return True


class _Lost(Exception):
    """The lease went to another worker: this worker's result is dropped."""


def _literal(text: str) -> Callable[[re.Match], str]:
    """A replacement for re.sub that inserts `text` as it is (no backslash escapes)."""
    return lambda _match: text


def _sanitize(text: str, hide: dict[str, str]) -> str:
    """`text` on one line with each path of `hide` replaced by what it shows, where it stands as a whole path: not
    after a character of a path (so not inside a word or another path), and, unless it ends with "/", not before
    one but a full stop ending a sentence. With DIR `ch`, "synchronously" stays itself and "ch/hidden" becomes
    "<challenge>/hidden". The longest paths first."""
    for path, shown in sorted(hide.items(), key=lambda item: -len(item[0])):
        if path in ("", ".", "/"):
            continue
        tail = "" if path.endswith("/") else r"(?![\w\-]|\.[\w.])"  # a sentence's full stop may follow
        text = re.sub(r"(?<![\w.\-/])" + re.escape(path) + tail, _literal(shown), text)
    return " ".join(text.split())


def evaluate_submission(layout: Layout, config: dict, pins: dict, sid: str) -> Outcome:
    """Score submission `sid`'s stored archive: extract it (checked) into a fresh work directory, evaluate each
    part of each hidden set on hard links to its files (the simulated set always; a further set, e.g. real
    captures, when the archive holds any of its files, and then all of them), verify the ground truth against the
    pins; returns the outcome (score rows per part key: "public", "private", "real-public", ...)."""
    from dsr_bench.challenge.storage import check_archive
    from dsr_bench.scoring.evaluate import evaluate

    work = layout.work / f"{sid}-{secrets.token_hex(4)}"
    layout.work.mkdir(parents=True, exist_ok=True)
    hide = {str(work.resolve()) + "/all/": "", str(work.resolve()): "<submission>", str(work) + "/all/": "",
            str(work): "<submission>", str(layout.root.resolve()): "<challenge>", str(layout.root): "<challenge>"}
    sets = hidden_sets(config)
    for hset in sets:
        where = layout.hidden_set(hset.name)
        hide = {str(where.resolve()): "<hidden>", str(where): "<hidden>", **hide}
    try:
        work.mkdir(mode=0o700)
        allowed = {f"{n}.h5" for n in all_sequences(config)} | {META_NAME}
        problems = check_archive(layout.archive(sid), allowed, int(config["max_extracted_bytes"]),
                                 float(config["max_ratio"]), extract_to=work / "all")
        if problems:
            return Outcome("refused", problems)
        outcome = Outcome("scored")
        messages: list[str] = []
        expected: list[str] = []
        for hset in sets:
            # the simulated set is always scored; a further set (real captures) when the archive holds any of it
            if hset.name != SIMULATED and not any((work / "all" / f"{n}.h5").exists() for n in hset.sequences):
                continue
            for part in PARTS:
                key = hset.part_key(part)
                expected.append(key)
                part_dir = work / f"part-{key}"
                part_dir.mkdir()
                for name in hset.part(part):
                    if (work / "all" / f"{name}.h5").exists():
                        os.link(work / "all" / f"{name}.h5", part_dir / f"{name}.h5")
                if (work / "all" / META_NAME).exists():
                    os.link(work / "all" / META_NAME, part_dir / META_NAME)
                evaluation = evaluate(part_dir, layout.hidden_set(hset.name), part, workers=1)
                messages += [line for where, problem in evaluation.problems
                             if (line := _sanitize(f"{where}: {problem}" if where else problem, hide)) not in messages]
                if evaluation.results is not None:
                    results = evaluation.results
                    truth = expected_truth_checksum(pins, list(hset.part(part)), results["metrics"])
                    if results["ground_truth_sha256"] != truth:
                        return Outcome("failed", ["the server's hidden ground truth failed its check against the "
                                                  "challenge's pins; the host is told (nothing of yours is wrong)"],
                                       reason=f"hidden set {hset.name}, {part} part: the ground truth read has "
                                       f"checksum {results['ground_truth_sha256']}, pins.json gives {truth}: a "
                                       f"file of {layout.hidden_set(hset.name)} changed since it was pinned")
                    outcome.parts[key] = {"metrics": results["metrics"], "breakdowns": results["breakdowns"],
                                          "coverage": results["coverage"],
                                          "toolkit_version": results["toolkit_version"],
                                          "predictions_checksum": results["predictions_checksum"]}
        if messages or set(outcome.parts) != set(expected):
            return Outcome("refused", messages or ["no score: fix the problems above"])
        outcome.track, mixed = track_of(outcome.parts)  # one track in every part, as evaluate requires of a folder
        if mixed:
            return Outcome("refused", [mixed])
        return outcome
    finally:
        shutil.rmtree(work, ignore_errors=True)


def run_worker(root: str, db_url: str, owner: str | None = None, lease: float = 60.0, poll: float = 0.5,
               stop: threading.Event | None = None, once: bool = False, parent: int | None = None) -> int:
    """The worker loop: claim, evaluate, record, until `stop` is set (or, with `once`, until nothing is queued);
    returns the number of jobs recorded. Runs in its own process (`dsr-bench serve` starts them, giving its pid as
    `parent`: the worker ends with it; `challenge worker` runs one alone). DIR and the database must not belong to
    different challenges (`binding.check`); this host's dead workers' jobs go back to the queue first."""
    from dsr_bench.challenge.binding import open_bound
    from dsr_bench.challenge.recovery import clean_work, release_dead_leases
    from dsr_bench.memory import keep_freed_memory

    keep_freed_memory()
    layout, config = open_challenge(root)
    pins = load_pins(layout)
    engine, session_factory = open_bound(layout, db_url, bind_new=False)
    owner = owner or worker_owner()
    stop = stop or threading.Event()
    current: dict[str, str | None] = {"sid": None}
    if parent is not None:
        threading.Thread(target=_watch_parent, args=(parent, layout, session_factory, owner, current),
                         daemon=True).start()
    for released in release_dead_leases(session_factory):
        log.warning("submission %s: its worker on this host is gone; back in the queue", released)
    done = 0
    while not stop.is_set():
        sid = claim(session_factory, owner, lease)
        if sid is None:
            if once:
                break
            stop.wait(poll)
            continue
        current["sid"] = sid
        clean_work(layout, sid)  # what a worker killed on this job extracted
        with session_factory() as session:
            attempts = session.get(Submission, sid).attempts
        lost = threading.Event()

        def heartbeat(sid: str = sid, lost: threading.Event = lost) -> None:
            while not lost.wait(lease / 3):
                if not renew(session_factory, sid, owner, lease):
                    lost.set()

        beat = threading.Thread(target=heartbeat, daemon=True)
        beat.start()
        try:
            if attempts > MAX_ATTEMPTS:
                outcome = Outcome("failed", [f"its evaluation stopped {MAX_ATTEMPTS} times without finishing; the "
                                             "host is told"], reason=f"{MAX_ATTEMPTS} workers stopped while "
                                  "scoring it (killed, or out of memory?)")
            else:
                _, config = open_challenge(root)  # the host may have changed limits or ranking
                pins = load_pins(layout)  # or added a hidden set (add-hidden-set) while the server runs
                try:
                    outcome = evaluate_submission(layout, config, pins, sid)
                except Exception as exc:  # a server fault: the job is failed, the worker goes on
                    outcome = Outcome("failed", [f"the server failed while scoring ({type(exc).__name__}); the host "
                                                 "is told"], reason=f"{type(exc).__name__}: {exc}", error=exc)
            try:
                finish(session_factory, sid, owner, outcome, config)
                done += 1
                _log_outcome(sid, outcome)
            except _Lost:
                log.info("submission %s: its lease went to another worker or the host cancelled it; this result "
                         "is dropped", sid)
        finally:
            lost.set()
            beat.join()
            clean_work(layout, sid)
            current["sid"] = None
    engine.dispose()
    return done


def _log_outcome(sid: str, outcome: Outcome) -> None:
    """The host's record of a job: one line, and for a failure its reason and traceback."""
    if outcome.state == "failed":
        log.error("submission %s failed: %s", sid, outcome.reason or "; ".join(outcome.messages),
                  exc_info=(type(outcome.error), outcome.error, outcome.error.__traceback__) if outcome.error else None)
    elif outcome.state == "refused":
        log.info("submission %s refused: %s", sid, outcome.messages[0] if outcome.messages else "")
    else:
        log.info("submission %s %s (%s)", sid, outcome.state, ", ".join(sorted(outcome.parts)))


def _watch_parent(parent: int, layout: Layout, session_factory: sessionmaker, owner: str,
                  current: dict[str, str | None]) -> None:
    """End this worker when its server (`parent`) is gone: its job back to the queue, its work directory removed.
    The parent's pid is polled (a killed server's children are given to init or a subreaper: the pid changes)."""
    from dsr_bench.challenge.recovery import clean_work, release

    while os.getppid() == parent:
        time.sleep(PARENT_POLL)
    sid = current["sid"]
    try:
        log.warning("the server (pid %d) is gone: this worker stops%s", parent,
                    f"; submission {sid} goes back to the queue" if sid else "")
        if sid is not None:
            release(session_factory, sid, owner)
            clean_work(layout, sid)
    finally:
        os._exit(0)


def log_to_stderr() -> None:
    """Send the worker's log lines to stderr (the server's log): time, level, pid, message."""
    if not log.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s challenge worker %(process)d: %(message)s"))
        log.addHandler(handler)
        log.setLevel(logging.INFO)
        log.propagate = False


def worker_main(root: str, db_url: str, parent: int | None = None) -> None:
    """A worker process's entry point: runs until SIGTERM (or until its server, `parent`, is gone)."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    log_to_stderr()
    run_worker(root, db_url, stop=stop, parent=parent)


def wait_for(session_factory: sessionmaker, sid: str, states=("scored", "refused", "failed"),
             timeout: float = 60.0) -> str:
    """Poll until `sid` is in one of `states` (or `timeout` s pass); returns its state."""
    end = time.monotonic() + timeout
    while True:
        with session_factory() as session:
            state = session.get(Submission, sid).state
        if state in states or time.monotonic() > end:
            return state
        time.sleep(0.2)
