"""The benchmark's metrics (numpy; scipy's exact assignment solver when installed).

Definitions follow the official evaluation (docs/evaluation.md):
- motion, visible surface: squared end-point error summed over (dy, dx, dz), averaged over voxels
  with -0.99 < tsdf < 0 and a GT object (z = 0 slice excluded), x 0.16 (voxel^2 -> cm^2);
- motion, full volume: squared error averaged over all voxels and the 3 components, x 0.16;
- mask IoU: I / max(U, 1) between predicted slots and GT objects under the best one-to-one
  matching (Hungarian), averaged over the matched pairs; unordered = a matching per step,
  ordered = one matching per sequence maximising the IoU summed over its steps.
Scores are averaged over sequences per step index, then over step indices.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np

from dsr_bench.constants import TSDF_SURFACE_LOW, VOXEL2_TO_CM2
from dsr_bench.matching import (  # noqa: F401  (brute_force_assignment: the metrics' reference, for tests)
    Overlap, assignment, brute_force_assignment, matched_iou, official_iou, overlap)

MOVED_VOXELS = 0.5  # an object moved if its mean GT flow exceeds half a voxel (2 mm)
OCCLUDED_BELOW = 0.5  # visible fraction under which an object counts as mostly occluded
M2_TO_CM2 = 1e4


#: a float16 prediction with at most this fraction of nonzero values is subtracted sparsely
SPARSE_FLOAT16 = 0.25


def prediction_minus_truth(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """float32(pred) - gt, elementwise, as float32 (any shape). Every value equals the plain float32
    subtraction's except that a zero may have the other sign, so squares and sums are bit-identical.

    A float16 prediction that is mostly +0.0 (the yardsticks', a static scene's) is subtracted only
    where it is nonzero and is -gt elsewhere: numpy casts float16 in software, at about 2 ns a value,
    which made the cast the dearest part of `evaluate` (5 ms a step, against 0.8 ms this way)."""
    if pred.dtype != np.float16:
        return np.subtract(pred, gt, dtype=np.float32)
    bits = pred.reshape(-1).view(np.uint16)
    nonzero = np.flatnonzero(bits != 0)  # -0.0 (0x8000) and NaN count as nonzero: cast like the rest
    if nonzero.size > SPARSE_FLOAT16 * bits.size:
        return np.subtract(pred, gt, dtype=np.float32)
    diff = np.negative(gt, dtype=np.float32)  # 0 - g == -g exactly, up to the sign of a zero g
    flat, truth = diff.reshape(-1), gt.reshape(-1)
    flat[nonzero] = pred.reshape(-1)[nonzero].astype(np.float32) - truth[nonzero]
    return diff


def motion_errors(pred: np.ndarray, gt: np.ndarray, tsdf: np.ndarray, gt_mask: np.ndarray,
                  num_objects: int, object_index: np.ndarray | None = None) -> dict[str, float]:
    """Motion errors of one step (cm^2); pred, gt: (3, Y, X, Z) voxels; tsdf, gt_mask: (Y, X, Z); object_index:
    the flat indices of gt_mask's non-zero voxels, where the caller has them already.

    One full-volume pass for the full-volume error; everything else only touches object voxels."""
    diff = prediction_minus_truth(pred, gt).reshape(3, -1)
    flat = diff.reshape(-1)
    out = {"motion_full": float(np.einsum("i,i->", flat, flat, dtype=np.float64)) / flat.size * VOXEL2_TO_CM2}
    # a bool volume's nonzero is 10x faster than a uint8 one's
    idx = np.flatnonzero(gt_mask != 0) if object_index is None else object_index
    labels = gt_mask.reshape(-1)[idx].astype(np.int64)
    sq = np.einsum("ci,ci->i", diff[:, idx], diff[:, idx])
    depth_index = idx % gt_mask.shape[-1]
    t = tsdf.reshape(-1)[idx]
    visible = (t > TSDF_SURFACE_LOW) & (t < 0) & (depth_index > 0)
    out["motion_visible"] = float(sq[visible].mean() * VOXEL2_TO_CM2) if visible.any() else np.nan
    g = gt.reshape(3, -1)[:, idx]
    speed_sum = np.bincount(labels, weights=np.sqrt(np.einsum("ci,ci->i", g, g)), minlength=num_objects + 1)[1:]
    sums = np.bincount(labels, weights=sq, minlength=num_objects + 1)[1:]
    counts = np.bincount(labels, minlength=num_objects + 1)[1:]
    per_object = sums / np.maximum(counts, 1) * VOXEL2_TO_CM2
    present = counts > 0
    moved = present & (speed_sum / np.maximum(counts, 1) > MOVED_VOXELS)
    static = present & ~moved
    out["motion_moved"] = float(per_object[moved].mean()) if moved.any() else np.nan
    out["motion_static"] = float(per_object[static].mean()) if static.any() else np.nan
    return out


def motion_2d_error(pred: np.ndarray, gt: np.ndarray, mask_2d: np.ndarray) -> float:
    """Visible-surface 2D flow error (cm^2): squared error summed over components, averaged over
    pixels that see an object; pred, gt: (H, W, 3) metres."""
    sel = mask_2d > 0
    if not sel.any():
        return np.nan
    diff = pred[sel].astype(np.float64) - gt[sel]
    return float((diff ** 2).sum(1).mean() * M2_TO_CM2)


def sequence_scores(pred_mask: np.ndarray, gt_mask: np.ndarray, num_slots: int, num_objects: int,
                    visible_fraction: np.ndarray | None = None) -> dict[str, np.ndarray | list[np.ndarray]]:
    """Per-step IoU scores of one sequence: unordered and ordered (T,), and per-object IoU under
    the unordered matching split into mostly occluded and visible objects (lists per step)."""
    steps = pred_mask.shape[0]
    overlaps = [overlap(pred_mask[t], gt_mask[t], num_slots, num_objects) for t in range(steps)]
    unordered = np.zeros(steps)
    occluded: list[np.ndarray] = []
    visible: list[np.ndarray] = []
    for t, ov in enumerate(overlaps):
        rows, cols = assignment(ov.iou)
        unordered[t], per_object = matched_iou(ov, rows, cols)
        if visible_fraction is not None:
            present = ov.gt_size > 0
            occ = present & (visible_fraction[t] < OCCLUDED_BELOW)
            occluded.append(per_object[occ])
            visible.append(per_object[present & ~occ])
    rows, cols = assignment(cast(np.ndarray, sum(ov.iou for ov in overlaps)))  # the steps' IoU matrices summed
    ordered = np.array([matched_iou(ov, rows, cols)[0] for ov in overlaps])
    size = max(num_slots, num_objects)
    total = np.zeros((size, size))
    for ov in overlaps:
        total[:num_slots, :num_objects] += ov.iou
    rows, cols = assignment(total)
    return {"iou_unordered": unordered, "iou_ordered": ordered, "iou_occluded_objects": occluded,
            "iou_visible_objects": visible,
            "iou_unordered_official": np.array([official_iou(ov) for ov in overlaps]),
            "iou_ordered_official": np.array([official_iou(ov, rows, cols) for ov in overlaps])}


# --- The table of metrics ----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Step3D:
    """What a 3D metric sees of one step: the predicted motion (3, Y, X, Z) voxels (float16/32), the ground-truth
    flow (3, Y, X, Z), TSDF and object labels (Y, X, Z), the number of objects and the flat indices of the labels'
    non-zero voxels."""

    motion: np.ndarray
    flow: np.ndarray
    tsdf: np.ndarray
    gt_mask: np.ndarray
    num_objects: int
    objects: np.ndarray


@dataclass(frozen=True)
class Sequence3D:
    """What a per-sequence 3D metric sees: predicted slots and ground-truth objects (T, Y, X, Z), the slot and
    object counts, and each object's visible fraction per step (T, N) where the sequence has it."""

    pred_mask: np.ndarray
    gt_mask: np.ndarray
    num_slots: int
    num_objects: int
    visible_fraction: np.ndarray | None


