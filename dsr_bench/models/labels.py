"""The network's mask channels as benchmark labels: one rule for training's validation, the
predictor and the scripts."""

from __future__ import annotations

import torch


def slot_labels(mask: torch.Tensor) -> torch.Tensor:
    """Slot probabilities (or logits) (B, K, ...), the background slot last -> (B, ...) uint8 labels
    of the argmax slot: 0 for the background, k + 1 for object slot k (1..K-1)."""
    k = mask.shape[1]
    labels = mask.argmax(1)
    return torch.where(labels == k - 1, 0, labels + 1).to(torch.uint8)
