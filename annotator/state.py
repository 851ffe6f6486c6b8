"""The annotation state of one capture, and its undoable operations (pure Python + numpy, no I/O).

State: the pose (7,) = (x, y, z, qx, qy, qz, qw) in metres of every object at every step (NaN rows where unset), a
status per step and object ("unset" | "initialised" | "snapped" | "confirmed"), the last fit score of each, where
each pose was carried from (`carried`: {"step": s, "pose": the source pose it was carried from}, or None for a pose
set by hand), which steps were visited, the current step and selected object, undo / redo stacks and user action counts.

Every mutation is an `Operation` holding, for each (step, object) it touches, the entry before and after, plus the
cursor (current step) and visited flags before and after; undo applies the "before" side, redo the "after" side,
so both are exact. `to_dict` / `from_dict` give a JSON-able dict (poses as lists, NaN rows as null).

Journal records (`record` / `replay`): one JSON-able dict per change ("apply" with the operation, "undo", "redo",
"select", "cursor"), each with the cursor, selection and action counts after it; replaying a state's records in
order on the state they started from gives that state exactly (the session appends them to its journal file).

Everything read back (`from_dict`, `replay`) is checked as a file someone else may have written: types (an integer
is not true, a number not a string), ranges, poses of 7 finite numbers with a nonzero quaternion (`read_pose`),
statuses that agree with the pose (unset <-> no pose), and, for a replayed operation, that its "before" side is this
state's own; anything else is a StateError naming the cell or field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, TypeGuard

import numpy as np

STATE_FORMAT = "dsr-bench-annotation"
STATE_VERSION = 1
STATUSES: tuple[str, ...] = ("unset", "initialised", "snapped", "confirmed")
#: User action kinds counted by the session.
ACTION_KINDS: tuple[str, ...] = ("pick", "place", "previous", "nudge", "snap", "confirm", "step", "recarry", "undo",
                                 "redo")
#: Undo history kept (oldest operations are dropped beyond this).
MAX_HISTORY = 2000
#: Journal record kinds: a new operation, undo, redo, a selection, a cursor move to a visited step.
RECORD_KINDS: tuple[str, ...] = ("apply", "undo", "redo", "select", "cursor")
#: Kinds of the undoable operations (the actions that change poses or steps).
OPERATION_KINDS: tuple[str, ...] = tuple(k for k in ACTION_KINDS if k not in ("undo", "redo"))


class StateError(ValueError):
    """A state dict that cannot be loaded (wrong format, version or shapes)."""


@dataclass
class Entry:
    """One (step, object) cell: pose (7,) or None when unset, status, last fit score (dict) or None, and where the
    pose was carried from ({"step": s, "pose": [7 floats]}) or None when it was set by hand (or is unset)."""

    pose: list[float] | None
    status: str
    score: dict | None
    carried: dict | None = None

    def as_json(self) -> dict:
        out = {"pose": self.pose, "status": self.status, "score": self.score}
        if self.carried is not None:  # absent for hand-set poses (and in states written before it existed)
            out["carried"] = self.carried
        return out

    @classmethod
    def from_json(cls, d: Any, what: str = "a cell") -> Entry:
        """An entry read from a file, every field checked (`read_pose`, `read_score`); StateError naming `what`."""
        if not isinstance(d, dict) or "pose" not in d or "status" not in d:
            raise StateError(f"{what} must be an object with pose, status and score")
        status = d["status"]
        if not isinstance(status, str) or status not in STATUSES:
            raise StateError(f"{what}: unknown status {status!r} (one of {', '.join(STATUSES)})")
        pose = read_pose(d["pose"], f"{what} pose")
        if (pose is None) != (status == "unset"):
            raise StateError(f"{what}: status {status!r} with {'no pose' if pose is None else 'a pose'}")
        return cls(pose, status, read_score(d.get("score"), f"{what} score"), read_carried(d.get("carried"), what))


@dataclass
class Operation:
    """One undoable user action: changed cells (step, obj, before, after), cursor and visited flags before/after."""

    kind: str
    cells: list[tuple[int, int, Entry, Entry]] = field(default_factory=list)
    cursor: tuple[int, int] = (0, 0)
    visited: list[tuple[int, bool, bool]] = field(default_factory=list)

    def as_json(self) -> dict:
        return {"kind": self.kind, "cursor": list(self.cursor),
                "cells": [[s, i, b.as_json(), a.as_json()] for s, i, b, a in self.cells],
                "visited": [[s, b, a] for s, b, a in self.visited]}

    @classmethod
    def from_json(cls, d: Any) -> Operation:
        """An operation read from a file, every field's type checked (ranges: `AnnotationState.replay` and
        `from_dict`); StateError naming what is wrong."""
        if not isinstance(d, dict) or not all(k in d for k in ("kind", "cursor", "cells", "visited")):
            raise StateError("an operation must be an object with kind, cursor, cells and visited")
        if d["kind"] not in OPERATION_KINDS:
            raise StateError(f"unknown operation kind {d['kind']!r}")
        cursor, cells, visited = d["cursor"], d["cells"], d["visited"]
        if not (isinstance(cursor, list) and len(cursor) == 2 and all(_is_int(c) for c in cursor)):
            raise StateError(f"operation cursor {cursor!r} must be [step before, step after] (integers)")
        if not isinstance(cells, list) or not all(isinstance(c, list) and len(c) == 4 and _is_int(c[0])
                                                  and _is_int(c[1]) for c in cells):
            raise StateError("operation cells must be [step, object, before, after] with integer step and object")
        if not isinstance(visited, list) or not all(isinstance(v, list) and len(v) == 3 and _is_int(v[0])
                                                    and isinstance(v[1], bool) and isinstance(v[2], bool)
                                                    for v in visited):
            raise StateError("operation visited flags must be [step, before, after] (integer, true/false, true/false)")
        out = [(s, i, Entry.from_json(b, f"step {s} object {i + 1} before"),
                Entry.from_json(a, f"step {s} object {i + 1} after")) for s, i, b, a in cells]
        return cls(d["kind"], out, (cursor[0], cursor[1]), [(s, b, a) for s, b, a in visited])


def _clean_carried(carried) -> dict | None:
    """A carried-from record {"step": int, "pose": [7 floats]} (None stays None)."""
    if carried is None:
        return None
    pose = [float(x) for x in carried["pose"]]
    if len(pose) != 7 or not all(math.isfinite(x) for x in pose):
        raise StateError("a carried-from record's pose must be 7 finite numbers")
    return {"step": int(carried["step"]), "pose": pose}


def _is_int(value) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def read_pose(value, what: str) -> list[float] | None:
    """A pose read from a file: null (unset) or 7 finite numbers (x, y, z, qx, qy, qz, qw) with a nonzero
    quaternion; StateError naming `what` otherwise (a NaN or infinite pose never enters a state)."""
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != 7 or not all(_is_number(x) for x in value):
        raise StateError(f"{what} must be null or 7 numbers (x, y, z, qx, qy, qz, qw), got {str(value)[:80]}")
    try:
        pose = [float(x) for x in value]
    except OverflowError:
        pose = [math.inf]
    if not all(math.isfinite(x) for x in pose):
        raise StateError(f"{what} {str(value)[:80]} is not finite (a pose is 7 finite numbers)")
    if math.hypot(*pose[3:]) < 1e-6:
        raise StateError(f"{what} has a zero quaternion (no rotation)")
    return pose


def read_score(value, what: str) -> dict | None:
    """A fit score read from a file (`annotator.align.FitScore.as_dict`, NaN as null): null or an object of plain
    values (null, true/false, numbers, strings) whose rmse, coverage and fitness, where given, are numbers or null;
    StateError naming `what` otherwise."""
    if value is None:
        return None
    ok = isinstance(value, dict) and all(isinstance(k, str) and (v is None or isinstance(v, (bool, int, float, str)))
                                         for k, v in value.items()) \
        and all(value.get(k) is None or _is_number(value[k]) for k in ("rmse", "coverage", "fitness"))
    if not ok:
        raise StateError(f"{what} must be null or a fit score {{rmse, coverage, fitness, accepted, reason, visible}}")
    return dict(value)


def read_carried(value, what: str) -> dict | None:
    """A carried-from record read from a file: null or {"step": integer, "pose": 7 finite numbers}."""
    if value is None:
        return None
    if not isinstance(value, dict) or not _is_int(value.get("step")) or value.get("pose") is None:
        raise StateError(f"{what}: a carried-from record must be {{\"step\": s, \"pose\": [7 numbers]}} or null")
    return {"step": value["step"], "pose": read_pose(value["pose"], f"{what} carried-from pose")}


def _read_counts(value) -> dict[str, int]:
    """Action counts read from a file: {kind: integer >= 0}."""
    if not isinstance(value, dict) or not all(_is_int(v) and v >= 0 for v in value.values()):
        raise StateError(f"counts must map action kinds ({', '.join(ACTION_KINDS)}) to integers >= 0")
    return dict(value)


def _clean_score(score: dict | None) -> dict | None:
    """A score dict with NaN floats as None (JSON has no NaN)."""
    if score is None:
        return None
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in score.items()}


#: How an operation kind reads in "undone: ..." / "redone: ..." (the window's message).
_KIND_WORDS = {"pick": "placing by picked points", "place": "placing", "previous": "taking the previous step's pose",
               "nudge": "nudge", "snap": "snap", "confirm": "confirming", "step": "the visit of a new step",
               "recarry": "re-carry"}


def _numbers(values) -> str:
    values = sorted(set(values))
    return ", ".join(str(v) for v in values[:6]) + (" ..." if len(values) > 6 else "")


def _moved(before: list[float] | None, after: list[float] | None) -> str:
    """How far a pose moved: translation (mm) and rotation (degrees) between two poses (x, y, z, qx, qy, qz, qw)."""
    if before is None or after is None:
        return ""
    a, b = np.asarray(before, np.float64), np.asarray(after, np.float64)
    qa, qb = a[3:] / np.linalg.norm(a[3:]), b[3:] / np.linalg.norm(b[3:])
    angle = math.degrees(2.0 * math.acos(min(1.0, abs(float(qa @ qb)))))
    return f" ({float(np.linalg.norm(b[:3] - a[:3])) * 1000:.1f} mm, {angle:.1f} deg)"


def describe(op: Operation) -> str:
    """What an operation changed, in words, objects numbered from 1 as the window numbers them: "nudge of object 2 at
    step 3 (4.0 mm, 0.0 deg)", "the visit of a new step: step 4, carrying objects 1, 2, 3"."""
    words = _KIND_WORDS.get(op.kind, op.kind)
    objects = _numbers(i + 1 for _, i, _, _ in op.cells)
    steps = _numbers(st for st, _, _, _ in op.cells)
    if op.kind == "step":
        new = [st for st, _, after in op.visited if after] or [op.cursor[1]]
        return f"{words}: step {_numbers(new)}, carrying object{'s' if len(op.cells) != 1 else ''} {objects or '-'}"
    if not op.cells:
        return words
    plural_o = "s" if len({i for _, i, _, _ in op.cells}) > 1 else ""
    plural_s = "s" if len({st for st, _, _, _ in op.cells}) > 1 else ""
    moved = _moved(op.cells[0][2].pose, op.cells[0][3].pose) if len(op.cells) == 1 else ""
    status = ""
    if len(op.cells) == 1 and op.cells[0][2].status != op.cells[0][3].status:
        status = f", status {op.cells[0][2].status} <-> {op.cells[0][3].status}"
    return f"{words} of object{plural_o} {objects} at step{plural_s} {steps}{moved}{status}"