@dataclass(frozen=True)
class Step2D:
    """What a 2D metric sees of one step: the predicted and ground-truth 2D flow (H, W, 3) metres and the front
    camera's object labels (H, W)."""

    motion_2d: np.ndarray
    flow_2d: np.ndarray
    mask_2d: np.ndarray


def step_motion(step: Step3D) -> dict[str, float]:
    """The four motion errors of one step in one pass (`motion_errors`)."""
    return motion_errors(step.motion, step.flow, step.tsdf, step.gt_mask, step.num_objects, object_index=step.objects)


def sequence_ious(seq: Sequence3D) -> dict[str, np.ndarray | list[np.ndarray]]:
    """The mask IoUs of one sequence (`sequence_scores`): the ordered ones need all its steps at once."""
    return sequence_scores(seq.pred_mask, seq.gt_mask, seq.num_slots, seq.num_objects, seq.visible_fraction)


def step_motion_2d(step: Step2D) -> float:
    return motion_2d_error(step.motion_2d, step.flow_2d, step.mask_2d)


TRACKS = ("3D", "2D")
#: where a metric's mean lands in the results: "headline" in metrics, per_step and per_sequence (the leaderboard's
#: columns); "official" in metrics and per_step (the authors' definition beside ours); "breakdown" in per_step, and
#: its mean in breakdowns[Metric.breakdown]
ROLES = ("headline", "official", "breakdown")


