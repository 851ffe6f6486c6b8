"""Issue 32 part 2, the window's non-visual items: an annotation is locked for writing (a second process that would
change it is refused in one line naming the holder; --status, --export and --bop read it without the lock and write
nothing, not even the fold of the journal), and undo / redo say what they reverted or re-applied.

Fixture: the simulated capture of tests/conftest.py (3 objects, 3 pushes, 240 x 320), placed from its true poses.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dsr_bench.errors import UserError
from dsr_bench.geometry import pose_to_matrix
from helpers import place_from_truth

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str) -> subprocess.CompletedProcess:
    """`dsr-bench ARGS` in another process (the repository's package, as the CLI runs it)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run([sys.executable, "-m", "dsr_bench", *args], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=300)


def _files(work: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(work.iterdir()) if p.name != "lock"}


def test_a_second_process_that_would_change_the_annotation_is_refused_naming_the_holder(capture_dir, truth,
                                                                                     tmp_path):
    from dsr_bench.annotator.session import Session

    work = tmp_path / "work"
    session = Session.open(capture_dir, work)
    place_from_truth(session, truth)  # journal records not yet folded into state.json
    saved = _files(work)
    assert len((work / "journal.jsonl").read_text().splitlines()) > 1

    for args in (["--auto"], ["--place", str(tmp_path / "none.json")], []):  # --auto, --place, the window
        done = _run("annotate", str(capture_dir), "--work", str(work), *args)
        err = done.stderr.strip()
        assert done.returncode == 2 and len(err.splitlines()) == 1, (args, done.stderr)
        assert f"open for changes by pid {os.getpid()}" in err and "--status" in err, err
    assert _files(work) == saved

    # reading needs no lock and writes nothing: the journal stays unfolded, byte for byte
    done = _run("annotate", str(capture_dir), "--work", str(work), "--status")
    assert done.returncode == 0, done.stderr
    assert "1/4 steps done" in done.stdout and "actions: pick 3, snap 3" in done.stdout  # the records, replayed
    assert _files(work) == saved

    # the lock file names the holder; closing gives the lock back, and then another process may change it
    holder = (work / "lock").read_text()
    assert f'"pid": {os.getpid()}' in holder
    session.close()
    with pytest.raises(UserError, match="opened read-only .* or closed"):
        session.nudge(0, (0.001, 0.0, 0.0))
    code = (f"from annotator.session import Session; s = Session.open({str(capture_dir)!r}, {str(work)!r}); "
            "s.nudge(0, (0.001, 0.0, 0.0)); print(s.describe_undo())")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "nudge of object 1 at step 0 (1.0 mm, 0.0 deg), status snapped <-> initialised"


def test_sessions_of_one_process_share_the_lock_and_a_crash_releases_it(capture_dir, tmp_path):
    """The API's caller orders its own calls: a second Session of the same process opens; the lock lives as long as
    one of them holds it. A killed holder leaves no stale lock (the kernel drops it with the process)."""
    from dsr_bench.annotator.session import Session

    work = tmp_path / "work"
    a = Session.open(capture_dir, work)
    b = Session.open(capture_dir, work)
    a.close()
    assert _run("annotate", str(capture_dir), "--work", str(work), "--auto").returncode == 2  # b still holds it
    b.close()
    code = (f"import os; from annotator.session import Session; Session.open({str(capture_dir)!r}, {str(work)!r}); "
            "os.kill(os.getpid(), 9)")
    killed = subprocess.run([sys.executable, "-c", code], capture_output=True, cwd=ROOT, timeout=300,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert killed.returncode == -9
    with Session.open(capture_dir, work) as again:  # not refused by the dead process's lock
        assert not again.read_only


def test_a_read_only_session_writes_nothing_and_refuses_changes(capture_dir, tmp_path):
    from dsr_bench.annotator.session import Session

    work = tmp_path / "fresh"
    session = Session.open(capture_dir, work, read_only=True)
    assert not work.exists()  # not even the work directory
    for change in (lambda: session.nudge(0, (0.001, 0, 0)), lambda: session.select(1), lambda: session.go_to(1),
                   session.undo):
        with pytest.raises(UserError, match="read-only"):
            change()
    assert not work.exists() and session.state.undo_stack == []


def test_undo_and_redo_say_what_they_changed(capture_dir, truth, tmp_path):
    from dsr_bench.annotator.keys import Controller
    from dsr_bench.annotator.session import Session

    with Session.open(capture_dir, tmp_path / "work") as session:
        place_from_truth(session, truth)
        ctl = Controller(session, echo=lambda s: None)
        ctl.press("2")
        before = pose_to_matrix(session.poses()[1])
        ctl.press("D")  # move object 2 along +x
        moved = (pose_to_matrix(session.poses()[1])[:3, 3] - before[:3, 3]) * 1000
        ctl.press("Z")
        assert ctl.view.message == (f"undone: nudge of object 2 at step 0 ({np.linalg.norm(moved):.1f} mm, 0.0 deg), "
                                    "status snapped <-> initialised; now at step 0")
        ctl.press("Y")
        assert ctl.view.message.startswith("redone: nudge of object 2 at step 0 (")
        ctl.press("Z")
        ctl.press("N")  # visit step 1: carries the three objects
        ctl.press("Z")
        assert ctl.view.message == "undone: the visit of a new step: step 1, carrying objects 1, 2, 3; now at step 0"
        assert session.step == 0 and not session.visited(1)
        ctl.press("Y")
        assert ctl.view.message == "redone: the visit of a new step: step 1, carrying objects 1, 2, 3; now at step 1"
        while session.undo_depth:
            session.undo()
        ctl.press("Z")
        assert ctl.view.message == "nothing to undo"
