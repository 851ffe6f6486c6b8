"""Fast CPU inference of the DSR-Net family (issue 30 part 5): the same network, prepared once for prediction.

`FastDSRNet.from_network(net)` is a copy of a `DSRNet` that predicts what the network predicts with BatchNorm's
running statistics (eval mode), fp32, in less time on a CPU:

- **BatchNorm folded into the convolutions**: every conv -> BatchNorm pair becomes one conv with a bias
  (w' = w * gamma / sqrt(var + eps), b' = beta - mean * gamma / sqrt(var + eps), computed in fp64), so
  oneDNN runs one kernel where eager ran two passes over the volume;
- **channels_last_3d** weights and inputs, and every 3D conv through oneDNN (`OneDNNConv3d`: torch sends the
  batch-1 convs on the small volumes of the encoder's bottom and the SE(3) head to its slow reference kernel);
- **the history warp restructured** (`fast_forward_warp`): the per-axis corner weights, bounds and index
  strides computed once instead of once per corner, and the splat accumulated channel-major. It gives the
  same bits as `warp.forward_warp` for both kernels (the same products in the same order, the same
  accumulation order), in about half the time.

Only the first two change numbers, by rounding (about 1e-5 voxels of motion on the benchmark's grid with
random weights; `bench/bench_inference.py` measures it on real sequences). Batch statistics (the authors'
protocol, `official_bn`) cannot be folded: `FastDSRNet` refuses a network whose BatchNorm has no running
statistics. Everything here is CPU and fp32; on a GPU use `torch.compile` and bf16 (`bench/bench_model.py`).
"""

from __future__ import annotations

import functools
from typing import cast

import torch
from torch import nn

from dsr_bench.models.dsr_net import ConvBlock, DSRNet, ResBlock, batchnorm_layers
from dsr_bench.models.warp import FLOOR, check_kernel


