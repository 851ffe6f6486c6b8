"""The paper's cost of a predicted next state against the target (Sec. 3.1):

    cost = sum over target objects i of (lambda * L_pos_i - IoU_i)

L_pos_i: the mean over (x, y, z) of the squared difference (cm^2) between the centroid of the predicted slot
matched to object i and the centroid of object i in the target (centroids of the voxels' indices, 0.4 cm per
voxel); IoU_i: the voxel IoU of that slot and that object. Matching: the Hungarian assignment maximising
IoU (`dsr_bench.scoring.metrics.assignment`, as the benchmark's mask IoU), ties (no overlap at all) broken by
centroid distance (`MATCH_TIE_BREAK`). An object left without a non-empty slot scores IoU 0 and
`UNMATCHED_POSITION_MSE`. lambda: `COST_LAMBDA` (0.1 per cm^2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dsr_bench import matching
from dsr_bench.constants import VOXEL_SIZE
from dsr_bench.matching import Overlap, assignment, overlap
from dsr_bench.planning.protocol import COST_LAMBDA, MATCH_TIE_BREAK, UNMATCHED_POSITION_MSE

_CM_PER_VOXEL = VOXEL_SIZE * 100.0


@dataclass(frozen=True)
class CostTerms:
    """The cost of one prediction: total, and per target object (N,) its position MSE (cm^2), IoU and the
    matched slot id (0: none)."""

    total: float
    position_mse: np.ndarray
    iou: np.ndarray
    slot: np.ndarray


def centroids(mask: np.ndarray, num_labels: int) -> tuple[np.ndarray, np.ndarray]:
    """Centroids (L, 3) in voxels (iy, ix, iz) and voxel counts (L,) of labels 1..L of a volume (Y, X, Z); NaN
    centroids for empty labels."""
    flat = np.flatnonzero(mask)
    return _labelled_centroids(flat, mask.reshape(-1)[flat], mask.shape, num_labels)


def _labelled_centroids(flat: np.ndarray, labels: np.ndarray, shape: tuple[int, ...],
                        num_labels: int) -> tuple[np.ndarray, np.ndarray]:
    """`centroids` of the labelled voxels of a volume of `shape`: flat C-order indices (M,), ascending, and their
    labels (M,). Sums in index order, so a dense volume and its `SparseLabels` give the same bits."""
    labels = np.asarray(labels).astype(np.int64)
    keep = labels <= num_labels
    flat, labels = flat[keep], labels[keep]
    counts = np.bincount(labels, minlength=num_labels + 1)[1:].astype(np.float64)
    coords = np.unravel_index(flat, shape)
    sums = np.stack([np.bincount(labels, weights=c, minlength=num_labels + 1)[1:] for c in coords], 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums / counts[:, None], counts


@dataclass(frozen=True)
class SparseLabels:
    """A label volume of `shape` (Y, X, Z) as its labelled voxels: flat C-order indices (M,) int64, ascending and
    unique, and their labels (M,) uint8, all > 0."""

    flat: np.ndarray
    labels: np.ndarray
    shape: tuple[int, ...]

    @staticmethod
    def of(volume: np.ndarray) -> SparseLabels:
        """The labelled voxels of a volume (Y, X, Z)."""
        v = np.asarray(volume)
        flat = np.flatnonzero(v)
        return SparseLabels(flat, v.reshape(-1)[flat].astype(np.uint8), tuple(v.shape))

    def dense(self) -> np.ndarray:
        """The volume (Y, X, Z) uint8."""
        out = np.zeros(int(np.prod(self.shape)), np.uint8)
        out[self.flat] = self.labels
        return out.reshape(self.shape)


@dataclass(frozen=True)
class TargetStats:
    """What the cost needs of a target (Y, X, Z) uint8 with object ids 1..N, computed once per plan: its voxel
    counts (N,) and centroids (N, 3) in voxels."""

    sizes: np.ndarray
    centroids: np.ndarray

    @staticmethod
    def of(target: np.ndarray, num_objects: int) -> TargetStats:
        c, n = centroids(target, num_objects)
        return TargetStats(n, c)


def plan_cost(pred: np.ndarray | SparseLabels, target: np.ndarray, num_slots: int, num_objects: int,
              lam: float = COST_LAMBDA, stats: TargetStats | None = None) -> CostTerms:
    """The cost of predicted next masks `pred` (Y, X, Z) uint8 (slot ids 1..num_slots), dense or as its
    `SparseLabels` (the same bits, in time proportional to its labelled voxels), against the target's amodal
    masks (Y, X, Z) uint8 (object ids 1..num_objects; `stats`: its `TargetStats`, if computed); see the module
    doc."""
    sparse = pred if isinstance(pred, SparseLabels) else SparseLabels.of(pred)
    stats = TargetStats.of(target, num_objects) if stats is None else stats
    g1 = num_objects + 1
    labels = sparse.labels.astype(np.int64)
    keep = labels <= num_slots
    joint = np.bincount(labels[keep] * g1 + target.reshape(-1)[sparse.flat[keep]].astype(np.int64),
                        minlength=(num_slots + 1) * g1).reshape(num_slots + 1, g1)
    ov = Overlap(joint[1:, 1:].astype(np.float64), joint[1:].sum(1).astype(np.float64), stats.sizes)
    pc = _labelled_centroids(sparse.flat, sparse.labels, sparse.shape, num_slots)[0]
    tc = stats.centroids
    diff = (pc[:, None, :] - tc[None, :, :]) * _CM_PER_VOXEL  # (S, N, 3) cm
    mse = (diff * diff).mean(-1)
    usable = (ov.pred_size > 0)[:, None] & np.isfinite(mse)
    score = np.where(usable, ov.iou + MATCH_TIE_BREAK / (1.0 + np.sqrt(np.where(usable, mse * 3, 0.0))), -1.0)
    rows, cols = assignment(score)
    position = np.full(num_objects, UNMATCHED_POSITION_MSE)
    iou = np.zeros(num_objects)
    slot = np.zeros(num_objects, np.int64)
    good = usable[rows, cols]
    position[cols[good]] = mse[rows[good], cols[good]]
    iou[cols[good]] = ov.iou[rows[good], cols[good]]
    slot[cols[good]] = rows[good] + 1
    present = ov.gt_size > 0
    total = float(np.sum(lam * position[present] - iou[present]))
    return CostTerms(total, position, iou, slot)


def object_iou(final: np.ndarray, target: np.ndarray, num_objects: int) -> np.ndarray:
    """Per-object voxel IoU (N,) of two amodal states with the same object ids (final vs target of a task):
    object i against object i, no matching. An object absent from both counts 1."""
    ov = overlap(final, target, num_objects, num_objects)
    inter, union = np.diag(ov.inter), np.diag(ov.union)
    return np.where(union > 0, inter / np.maximum(union, 1), 1.0)


def matched_iou(final: np.ndarray, target: np.ndarray, num_objects: int) -> float:
    """Mean voxel IoU of two amodal states under the best one-to-one matching of their ids (Hungarian on IoU), as
    the benchmark's mask IoU (`dsr_bench.matching.matched_iou`: unmatched non-empty ids count 0)."""
    ov = overlap(final, target, num_objects, num_objects)
    rows, cols = assignment(ov.iou)
    return matching.matched_iou(ov, rows, cols)[0]


def occupancy_iou(final: np.ndarray, target: np.ndarray) -> float:
    """Voxel IoU of the occupied voxels (any object) of two states."""
    a, b = np.asarray(final) > 0, np.asarray(target) > 0
    union = int(np.count_nonzero(a | b))
    return float(np.count_nonzero(a & b) / union) if union else 1.0
