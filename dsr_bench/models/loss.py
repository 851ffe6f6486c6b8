"""DSR-Net's loss: motion MSE + 5 x mask cross-entropy under the best slot matching.

Ground-truth objects 1..K-1 are matched one-to-one to the K - 1 object slots (the last slot is the
background, always paired with empty space). The cross-entropy of a sample under a matching sigma
is const - sum_i S[i, sigma(i)] / V with S[i, j] = sum over object i's voxels of log p_j, so the
best matching maximises a (K-1) x (K-1) score matrix: one bmm per batch and an exact assignment
solver, never a loss per permutation. As in the official training loop, step 0 of a window uses
its own best matching and step t > 0 uses the best matching of step t - 1's prediction (temporal
consistency); `dsr_loss` returns the current best matching for the caller to pass on.
Official reduction: per-sample mean cross-entropy, summed over the batch ("sum"); "mean" averages.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.nn import functional as F

MASK_WEIGHT = 5.0
MOTION_WEIGHT = 1.0


def score_matrix(log_probs: torch.Tensor, gt_mask: torch.Tensor) -> torch.Tensor:
    """(B, K-1, K-1): [b, i, j] = summed log-probability of slot j over ground-truth object i+1's voxels.

    log_probs: (B, K, ...) log-softmax, background last; gt_mask: (B, ...) ids 0..K-1 (0 = empty)."""
    b, k = log_probs.shape[:2]
    ids = gt_mask.long().reshape(b, -1)
    onehot = F.one_hot(ids, k)[..., 1:].to(log_probs.dtype if log_probs.dtype == torch.float64 else torch.float32)
    lp = log_probs[:, : k - 1].reshape(b, k - 1, -1).to(onehot.dtype)  # (B, slots, V)
    return torch.bmm(lp, onehot).transpose(1, 2)  # (B, objects, slots)


def best_matching(scores: torch.Tensor) -> list[np.ndarray]:
    """For each sample, the slot of every ground-truth object (maximum total score, exact)."""
    from dsr_bench.metrics import assignment

    out = []
    for s in scores.detach().double().cpu().numpy():
        rows, cols = assignment(s)
        order = np.empty(s.shape[0], dtype=np.int64)
        order[rows] = cols
        out.append(order)
    return out


def matched_target(gt_mask: torch.Tensor, matching: list[np.ndarray], num_slots: int) -> torch.Tensor:
    """Per-voxel class targets (B, ...) int64: object i -> its slot, empty -> the background slot K-1."""
    lut = torch.full((len(matching), num_slots), num_slots - 1, dtype=torch.long, device=gt_mask.device)
    for b, order in enumerate(matching):
        lut[b, 1: 1 + len(order)] = torch.as_tensor(order, device=gt_mask.device)
    return torch.gather(lut, 1, gt_mask.long().reshape(len(matching), -1)).reshape(gt_mask.shape)


def check_ids(gt_mask: torch.Tensor, num_slots: int) -> None:
    """Ground-truth ids must fit the model's K - 1 object slots."""
    top = int(gt_mask.max()) if gt_mask.numel() else 0
    if top > num_slots - 1 or (gt_mask.numel() and int(gt_mask.min()) < 0):
        raise ValueError(f"mask_3d has object id {top}, but the model has {num_slots - 1} object slots "
                         f"(ids must be 0..{num_slots - 1}); train a model with more slots")


def dsr_loss(outputs: dict, gt_mask: torch.Tensor, gt_flow: torch.Tensor, matching: list[np.ndarray] | None = None,
             reduction: str = "sum", check: bool = True) -> tuple[torch.Tensor, dict, list[np.ndarray]]:
    """(total loss, float terms, best matching of this prediction).

    outputs: mask_logits (B, K, ...), motion (B, 3, ...) voxels; gt_mask (B, ...) ids; gt_flow
    (B, 3, ...) voxels. `matching`: the previous step's best matching (None at step 0: this
    prediction's own). reduction of the mask term over the batch: "sum" (official) or "mean"."""
    if reduction not in ("sum", "mean"):
        raise ValueError(f"reduction {reduction!r}: sum or mean")
    logits = outputs["mask_logits"]
    logits = logits if logits.dtype == torch.float64 else logits.float()
    b, k = logits.shape[:2]
    if check:
        check_ids(gt_mask, k)
    log_probs = F.log_softmax(logits, 1)
    best = best_matching(score_matrix(log_probs.detach(), gt_mask))
    target = matched_target(gt_mask, best if matching is None else matching, k)
    per_sample = F.nll_loss(log_probs, target, reduction="none").reshape(b, -1).mean(1)
    mask_loss = per_sample.sum() if reduction == "sum" else per_sample.mean()
    motion = outputs["motion"]
    motion_loss = F.mse_loss(motion if motion.dtype == torch.float64 else motion.float(), gt_flow.to(motion.dtype)
                             if motion.dtype == torch.float64 else gt_flow.float())
    total = MOTION_WEIGHT * motion_loss + MASK_WEIGHT * mask_loss
    return total, {"motion": float(motion_loss.detach()), "mask": float(mask_loss.detach()),
                   "total": float(total.detach())}, best
