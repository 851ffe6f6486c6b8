"""An annotation session: one capture, its annotation state, the operations a user performs, autosave and resume.

The window (`annotator.window`), the CLI (`dsr-bench annotate`) and the benchmark use only this class. Every
mutating call is one undoable user action, and it is saved before the call returns, so killing the process loses
nothing: its record is appended to `<work>/journal.jsonl` and fsync'd (cost independent of the history's length),
and every COMPACT_RECORDS records, and on resume, the journal is folded into `<work>/state.json` (written
atomically). `Session.open` resumes from both (`read_saved`); both are bound to the capture and to each other, and
read as files someone else may have written (`annotator.journal`).

Poses are (7,) = (x, y, z, qx, qy, qz, qw) in the table frame, metres (`dsr_bench.geometry.pose_to_matrix`); unset
poses read as NaN rows. Step s is observation s (0..T); push s moves the scene from step s to s + 1.

Over 500 lines on purpose: the carry-forward search of `go_to` (about 200 lines: `_carry`, `_search`, `_land`,
`_search_landed`) reads and commits the session's state at every stage, and split off it would need the session's
private operations (`_icp`, `_fit`, `_crop`, `_commit`) as an API of their own; the re-carry after a fix (`recarry`,
`stale_steps`, `to_check`) reuses that search and the state's carried-from records in the same way.
"""

from __future__ import annotations

import json
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from annotator import align
from annotator.align import FitScore
from annotator.images import RESIDUAL_FLOOR, RESIDUAL_SCALE, residual_ramp
from annotator.journal import (JOURNAL_FILE, JOURNAL_FORMAT, STATE_FILE, Saved, acquire_lock, append_record,
                               capture_digest, check_file, name_holder, read_saved, release_lock,
                               write_snapshot)
from annotator.state import ACTION_KINDS, AnnotationState, StateError, describe
from dsr_bench.atomic import check_writable
from dsr_bench.dataset.capture import Capture, load_capture
from dsr_bench.constants import RIG_PUSHER_RADIUS
from dsr_bench.errors import UserError
from dsr_bench.geometry import matrix_to_pose, pose_to_matrix

__all__ = ["JOURNAL_FILE", "JOURNAL_FORMAT", "STATE_FILE", "WORK_DIRNAME", "FitScore", "Saved", "Session", "SnapScore",
           "read_saved"]

WORK_DIRNAME = "annotation"
# state.json and the change journal next to it (journal.jsonl: a header binding it to state.json and the capture,
# then one JSON record per change, each appended and fsync'd before the call returns): `annotator.journal`.
#: The journal is folded into state.json after this many records (and when a session resumes from it).
COMPACT_RECORDS = 500
#: Crop radius around an object: its bounding sphere plus this margin (m).
CROP_MARGIN = 0.03
#: Carry-forward: an object counts as moved when its carried pose's coverage drops by this much (fraction) ...
MOVED_COVERAGE_DROP = 0.1
#: ... or its RMSE grows by this much (m), or its fit fails, or the pusher passed within this distance (m) of it.
MOVED_RMSE_RISE = 0.001
PUSH_CONTACT_MARGIN = 0.01
#: A snap of an object the fit does not flag as moved is kept only if it moves it at least this much (m, rad).
MIN_SNAP_CHANGE = (0.001, float(np.deg2rad(0.5)))
#: Start-pose search for a moved object whose carried pose does not snap: steps along the push (m), sideways
#: offsets (m), yaw candidates (rad), and how many of the best-scoring starts get an ICP.
SEARCH_STEP = 0.01
SEARCH_LATERAL = (-0.04, -0.02, 0.0, 0.02, 0.04)
#: Inlier distance (m) of the coarse score that ranks the search's start poses.
SEARCH_INLIER = 0.015
#: Surface samples used to rank the search's start poses.
SEARCH_SAMPLES = 400
SEARCH_YAWS = tuple(np.deg2rad([0, 15, -15, 30, -30, 60, -60, 90, -90, 180]))
SEARCH_ICP_STARTS = 6
#: Ranking penalty of a start pose or result per half turn (pi rad) away from the carried pose, in quality units
#: (coverage fraction): among fits of nearly equal quality the least turned one wins.
TURN_PENALTY = 0.05
#: A moved object that the search along the push does not find is looked for where the step's cloud shows surface
#: that no other object explains (a can or bottle lying on its side rolls on after the push, often farther than the
#: push and across it): cloud points above the table farther than this (m) from every other object's surface ...
EXPLAINED_DISTANCE = 0.01
#: ... in SEARCH_STEP cells holding at least this many of them put the object's centre over the cell, at its carried
#: height, turned about the vertical by SEARCH_YAWS.
LANDING_MIN_POINTS = 3
#: Ranking penalty of such a start pose or result per metre away from the carried pose, in quality units: among
#: fits of nearly equal quality (the same shape elsewhere) the nearest one wins.
DISTANCE_PENALTY = 0.5
#: Start poses screened at once (bounds the memory of the vectorised screen).
SCREEN_CHUNK = 1000
#: The screen runs in two passes when there are more than SCREEN_KEEP start poses: every start with one in
#: SCREEN_COARSE of the SEARCH_SAMPLES samples, then the best SCREEN_KEEP (at least; SCREEN_KEEP_FRACTION of them
#: when more) with all; the SEARCH_ICP_STARTS best of the second pass get an ICP. On the simulated captures the
#: starts chosen are those of one full pass (checked on 4 captures, every search), at a third of its time.
SCREEN_COARSE = 3
SCREEN_KEEP = 60
SCREEN_KEEP_FRACTION = 0.12
#: Clouds kept in memory (steps).
CLOUD_CACHE = 4
#: The window draws a subset of a step's cloud (`Session.shown`): one point per cube of DISPLAY_VOXEL (m) above the
#: table (what a person aligns a mesh to: every surface still covered, at most a cube's diagonal, 3.5 mm, from a drawn
#: point) and per cube of DISPLAY_TABLE_VOXEL (m) on it (the table is there to orient). Fitting and scores use the
#: whole cloud.
DISPLAY_VOXEL = 0.002
DISPLAY_TABLE_VOXEL = 0.006
#: Occluder depth renders kept in memory (one per step and set of the other objects' poses).
OCCLUDER_CACHE = 64
#: Ranking penalty (quality units) of a search's ICP result whose fit is not accepted (e.g. a physical check
#: failed: it sits inside another object or in front of what a camera measured): the best physically valid fit wins.
REJECTED_PENALTY = 1.0


