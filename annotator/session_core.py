"""The session's state and its navigation: what a `annotator.session.Session` holds (capture, annotation state,
caches of clouds and surface samples), its persistence (every change appended to the journal before the call
returns, folded into state.json every COMPACT_RECORDS records: `annotator.journal`), its read-only views (step,
poses, statuses, clouds and the window's subset of them) and the checks of a step or object index.

`SessionCore` is the first of the Session's layers: `annotator.scoring` (fit scores and their checks),
`annotator.carry` (carrying poses to a new step and the searches), `annotator.review` (re-carrying after a fix, what
is left to check, progress) and `annotator.session` (opening, the user's actions, export) build on it.
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

import numpy as np

from dsr_bench.annotator import align
from dsr_bench.annotator.journal import STATE_FILE, JOURNAL_FILE, append_record, capture_digest, write_snapshot
from dsr_bench.annotator.state import ACTION_KINDS, AnnotationState
from dsr_bench.annotator.thresholds import THRESHOLDS, Thresholds
from dsr_bench.dataset.capture import Capture
from dsr_bench.errors import UserError

WORK_DIRNAME = "annotation"
# state.json and the change journal next to it (journal.jsonl: a header binding it to state.json and the capture,
# then one JSON record per change, each appended and fsync'd before the call returns): `annotator.journal`.
#: The journal is folded into state.json after this many records (and when a session resumes from it).
COMPACT_RECORDS = 500
#: Clouds kept in memory (steps).
CLOUD_CACHE = 4
#: The window draws a subset of a step's cloud (`Session.shown`): one point per cube of DISPLAY_VOXEL (m) above the
#: table (what a person aligns a mesh to: every surface still covered, at most a cube's diagonal, 3.5 mm, from a drawn
#: point) and per cube of DISPLAY_TABLE_VOXEL (m) on it (the table is there to orient). Fitting and scores use the
#: whole cloud.
DISPLAY_VOXEL = 0.002
DISPLAY_TABLE_VOXEL = 0.006


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


class SessionCore:
    """The state, caches and persistence of one capture being annotated (see the module docstring); a
    `annotator.session.Session` is made with `Session.open`. `limits`: the thresholds of its fit checks (default
    `annotator.thresholds.THRESHOLDS`); set them before scoring: the other objects' refinements cached for the
    shared shift are not recomputed when they change."""

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
        self.limits: Thresholds = THRESHOLDS  # the thresholds of the fit checks (`annotator.thresholds`)

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
            self._shown[step] = voxel_subset(points, DISPLAY_VOXEL, DISPLAY_TABLE_VOXEL, THRESHOLDS.table_margin)
        return self._shown[step]

    def _views(self, step: int) -> list[align.View]:
        self.cloud(step)
        return self._clouds[step][3]

    # step and object indices ------------------------------------------------------------------------------------------
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

    def _commit(self, kind: str, changes: dict, cursor: int | None = None, visit: list[int] | None = None) -> None:
        """Apply one undoable operation setting cells {(step, obj): (pose, status, score[, carried])} and save it."""
        self._writable()
        op = self.state.operation(kind, changes, cursor=cursor, visit=visit)
        self.state.apply(op)
        self.state.count(kind)
        self._save("apply", op)
