"""Forward warping of a feature volume by a flow field: a differentiable trilinear splat.

Each source voxel i with features f_i moves to p_i = x_i + flow_i and splats onto the 8 voxels
around floor(p_i) with weights m_i * prod(1 - |p_i - corner|) (m_i: the source's foreground
probability); the output is sum(w f) / max(sum(w), eps). Floor, not truncation, so negative
positions land correctly (the official CUDA kernel truncates). Pure PyTorch: CPU and GPU,
differentiable in features, flow and weights. `deterministic=True` accumulates with
index_put_(accumulate=True) under torch's deterministic algorithms (sort-based on CUDA).
"""

from __future__ import annotations

import torch

_CORNERS = torch.tensor([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])


def forward_warp(features: torch.Tensor, flow: torch.Tensor, weight: torch.Tensor, eps: float = 1e-3,
                 deterministic: bool = False) -> torch.Tensor:
    """Warp features (B, C, D0, D1, D2) by flow (B, 3, D0, D1, D2) in voxels (components along the
    three volume axes) with per-voxel weights (B, D0, D1, D2); returns (B, C, D0, D1, D2)."""
    b, c, *dims = features.shape
    dims_t = torch.tensor(dims, device=features.device)
    n = dims[0] * dims[1] * dims[2]
    grid = torch.stack(torch.meshgrid(*(torch.arange(d, device=features.device, dtype=flow.dtype) for d in dims),
                                      indexing="ij"))  # (3, D0, D1, D2)
    target = (grid.unsqueeze(0) + flow).reshape(b, 3, n)  # (B, 3, N)
    base = torch.floor(target)
    frac = target - base
    base = base.long()
    feats = features.reshape(b, c, n).float()
    w_src = weight.reshape(b, n).float()
    out = torch.zeros(b, c, n, device=features.device, dtype=torch.float32)
    norm = torch.zeros(b, n, device=features.device, dtype=torch.float32)
    batch_offset = (torch.arange(b, device=features.device) * n).unsqueeze(1)
    for corner in _CORNERS.to(features.device):
        idx = base + corner.view(1, 3, 1)
        w = w_src.clone()
        for axis in range(3):
            f = frac[:, axis].float()
            w = w * (f if corner[axis] == 1 else 1 - f)
        valid = ((idx >= 0) & (idx < dims_t.view(1, 3, 1))).all(1)
        flat = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
        flat = torch.where(valid, flat, torch.zeros_like(flat)) + batch_offset
        w = w * valid
        contrib = feats * w.unsqueeze(1)  # (B, C, N)
        if deterministic:
            with _deterministic():
                norm = norm.reshape(-1).index_put((flat.reshape(-1),), w.reshape(-1), accumulate=True).reshape(b, n)
                out_t = out.transpose(0, 1).reshape(c, -1)
                src = contrib.transpose(0, 1).reshape(c, -1)
                out = out_t.index_put((torch.arange(c, device=out.device).unsqueeze(1), flat.reshape(1, -1)), src,
                                      accumulate=True).reshape(c, b, n).transpose(0, 1)
        else:
            norm = norm.reshape(-1).index_add(0, flat.reshape(-1), w.reshape(-1)).reshape(b, n)
            out = out.transpose(0, 1).reshape(c, -1).index_add(1, flat.reshape(-1), contrib.transpose(0, 1).reshape(c, -1)
                                                               ).reshape(c, b, n).transpose(0, 1)
    out = out / torch.clamp(norm, min=eps).unsqueeze(1)
    return out.reshape(b, c, *dims).to(features.dtype)


class _deterministic:
    def __enter__(self):
        self.previous = torch.are_deterministic_algorithms_enabled()
        torch.use_deterministic_algorithms(True)

    def __exit__(self, *exc):
        torch.use_deterministic_algorithms(self.previous)
