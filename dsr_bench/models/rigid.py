"""Rigid motions of point clouds for the 2D track's SE3 models (torch): poses as 4x4 matrices, motions
about pivots, and the mask-blended flow of SE3-Net and SE3Pose-Net.

Points and translations are world (x, y, z) metres; rotations are R = Rz Ry Rx of standard (active)
elementary rotations about the world axes, angles in radians (`se3.euler_to_matrix`, "standard").
Masks are (B, K, N) probabilities over K slots, the last the background, which does not move.
"""

from __future__ import annotations

import torch

from dsr_bench.models.se3 import euler_to_matrix


def homogeneous(rotations: torch.Tensor, translations: torch.Tensor) -> torch.Tensor:
    """4x4 matrices (..., 4, 4) of rotations (..., 3, 3) and translations (..., 3)."""
    top = torch.cat([rotations, translations.unsqueeze(-1)], -1)
    bottom = torch.zeros(top.shape[:-2] + (1, 4), dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def pose_matrices(params: torch.Tensor) -> torch.Tensor:
    """4x4 poses (..., 4, 4) from (..., 6) = translation (x, y, z) metres, then Euler angles (x, y, z) radians."""
    return homogeneous(euler_to_matrix(params[..., 3:], "standard"), params[..., :3])


def rigid_inverse(transforms: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid 4x4 transforms (..., 4, 4): [R^T | -R^T t]."""
    rt = transforms[..., :3, :3].transpose(-1, -2)
    return homogeneous(rt, -(rt @ transforms[..., :3, 3:]).squeeze(-1))


def about_pivots(rotations: torch.Tensor, translations: torch.Tensor, pivots: torch.Tensor) -> torch.Tensor:
    """4x4 transforms (..., 4, 4) of x -> R (x - p) + p + t: a rotation about the pivot p, then a translation."""
    offset = translations + pivots - (rotations @ pivots.unsqueeze(-1)).squeeze(-1)
    return homogeneous(rotations, offset)


def masked_centroids(points: torch.Tensor, masks: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Each object slot's probability-weighted mean point (B, K-1, 3): points (B, N, 3), masks (B, K, N)
    (zero where a pixel has no point)."""
    weights = masks[:, :-1]
    return (weights @ points) / (weights.sum(-1, keepdim=True) + eps)


def blended_flow(points: torch.Tensor, masks: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Flow (B, N, 3) metres = sum_k mask_k (T_k x - x) over the K - 1 object slots (the background's
    motion is the identity): points (B, N, 3), masks (B, K, N), transforms (B, K-1, 4, 4)."""
    moved = points.unsqueeze(1) @ transforms[..., :3, :3].transpose(-1, -2) + transforms[..., None, :3, 3]
    return (masks[:, :-1].unsqueeze(-1) * (moved - points.unsqueeze(1))).sum(1)


def flow_from_poses(points: torch.Tensor, masks: torch.Tensor, poses: torch.Tensor,
                    next_poses: torch.Tensor) -> torch.Tensor:
    """SE3Pose-Net's flow (B, N, 3): each object slot's points moved by T_k = P'_k P_k^-1 (pose at t+1
    times the inverse pose at t: a point fixed in object k's frame follows it), blended by the masks.
    poses, next_poses: (B, K-1, 4, 4) object-to-world."""
    return blended_flow(points, masks, next_poses @ rigid_inverse(poses))