def cloud_bounds() -> np.ndarray:
    """The box (2, 3) (lowest, highest x, y, z; m, table frame) that `Capture.cloud` keeps points in: the grid's
    bounds plus CLOUD_MARGIN, from CLOUD_MARGIN below the table."""
    from dsr_bench.constants import GRID_BOUNDS
    from dsr_bench.dataset.capture import CLOUD_MARGIN

    lo, hi = GRID_BOUNDS[:, 0] - CLOUD_MARGIN, GRID_BOUNDS[:, 1] + CLOUD_MARGIN
    lo[2] = -CLOUD_MARGIN
    return np.stack([lo, hi])


def voxel_subset(points: np.ndarray, voxel: float, table_voxel: float, table_height: float) -> np.ndarray:
    """Indices (K,) ascending into points (M, 3) m of one point per occupied cube: cubes of `voxel` m for the points
    above `table_height` m, of `table_voxel` m for the others (each cube's first point in index order). Every point
    lies within its cube's diagonal of a kept one."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(0, np.int64)
    high = points[:, 2] > table_height
    cells = np.floor(points / np.where(high, voxel, table_voxel)[:, None]).astype(np.int64)
    cells -= cells.min(0)
    span = cells.max(0) + 1
    key = ((cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]) * 2 + high
    return np.sort(np.unique(key, return_index=True)[1])


def _mm(value: float) -> str:
    return f"{value * 1000:.1f} mm" if np.isfinite(value) else "-"


@dataclass
class SnapScore(FitScore):
    """What `Session.snap` returns: the FitScore of the kept result (or, when rejected, of the unchanged start pose)
    and `kept`: whether the snap changed the pose (False: rejected, nothing changed)."""

    kept: bool = False

    @classmethod
    def of(cls, score: FitScore, kept: bool) -> SnapScore:
        return cls(score.rmse, score.coverage, score.fitness, score.accepted, score.reason, score.visible, kept)

    def as_dict(self) -> dict:
        out = super().as_dict()
        out.pop("kept", None)
        return out


def _rank(score: FitScore) -> float:
    """Rank of a fit among a search's results: its quality, less REJECTED_PENALTY when it is not accepted."""
    return score.quality() - (0.0 if score.accepted else REJECTED_PENALTY)


def _screen(samples: align.SurfaceSamples, starts: np.ndarray, tree, views: list[align.View],
            min_visible: int = 20) -> np.ndarray:
    """`align.screen_quality` (C,) of start poses (C, 4, 4), SCREEN_CHUNK at a time."""
    return np.concatenate([align.screen_quality(samples, starts[k:k + SCREEN_CHUNK], tree, views, SEARCH_INLIER,
                                                min_visible) for k in range(0, len(starts), SCREEN_CHUNK)])


