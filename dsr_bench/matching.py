"""Matching label volumes: the one-to-one matching of predicted slots with objects (Hungarian; scipy's exact
solver when installed, else enumeration), their overlap counts, and the mean IoU under a matching.

The benchmark's mask IoU (`dsr_bench.scoring.metrics`), the planning track's cost and scores, the trainer's and the
loss's slot matching and the viewer all match label volumes this one way; numpy only (scipy imported on use).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np


def assignment(score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the one-to-one matching maximising the total score (rectangular ok)."""
    try:
        from scipy.optimize import linear_sum_assignment
    except ImportError:  # e.g. a GPU box without scipy: exact enumeration, fine for a few slots
        return brute_force_assignment(score)
    rows, cols = linear_sum_assignment(score, maximize=True)
    return rows, cols


def brute_force_assignment(score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same matching by enumerating every injective map (reference for tests)."""
    flip = score.shape[0] > score.shape[1]
    s = score.T if flip else score
    best, best_cols = -np.inf, None
    for perm in itertools.permutations(range(s.shape[1]), s.shape[0]):
        total = s[np.arange(s.shape[0]), perm].sum()
        if total > best + 1e-12:
            best, best_cols = total, perm
    rows, cols = np.arange(s.shape[0]), np.array(best_cols, dtype=np.int64)
    if flip:
        rows, cols = cols, rows
        order = np.argsort(rows)
        rows, cols = rows[order], cols[order]
    return rows, cols


@dataclass(frozen=True)
class Overlap:
    """Intersections (S, N) between predicted slots 1..S and GT objects 1..N, and their sizes."""

    inter: np.ndarray
    pred_size: np.ndarray
    gt_size: np.ndarray

    @property
    def union(self) -> np.ndarray:
        return self.pred_size[:, None] + self.gt_size[None, :] - self.inter

    @property
    def iou(self) -> np.ndarray:
        return self.inter / np.maximum(self.union, 1)


def overlap(pred: np.ndarray, gt: np.ndarray, num_slots: int, num_objects: int) -> Overlap:
    """Slot x object intersection counts of two label volumes with one bincount over the voxels
    occupied in either (empty-empty voxels count towards nothing)."""
    g1 = num_objects + 1
    p, g = pred.reshape(-1), gt.reshape(-1)
    occupied = np.flatnonzero(p | g) if p.dtype == g.dtype == np.uint8 else np.flatnonzero((p > 0) | (g > 0))
    joint = np.bincount(p[occupied].astype(np.int64) * g1 + g[occupied].astype(np.int64),
                        minlength=(num_slots + 1) * g1).reshape(num_slots + 1, g1)
    return Overlap(joint[1:, 1:].astype(np.float64), joint[1:].sum(1).astype(np.float64),
                   joint[:, 1:].sum(0).astype(np.float64))


def matched_iou(ov: Overlap, rows: np.ndarray, cols: np.ndarray) -> tuple[float, np.ndarray]:
    """(Mean IoU over matched pairs and unmatched non-empty slots/objects, per-object IoU (N,)).

    Empty-empty pairs are not counted (the official code counts them as 0 when a scene has fewer
    objects than slots; with as many objects as slots the two agree)."""
    iou = ov.iou
    per_object = np.zeros(ov.gt_size.shape[0])
    per_object[cols] = iou[rows, cols]
    values = list(iou[rows, cols][ov.union[rows, cols] > 0])
    unmatched_slots = np.setdiff1d(np.arange(iou.shape[0]), rows)
    unmatched_objects = np.setdiff1d(np.arange(iou.shape[1]), cols)
    values += [0.0] * int((ov.pred_size[unmatched_slots] > 0).sum() + (ov.gt_size[unmatched_objects] > 0).sum())
    return (float(np.mean(values)) if values else 1.0), per_object


def official_iou(ov: Overlap, rows: np.ndarray | None = None, cols: np.ndarray | None = None) -> float:
    """The official code's IoU score: slots and objects padded to a square of max(S, N), best (or
    the given) matching, mean over all of its pairs, empty-empty pairs counting 0. Equals
    `matched_iou` when every slot and object is non-empty and S == N (the paper's 4 and 4)."""
    iou = ov.iou
    size = max(iou.shape)
    square = np.zeros((size, size))
    square[: iou.shape[0], : iou.shape[1]] = iou
    if rows is None or cols is None:
        rows, cols = assignment(square)
    return float(square[rows, cols].sum() / size) if size else 1.0
