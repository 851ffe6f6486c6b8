"""Forward warping of a feature volume by a flow field: a differentiable trilinear splat, in two kernels.

Each source voxel i with features f_i moves to p_i = x_i + flow_i (per axis) and splats onto the 8
corners base_i + d, d in {0, 1}^3, with weights m_i * prod_axes(w_d) (m_i: the source's foreground
probability), w_0 = base + 1 - p and w_1 = p - base; corners outside the grid are dropped, and the
output at voxel j is sum_i w_ij f_i / max(sum_i w_ij, eps). The kernels differ only in the base corner:

- `FLOOR` ("floor", ours, the default): base = floor(p), so every weight is in [0, 1] and negative
  positions land correctly (p = -0.25 puts 0.75 on voxel 0 and drops voxel -1).
- `OFFICIAL` ("official"): base = trunc(p), C's int() toward zero, as the authors' CUDA kernel does; it
  equals `FLOOR` for p >= 0 and is bit for bit the same there. For -1 < p < 0 the base is 0: voxel 0
  gets 1 - p > 1 and voxel 1 gets p < 0 (a negative weight); for -2 < p <= -1 the base is -1, so only
  voxel 0 is in the grid, with weight p + 1 <= 0; for p <= -2 nothing lands. A voxel whose summed
  weight is negative or below eps is divided by eps. The authors' checkpoints were trained and tested
  with it, and `inference.load_official_predictor` (`predict --weights`) runs them with it; our own
  models keep `FLOOR` (`DSRNet.set_warp_kernel` chooses).

Pure PyTorch (CPU and GPU), differentiable in features, flow and weights (both kernels). Computes in
fp32 (fp64 when the features or the flow are fp64). `deterministic=True` accumulates with
index_put_(accumulate=True) under torch's deterministic algorithms (sort-based on CUDA), so repeated
runs give identical bits; the default index_add_ uses atomics on CUDA.
"""

from __future__ import annotations

import torch

_CORNERS = [(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]

#: The warp kernels, named here only: ours (base corner floor(p)) and the authors' (trunc(p)); module docstring.
FLOOR = "floor"
OFFICIAL = "official"
WARP_KERNELS = (FLOOR, OFFICIAL)


def check_kernel(kernel: str) -> str:
    """`kernel` if it is one of WARP_KERNELS, else ValueError naming the choices."""
    if kernel not in WARP_KERNELS:
        raise ValueError(f"warp kernel {kernel!r}: choose one of {', '.join(WARP_KERNELS)}")
    return kernel


def forward_warp(features: torch.Tensor, flow: torch.Tensor, weight: torch.Tensor, eps: float = 1e-3,
                 deterministic: bool = False, kernel: str = FLOOR) -> torch.Tensor:
    """Warp features (B, C, D0, D1, D2) by flow (B, 3, D0, D1, D2) in voxels (components along the
    three volume axes) with per-voxel weights (B, D0, D1, D2); returns (B, C, D0, D1, D2) in the
    computation dtype (fp32, or fp64 for fp64 inputs). kernel: FLOOR (ours) or OFFICIAL (the
    authors' truncating kernel), see the module docstring."""
    check_kernel(kernel)
    b, c, *dims = features.shape
    if flow.shape != (b, 3, *dims) or weight.shape != (b, *dims):
        raise ValueError(f"forward_warp: features {tuple(features.shape)}, flow {tuple(flow.shape)} and weight "
                         f"{tuple(weight.shape)} disagree (expected (B, 3, *G) and (B, *G))")
    dtype = torch.float64 if torch.float64 in (features.dtype, flow.dtype) else torch.float32
    device = features.device
    n = dims[0] * dims[1] * dims[2]
    axes = [torch.arange(d, device=device, dtype=dtype) for d in dims]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij")).reshape(1, 3, n)
    target = grid + flow.to(dtype).reshape(b, 3, n)  # (B, 3, N)
    base = torch.floor(target) if kernel == FLOOR else torch.trunc(target)
    frac = target - base  # exact; FLOOR: in [0, 1); OFFICIAL: in (-1, 1), negative where p < 0
    base = base.long()
    # one row per source voxel: [w * features..., w]; rows of all samples stacked (B * N, C + 1)
    values = torch.cat([features.to(dtype).reshape(b, c, n), torch.ones(b, 1, n, device=device, dtype=dtype)], 1)
    values = values.transpose(1, 2).reshape(b * n, c + 1)
    w_src = weight.to(dtype).reshape(b * n)
    sample_offset = (torch.arange(b, device=device) * n).view(b, 1)
    out = torch.zeros(b * n, c + 1, device=device, dtype=dtype)
    for corner in _CORNERS:  # offsets and bounds are Python ints: no small host-to-device copies
        idx = [base[:, axis] + corner[axis] for axis in range(3)]  # 3 x (B, N)
        # an out-of-grid corner adds zero at the nearest voxel: spread over the border, never one
        # hot address that every dropped corner's atomic add would queue on
        inside = ((idx[0] >= 0) & (idx[0] < dims[0]) & (idx[1] >= 0) & (idx[1] < dims[1]) & (idx[2] >= 0)
                  & (idx[2] < dims[2])).reshape(b * n)
        idx = [i.clamp(0, d - 1) for i, d in zip(idx, dims)]
        w = w_src * inside
        for axis in range(3):
            f = frac[:, axis].reshape(b * n)
            w = w * (f if corner[axis] else 1 - f)  # p - base and base + 1 - p (negative for OFFICIAL, p < 0)
        flat = ((idx[0] * dims[1] + idx[1]) * dims[2] + idx[2] + sample_offset).reshape(b * n)
        contrib = values * w.unsqueeze(1)
        if deterministic:
            with _deterministic():
                out = out.index_put((flat,), contrib, accumulate=True)
        else:
            out = out.index_add(0, flat, contrib)
    out = out.reshape(b, n, c + 1)
    result = out[..., :c] / torch.clamp(out[..., c:], min=eps)
    return result.transpose(1, 2).reshape(b, c, *dims)


class _deterministic:
    """Context manager: torch's deterministic algorithms on, restored afterwards."""

    def __enter__(self):
        self.previous = torch.are_deterministic_algorithms_enabled()
        self.warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
        torch.use_deterministic_algorithms(True)

    def __exit__(self, *exc):
        torch.use_deterministic_algorithms(self.previous, warn_only=self.warn_only)