def _best_starts(samples: align.SurfaceSamples, starts: np.ndarray, penalties: np.ndarray, tree,
                 views: list[align.View]) -> np.ndarray:
    """Indices of the SEARCH_ICP_STARTS start poses (C, 4, 4) of best screened quality (`align.screen_quality` of
    SEARCH_SAMPLES of the object's surface samples, against a cKDTree of the cloud) less `penalties` (C,), best
    first, ties in index order; over SCREEN_KEEP starts in two passes (see SCREEN_COARSE)."""
    every = max(1, len(samples.points) // SEARCH_SAMPLES)
    screen = align.SurfaceSamples(samples.points[::every], samples.normals[::every], samples.centre, samples.radius)
    keep = np.arange(len(starts))
    if len(starts) > SCREEN_KEEP:
        coarse = align.SurfaceSamples(screen.points[::SCREEN_COARSE], screen.normals[::SCREEN_COARSE],
                                      samples.centre, samples.radius)
        first = _screen(coarse, starts, tree, views, max(1, 20 // SCREEN_COARSE)) - penalties
        count = max(SCREEN_KEEP, int(SCREEN_KEEP_FRACTION * len(starts)))
        keep = np.sort(np.argsort(-first, kind="stable")[:count])
    quality = _screen(screen, starts[keep], tree, views) - penalties[keep]
    return keep[np.argsort(-quality, kind="stable")[:SEARCH_ICP_STARTS]]


def _same_poses(a: list[tuple[int, np.ndarray]], b: list[tuple[int, np.ndarray]]) -> bool:
    """Whether two lists of (object, pose) hold the same objects at exactly the same poses."""
    return len(a) == len(b) and all(i == j and np.array_equal(p, q) for (i, p), (j, q) in zip(a, b))


def _nan_score(d: dict | None) -> FitScore | None:
    """The FitScore of a stored score dict; None when there is none or it is not a whole score (then refitted)."""
    if d is None:
        return None
    try:
        return FitScore.from_dict({k: (float("nan") if v is None else v) for k, v in d.items()})
    except (KeyError, TypeError, ValueError):
        return None


class Session:
    """One capture being annotated (see the module docstring); create with `Session.open`."""

    def __init__(self, capture: Capture, work_dir: Path, state: AnnotationState, capture_sha256: str | None = None):
        self.capture = capture
        self.work_dir = Path(work_dir)
        self.state = state
        self._samples: dict[int, align.SurfaceSamples] = {}
        self._clouds: OrderedDict[int, tuple] = OrderedDict()
        self._shown: dict[int, np.ndarray] = {}  # the window's subset of each cached cloud (`shown`)
        self._occluders: OrderedDict[tuple, list] = OrderedDict()  # (step, others' poses) -> depth per view
        self._colours: OrderedDict[tuple, np.ndarray] = OrderedDict()  # (object, step, pose) -> `_reference_colours`
        self._shifts: OrderedDict[tuple, np.ndarray] = OrderedDict()  # (step, object, pose) -> refinement's shift
        self._generation = 0  # journal generation of the last snapshot written or read
        self._records = 0  # records in the journal since
        self._capture_sha256 = capture_sha256 or capture_digest(capture)  # what state.json and the journal are bound to
        self._state_sha256: str | None = None  # sha256 of the last state.json written or read
        self.notes: list[str] = []  # what resuming had to leave out (a journal's cut-short tail)
        self.read_only = False  # opened to read (--status, --export): nothing is written, no lock is held
        self._lock: str | None = None  # the work directory's write lock this session holds (`annotator.journal`)

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

    def _writable(self) -> None:
        if self.read_only:
            raise UserError(f"{self.work_dir}: this annotation was opened read-only (--status, --export, --bop) or "
                            "closed; open it without them to change it")

    @property
    def state_path(self) -> Path:
        return self.work_dir / STATE_FILE

    @property
    def journal_path(self) -> Path:
        return self.work_dir / JOURNAL_FILE

    def _write_snapshot(self) -> None:
        """Fold everything into state.json under the next journal generation, bound to the capture's digest, then
        start that generation's journal (`annotator.journal.write_snapshot`: both atomic)."""
        self._writable()
        self._generation += 1
        self._state_sha256 = write_snapshot(self.work_dir, self.state, self._generation, self._capture_sha256,
                                            self._state_sha256)
        self._records = 0

    def _save(self, kind: str, op=None) -> None:
        """Make the change just applied in memory durable before the call returns: append its record to the journal
        and fsync it (a few hundred bytes, whatever the history's length); every COMPACT_RECORDS records the
        journal is folded into state.json instead."""
        self._writable()
        if self._records >= COMPACT_RECORDS:
            self._write_snapshot()
            return
        append_record(self.journal_path, self.state.record(kind, op))
        self._records += 1

    # read-only views -------------------------------------------------------------------------------------------------
    @property
    def step(self) -> int:
        """The current step (observation index 0..T)."""
        return self.state.step

    @property
    def selected(self) -> int:
        return self.state.selected

    @property
    def num_steps(self) -> int:
        """Pushes T (the capture has T + 1 steps)."""
        return self.capture.num_steps

    @property
    def num_objects(self) -> int:
        return self.capture.num_objects

    @property
    def action_counts(self) -> dict[str, int]:
        """User actions by kind (pick, previous, nudge, snap, confirm, step, undo, redo)."""
        return {k: int(self.state.counts.get(k, 0)) for k in ACTION_KINDS}

    @property
    def undo_depth(self) -> int:
        """Changes that `undo` can revert."""
        return len(self.state.undo_stack)

    @property
    def redo_depth(self) -> int:
        """Undone changes that `redo` can re-apply."""
        return len(self.state.redo_stack)

    def visited(self, step: int) -> bool:
        return bool(self.state.visited[self._check_step(step)])

    def poses(self, step: int | None = None) -> np.ndarray:
        """Poses (N, 7) at a step (default the current one); NaN rows where unset."""
        return self.state.poses[self._step(step)].copy()

    def status(self, step: int | None = None) -> list[str]:
        """Status per object at a step: 'unset' | 'initialised' | 'snapped' | 'confirmed'."""
        return [str(s) for s in self.state.status[self._step(step)]]

    def samples(self, obj: int) -> align.SurfaceSamples:
        """Surface samples of object `obj`'s mesh (object frame), cached."""
        if obj not in self._samples:
            self._samples[obj] = align.sample_surface(*self.capture.mesh(obj), seed=obj)
        return self._samples[obj]

    def cloud(self, step: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The fused cloud of a step (points (M, 3) m, colours (M, 3) 0..1, camera index (M,)), cached."""
        step = self._step(step)
        if step not in self._clouds:
            bounds, views = cloud_bounds(), []
            for name, cam in self.capture.cameras.items():
                depth = self.capture.depth(step, name)
                views.append(align.View(cam.camera, depth, bounds=bounds, near=align.near_depth(depth),
                                        color=self.capture.color(step, name)))
            self._clouds[step] = self.capture.cloud(step) + (views,)
            while len(self._clouds) > CLOUD_CACHE:
                self._shown.pop(self._clouds.popitem(last=False)[0], None)
        self._clouds.move_to_end(step)
        return self._clouds[step][:3]

    def shown(self, step: int | None = None) -> np.ndarray:
        """Indices (K,) ascending into `cloud(step)` of the points the window draws, chosen once per step: one per
        cube of DISPLAY_VOXEL m above the table and of DISPLAY_TABLE_VOXEL m on it (`voxel_subset`), so that every
        surface the cameras saw is drawn (each cloud point within a cube's diagonal of a drawn one) with a fraction
        of the points (111k -> 32k on a simulated pair of 640 x 480 cameras)."""
        step = self._step(step)
        points = self.cloud(step)[0]
        if step not in self._shown:
            self._shown[step] = voxel_subset(points, DISPLAY_VOXEL, DISPLAY_TABLE_VOXEL, align.TABLE_MARGIN)
        return self._shown[step]

    def _views(self, step: int) -> list[align.View]:
        self.cloud(step)
        return self._clouds[step][3]

    # checks ---------------------------------------------------------------------------------------------------------
    def _check_step(self, step: int) -> int:
        step = int(step)
        if not 0 <= step <= self.num_steps:
            raise UserError(f"step {step} out of range: this capture has steps 0..{self.num_steps}")
        return step

    def _step(self, step: int | None) -> int:
        return self.state.step if step is None else self._check_step(step)

    def _check_obj(self, obj: int) -> int:
        obj = int(obj)
        if not 0 <= obj < self.num_objects:
            raise UserError(f"object {obj + 1} out of range: this capture has objects 1..{self.num_objects}")
        return obj

    def _require_pose(self, obj: int, step: int) -> np.ndarray:
        pose = self.state.pose(step, obj)
        if pose is None:
            raise UserError(f"object {obj + 1} has no pose at step {step} yet: initialise it first (pick 3+ point "
                            "pairs, or take the previous step's pose)")
        return pose

    # scoring ----------------------------------------------------------------------------------------------------------
    def _crop(self, step: int, transform: np.ndarray, samples: align.SurfaceSamples, extra: float = 0.0) -> np.ndarray:
        points = self.cloud(step)[0]
        centre = transform[:3, :3] @ samples.centre + transform[:3, 3]
        return align.crop_cloud(points, centre, samples.radius + CROP_MARGIN + extra)

    def _others(self, obj: int, step: int) -> list[tuple[int, np.ndarray]]:
        """(object, pose (7,)) of the other objects posed at a step in the state."""
        return [(k, p) for k in range(self.num_objects) if k != obj and (p := self.state.pose(step, k)) is not None]

    def _context(self, obj: int, step: int, others: list[tuple[int, np.ndarray]] | None = None,
                 colours: bool = True) -> tuple[list[align.View], dict]:
        """(views, keywords) to score object `obj` at a step with: the step's views with the other objects' posed
        meshes as occluders (`align.View.occluders`), and the keywords of `align.fit_score` / `align.icp` for the
        physical checks: `neighbours`, those objects as (name, samples, 4x4 transform), `explain`, whether
        they are all the other objects (then the cloud around the object must be explained), and
        `reference_colours`, the object's colours at another checked step (`_reference_colours`; None without
        `colours`). others: (object, pose (7,)) of the other objects (default: the state's)."""
        others = self._others(obj, step) if others is None else [(k, p) for k, p in others if k != obj]
        others = [(k, np.asarray(p, dtype=np.float64)) for k, p in others if np.all(np.isfinite(p))]
        views = self._views(step)
        key = (step, tuple((k, p.tobytes()) for k, p in sorted(others, key=lambda e: e[0])))
        if key not in self._occluders:
            meshes = []
            for k, p in others:
                v, f = self.capture.mesh(k)
                m = pose_to_matrix(p)
                meshes.append((np.asarray(v, np.float64) @ m[:3, :3].T + m[:3, 3], f))
            self._occluders[key] = [align.render_depth(view.camera, meshes) if meshes else None for view in views]
            while len(self._occluders) > OCCLUDER_CACHE:
                self._occluders.popitem(last=False)
        self._occluders.move_to_end(key)
        views = [view.with_occluders(occ) for view, occ in zip(views, self._occluders[key])]
        neighbours = [(f"object {k + 1} ({self.capture.objects[k].name})", self.samples(k), pose_to_matrix(p))
                      for k, p in others]
        return views, {"neighbours": neighbours, "explain": len({k for k, _ in others}) == self.num_objects - 1,
                       "reference_colours": self._reference_colours(obj, step) if colours else None}

    def _reference_colours(self, obj: int, step: int) -> np.ndarray | None:
        """The colours (S, 3) 0..1 the cameras saw at object `obj`'s surface samples (`align.sample_colours`, NaN
        unseen) at the nearest other step (the earlier of two) where its pose is confirmed, or snapped with an
        accepted score, or None when there is none; cached per step and pose."""
        checked = [s for s in range(self.num_steps + 1) if s != step and (
            self.state.status[s, obj] == "confirmed" or (self.state.status[s, obj] == "snapped"
                                                         and (self.state.scores[s][obj] or {}).get("accepted")))]
        if not checked:
            return None
        ref = min(checked, key=lambda s: (abs(s - step), s))
        pose = self.state.pose(ref, obj)
        assert pose is not None  # a checked status has a pose
        key = (obj, ref, pose.tobytes())
        if key not in self._colours:
            views, _ = self._context(obj, ref, colours=False)
            self._colours[key] = align.sample_colours(*align.posed_samples(self.samples(obj), pose_to_matrix(pose)),
                                                      views)
            while len(self._colours) > OCCLUDER_CACHE:
                self._colours.popitem(last=False)
        return self._colours[key]

    def _fit(self, obj: int, step: int, pose: np.ndarray, others: list[tuple[int, np.ndarray]] | None = None
             ) -> FitScore:
        """Fit score of object `obj` at `pose` (7,) at a step, occlusion-aware and with the physical checks against
        the other objects (`others`: (object, pose); default: the state's poses at the step), the colours of a
        checked step (`_reference_colours`) and the refinement (a snap may not improve it beyond the shift the
        other objects share: `align.refinement`, `_shared_shift`)."""
        transform = pose_to_matrix(pose)
        samples = self.samples(obj)
        views, checks = self._context(obj, step, others)
        posed = self._others(obj, step) if others is None else others
        return align.fit_score(samples, transform, self._crop(step, transform, samples), views, refine=True,
                               shared_shift=lambda: self._shared_shift(obj, step, posed), **checks)

    def _shared_shift(self, obj: int, step: int, others: list[tuple[int, np.ndarray]]) -> np.ndarray | None:
        """The shift (3,) m that the refinement (`align.refinement`, the step's views without occluders) gives the
        objects other than `obj` at their poses (`others`: (object, pose)), the median per axis; None with fewer
        than 2 of them. Every object of a step shares the cameras' calibration error against the table frame (3-4 mm
        in some simulated captures), so only a move beyond it says a pose is wrong. Cached per step, object and
        pose."""
        shifts = []
        for k, p in others:
            pose = np.asarray(p, dtype=np.float64)
            if k == obj or not np.all(np.isfinite(pose)):
                continue
            key = (step, k, pose.tobytes())
            if key not in self._shifts:
                m, samples = pose_to_matrix(pose), self.samples(k)
                self._shifts[key] = align.refinement(samples, m, self._crop(step, m, samples), self._views(step)).shift
                while len(self._shifts) > OCCLUDER_CACHE:
                    self._shifts.popitem(last=False)
            shifts.append(self._shifts[key])
        return np.median(np.asarray(shifts), axis=0) if len(shifts) >= 2 else None

    def score(self, obj: int, step: int | None = None) -> FitScore:
        """Fit score of object `obj`'s current pose at a step (default the current one) against its cloud."""
        obj, step = self._check_obj(obj), self._step(step)
        pose = self.state.pose(step, obj)
        if pose is None:
            return FitScore(float("nan"), 0.0, 0.0, False, "unset")
        return self._fit(obj, step, pose)

    def stored_score(self, obj: int, step: int | None = None) -> FitScore | None:
        """The score recorded with the object's last change at a step (None if never scored)."""
        return _nan_score(self.state.scores[self._step(step)][self._check_obj(obj)])

    # mutations --------------------------------------------------------------------------------------------------------
    def _commit(self, kind: str, changes: dict, cursor: int | None = None, visit: list[int] | None = None) -> None:
        self._writable()
        op = self.state.operation(kind, changes, cursor=cursor, visit=visit)
        self.state.apply(op)
        self.state.count(kind)
        self._save("apply", op)

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
            if not result.score.quality() > before.quality():
                before.accepted = False
                before.reason = (f"the ICP result fits worse than the start (coverage {before.coverage:.0%} -> "
                                 f"{result.score.coverage:.0%}, rmse {_mm(before.rmse)} -> {_mm(result.score.rmse)}); "
                                 "nudge the object onto its points and snap again")
                self.state.count("snap")
                return SnapScore.of(before, kept=False)
        if not result.applied:
            self.state.count("snap")
            return SnapScore.of(result.score, kept=False)
        status = "snapped" if result.score.accepted else "initialised"
        self._set_pose("snap", obj, matrix_to_pose(result.transform), status, result.score)
        return SnapScore.of(result.score, kept=True)

    def _icp(self, obj: int, step: int, start: np.ndarray, extra_crop: float = 0.0,
             others: list[tuple[int, np.ndarray]] | None = None, **kwargs) -> align.IcpResult:
        """ICP of object `obj` at a step from `start` (4, 4), scored against the other objects (`others`:
        (object, pose); default: the state's poses at the step)."""
        samples = self.samples(obj)
        crop = self._crop(step, start, samples, extra_crop)
        views, checks = self._context(obj, step, others)
        return align.icp(samples, crop, start, views, **checks, **kwargs)

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

    # steps ------------------------------------------------------------------------------------------------------------
    def go_to(self, step: int) -> list[int]:
        """Make `step` current. A step not visited before gets the poses of the nearest earlier visited step
        carried forward, and only the objects that moved are snapped (ICP; a start-pose search along the push
        when the carried pose does not converge; then, for an object that left its place and is still not snapped,
        a search over the cloud that no other object explains, e.g. a lying can that rolled on across the push).
        Returns the objects whose pose the snapping changed.

        Moving to a visited step only moves the cursor (not an undoable action); visiting a new step is one.
        """
        step = self._check_step(step)
        self._writable()
        if self.state.visited[step]:
            if step != self.state.step:
                self.state.step = step
                self.state.count("step")
                self._save("cursor")
            return []
        source = max(s for s in range(step) if self.state.visited[s])
        carries = {obj: (source, pose, None, None) for obj in range(self.num_objects)
                   if (pose := self.state.pose(source, obj)) is not None}
        changes, snapped = self._carry_objects(step, carries)
        self._commit("step", changes, cursor=step, visit=[step])
        return snapped

    def _carry_objects(self, step: int, carries: dict) -> tuple[dict, list[int]]:
        """Carry objects to `step`: carries {obj: (source step, source pose, source score or None, source status or
        None)} (None: the state's). Returns the changes {(step, obj): (pose, status, score dict, (source, source
        pose))} and the objects whose pose the snapping changed. Objects not carried keep their pose at `step`.

        The objects the pusher passed go first, each scored without the pushed ones not carried yet (their poses
        here are unknown), and the others stay still as hypotheses, scored against the new poses (an object that
        moved in front of a still one hides part of it); once every object has a pose, each is scored again
        against the others' final poses: a moved object whose new pose now fits (accepted, about as well covered
        as at the source) is snapped, and an object whose pose is not accepted (another object now hides it, or
        it interpenetrates one) is carried again against them."""
        current = {k: p for k in range(self.num_objects)
                   if k not in carries and (p := self.state.pose(step, k)) is not None}
        current.update({obj: c[1] for obj, c in carries.items()})
        pushed = {o for o in carries if self._near_push(o, carries[o][1], carries[o][0], step)}
        order = sorted(carries, key=lambda o: (o not in pushed, o))
        results, used = {}, {}
        for obj in order:
            source, pose, before, src_status = carries[obj]
            # the objects the pusher passed that are not carried yet have no pose here yet: left out
            pending = {k for k in pushed if k not in results}
            used[obj] = self._others_of(obj, {k: p for k, p in current.items() if k not in pending})
            results[obj] = self._carry(obj, source, step, pose, before, src_status, used[obj])
            current[obj] = results[obj][0]
        for obj in order:
            new_pose, status, score, moved = results[obj]
            others = self._others_of(obj, current)
            if _same_poses(others, used[obj]):
                continue  # scored against these poses already
            final = self._fit(obj, step, new_pose, others)
            source, pose, before, src_status = carries[obj]
            if final.accepted and (status == "snapped" or moved):
                before = before or self._fit(obj, source, pose)
                if status == "snapped" or final.coverage >= before.coverage - MOVED_COVERAGE_DROP:
                    results[obj] = (new_pose, "snapped", final, moved)  # its fit holds against the final poses
                    continue
            results[obj] = self._carry(obj, source, step, pose, before, src_status, others)
            current[obj] = results[obj][0]
        changes, snapped = {}, []
        for obj in sorted(results):
            new_pose, status, score, moved = results[obj]
            changes[(step, obj)] = (new_pose, status, score.as_dict(), (carries[obj][0], carries[obj][1]))
            if moved:
                snapped.append(obj)
        # once every object near its push has its new pose: an object that left its place and was not found near
        # the push is looked for where the cloud shows surface that no other object explains
        for obj in [k for (_, k), change in changes.items() if change[1] != "snapped"]:
            others = self._others_of(obj, {k: change[0] for (_, k), change in changes.items()} |
                                     {k: p for k, p in current.items() if k not in carries})
            source, pose, before, _ = carries[obj]
            landed = self._land(obj, source, step, pose, others, before)
            if landed is not None:
                changes[(step, obj)] = (landed[0], "snapped", landed[1].as_dict(), (source, pose))
                snapped = sorted(set(snapped) | {obj})
        return changes, snapped

    @staticmethod
    def _others_of(obj: int, poses: dict) -> list[tuple[int, np.ndarray]]:
        """(object, pose) of the entries of {object: pose} other than `obj`."""
        return [(k, np.asarray(p, dtype=np.float64)) for k, p in sorted(poses.items()) if k != obj]

    # re-carrying after a fix, and what is left to check -------------------------------------------------------------
    def carried_from(self, obj: int, step: int | None = None) -> tuple[int, np.ndarray] | None:
        """(source step, source pose (7,)) that object `obj`'s pose at a step was carried from, or None when the
        pose was set by hand (pick, place, previous, nudge, snap, confirm) or is unset."""
        rec = self.state.carried[self._step(step)][self._check_obj(obj)]
        return None if rec is None else (int(rec["step"]), np.asarray(rec["pose"], dtype=np.float64))

    def is_stale(self, obj: int, step: int | None = None) -> bool:
        """Whether object `obj`'s pose at a step was carried from a pose that has changed since (its source step
        now holds another pose: a fix there, or a re-carry of it)."""
        found = self.carried_from(obj, step)
        if found is None:
            return False
        now = self.state.pose(found[0], obj)
        return now is not None and not np.array_equal(now, found[1])

    def _recarry_plan(self, obj: int, step: int) -> list[tuple[int, int]]:
        """(step, source) to re-carry, in step order: see `stale_steps`."""
        source = self.carried_from(obj, step) if self.is_stale(obj, step) else None
        if source is not None:  # stale: carried, from a source that has changed since
            step = source[0]
        chain, affected, plan = {step}, set(), []
        for t in range(step + 1, self.num_steps + 1):
            rec = self.carried_from(obj, t)
            if rec is None or rec[0] not in chain:
                continue  # set by hand (or carried from elsewhere): its pose is the user's, it stops the chain
            chain.add(t)
            if rec[0] in affected or self.is_stale(obj, t):
                affected.add(t)
                plan.append((t, rec[0]))
        return plan

    def stale_steps(self, obj: int, step: int | None = None) -> list[int]:
        """The steps `recarry(obj, step)` would re-carry: the later steps whose pose of object `obj` was carried
        (directly or through other carried steps) from `step` (default the current one) and not set by hand since,
        where the pose it was carried from has changed (or a step before it in the chain is re-carried). When the
        pose at `step` is itself such a stale carried pose, the chain starts at its source and includes `step`."""
        return [t for t, _ in self._recarry_plan(self._check_obj(obj), self._step(step))]

    def recarry(self, obj: int, step: int | None = None) -> list[int]:
        """Carry object `obj` again, from its fixed pose, to the steps `stale_steps` lists, exactly as visiting
        each step did (keep it when the fit holds, else snap, search along the push, search the unexplained cloud),
        in step order, each from its (re-carried) source. One undoable action; the other objects and every pose
        set by hand stay as they are. Returns the re-carried steps ([] when nothing is stale)."""
        self._writable()
        obj = self._check_obj(obj)
        plan = self._recarry_plan(obj, self._step(step))
        if not plan:
            return []
        redone: dict[int, tuple] = {}
        changes = {}
        for t, source in plan:
            if source in redone:
                pose, status, score = redone[source]
            else:
                pose, status, score = self.state.pose(source, obj), str(self.state.status[source, obj]), None
            done, _ = self._carry_objects(t, {obj: (source, pose, score, status)})
            changes.update(done)
            new_pose, new_status, new_score = done[(t, obj)][:3]
            redone[t] = (np.asarray(new_pose, dtype=np.float64), new_status, _nan_score(new_score))
        self._commit("recarry", changes)
        return [t for t, _ in plan]

    def to_check(self) -> list[tuple[int, int, str]]:
        """(step, object, why) of every object at a visited step that needs a look, in step then object order:
        'unset', 'unchecked' (initialised), 'poor fit' (its last score failed the fit checks; confirmed poses are
        the user's call and are left out), 'carried from a changed pose' (`is_stale`, or carried from such a
        step) or 'interpenetrates object k' (with another object's pose as it is now, which may have changed since
        this object's score was taken)."""
        out = []
        stale = [self._stale_all(i) for i in range(self.num_objects)]
        for t in range(self.num_steps + 1):
            if not self.state.visited[t]:
                continue
            inside = self._interpenetrating(t)
            for i in range(self.num_objects):
                status, score = str(self.state.status[t, i]), self.state.scores[t][i]
                if status == "unset":
                    out.append((t, i, "unset"))
                elif status == "initialised":
                    out.append((t, i, "unchecked"))
                elif status != "confirmed" and score is not None and not score.get("accepted", True):
                    out.append((t, i, "poor fit"))
                elif status != "confirmed" and t in stale[i]:
                    out.append((t, i, "carried from a changed pose"))
                elif status != "confirmed" and i in inside:
                    out.append((t, i, f"interpenetrates object {inside[i] + 1}"))
        return out

    def _interpenetrating(self, step: int) -> dict[int, int]:
        """{object: another object it interpenetrates by more than align.PENETRATION_TOLERANCE} at a step, from
        the poses as they are now (geometry only: cheap enough to run on every look)."""
        posed = [(k, pose_to_matrix(p)) for k in range(self.num_objects) if (p := self.state.pose(step, k)) is not None]
        out: dict[int, int] = {}
        for x, (a, ta) in enumerate(posed):
            for b, tb in posed[x + 1:]:
                if align.penetration_depth(self.samples(a), ta, self.samples(b), tb) > align.PENETRATION_TOLERANCE:
                    out.setdefault(a, b)
                    out.setdefault(b, a)
        return out

    def _stale_all(self, obj: int) -> set[int]:
        """Steps whose pose of object `obj` is stale or carried (through carried steps) from a stale one."""
        affected: set[int] = set()
        for t in range(1, self.num_steps + 1):
            rec = self.carried_from(obj, t)
            if rec is not None and (rec[0] in affected or self.is_stale(obj, t)):
                affected.add(t)
        return affected

    def next_to_check(self) -> tuple[int, int, str] | None:
        """The first entry of `to_check` after the current step and selected object (wrapping around; the
        selected object itself comes last), or None when nothing at a visited step needs a look."""
        todo = self.to_check()
        if not todo:
            return None
        here = (self.state.step, self.state.selected)
        return next((e for e in todo if (e[0], e[1]) > here), todo[0])

    def _near_push(self, obj: int, pose: np.ndarray, source: int, step: int) -> bool:
        """Whether the pusher passed within its radius + PUSH_CONTACT_MARGIN of the object (xy) between steps."""
        pts, _ = align.posed_samples(self.samples(obj), pose_to_matrix(pose))
        pts = pts[:, :2]
        for a, b in self.capture.pushes_world[source:step, :, :2]:
            ab = b - a
            u = np.clip(((pts - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
            d = np.linalg.norm(pts - (a + u[:, None] * ab), axis=1)
            if d.min() < RIG_PUSHER_RADIUS + PUSH_CONTACT_MARGIN:
                return True
        return False

    def _carry(self, obj: int, source: int, step: int, pose: np.ndarray, before: FitScore | None = None,
               src_status: str | None = None, others: list[tuple[int, np.ndarray]] | None = None
               ) -> tuple[np.ndarray, str, FitScore, bool]:
        """(pose, status, score, moved) of an object carried from `source` to `step`; `before` / `src_status`: the
        source's score and status (default: scored now against the source's other objects, and the state's status);
        `others`: (object, pose) of the other objects at `step` (default: the state's). Coverage counts only the
        surface no other object hides, at both steps, so an object that another one moved in front of keeps its
        coverage; a pose that fails a physical check is not accepted."""
        before = before or self._fit(obj, source, pose)
        carried = self._fit(obj, step, pose, others)
        src_status = str(self.state.status[source, obj]) if src_status is None else src_status
        checked = src_status in ("snapped", "confirmed")
        rmse_before = before.rmse if np.isfinite(before.rmse) else 0.0
        dropped = (not carried.accepted or carried.coverage < before.coverage - MOVED_COVERAGE_DROP
                   or not np.isfinite(carried.rmse) or carried.rmse > rmse_before + MOVED_RMSE_RISE)
        if not dropped and not self._near_push(obj, pose, source, step):
            return pose, ("snapped" if checked else "initialised"), carried, False
        start = pose_to_matrix(pose)
        result = self._icp(obj, step, start, others=others)

        def good(r: align.IcpResult) -> bool:  # accepted, and about as well covered as at the source step
            return r.applied and r.score.accepted and r.score.coverage >= before.coverage - MOVED_COVERAGE_DROP

        if not dropped:
            # near the push but the fit did not change: keep the carried pose unless a good ICP fit clearly moves it
            moved_t, moved_r = align.pose_delta(start, result.transform)
            if not good(result) or (moved_t < MIN_SNAP_CHANGE[0] and moved_r < MIN_SNAP_CHANGE[1]):
                return pose, ("snapped" if checked else "initialised"), carried, False
            return matrix_to_pose(result.transform), "snapped", result.score, True
        if not good(result):
            searched = self._search(obj, source, step, start, others)
            if searched is not None and (not result.applied or _rank(searched.score) > _rank(result.score)):
                result = searched
        if good(result):
            return matrix_to_pose(result.transform), "snapped", result.score, True
        if result.applied and _rank(result.score) > _rank(carried):
            return matrix_to_pose(result.transform), "initialised", result.score, True
        carried.reason = f"moved, not snapped: {result.score.reason}"
        return pose, "initialised", carried, False

    def _search(self, obj: int, source: int, step: int, start: np.ndarray,
                others: list[tuple[int, np.ndarray]] | None = None) -> align.IcpResult | None:
        """Best kept ICP result from start poses along the push direction (the pushes between `source` and
        `step`, `capture.pushes_world`), sideways and turned about z; `others`: (object, pose) of the other objects
        at `step` (occluders, and the physical checks: the best physically valid fit wins)."""
        pushes = self.capture.pushes_world[source:step]
        samples = self.samples(obj)
        vec = pushes[-1, 1, :2] - pushes[-1, 0, :2]
        length = float(np.linalg.norm(vec))
        direction = vec / length if length > 1e-6 else np.array([1.0, 0.0])
        side = np.array([-direction[1], direction[0]])
        reach = float(sum(np.linalg.norm(p[1, :2] - p[0, :2]) for p in pushes)) + 0.03
        wide = self._crop(step, start, samples, extra=reach)
        if len(wide) < align.MIN_CORRESPONDENCES:
            return None
        from scipy.spatial import cKDTree

        tree = cKDTree(wide)
        views, checks = self._context(obj, step, others)
        centre = start[:3, :3] @ samples.centre + start[:3, 3]
        starts, turns = [], []
        for along in np.arange(0.0, reach + 1e-9, SEARCH_STEP):
            for lateral in SEARCH_LATERAL:
                for yaw in SEARCH_YAWS:
                    rz = align.rotvec_to_matrix(np.array([0.0, 0.0, yaw]))
                    cand = np.eye(4)
                    cand[:3, :3] = rz @ start[:3, :3]
                    shift = np.zeros(3)
                    shift[:2] = along * direction + lateral * side
                    cand[:3, 3] = rz @ (start[:3, 3] - centre) + centre + shift
                    starts.append(cand)
                    turns.append(abs(yaw))
        # among equally good fits prefer the least turn: a symmetric object's turned twin fits as well but would
        # give the wrong motion (flow)
        best_starts = _best_starts(samples, np.stack(starts), TURN_PENALTY * np.asarray(turns) / np.pi, tree, views)
        best, best_rank = None, -np.inf
        for k in best_starts:
            cand = starts[k]
            result = align.icp(samples, self._crop(step, cand, samples), cand, views, **checks)
            rank = _rank(result.score) - TURN_PENALTY * align.pose_delta(start, result.transform)[1] / np.pi
            if result.applied and rank > best_rank:
                best, best_rank = result, rank
        return best

    def _land(self, obj: int, source: int, step: int, pose: np.ndarray, others: list[tuple[int, np.ndarray]],
              before: FitScore | None = None) -> tuple[np.ndarray, FitScore] | None:
        """(pose, score) of an object that left its place (its carried pose lost MOVED_COVERAGE_DROP of its
        coverage) found by `_search_landed` with a good fit (accepted, about as well covered as at `source`), or
        None. `others`: (object, pose) of the other objects at `step`; `before`: the source's score (default the
        state's)."""
        before = before or self._fit(obj, source, pose)
        carried = self._fit(obj, step, pose, others)
        if carried.coverage >= before.coverage - MOVED_COVERAGE_DROP:
            return None  # still (partly) where it was: not free to go looking elsewhere
        result = self._search_landed(obj, step, pose_to_matrix(pose), others)
        if result is None or not (result.applied and result.score.accepted
                                  and result.score.coverage >= before.coverage - MOVED_COVERAGE_DROP):
            return None
        return matrix_to_pose(result.transform), result.score

    def _search_landed(self, obj: int, step: int, start: np.ndarray,
                       others: list[tuple[int, np.ndarray]]) -> align.IcpResult | None:
        """Best kept ICP result from start poses over the step's unexplained surface: cloud points above the table
        farther than EXPLAINED_DISTANCE from every other object's surface at its pose (`others`: (object, pose)),
        binned in SEARCH_STEP cells (at least LANDING_MIN_POINTS points); the object's centre goes over each cell
        at its carried height, turned about the vertical by SEARCH_YAWS. Finds an object wherever it went (a can
        lying on its side rolls on across the push); ties go to the least turn, then to the nearest."""
        from scipy.spatial import cKDTree

        above = self.cloud(step)[0]
        above = points = above[above[:, 2] > align.TABLE_MARGIN]
        if others and len(points):
            surfaces = np.vstack([align.posed_samples(self.samples(k), pose_to_matrix(p))[0] for k, p in others])
            d, _ = cKDTree(surfaces).query(points, distance_upper_bound=EXPLAINED_DISTANCE)
            points = points[~np.isfinite(d)]
        if len(points) < align.MIN_CORRESPONDENCES:
            return None
        cells, counts = np.unique(np.floor(points[:, :2] / SEARCH_STEP).astype(np.int64), axis=0, return_counts=True)
        cells = cells[counts >= LANDING_MIN_POINTS]
        if len(cells) == 0:
            return None
        samples = self.samples(obj)
        centre = start[:3, :3] @ samples.centre + start[:3, 3]
        xy = (cells + 0.5) * SEARCH_STEP
        starts, penalties = [], []
        for yaw in SEARCH_YAWS:
            rot = align.rotvec_to_matrix(np.array([0.0, 0.0, yaw])) @ start[:3, :3]
            for x, y in xy:
                cand = np.eye(4)
                cand[:3, :3] = rot
                cand[:3, 3] = np.array([x, y, centre[2]]) - rot @ samples.centre
                starts.append(cand)
                penalties.append(TURN_PENALTY * abs(yaw) / np.pi + DISTANCE_PENALTY * np.hypot(x - centre[0],
                                                                                               y - centre[1]))
        tree = cKDTree(above)
        views, checks = self._context(obj, step, others)
        best, best_rank = None, -np.inf
        for k in _best_starts(samples, np.stack(starts), np.asarray(penalties), tree, views):
            result = align.icp(samples, self._crop(step, starts[k], samples), starts[k], views, **checks)
            moved_t, turned = align.pose_delta(start, result.transform)
            rank = _rank(result.score) - TURN_PENALTY * turned / np.pi - DISTANCE_PENALTY * moved_t
            if result.applied and rank > best_rank:
                best, best_rank = result, rank
        return best

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
        above = np.flatnonzero(points[:, 2] > align.TABLE_MARGIN)  # the table's points stay grey: not queried
        d = np.full(len(points), np.inf)
        if surfaces:
            d[above] = cKDTree(np.vstack(surfaces)).query(points[above], distance_upper_bound=2 * max_residual)[0]
        near = np.isfinite(d)
        out[near] = residual_ramp(d[near] / max_residual)
        out[~near & (points[:, 2] > RESIDUAL_FLOOR)] = residual_ramp(np.ones(1))
        return out

    def progress(self) -> dict:
        """Per step and object: status and last fit score; steps done; action counts (JSON-able)."""
        steps = []
        for s in range(self.num_steps + 1):
            objs = [{"status": str(self.state.status[s, i]), "score": self.state.scores[s][i]}
                    for i in range(self.num_objects)]
            done = all(o["status"] in ("snapped", "confirmed") for o in objs)
            steps.append({"step": s, "visited": bool(self.state.visited[s]), "done": done, "objects": objs})
        return {"capture": self.capture.name, "num_steps": self.num_steps, "num_objects": self.num_objects,
                "current_step": self.step, "steps_done": sum(s["done"] for s in steps), "steps": steps,
                "action_counts": self.action_counts}

    def progress_table(self) -> str:
        """The progress as a text table: one row per step, one column per object (status, coverage, RMSE)."""
        p = self.progress()
        head = (f"capture {p['capture']}: {p['num_steps'] + 1} steps x {p['num_objects']} objects, "
                f"{p['steps_done']}/{p['num_steps'] + 1} steps done, current step {p['current_step']}")
        names = [f"{i + 1} {o.name}" for i, o in enumerate(self.capture.objects)]  # numbered from 1, as the panel
        width = 24
        lines = [head, "step  " + "".join(f"{n[:width - 2]:<{width}}" for n in names)]
        for s in p["steps"]:
            cells = []
            for o in s["objects"]:
                sc = o["score"]
                text = o["status"]
                if sc is not None and o["status"] != "unset":
                    rmse = sc.get("rmse")
                    text += f" {sc.get('coverage', 0):.0%}"
                    text += f" {rmse * 1000:.1f}mm" if isinstance(rmse, (int, float)) else " -"
                cells.append(f"{text:<{width}}")
            mark = ">" if s["step"] == p["current_step"] else " "
            lines.append(f"{mark}{s['step']:<4} " + "".join(cells))
        counts = ", ".join(f"{k} {v}" for k, v in p["action_counts"].items() if v)
        lines.append(f"actions: {counts or 'none'}")
        return "\n".join(lines)

    def unchecked(self) -> list[tuple[int, int, str]]:
        """(step, object, status) of every object not yet 'snapped' or 'confirmed'."""
        return [(s, i, str(self.state.status[s, i])) for s in range(self.num_steps + 1) for i in range(self.num_objects)
                if self.state.status[s, i] not in ("snapped", "confirmed")]

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
        from annotator.export import export_sequence

        return export_sequence(self, out, allow_unchecked=allow_unchecked)
