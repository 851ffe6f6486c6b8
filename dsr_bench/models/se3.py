"""SE(3) utilities of DSR-Net: Euler rotations (official passive convention or standard), soft
centroid pivots, and the mask-blended rigid motion field, all in voxel units, axes (D0, D1, D2)
= (world y, world x, z). Everything here runs in fp32 (or fp64) even under autocast."""

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
    """Rotation matrices (..., 3, 3) = Rz Ry Rx from angles (..., 3) = (x, y, z) in radians, where
    x, y, z are the volume axes 0, 1, 2. "official": passive elementary matrices (R_x(a) is the
    usual R_x(-a)), as the official se3euler; "standard": the usual active ones."""
    if convention not in ("official", "standard"):
        raise ValueError(f"euler convention {convention!r}: choose official or standard")
    passive = convention == "official"
    rx = _elementary(euler[..., 0], 0, passive)
    ry = _elementary(euler[..., 1], 1, passive)
    rz = _elementary(euler[..., 2], 2, passive)
    return rz @ ry @ rx


def voxel_grid(dims, device, dtype=torch.float32) -> torch.Tensor:
    """Voxel index coordinates (3, D0, D1, D2)."""
    return torch.stack(torch.meshgrid(*(torch.arange(d, device=device, dtype=dtype) for d in dims), indexing="ij"))


def soft_centroids(mask: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Pivots (B, K, 3) in voxels: each channel's probability-weighted mean voxel index.

    mask: (B, K, D0, D1, D2) probabilities; computed from the three marginals (exact, cheap)."""
    mask = mask if mask.dtype == torch.float64 else mask.float()
    total = mask.sum(dim=(2, 3, 4))  # (B, K)
    out = []
    for axis in range(3):
        others = tuple(a for a in (2, 3, 4) if a != axis + 2)
        marginal = mask.sum(dim=others)  # (B, K, D_axis)
        index = torch.arange(marginal.shape[-1], device=mask.device, dtype=mask.dtype)
        out.append((marginal * index).sum(-1))
    return torch.stack(out, -1) / (total.unsqueeze(-1) + eps)


def blended_motion(mask: torch.Tensor, rotations: torch.Tensor, translations: torch.Tensor,
                   pivots: torch.Tensor) -> torch.Tensor:
    """Motion (B, 3, D0, D1, D2) in voxels = sum_k mask_k (R_k (x - p_k) + p_k + t_k - x) over the
    K - 1 object channels (the last, background, channel does not move).

    mask (B, K, D0, D1, D2) probabilities; rotations (B, K-1, 3, 3); translations and pivots
    (B, K-1, 3) in voxels. Evaluated as sum_k mask_k [R_k - I | t_k + p_k - R_k p_k] [x; 1]."""
    b, k = mask.shape[:2]
    dims = mask.shape[2:]
    dtype = torch.float64 if mask.dtype == torch.float64 else torch.float32
    rotations, translations, pivots = rotations.to(dtype), translations.to(dtype), pivots.to(dtype)
    eye = torch.eye(3, device=mask.device, dtype=dtype)
    offset = translations + pivots - (rotations @ pivots.unsqueeze(-1)).squeeze(-1)  # (B, K-1, 3)
    affine = torch.cat([rotations - eye, offset.unsqueeze(-1)], -1)  # (B, K-1, 3, 4)
    grid = voxel_grid(dims, mask.device, dtype).reshape(3, -1)
    homogeneous = torch.cat([grid, torch.ones_like(grid[:1])], 0)  # (4, N)
    per_voxel = torch.einsum("bkn,bkij->bijn", mask[:, : k - 1].reshape(b, k - 1, -1).to(dtype), affine)  # (B,3,4,N)
    return (per_voxel * homogeneous).sum(2).reshape(b, 3, *dims)
