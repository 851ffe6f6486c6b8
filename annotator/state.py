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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

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
    def from_json(cls, d: dict) -> Entry:
        return cls(None if d["pose"] is None else [float(x) for x in d["pose"]], str(d["status"]), d.get("score"),
                   _clean_carried(d.get("carried")))


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
    def from_json(cls, d: dict) -> Operation:
        cells = [(int(s), int(i), Entry.from_json(b), Entry.from_json(a)) for s, i, b, a in d["cells"]]
        return cls(str(d["kind"]), cells,
                   (int(d["cursor"][0]), int(d["cursor"][1])), [(int(s), bool(b), bool(a)) for s, b, a in d["visited"]])


def _clean_carried(carried) -> dict | None:
    """A carried-from record {"step": int, "pose": [7 floats]} (None stays None)."""
    if carried is None:
        return None
    pose = [float(x) for x in carried["pose"]]
    if len(pose) != 7 or not all(math.isfinite(x) for x in pose):
        raise StateError("a carried-from record's pose must be 7 finite numbers")
    return {"step": int(carried["step"]), "pose": pose}


def _clean_score(score: dict | None) -> dict | None:
    """A score dict with NaN floats as None (JSON has no NaN)."""
    if score is None:
        return None
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in score.items()}


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
        return Entry(None if np.isnan(pose).any() else [float(x) for x in pose], str(self.status[step, obj]),
                     None if self.scores[step][obj] is None else dict(self.scores[step][obj]),
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
        """Re-apply one journal record (`record`); raises StateError when it cannot apply to this state."""
        try:
            kind = record["kind"]
            if kind == "apply":
                op = Operation.from_json(record["op"])
                t1 = self.num_steps + 1
                if any(not (0 <= s < t1 and 0 <= i < self.num_objects) for s, i, _, _ in op.cells) \
                        or any(not 0 <= s < t1 for s, _, _ in op.visited) or not 0 <= op.cursor[1] < t1:
                    raise StateError("journal: an operation outside this capture's steps and objects")
                self.apply(op)
            elif kind in ("undo", "redo") and (self.undo() if kind == "undo" else self.redo()) is None:
                raise StateError(f"journal: nothing to {kind}")
            elif kind not in RECORD_KINDS:
                raise StateError(f"journal: unknown record {kind!r}")
            step, selected = int(record["step"]), int(record["selected"])
            if not (0 <= step <= self.num_steps and 0 <= selected < self.num_objects):
                raise StateError(f"journal: step {step} or object {selected + 1} out of range")
            self.step, self.selected = step, selected
            self.counts.update({str(k): int(v) for k, v in record["counts"].items()})
        except StateError:
            raise
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            raise StateError(f"journal: malformed record ({type(exc).__name__}: {exc})") from None

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
            state = cls(str(d["capture"]), int(d["num_steps"]), int(d["num_objects"]))
            t1, n = state.num_steps + 1, state.num_objects
            if len(d["poses"]) != t1 or any(len(r) != n for r in d["poses"]) or len(d["status"]) != t1 \
                    or any(len(r) != n for r in d["status"]) or len(d["visited"]) != t1 or len(d["scores"]) != t1:
                raise StateError(f"poses/status/visited do not have {t1} steps x {n} objects")
            for s in range(t1):
                for i in range(n):
                    pose, status = d["poses"][s][i], d["status"][s][i]
                    if status not in STATUSES:
                        raise StateError(f"step {s} object {i + 1}: unknown status {status!r}")
                    if pose is not None:
                        pose = np.asarray(pose, dtype=np.float64)
                        if pose.shape != (7,) or not np.all(np.isfinite(pose)):
                            raise StateError(f"step {s} object {i + 1}: pose must be 7 finite numbers or null")
                        state.poses[s, i] = pose
                    state.status[s, i] = status
                    state.scores[s][i] = d["scores"][s][i]
                    # absent in states written before carried-from records: every pose then counts as set by hand
                    carried = d.get("carried")
                    state.carried[s][i] = None if carried is None else _clean_carried(carried[s][i])
            state.visited = [bool(v) for v in d["visited"]]
            state.step = int(d["step"])
            state.selected = int(d["selected"])
            if not (0 <= state.step < t1 and 0 <= state.selected < n):
                raise StateError(f"current step {state.step} or selected object {state.selected + 1} out of range")
            state.counts.update({str(k): int(v) for k, v in d.get("counts", {}).items()})
            state.undo_stack = [Operation.from_json(o) for o in d.get("undo", [])]
            state.redo_stack = [Operation.from_json(o) for o in d.get("redo", [])]
        except StateError:
            raise
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise StateError(f"malformed state ({type(exc).__name__}: {exc})") from None
        return state