@dataclass(frozen=True)
class Metric:
    """One metric: its key in the results, its track ("3D": scored from mask and motion, "2D": from motion_2d), how
    it is computed and where its mean is reported.

    step: a function of one step (`Step3D`, or `Step2D` on the 2D track) giving the metric's value there, or a dict
    of values by key when one pass computes several metrics (then each of them names the same function); sequence:
    instead, a function of the whole sequence (`Sequence3D`) giving its per-step values (T,) (or a dict of them,
    plus any per-object lists it keeps). Either way the value of a step with nothing to score is NaN. Aggregation is
    the official one for every metric: the mean over sequences at each step index, then over step indices
    (`evaluate.aggregate`). title: its row in `dsr-bench evaluate`'s table; column: its column in the leaderboard's
    table of its track (a headline metric's; "" for none)."""

    key: str
    track: str
    role: str
    title: str = ""
    lower_is_better: bool = True
    step: Callable | None = None
    sequence: Callable | None = None
    breakdown: str = ""
    column: str = ""

    def __post_init__(self):
        if self.track not in TRACKS or self.role not in ROLES:
            raise ValueError(f"metric {self.key!r}: track one of {', '.join(TRACKS)}, role one of {', '.join(ROLES)}")
        if (self.step is None) == (self.sequence is None) or (self.sequence is not None and self.track != "3D"):
            raise ValueError(f"metric {self.key!r}: give step, or sequence (3D track only), not both")
        if (self.role == "breakdown") != bool(self.breakdown):
            raise ValueError(f"metric {self.key!r}: a breakdown metric (and only one) names its breakdowns key")
        if bool(self.column) != (self.role == "headline"):
            raise ValueError(f"metric {self.key!r}: a headline metric (and only one) names its leaderboard column")


#: Every metric of the benchmark, in the order of the results' keys (docs/evaluation.md; adding one: "Adding a
#: metric" there). Every list of metric keys (evaluate's results, its table, the leaderboard entries' checks)
#: comes from here.
METRICS: tuple[Metric, ...] = (
    Metric("motion_visible", "3D", "headline", "flow MSE, visible surface (cm²)", step=step_motion,
           column="flow MSE visible (cm²)"),
    Metric("motion_full", "3D", "headline", "flow MSE, full volume (cm²)", step=step_motion,
           column="flow MSE full (cm²)"),
    Metric("iou_unordered", "3D", "headline", "mask IoU, unordered", False, sequence=sequence_ious,
           column="IoU unordered"),
    Metric("iou_ordered", "3D", "headline", "mask IoU, ordered", False, sequence=sequence_ious, column="IoU ordered"),
    Metric("motion_moved", "3D", "breakdown", step=step_motion, breakdown="motion_moved_objects"),
    Metric("motion_static", "3D", "breakdown", step=step_motion, breakdown="motion_static_objects"),
    Metric("iou_unordered_official", "3D", "official", lower_is_better=False, sequence=sequence_ious),
    Metric("iou_ordered_official", "3D", "official", lower_is_better=False, sequence=sequence_ious),
    Metric("motion_2d", "2D", "headline", "2D flow MSE, visible (cm²)", step=step_motion_2d,
           column="2D flow MSE (cm²)"),
)
#: the per-object IoUs `sequence_ious` keeps beside its metrics: pooled over every object and step, they are the
#: breakdowns of mostly occluded and visible objects
OBJECT_IOUS = (("iou_occluded_objects", "occluded_object_steps"), ("iou_visible_objects", "visible_object_steps"))


def metric_keys(tracks=TRACKS, roles=ROLES, scope: str | None = None) -> tuple[str, ...]:
    """The keys of the metrics of these tracks and roles (computed per "step" or per "sequence": either without
    `scope`), in the table's order."""
    return tuple(m.key for m in METRICS if m.track in tracks and m.role in roles
                 and (scope is None or getattr(m, scope) is not None))


def compute_step(track: str, inputs) -> dict[str, float]:
    """Every per-step metric of `track` on one step's inputs (`Step3D` or `Step2D`), by key: each function once."""
    values: dict[str, float] = {}
    for function, keys in _grouped(track, "step"):
        _collect(values, function(inputs), keys)
    return values


def compute_sequence(inputs: Sequence3D) -> dict[str, np.ndarray | list[np.ndarray]]:
    """Every per-sequence metric (and what its function keeps beside, e.g. OBJECT_IOUS) of one sequence, by key."""
    values: dict = {}
    for function, keys in _grouped("3D", "sequence"):
        _collect(values, function(inputs), keys)
    return values


def _grouped(track: str, scope: str) -> list[tuple[Callable, list[str]]]:
    """The distinct functions of a track's metrics of one scope ("step", "sequence"), each with its metrics' keys."""
    groups: dict[Callable, list[str]] = {}
    for m in METRICS:
        function = getattr(m, scope)
        if m.track == track and function is not None:
            groups.setdefault(function, []).append(m.key)
    return list(groups.items())


def _collect(values: dict, out, keys: list[str]) -> None:
    if isinstance(out, dict):
        values.update(out)
    else:
        values[keys[0]] = out
