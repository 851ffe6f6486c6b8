"""An annotation session: one capture, its annotation state, the operations a user performs, autosave and resume.

The window (`annotator.window`), the CLI (`dsr-bench annotate`) and the benchmark use only this class. Every
mutating call is one undoable user action, and it is saved before the call returns, so killing the process loses
nothing: its record is appended to `<work>/journal.jsonl` and fsync'd (cost independent of the history's length),
and every COMPACT_RECORDS records, and on resume, the journal is folded into `<work>/state.json` (written
atomically). `Session.open` resumes from both (`read_saved`); both are bound to the capture and to each other, and
read as files someone else may have written (`annotator.journal`).

Poses are (7,) = (x, y, z, qx, qy, qz, qw) in the table frame, metres (`dsr_bench.geometry.pose_to_matrix`); unset
poses read as NaN rows. Step s is observation s (0..T); push s moves the scene from step s to s + 1.

`Session` is built in layers, one module each: `annotator.session_core` (state, caches, persistence, read-only
views), `annotator.scoring` (fit scores and their checks, ICP), `annotator.carry` (carrying poses to a new step, the
searches), `annotator.review` (re-carrying after a fix, what is left to check, progress); this module opens a
session and holds the user's actions (picks, nudges, snaps, confirmations, undo / redo), the residual colours, `auto`
and `export`.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dsr_bench.annotator import align
from dsr_bench.annotator.align import FitScore
from dsr_bench.annotator.carry import MOVED_COVERAGE_DROP, SEARCH_LATERAL  # noqa: F401 - re-exported for the tests
from dsr_bench.annotator.checks import Check
from dsr_bench.annotator.images import RESIDUAL_FLOOR, RESIDUAL_SCALE, residual_ramp
from dsr_bench.annotator.journal import (JOURNAL_FILE, JOURNAL_FORMAT, STATE_FILE, Saved, acquire_lock, capture_digest,
                                         check_file, name_holder, read_saved, release_lock)
from dsr_bench.annotator.review import Reviewing
from dsr_bench.annotator.session_core import (COMPACT_RECORDS, DISPLAY_TABLE_VOXEL,  # noqa: F401 - re-exported
                                              DISPLAY_VOXEL, WORK_DIRNAME, cloud_bounds, voxel_subset)
from dsr_bench.annotator.state import AnnotationState, StateError, describe
from dsr_bench.annotator.thresholds import THRESHOLDS
from dsr_bench.atomic import check_writable
from dsr_bench.dataset.capture import Capture, load_capture
from dsr_bench.errors import UserError
from dsr_bench.geometry import matrix_to_pose, pose_to_matrix

__all__ = ["JOURNAL_FILE", "JOURNAL_FORMAT", "STATE_FILE", "WORK_DIRNAME", "FitScore", "Saved", "Session", "SnapScore",
           "read_saved"]


def _mm(value: float) -> str:
    return f"{value * 1000:.1f} mm" if np.isfinite(value) else "-"


@dataclass
class SnapScore(FitScore):
    """What `Session.snap` returns: the FitScore of the kept result (or, when rejected, of the unchanged start pose)
    and `kept`: whether the snap changed the pose (False: rejected, nothing changed)."""

    kept: bool = False

    @classmethod
    def of(cls, score: FitScore, kept: bool) -> SnapScore:
        return cls(score.rmse, score.coverage, score.fitness, score.accepted, score.reason, score.visible,
                   checks=score.checks, kept=kept)

    def as_dict(self) -> dict:
        out = super().as_dict()
        out.pop("kept", None)
        return out


class Session(Reviewing):
    """One capture being annotated (see the module docstring); create with `Session.open`."""

    _lock: str | None  # set by SessionCore (annotator/session_core.py)

    # opening and saving ------------------------------------------------------------------------------------------
    @classmethod
    def open(cls, capture_dir: str | Path, work_dir: str | Path | None = None, read_only: bool = False) -> Session:
        """Open a capture (validated) and resume `<work_dir>/state.json` plus its journal if present (default work
        dir: `<capture_dir>/annotation/`). Raises UserError (one line, nothing written) when the saved state is
        unreadable or belongs to another capture, or the journal is not its own or is malformed
        (`annotator.journal`). A journal whose last record is cut short (a crash mid-write) resumes without it,
        with a note in `notes` (the library prints nothing: `dsr-bench annotate` prints them).

        To change the annotation the session takes the work directory's write lock first (`annotator.journal.
        acquire_lock`; held until `close` or the process ends): while another process holds it, opening is refused
        in one line naming that process. `read_only`: read state.json and its journal without the lock and write
        nothing (not even the fold of the journal); every change is then refused."""
        capture = load_capture(capture_dir)
        work = Path(work_dir) if work_dir is not None else capture.path / WORK_DIRNAME
        digest = capture_digest(capture)
        check_file(work / JOURNAL_FILE, "journal")
        lock = None
        if not read_only:
            check_writable(work, "--work")
            lock = acquire_lock(work)  # before reading: what this process reads is what it alone will change
        try:
            session = cls._resume(capture, work, digest, read_only)
        except BaseException:
            if lock is not None:
                release_lock(lock)
            raise
        if lock is not None:
            name_holder(lock)
        session._lock = lock
        return session

    @classmethod
    def _resume(cls, capture: Capture, work: Path, digest: str, read_only: bool) -> Session:
        path = work / STATE_FILE
        if not check_file(path, "state"):
            session = cls(capture, work, AnnotationState(capture.name, capture.num_steps, capture.num_objects), digest)
            session.read_only = read_only
            if not read_only:
                session._write_snapshot()
            return session
        try:
            saved = read_saved(work, capture, digest)
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError, OSError, StateError) as exc:
            raise UserError(f"{path}: unreadable annotation state ({exc}); move it away to start afresh or give "
                            "another --work directory") from None
        session = cls(capture, work, saved.state, digest)
        session._generation, session._state_sha256 = saved.generation, saved.state_sha256
        session.notes = saved.notes
        session.read_only = read_only
        if not read_only and (saved.replayed or saved.notes or not saved.journal_current or not saved.bound):
            session._write_snapshot()  # fold the journal in, start one (none yet, or a stale one), or bind them
        return session

    def close(self) -> None:
        """Give back the write lock (a later `open`, in any process, may change the annotation); the session can
        no longer be changed. Everything was already saved."""
        if self._lock is not None:
            release_lock(self._lock)
            self._lock = None
        self.read_only = True

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _set_pose(self, kind: str, obj: int, pose: np.ndarray, status: str, score: FitScore | None = None) -> None:
        step = self.state.step
        score = self._fit(obj, step, pose) if score is None else score
        self._commit(kind, {(step, obj): (pose, status, score.as_dict())})

    def select(self, obj: int) -> None:
        """Select object `obj` (the target of the window's keys); saved, not an undoable action."""
        self._writable()
        self.state.selected = self._check_obj(obj)
        self._save("select")

    def init_from_picks(self, obj: int, mesh_points: np.ndarray, cloud_points: np.ndarray) -> np.ndarray:
        """Place object `obj` at the current step from k >= 3 picked pairs: mesh points (k, 3) in the object
        frame and cloud points (k, 3) in the world, metres. Returns the pose (7,); status 'initialised'."""
        self._writable()
        obj = self._check_obj(obj)
        pose = matrix_to_pose(align.kabsch(mesh_points, cloud_points))
        self._set_pose("pick", obj, pose, "initialised")
        return pose

    def place(self, obj: int, matrix: np.ndarray) -> np.ndarray:
        """Place object `obj` at the current step at a given 4x4 pose (object -> table frame, metres; e.g. from a
        poses file, `annotator.placement`). Returns the pose (7,); status 'initialised'."""
        self._writable()
        obj = self._check_obj(obj)
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise UserError(f"a pose for object {obj + 1} must be a finite 4x4 matrix (object -> table, metres)")
        pose = matrix_to_pose(m)
        self._set_pose("place", obj, pose, "initialised")
        return pose

    def _previous_pose(self, obj: int, step: int) -> tuple[int, np.ndarray] | None:
        for s in range(step - 1, -1, -1):
            pose = self.state.pose(s, obj)
            if pose is not None:
                return s, pose
        return None

    def init_from_previous(self, obj: int) -> None:
        """Copy object `obj`'s pose from the nearest earlier step that has one; status 'initialised'."""
        self._writable()
        obj, step = self._check_obj(obj), self.state.step
        found = self._previous_pose(obj, step)
        if found is None:
            raise UserError(f"object {obj + 1} has no pose at any step before {step}: pick 3+ point pairs to place it")
        self._set_pose("previous", obj, found[1], "initialised")

    def nudge(self, obj: int, translation=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0), frame: str = "table") -> None:
        """Move object `obj` at the current step: translation (3,) m and rotation (3,) axis-angle rad about the
        object's centre (its mesh's bounding-box centre), both in table axes (`frame='table'`) or the object's
        axes (`frame='object'`). Status becomes 'initialised'."""
        self._writable()
        obj = self._check_obj(obj)
        if frame not in ("table", "object"):
            raise UserError(f"frame {frame!r}: use 'table' or 'object'")
        m = pose_to_matrix(self._require_pose(obj, self.state.step))
        rot, t = m[:3, :3], m[:3, 3]
        dt = np.asarray(translation, dtype=np.float64).reshape(3)
        dr = align.rotvec_to_matrix(np.asarray(rotation, dtype=np.float64).reshape(3))
        centre = rot @ self.samples(obj).centre + t
        if frame == "table":
            new_rot = dr @ rot
        else:
            new_rot = rot @ dr
            dt = rot @ dt
        out = np.eye(4)
        out[:3, :3] = new_rot
        out[:3, 3] = centre - new_rot @ self.samples(obj).centre + dt
        self._set_pose("nudge", obj, matrix_to_pose(out), "initialised")

    def snap(self, obj: int) -> SnapScore:
        """ICP-align object `obj` at the current step to a crop of the fused cloud around it.

        The decision: a result whose fit is good (`accepted`) is kept as 'snapped'; a result whose fit is still
        poor is kept as 'initialised' only when it fits better than the start pose (`FitScore.quality`), so that a
        snap never makes a pose worse; anything else is rejected: ICP's own rejections (a jump beyond its limits,
        too few correspondences) and results that fit worse than the start (e.g. a can tilted into the table).
        A rejected snap changes nothing: pose, status, score, undo / redo history and the state file stay exactly
        as they were (the snap is counted in memory; the count is written with the next change). Returns the
        score of the kept result, or for a rejection the start pose's score with `accepted` False and the reason;
        `kept` says which (see `SnapScore`)."""
        self._writable()
        obj, step = self._check_obj(obj), self.state.step
        pose = self._require_pose(obj, step)
        start = pose_to_matrix(pose)
        result = self._icp(obj, step, start)
        if result.applied and not result.score.accepted:
            before = self._fit(obj, step, pose)
            after = result.score.quality()
            if not after > before.quality():
                worse = Check("snap_quality", after, before.quality(), False,
                              f"the ICP result fits worse than the start (coverage {before.coverage:.0%} -> "
                              f"{result.score.coverage:.0%}, rmse {_mm(before.rmse)} -> {_mm(result.score.rmse)}); "
                              "nudge the object onto its points and snap again")
                self.state.count("snap")
                return SnapScore.of(before.refused(worse), kept=False)
        if not result.applied:
            self.state.count("snap")
            return SnapScore.of(result.score, kept=False)
        status = "snapped" if result.score.accepted else "initialised"
        self._set_pose("snap", obj, matrix_to_pose(result.transform), status, result.score)
        return SnapScore.of(result.score, kept=True)

    def confirm(self, obj: int) -> None:
        """Mark object `obj`'s pose at the current step as checked by the user ('confirmed')."""
        self._writable()
        obj, step = self._check_obj(obj), self.state.step
        self._set_pose("confirm", obj, self._require_pose(obj, step), "confirmed")

    def undo(self) -> bool:
        """Revert the latest change exactly; False if there is none (`describe_undo` says what it reverts)."""
        self._writable()
        if self.state.undo() is None:
            return False
        self.state.count("undo")
        self._save("undo")
        return True

    def describe_undo(self) -> str | None:
        """What `undo` would revert now, in words (`annotator.state.describe`); None when there is nothing."""
        return describe(self.state.undo_stack[-1]) if self.state.undo_stack else None

    def describe_redo(self) -> str | None:
        """What `redo` would re-apply now, in words; None when there is nothing."""
        return describe(self.state.redo_stack[-1]) if self.state.redo_stack else None

    def redo(self) -> bool:
        """Re-apply the latest undone change; False if there is none (`describe_redo` says what it re-applies)."""
        self._writable()
        if self.state.redo() is None:
            return False
        self.state.count("redo")
        self._save("redo")
        return True

    # display helpers --------------------------------------------------------------------------------------------------
    def residual_colors(self, step: int | None = None, max_residual: float = RESIDUAL_SCALE,
                        index: np.ndarray | None = None) -> np.ndarray:
        """Colours (M, 3) in 0..1 of `cloud(step)`'s points (of those at `index` (K,) only, e.g. `shown(step)`: then
        (K, 3)) by their distance to the nearest posed mesh surface: blue (0) through green and yellow to red
        (>= `max_residual` m, `residual_ramp`) within 2 x `max_residual`; the points higher than RESIDUAL_FLOOR
        above the table farther from every posed mesh are red too (surface no posed mesh explains: where a wrongly
        placed object really is, or an object not placed yet); the others (the table) keep a dimmed grey of their
        own colour."""
        from scipy.spatial import cKDTree

        step = self._step(step)
        points, colors, _ = self.cloud(step)
        if index is not None:
            points, colors = points[index], colors[index]
        out = np.repeat(colors.mean(1, keepdims=True), 3, axis=1) * 0.5 + 0.1
        surfaces = [align.posed_samples(self.samples(i), pose_to_matrix(p))[0]
                    for i in range(self.num_objects) if (p := self.state.pose(step, i)) is not None]
        above = np.flatnonzero(points[:, 2] > THRESHOLDS.table_margin)  # the table's points stay grey: not queried
        d = np.full(len(points), np.inf)
        if surfaces:
            d[above] = cKDTree(np.vstack(surfaces)).query(points[above], distance_upper_bound=2 * max_residual)[0]
        near = np.isfinite(d)
        out[near] = residual_ramp(d[near] / max_residual)
        out[~near & (points[:, 2] > RESIDUAL_FLOOR)] = residual_ramp(np.ones(1))
        return out

    def auto(self, progress: Callable[[int, int, list[int]], None] | None = None) -> dict[int, list[int]]:
        """Visit every step not yet visited in order (carry forward + snap what moved); returns the objects
        snapped per newly visited step. Step 0 must be initialised (every object posed). `progress(step, last
        step, objects snapped)`: called after each step visited."""
        self._writable()
        missing = [i for i in range(self.num_objects) if self.state.pose(0, i) is None]
        if missing:
            raise UserError(f"step 0 has objects without a pose ({', '.join(str(i + 1) for i in missing)}): place them "
                            "first (--place POSES.json, or pick 3+ point pairs per object in the window), then --auto")
        out = {}
        for s in range(1, self.num_steps + 1):
            if not self.state.visited[s]:
                out[s] = self.go_to(s)
                if progress is not None:
                    progress(s, self.num_steps, out[s])
        return out

    def export(self, out: str | Path, allow_unchecked: bool = False) -> Path:
        """Write the annotated sequence file (see `annotator.export.export_sequence`)."""
        from dsr_bench.annotator.export import export_sequence

        return export_sequence(self, out, allow_unchecked=allow_unchecked)
