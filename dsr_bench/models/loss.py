"""DSR-Net's loss: motion MSE + 5 x mask cross-entropy under the best slot matching.

The matching between ground-truth objects (ids 1..N) and the K - 1 object slots (the last slot is
the background) maximises the log-likelihood the prediction gives the ground truth, from one
K x K score matrix per sample (not a loss per permutation), solved exactly; the matching found at
the first step of a sequence is carried to the next steps (temporal consistency).
"""

from __future__ import annotations

import numpy as np
import torch
from torch.nn import functional as F

MASK_WEIGHT = 5.0


def score_matrix(log_probs: torch.Tensor, gt_mask: torch.Tensor) -> torch.Tensor:
    """(B, K-1, K-1) summed log-probability of slot j over ground-truth object i's voxels.

    log_probs: (B, K, ...) log-softmax; gt_mask: (B, ...) ids 0..K-1 (0 = empty)."""
    b, k = log_probs.shape[:2]
    onehot = F.one_hot(gt_mask.long().clamp(max=k - 1), k).reshape(b, -1, k)[..., 1:].float()  # (B, N, K-1)
    lp = log_probs[:, : k - 1].reshape(b, k - 1, -1).float()  # (B, K-1, N)
    return torch.bmm(lp, onehot).transpose(1, 2)  # (B, objects, slots)


def best_matching(scores: torch.Tensor) -> list[np.ndarray]:
    """For each sample, slot index of every ground-truth object (maximum total score)."""
    from dsr_bench.metrics import assignment

    out = []
    for s in scores.detach().cpu().numpy():
        rows, cols = assignment(s)
        order = np.empty(s.shape[0], dtype=np.int64)
        order[rows] = cols
        out.append(order)
    return out


def matched_target(gt_mask: torch.Tensor, matching: list[np.ndarray], num_slots: int) -> torch.Tensor:
    """Per-voxel class targets (B, ...): object i -> its slot, empty -> the background slot K-1."""
    lut = torch.full((len(matching), num_slots), num_slots - 1, dtype=torch.long, device=gt_mask.device)
    for b, order in enumerate(matching):
        lut[b, 1: 1 + len(order)] = torch.as_tensor(order, device=gt_mask.device)
    ids = gt_mask.long().clamp(max=num_slots - 1)
    return torch.gather(lut, 1, ids.reshape(len(matching), -1)).reshape(gt_mask.shape)


def dsr_loss(outputs: dict, gt_mask: torch.Tensor, gt_flow: torch.Tensor,
             matching: list[np.ndarray] | None = None) -> tuple[torch.Tensor, dict, list[np.ndarray]]:
    """(total loss, terms, matching used). Pass the previous step's matching to carry it over."""
    logits = outputs["mask_logits"].float()
    k = logits.shape[1]
    log_probs = F.log_softmax(logits, 1)
    if matching is None:
        matching = best_matching(score_matrix(log_probs, gt_mask))
    target = matched_target(gt_mask, matching, k)
    mask_loss = F.nll_loss(log_probs, target)
    motion_loss = F.mse_loss(outputs["motion"].float(), gt_flow.float())
    total = motion_loss + MASK_WEIGHT * mask_loss
    return total, {"motion": float(motion_loss.detach()), "mask": float(mask_loss.detach()),
                   "total": float(total.detach())}, matching
