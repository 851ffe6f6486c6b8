"""The network's mask channels as benchmark labels: one rule for training's validation, the
predictor and the scripts."""

from __future__ import annotations

import torch


def slot_labels(mask: torch.Tensor) -> torch.Tensor:
    """Slot probabilities (or logits) (B, K, ...), the background slot last -> (B, ...) uint8 labels
    of the argmax slot: 0 for the background, k + 1 for object slot k (1..K-1)."""
    k = mask.shape[1]
    if mask.dim() == 5:  # the same argmax over channels adjacent in memory: several times faster on a CPU
        mask = mask.contiguous(memory_format=torch.channels_last_3d)
    table = torch.arange(1, k + 1, dtype=torch.uint8, device=mask.device)  # slot k -> k + 1, background -> 0
    table[-1] = 0
    return table[mask.argmax(1)]
