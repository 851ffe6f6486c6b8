"""DSR-Net's loss: motion MSE + 5 x mask cross-entropy under the best slot matching.

Ground-truth objects 1..K-1 are matched one-to-one to the K - 1 object slots (the last slot is the
background, always paired with empty space). The cross-entropy of a sample under a matching sigma
is const - sum_i S[i, sigma(i)] / V with S[i, j] = sum over object i's voxels of log p_j, so the
best matching maximises a (K-1) x (K-1) score matrix: one bmm per batch and an exact assignment,
never a loss per permutation. As in the official training loop, step 0 of a window uses its own
best matching and step t > 0 uses the best matching of step t - 1's prediction (temporal
consistency); `dsr_loss` returns the current best matching for the caller to pass on.
Official reduction: per-sample mean cross-entropy, summed over the batch ("sum"); "mean" averages.

Nothing here waits for the GPU: for up to `MAX_ENUMERATED` objects the assignment is an argmax over
every permutation's total score, computed on the scores' device (24 permutations for K = 5), the
matching is a (B, K-1) tensor on that device and the loss terms are detached 0-dim tensors. A
training loop can then queue a whole window of steps and read the terms once.
"""

from __future__ import annotations

import itertools
from functools import lru_cache

import numpy as np
import torch
from torch.nn import functional as F

MASK_WEIGHT = 5.0
MOTION_WEIGHT = 1.0
#: Up to this many objects the assignment enumerates permutations on the device (6! = 720 rows).
MAX_ENUMERATED = 6


def score_matrix(log_probs: torch.Tensor, gt_mask: torch.Tensor) -> torch.Tensor:
    """(B, K-1, K-1): [b, i, j] = summed log-probability of slot j over ground-truth object i+1's voxels.

    log_probs: (B, K, ...) log-softmax, background last; gt_mask: (B, ...) ids 0..K-1 (0 = empty).
    fp32 (fp64 for fp64 log_probs)."""
    b, k = log_probs.shape[:2]
    dtype = torch.float64 if log_probs.dtype == torch.float64 else torch.float32
    ids = gt_mask.reshape(b, -1, 1)
    onehot = (ids == torch.arange(1, k, device=ids.device, dtype=ids.dtype)).to(dtype)  # (B, V, objects)
    lp = log_probs[:, : k - 1].reshape(b, k - 1, -1).to(dtype)  # (B, slots, V)
    return torch.bmm(lp, onehot).transpose(1, 2)  # (B, objects, slots)


@lru_cache(maxsize=None)
def _permutations(n: int, device: torch.device) -> torch.Tensor:
    """Every permutation of range(n) in itertools order, (n!, n) int64 on `device`; cached, so the
    host-to-device copy (which waits for the device) happens once per process."""
    return torch.tensor(list(itertools.permutations(range(n))), dtype=torch.long, device=device).reshape(-1, n)


def best_matching(scores: torch.Tensor) -> torch.Tensor:
    """(B, n) int64 on the scores' device: the slot of every ground-truth object under the one-to-one
    matching of maximum total score (exact). scores: (B, n objects, n slots).

    Up to MAX_ENUMERATED objects: the argmax over all permutations, on the device, no host sync
    (ties go to the first permutation in itertools order). Beyond: scipy's solver on the CPU."""
    b, n = scores.shape[:2]
    scores = scores.detach()
    if n <= MAX_ENUMERATED:
        perms = _permutations(n, scores.device)  # (P, n)
        rows = torch.arange(n, device=scores.device).expand_as(perms)
        totals = scores[:, rows, perms].sum(-1)  # (B, P): sum_i scores[b, i, perm[i]]
        return perms[totals.argmax(1)]
    from dsr_bench.matching import assignment

    out = np.empty((b, n), dtype=np.int64)
    for i, s in enumerate(scores.double().cpu().numpy()):
        objects, slots = assignment(s)
        out[i, objects] = slots
    return torch.as_tensor(out, device=scores.device)


def _as_matching(matching, batch: int, device) -> torch.Tensor:
    """A matching given as a (B, n) tensor or a list of B arrays -> (B, n) int64 tensor on `device`."""
    if isinstance(matching, torch.Tensor):
        out = matching.to(device=device, dtype=torch.long)
    else:
        out = torch.as_tensor(np.stack([np.asarray(m, dtype=np.int64) for m in matching]), device=device)
    if out.ndim != 2 or out.shape[0] != batch:
        raise ValueError(f"matching of shape {tuple(out.shape)}; expected ({batch}, objects)")
    return out


def matched_target(gt_mask: torch.Tensor, matching, num_slots: int) -> torch.Tensor:
    """Per-voxel class targets (B, ...) int64: object i -> its slot, empty -> the background slot K-1.

    matching: (B, n) slots of objects 1..n (a tensor, or a list of B arrays)."""
    b = gt_mask.shape[0]
    order = _as_matching(matching, b, gt_mask.device)
    lut = torch.full((b, num_slots), num_slots - 1, dtype=torch.long, device=gt_mask.device)
    lut[:, 1: 1 + order.shape[1]] = order
    return torch.gather(lut, 1, gt_mask.long().reshape(b, -1)).reshape(gt_mask.shape)


class MaskIdError(ValueError):
    """A ground-truth id does not fit the model's object slots."""


def check_ids(gt_mask: torch.Tensor, num_slots: int) -> None:
    """Ground-truth ids must fit the model's K - 1 object slots (reads the tensor: a host sync on a GPU)."""
    if not gt_mask.numel():
        return
    low, top = (int(v) for v in torch.aminmax(gt_mask))
    if top > num_slots - 1 or low < 0:
        bad = top if top > num_slots - 1 else low
        raise MaskIdError(f"mask_3d has object id {bad}, but the model has {num_slots - 1} object slots "
                         f"(ids must be 0..{num_slots - 1}); train a model with more slots")


def dsr_loss(outputs: dict, gt_mask: torch.Tensor, gt_flow: torch.Tensor, matching=None,
             reduction: str = "sum", check: bool = True,
             voxel_factor: int = 1) -> tuple[torch.Tensor, dict, torch.Tensor]:
    """(total loss, terms, best matching of this prediction).

    outputs: mask_logits (B, K, ...), motion (B, 3, ...) voxels; gt_mask (B, ...) ids; gt_flow
    (B, 3, ...) voxels. `matching`: the previous step's best matching, (B, K-1) (None at step 0:
    this prediction's own). reduction of the mask term over the batch: "sum" (official) or "mean".
    terms: "total", "motion", "mask" as detached 0-dim fp32/fp64 tensors (float() them to log).
    `check=False` skips the id check, which reads the mask (callers that checked the ids on the CPU).
    `voxel_factor`: benchmark voxels per model voxel (`ModelConfig.voxel_factor`): the motion term is
    taken in benchmark voxels (x factor^2), so it weighs against the mask term as at full size."""
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
    motion = motion if motion.dtype == torch.float64 else motion.float()
    motion_loss = F.mse_loss(motion, gt_flow.to(motion.dtype)) * voxel_factor ** 2
    total = MOTION_WEIGHT * motion_loss + MASK_WEIGHT * mask_loss
    return total, {"total": total.detach(), "motion": motion_loss.detach(), "mask": mask_loss.detach()}, best