class AnnotationState:
    """Poses, statuses, scores and history of one capture with `num_steps` pushes (T + 1 steps) and N objects."""

    def __init__(self, capture: str, num_steps: int, num_objects: int):
        self.capture = capture
        self.num_steps = int(num_steps)
        self.num_objects = int(num_objects)
        shape = (self.num_steps + 1, self.num_objects)
        self.poses = np.full(shape + (7,), np.nan)
        self.status = np.full(shape, "unset", dtype=object)
        self.scores: list[list[dict | None]] = [[None] * self.num_objects for _ in range(self.num_steps + 1)]
        self.carried: list[list[dict | None]] = [[None] * self.num_objects for _ in range(self.num_steps + 1)]
        self.visited = [False] * (self.num_steps + 1)
        self.visited[0] = True
        self.step = 0
        self.selected = 0
        self.undo_stack: list[Operation] = []
        self.redo_stack: list[Operation] = []
        self.counts: dict[str, int] = {k: 0 for k in ACTION_KINDS}

    # cells --------------------------------------------------------------------------------------------------
    def entry(self, step: int, obj: int) -> Entry:
        pose = self.poses[step, obj]
        carried = self.carried[step][obj]
        score = self.scores[step][obj]
        return Entry(None if np.isnan(pose).any() else [float(x) for x in pose], str(self.status[step, obj]),
                     None if score is None else dict(score),
                     None if carried is None else {"step": carried["step"], "pose": list(carried["pose"])})

    def _set(self, step: int, obj: int, entry: Entry) -> None:
        self.poses[step, obj] = np.nan if entry.pose is None else np.asarray(entry.pose, dtype=np.float64)
        self.status[step, obj] = entry.status
        self.scores[step][obj] = None if entry.score is None else dict(entry.score)
        self.carried[step][obj] = None if entry.carried is None else dict(entry.carried)

    def pose(self, step: int, obj: int) -> np.ndarray | None:
        """Pose (7,) of an object at a step, or None while unset."""
        p = self.poses[step, obj]
        return None if np.isnan(p).any() else p.copy()

    # operations -----------------------------------------------------------------------------------------------
    def operation(self, kind: str, changes: dict[tuple[int, int], tuple], cursor: int | None = None,
                  visit: list[int] | None = None) -> Operation:
        """Build (without applying) an operation that sets cells {(step, obj): (pose, status, score[, carried])},
        moves the cursor to `cursor` (default: stays) and marks the steps in `visit` as visited. `carried`: the
        carried-from record (step, source pose) of a pose carried forward; left out (None) for a pose set by hand."""
        cells = []
        for (step, obj), change in sorted(changes.items()):
            pose, status, score = change[:3]
            carried = change[3] if len(change) > 3 else None
            if status not in STATUSES:
                raise ValueError(f"unknown status {status!r}")
            if carried is not None:
                carried = _clean_carried({"step": carried[0], "pose": np.asarray(carried[1], dtype=np.float64)}
                                         if isinstance(carried, tuple) else carried)
            after = Entry(None if pose is None else [float(x) for x in np.asarray(pose, dtype=np.float64)], status,
                          _clean_score(score), carried)
            cells.append((step, obj, self.entry(step, obj), after))
        visited = [(s, self.visited[s], True) for s in (visit or [])]
        return Operation(kind, cells, (self.step, self.step if cursor is None else int(cursor)), visited)

    def _apply(self, op: Operation, side: str) -> None:
        after = side == "after"
        for step, obj, before, aft in op.cells:
            self._set(step, obj, aft if after else before)
        for step, was, now in op.visited:
            self.visited[step] = now if after else was
        self.step = op.cursor[1] if after else op.cursor[0]

    def apply(self, op: Operation) -> None:
        """Apply a new operation: it becomes the latest undo entry and the redo stack is cleared."""
        self._apply(op, "after")
        self.undo_stack.append(op)
        del self.undo_stack[:-MAX_HISTORY]
        self.redo_stack.clear()

    def undo(self) -> Operation | None:
        """Revert the latest operation exactly; None if there is nothing to undo."""
        if not self.undo_stack:
            return None
        op = self.undo_stack.pop()
        self._apply(op, "before")
        self.redo_stack.append(op)
        return op

    def redo(self) -> Operation | None:
        """Re-apply the latest undone operation; None if there is nothing to redo."""
        if not self.redo_stack:
            return None
        op = self.redo_stack.pop()
        self._apply(op, "after")
        self.undo_stack.append(op)
        return op

    def count(self, kind: str) -> None:
        """Count one user action of a kind (see ACTION_KINDS)."""
        self.counts[kind] = self.counts.get(kind, 0) + 1

    # journal records ------------------------------------------------------------------------------------------
    def record(self, kind: str, op: Operation | None = None) -> dict[str, Any]:
        """The journal record (JSON-able) of a change just made: `kind` (RECORD_KINDS), the operation of "apply",
        and the cursor, selection and action counts after the change."""
        if kind not in RECORD_KINDS or (kind == "apply") != (op is not None):
            raise ValueError(f"bad journal record {kind!r}")
        out: dict[str, Any] = {"kind": kind, "step": self.step, "selected": self.selected, "counts": dict(self.counts)}
        if op is not None:
            out["op"] = op.as_json()
        return out

    def replay(self, record: Any) -> None:
        """Re-apply one journal record (`record`); raises StateError (naming what is wrong) when it is malformed or
        cannot apply to this state: every field is checked (types, ranges, finite poses), and an operation's
        "before" side (poses, statuses, visited flags, cursor) must be this state's own, so a record written on
        another state (another capture's journal) does not apply."""
        try:
            if not isinstance(record, dict) or record.get("kind") not in RECORD_KINDS:
                raise StateError(f"unknown record kind {record.get('kind') if isinstance(record, dict) else record!r}"
                                 f" (one of {', '.join(RECORD_KINDS)})")
            kind = record["kind"]
            step, selected, counts = record.get("step"), record.get("selected"), record.get("counts")
            if not (_is_int(step) and _is_int(selected) and 0 <= step <= self.num_steps
                    and 0 <= selected < self.num_objects):
                raise StateError(f"step {step!r} or selected object {selected!r} is not in this capture's steps "
                                 f"0..{self.num_steps} and objects 0..{self.num_objects - 1}")
            counts = _read_counts(counts)
            if kind == "apply":
                op = Operation.from_json(record.get("op"))
                self._check_applies(op)
                self.apply(op)
            elif kind in ("undo", "redo") and (self.undo() if kind == "undo" else self.redo()) is None:
                raise StateError(f"nothing to {kind}")
            self.step, self.selected = step, selected
            self.counts.update(counts)
        except StateError as exc:
            raise StateError(f"journal: {exc}") from None
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            raise StateError(f"journal: malformed record ({type(exc).__name__}: {exc})") from None

    def _check_inside(self, op: Operation) -> Operation:
        """`op`, or StateError unless it stays inside this capture's steps and objects."""
        t1 = self.num_steps + 1
        if any(not (0 <= s < t1 and 0 <= i < self.num_objects) for s, i, _, _ in op.cells) \
                or any(not 0 <= s < t1 for s, _, _ in op.visited) or not all(0 <= c < t1 for c in op.cursor):
            raise StateError("an operation outside this capture's steps and objects")
        return op

    def _check_applies(self, op: Operation) -> None:
        """StateError unless `op` stays inside this capture's steps and objects and starts from this state."""
        self._check_inside(op)
        for s, i, before, _ in op.cells:
            here = self.entry(s, i)
            if (before.pose, before.status) != (here.pose, here.status):
                raise StateError(f"its {op.kind} of step {s} object {i + 1} starts from a {before.status} pose this "
                                 f"state does not hold (here: {here.status}): the record was written on another state")
        if any(self.visited[s] != was for s, was, _ in op.visited) or op.cursor[0] != self.step:
            raise StateError(f"its {op.kind} starts from another cursor or visited steps than this state's: the "
                             "record was written on another state")

    # serialisation --------------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict of the whole state (including history)."""
        return {
            "format": STATE_FORMAT, "version": STATE_VERSION, "capture": self.capture,
            "num_steps": self.num_steps, "num_objects": self.num_objects,
            "poses": [[None if np.isnan(p).any() else [float(x) for x in p] for p in row] for row in self.poses],
            "status": [[str(s) for s in row] for row in self.status],
            "scores": [[_clean_score(s) for s in row] for row in self.scores],
            "carried": [[None if c is None else dict(c) for c in row] for row in self.carried],
            "visited": list(self.visited), "step": self.step, "selected": self.selected,
            "counts": dict(self.counts),
            "undo": [op.as_json() for op in self.undo_stack], "redo": [op.as_json() for op in self.redo_stack],
        }

    @classmethod
    def from_dict(cls, d: Any) -> AnnotationState:
        """Load a dict written by `to_dict`; raises StateError naming what is wrong."""
        if not isinstance(d, dict) or d.get("format") != STATE_FORMAT:
            raise StateError(f"not an annotation state (format must be {STATE_FORMAT!r})")
        if d.get("version") != STATE_VERSION:
            raise StateError(f"state version {d.get('version')!r}; this annotator reads version {STATE_VERSION}")
        try:
            capture, steps, objects, poses = d["capture"], d["num_steps"], d["num_objects"], d["poses"]
            if not (isinstance(capture, str) and _is_int(steps) and _is_int(objects) and steps >= 1 and objects >= 1):
                raise StateError("capture must be a name and num_steps, num_objects integers >= 1")
            t1, n = steps + 1, objects
            rows = [d[k] for k in ("poses", "status", "scores")] + ([] if d.get("carried") is None else [d["carried"]])
            if not all(isinstance(r, list) and len(r) == t1 and all(isinstance(c, list) and len(c) == n for c in r)
                       for r in rows) or not isinstance(d["visited"], list) or len(d["visited"]) != t1:
                raise StateError(f"poses/status/scores/visited do not have {t1} steps x {n} objects")
            state = cls(capture, steps, objects)  # its arrays are no larger than the lists just read
            carried = d.get("carried")  # absent in states written before carried-from records: all set by hand
            for s in range(t1):
                for i in range(n):
                    state._set(s, i, Entry.from_json({"pose": poses[s][i], "status": d["status"][s][i],
                                                      "score": d["scores"][s][i],
                                                      "carried": None if carried is None else carried[s][i]},
                                                     f"step {s} object {i + 1}"))
            if not all(isinstance(v, bool) for v in d["visited"]):
                raise StateError("visited must be true/false per step")
            state.visited = list(d["visited"])
            state.step, state.selected = d["step"], d["selected"]
            if not (_is_int(state.step) and _is_int(state.selected) and 0 <= state.step < t1
                    and 0 <= state.selected < n):
                raise StateError(f"current step {state.step!r} or selected object {state.selected!r} out of range")
            state.counts.update(_read_counts(d.get("counts", {})))
            state.undo_stack = [state._check_inside(Operation.from_json(o)) for o in d.get("undo", [])]
            state.redo_stack = [state._check_inside(Operation.from_json(o)) for o in d.get("redo", [])]
        except StateError:
            raise
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise StateError(f"malformed state ({type(exc).__name__}: {exc})") from None
        return state
