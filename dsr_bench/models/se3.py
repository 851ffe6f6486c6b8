"""SE(3) utilities of DSR-Net: Euler rotations (official passive convention or standard), soft
centroid pivots, and the mask-blended rigid motion field, all in voxel units, axes (D0, D1, D2)."""

from __future__ import annotations

import torch


def _elementary(angle: torch.Tensor, axis: int, passive: bool) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    if passive:
        s = -s
    one, zero = torch.ones_like(angle), torch.zeros_like(angle)
    if axis == 0:
        rows = [[one, zero, zero], [zero, c, -s], [zero, s, c]]
    elif axis == 1:
        rows = [[c, zero, s], [zero, one, zero], [-s, zero, c]]
    else:
        rows = [[c, -s, zero], [s, c, zero], [zero, zero, one]]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def euler_to_matrix(euler: torch.Tensor, convention: str = "official") -> torch.Tensor:
    """Rotation matrices (..., 3, 3) = Rz Ry Rx from angles (..., 3) = (x, y, z) in radians.
    "official": passive elementary matrices (R_x(a) is the usual R_x(-a)); "standard": active."""
    passive = convention == "official"
    rx = _elementary(euler[..., 0], 0, passive)
    ry = _elementary(euler[..., 1], 1, passive)
    rz = _elementary(euler[..., 2], 2, passive)
    return rz @ ry @ rx


def voxel_grid(dims, device, dtype=torch.float32) -> torch.Tensor:
    """Voxel coordinates (3, D0, D1, D2)."""
    return torch.stack(torch.meshgrid(*(torch.arange(d, device=device, dtype=dtype) for d in dims), indexing="ij"))


def soft_centroids(mask: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Pivots (B, K, 3) in voxels: each channel's probability-weighted mean voxel position (fp32)."""
    mask = mask.float()
    grid = voxel_grid(mask.shape[2:], mask.device)
    total = mask.sum(dim=(2, 3, 4))  # (B, K)
    weighted = torch.einsum("bkxyz,cxyz->bkc", mask, grid)
    return weighted / (total.unsqueeze(-1) + eps)


def blended_motion(mask: torch.Tensor, rotations: torch.Tensor, translations: torch.Tensor,
                   pivots: torch.Tensor) -> torch.Tensor:
    """Motion (B, 3, D0, D1, D2) = sum_k mask_k (R_k (x - p_k) + p_k + t_k - x) for the K - 1 object
    channels (the last, background, channel does not move). mask: (B, K, ...) probabilities;
    rotations (B, K-1, 3, 3); translations, pivots (B, K-1, 3)."""
    b, k = mask.shape[:2]
    grid = voxel_grid(mask.shape[2:], mask.device).reshape(3, -1)  # (3, N)
    rel = grid.unsqueeze(0).unsqueeze(0) - pivots.unsqueeze(-1)  # (B, K-1, 3, N)
    moved = rotations @ rel + pivots.unsqueeze(-1) + translations.unsqueeze(-1)  # (B, K-1, 3, N)
    disp = moved - grid  # (B, K-1, 3, N)
    weights = mask[:, : k - 1].reshape(b, k - 1, 1, -1).float()
    return (weights * disp).sum(1).reshape(b, 3, *mask.shape[2:])