class OneDNNConv3d(nn.Conv3d):
    """A Conv3d that a CPU always runs through oneDNN (fp32). torch sends a batch-1 conv whose batch x channels x
    D0 x D1 is under 20,480 to its slow reference kernel: the encoder's bottom and the SE(3) head (64 channels on
    16 x 16 x 6: 13.5 ms there, 0.7 ms in oneDNN). Elsewhere (a GPU, bf16, under torch.compile) it is a plain
    Conv3d."""

    def _conv_forward(self, input: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
        if (input.device.type == "cpu" and input.dtype == torch.float32 == weight.dtype and self.padding_mode == "zeros"
                and isinstance(self.padding, tuple) and torch.backends.mkldnn.is_available()
                and not torch.compiler.is_compiling()):  # (the op has no fake-tensor rule; inductor picks its own)
            return torch.ops.aten.mkldnn_convolution(input, weight, bias, self.padding, self.stride, self.dilation,
                                                     self.groups)
        return super()._conv_forward(input, weight, bias)


def _onednn(conv: nn.Conv3d) -> OneDNNConv3d:
    """The same conv (its weights shared) as a OneDNNConv3d."""
    out = OneDNNConv3d(conv.in_channels, conv.out_channels, cast(tuple, conv.kernel_size), cast(tuple, conv.stride),
                       cast(tuple, conv.padding), cast(tuple, conv.dilation), conv.groups, conv.bias is not None,
                       device="meta")
    out.weight, out.bias = conv.weight, conv.bias
    return out


def _folded(conv: nn.Module, norm: nn.Module) -> nn.Module:
    """`conv` followed by the BatchNorm `norm` (running statistics) as one conv with a bias (computed in fp64)."""
    conv, norm = cast(nn.Conv3d, conv), cast(nn.BatchNorm3d, norm)
    if norm.running_mean is None or norm.running_var is None:
        raise ValueError("BatchNorm without running statistics cannot be folded (batch statistics: use the eager "
                         "network)")
    scale = norm.weight.detach().double() / torch.sqrt(norm.running_var.double() + norm.eps)
    bias = norm.bias.detach().double() - norm.running_mean.double() * scale
    if conv.bias is not None:
        bias = bias + conv.bias.detach().double() * scale
    fused = type(conv)(conv.in_channels, conv.out_channels, cast(tuple, conv.kernel_size), cast(tuple, conv.stride),
                       cast(tuple, conv.padding), cast(tuple, conv.dilation), conv.groups, bias=True)
    shape = (-1,) + (1,) * (conv.weight.dim() - 1)
    with torch.no_grad():
        fused.weight.copy_((conv.weight.detach().double() * scale.view(shape)).to(conv.weight.dtype))
        cast(torch.Tensor, fused.bias).copy_(bias.to(conv.weight.dtype))
    return fused.to(conv.weight.device)


def fold_batchnorm_(net: DSRNet) -> DSRNet:
    """Fold every BatchNorm of `net` (in place) into the conv before it, with its running statistics: each
    ConvBlock's and ResBlock's BatchNorm becomes nn.Identity and its conv gets the bias. The network then
    computes what it computed in eval mode, up to rounding. ValueError if a BatchNorm is left unfolded."""
    pairs = {ConvBlock: (("conv", "norm"),), ResBlock: (("conv1", "bn1"), ("conv2", "bn2"))}  # conv, its norm
    for module in list(net.modules()):
        for conv, norm in pairs.get(type(module), ()):
            if not isinstance(getattr(module, norm), nn.Identity):
                setattr(module, conv, _folded(getattr(module, conv), getattr(module, norm)))
                setattr(module, norm, nn.Identity())
    left = batchnorm_layers(net)
    if left:
        raise ValueError(f"{len(left)} BatchNorm layers are not after a conv block and were not folded")
    return net


def fast_forward_warp(features: torch.Tensor, flow: torch.Tensor, weight: torch.Tensor, eps: float = 1e-3,
                      deterministic: bool = False, kernel: str = FLOOR) -> torch.Tensor:
    """`warp.forward_warp` (same arguments, same result bit for bit on a CPU, fp32), restructured for speed:
    features (B, C, D0, D1, D2), flow (B, 3, D0, D1, D2) in voxels along the three volume axes, weight
    (B, D0, D1, D2); returns (B, C, D0, D1, D2) float32. The base corner is floor(p) (`warp.FLOOR`) or
    trunc(p) (`warp.OFFICIAL`); each axis' two corner weights, in-grid flags and index strides are computed
    once, and the 8 corners' splats are accumulated channel-major ((C + 1) x B*N, one index_add_ per corner,
    in the eager warp's corner order, so every voxel's sum is taken in the same order). `deterministic`
    is accepted for the same signature: on a CPU index_add_ is already deterministic."""
    check_kernel(kernel)
    b, c, *dims = features.shape
    if flow.shape != (b, 3, *dims) or weight.shape != (b, *dims):
        raise ValueError(f"fast_forward_warp: features {tuple(features.shape)}, flow {tuple(flow.shape)} and "
                         f"weight {tuple(weight.shape)} disagree (expected (B, 3, *G) and (B, *G))")
    dtype, device = torch.float32, features.device
    n = dims[0] * dims[1] * dims[2]
    strides = (dims[1] * dims[2], dims[2], 1)
    values = features.to(dtype).reshape(b, c, n).transpose(0, 1).reshape(c, b * n)  # channel-major (C, B*N)
    w_src = weight.to(dtype).reshape(b * n)
    weights, indices = [], []  # per axis: (lower, upper) corner weight with its in-grid flag, and index * stride
    for axis, d in enumerate(dims):
        shape = [1, 1, 1, 1]
        shape[axis + 1] = d
        target = (torch.arange(d, device=device, dtype=dtype).view(shape) + flow[:, axis].to(dtype)).reshape(b * n)
        base = torch.floor(target) if kernel == FLOOR else torch.trunc(target)
        frac = target - base  # as the eager warp: exact
        lower = base.long()
        upper = lower + 1
        # (1 - f) and f times 0 or 1: the eager warp's products, the flag folded in where it multiplies exactly
        weights.append(((1 - frac) * ((lower >= 0) & (lower < d)), frac * ((upper >= 0) & (upper < d))))
        indices.append((lower.clamp_(0, d - 1) * strides[axis], upper.clamp_(0, d - 1) * strides[axis]))
    offset = (torch.arange(b, device=device) * n).view(b, 1).expand(b, n).reshape(b * n)
    out = torch.zeros(c + 1, b * n, device=device, dtype=dtype)  # rows: w * features (C), w (1)
    contrib = torch.empty(c + 1, b * n, device=device, dtype=dtype)
    for i0 in (0, 1):  # the eager warp's corner order (0, 0, 0), (0, 0, 1), ..., (1, 1, 1)
        w0, idx0 = w_src * weights[0][i0], indices[0][i0] + offset
        for i1 in (0, 1):
            w01, idx01 = w0 * weights[1][i1], idx0 + indices[1][i1]
            for i2 in (0, 1):
                torch.mul(w01, weights[2][i2], out=contrib[c])
                torch.mul(values, contrib[c], out=contrib[:c])
                out.index_add_(1, idx01 + indices[2][i2], contrib)
    result = out[:c] / torch.clamp(out[c:], min=eps)
    return result.reshape(c, b, *dims).transpose(0, 1)


class FastDSRNet(DSRNet):
    """A DSRNet prepared for CPU inference (module docstring): BatchNorm folded with its running statistics,
    channels_last_3d, the history warped by `fast_forward_warp` with the source network's kernel. Use it in
    place of the network for forward passes and `next_state`; it is not for training (no BatchNorm)."""

    @classmethod
    def from_network(cls, net: DSRNet, onednn: bool = True) -> FastDSRNet:
        """The fast copy of `net` (its weights, running statistics and warp kernel; `net` is not changed).
        `onednn=False` keeps plain Conv3d modules (for torch.compile, which lowers the convs itself).
        ValueError if a BatchNorm layer of `net` keeps no running statistics."""
        fast = cls(net.config)
        fast.load_state_dict(net.state_dict())
        fast.to(net.coords.device)
        fold_batchnorm_(fast)
        for parent in list(fast.modules()) if onednn else []:
            for name, child in list(parent.named_children()):
                if type(child) is nn.Conv3d:
                    setattr(parent, name, _onednn(child))
        fast.to_channels_last()
        fast.set_warp_kernel(net.warp_kernel)
        return fast.eval()

    def _warp_function(self):
        """fast_forward_warp with this network's kernel (compile_warp() does not apply: CPU)."""
        return functools.partial(fast_forward_warp, kernel=self.warp_kernel)
