"""DSR-Net (paper appendix, official code's layer layout) and its baselines in one network.

Input per step: TSDF (1), voxel coordinates / grid size (3) and the 8-channel state (the warped
representation of the previous step; zeros at t = 0 or without history): 12 channels on the grid.
Every conv block is conv3 -> BatchNorm -> LeakyReLU (-> x2 trilinear upsampling, align_corners).

- Volume encoder: 10 convs (strides 2 on the 1st, 2nd, 6th, 10th; 16/32/64/128 channels) and two
  residual blocks; feature decoder: 8 convs with x2 upsampling and skips at 1/8, 1/4, 1/2, giving
  the representation S_t (8 channels, full grid).
- Mask head: 1x1x1 conv to K channels, softmax, background last.
- SE(3) head: an action encoder (2D convs on the 8 x D0 x D1 one-hot map, embeddings of 8
  channels at 1/2 and 16 at 1/4), 3D convs fed with S_t, the action and the embeddings (five
  strided), a conv over the remaining volume to a 128-vector and an MLP to (K - 1) x
  [translation (3), Euler angles (3)]; pivots are soft centroids; motion blended by the masks.
- 3DFlow: a 3D conv decoder (3 strided convs fed with the action embeddings, 3 upsampling convs
  with additive skips) to per-voxel flow. (The official 3DFlow has no mask head; ours keeps it so
  the baseline also fills the predictions' masks.)
Motion is in voxels along (D0, D1, D2) = (dy, dx, dz).

`batchnorm_statistics(net, batch)` sets which statistics BatchNorm normalises with outside
training: the running averages (eval mode) or each batch's own (the official code's evaluation),
the latter without touching the stored running statistics.

The history warp's kernel (`warp.WARP_KERNELS`) is `net.warp_kernel`: `warp.FLOOR` (ours) unless set
with `net.set_warp_kernel(warp.OFFICIAL)`, as the loader of the authors' checkpoints does. It is a
property of how a network is run, not of its weights, and is not saved in dsr-bench checkpoints.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator
from typing import cast

import torch
from torch import nn
from torch.nn import functional as F

from dsr_bench.models.config import ModelConfig
from dsr_bench.models.se3 import blended_motion, euler_to_matrix, soft_centroids
from dsr_bench.models.warp import FLOOR, check_kernel, forward_warp


def batchnorm_layers(net: nn.Module) -> list[nn.modules.batchnorm._BatchNorm]:
    """Every BatchNorm layer (2D and 3D) of a network, in module order."""
    return [m for m in net.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]


@contextlib.contextmanager
def batchnorm_statistics(net: nn.Module, batch: bool) -> Iterator[nn.Module]:
    """The network in eval mode for forward passes outside training, BatchNorm normalising with
    the running statistics (`batch=False`) or with each batch's own statistics (`batch=True`, as the
    official code evaluates). With batch statistics the stored running_mean, running_var and
    num_batches_tracked are neither read nor updated (the layers run in train mode with
    `track_running_stats` off for the duration): predicting never changes the model, and predicting
    twice gives the same outputs. Every module's mode and flag are restored on exit."""
    modes = [(m, m.training) for m in net.modules()]
    layers = batchnorm_layers(net)
    tracking = [m.track_running_stats for m in layers]
    net.eval()
    if batch:
        for m in layers:
            m.train()
            m.track_running_stats = False  # F.batch_norm then gets no running buffers: nothing updated
    try:
        yield net
    finally:
        for m, flag in zip(layers, tracking):
            m.track_running_stats = flag
        for module, mode in modes:
            module.training = mode


class ConvBlock(nn.Module):
    """conv (kernel 3, padding 1, no bias) -> BatchNorm -> LeakyReLU [-> x2 upsampling], 2D or 3D."""

    def __init__(self, cin: int, cout: int, slope: float, stride: int = 1, up: bool = False, dims: int = 3):
        super().__init__()
        conv, norm = (nn.Conv3d, nn.BatchNorm3d) if dims == 3 else (nn.Conv2d, nn.BatchNorm2d)
        self.conv = conv(cin, cout, 3, stride, 1, bias=False)
        self.norm = norm(cout)
        self.act = nn.LeakyReLU(slope, inplace=True)
        self.up = up
        self.mode = "trilinear" if dims == 3 else "bilinear"

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.act(self.norm(self.conv(x)))
        return F.interpolate(x, scale_factor=2, mode=self.mode, align_corners=True) if self.up else x


class ResBlock(nn.Module):
    """Two 3D convs with BatchNorm and an identity shortcut, LeakyReLU after the sum."""

    def __init__(self, channels: int, slope: float):
        super().__init__()
        self.conv1 = nn.Conv3d(channels, channels, 3, 1, 1, bias=False)
        self.bn1 = nn.BatchNorm3d(channels)
        self.conv2 = nn.Conv3d(channels, channels, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm3d(channels)
        self.act = nn.LeakyReLU(slope, inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.act(self.bn1(self.conv1(x)))
        return self.act(self.bn2(self.conv2(out)) + x)


def _narrowed(width: int):
    """Channel counts of the official network divided by `width` (ModelConfig.width; 1: official)."""
    return lambda n: n // width


class VolumeEncoder(nn.Module):
    """(B, cin, G) -> bottleneck (B, 128, G/16) and skips at 1/8 (64 ch), 1/4 (32), 1/2 (16)
    (channel counts divided by `width`)."""

    def __init__(self, cin: int, slope: float, width: int = 1):
        super().__init__()
        s, w = slope, _narrowed(width)
        self.level0 = ConvBlock(cin, w(16), s, 2)
        self.level1 = nn.Sequential(ConvBlock(w(16), w(32), s, 2), *(ConvBlock(w(32), w(32), s) for _ in range(3)))
        self.level2 = nn.Sequential(ConvBlock(w(32), w(64), s, 2), *(ConvBlock(w(64), w(64), s) for _ in range(3)))
        self.level3 = nn.Sequential(ConvBlock(w(64), w(128), s, 2), ResBlock(w(128), s), ResBlock(w(128), s))

    def forward(self, x: torch.Tensor):
        x0 = self.level0(x)
        x1 = self.level1(x0)
        x2 = self.level2(x1)
        return self.level3(x2), (x2, x1, x0)


class FeatureDecoder(nn.Module):
    """Bottleneck and skips -> representation (B, cout, G); the last block keeps BN + LeakyReLU."""

    def __init__(self, cout: int, slope: float, width: int = 1):
        super().__init__()
        s, w = slope, _narrowed(width)
        self.up0 = nn.Sequential(ConvBlock(w(128), w(64), s, up=True), ConvBlock(w(64), w(64), s))
        self.up1 = nn.Sequential(ConvBlock(w(64) + w(64), w(32), s, up=True), ConvBlock(w(32), w(32), s))
        self.up2 = nn.Sequential(ConvBlock(w(32) + w(32), w(16), s, up=True), ConvBlock(w(16), w(16), s))
        self.up3 = nn.Sequential(ConvBlock(w(16) + w(16), 8, s, up=True), ConvBlock(8, cout, s))

    def forward(self, x: torch.Tensor, skips) -> torch.Tensor:
        s2, s1, s0 = skips
        x = self.up0(x)
        x = self.up1(torch.cat([x, s2], 1))
        x = self.up2(torch.cat([x, s1], 1))
        return self.up3(torch.cat([x, s0], 1))


class ActionEncoder(nn.Module):
    """(B, 8, D0, D1) one-hot action map -> embeddings (B, 8, D0/2, D1/2) and (B, 16, D0/4, D1/4)."""

    def __init__(self, slope: float, width: int = 1):
        super().__init__()
        s, w = slope, _narrowed(width)
        self.trunk1 = nn.Sequential(ConvBlock(8, w(64), s, 2, dims=2),
                                    *(ConvBlock(w(64), w(64), s, dims=2) for _ in range(3)))
        self.emb1 = ConvBlock(w(64), 8, s, dims=2)
        self.trunk2 = nn.Sequential(ConvBlock(w(64), w(128), s, 2, dims=2),
                                    *(ConvBlock(w(128), w(128), s, dims=2) for _ in range(3)))
        self.emb2 = ConvBlock(w(128), 16, s, dims=2)

    def forward(self, action: torch.Tensor):
        h1 = self.trunk1(action)
        return self.emb1(h1), self.emb2(self.trunk2(h1))


def _with_plane(volume: torch.Tensor, plane: torch.Tensor) -> torch.Tensor:
    """Concatenate a (B, C, D0, D1) map, repeated along D2, to a (B, C', D0, D1, D2) volume."""
    return torch.cat([volume, plane.unsqueeze(-1).expand(-1, -1, -1, -1, volume.shape[-1])], 1)


def _halved(n: int, times: int) -> int:
    for _ in range(times):
        n = (n + 1) // 2  # a kernel-3, padding-1, stride-2 conv
    return n


class SE3Head(nn.Module):
    """Representation + action -> (B, K-1, 6) = [translation (3) in voxels, Euler angles (3)]."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        s, c, w = config.leaky_slope, config.state_channels, _narrowed(config.width)
        self.action = ActionEncoder(s, config.width)
        self.conv0 = ConvBlock(c + 8, 8, s, 2)
        self.conv1 = ConvBlock(8 + 8, 16, s, 2)
        self.conv2 = nn.Sequential(ConvBlock(16 + 16, w(32), s, 2), ConvBlock(w(32), w(32), s),
                                   ConvBlock(w(32), w(32), s), ConvBlock(w(32), w(64), s),
                                   ConvBlock(w(64), w(128), s, 2), ConvBlock(w(128), w(128), s, 2))
        ry, rx, rz = (_halved(int(g), 5) for g in config.grid)  # (4, 4, 2) on the 128 x 128 x 48 grid
        self.to_vector = nn.Conv3d(w(128), w(128), (ry, rx, rz))
        layers: list[nn.Module] = []
        prev = w(128)
        for _ in range(config.mlp_layers - 1):
            layers += [nn.Linear(prev, config.mlp_hidden), nn.LeakyReLU(s)]
            prev = config.mlp_hidden
        layers.append(nn.Linear(prev, 6 * (config.num_slots - 1)))
        self.mlp = nn.Sequential(*layers)
        self.objects = config.num_slots - 1

    def forward(self, rep: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        emb1, emb2 = self.action(action)
        x = self.conv0(_with_plane(rep, action))
        x = self.conv1(_with_plane(x, emb1))
        x = self.conv2(_with_plane(x, emb2))
        return self.mlp(self.to_vector(x).flatten(1)).reshape(-1, self.objects, 6)


class FlowHead(nn.Module):
    """3DFlow: representation + action -> per-voxel flow (B, 3, G) in voxels."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        s, c = config.leaky_slope, config.state_channels
        self.action = ActionEncoder(s, config.width)
        self.down0 = ConvBlock(c + 8, 8, s, 2)
        self.down1 = ConvBlock(8 + 8, 16, s, 2)
        self.down2 = ConvBlock(16 + 16, 32, s, 2)
        self.up0 = ConvBlock(32, 16, s, up=True)
        self.up1 = ConvBlock(16, 8, s, up=True)
        self.up2 = ConvBlock(8, 8, s, up=True)
        self.out = nn.Conv3d(8, 3, 3, 1, 1)

    def forward(self, rep: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        emb1, emb2 = self.action(action)
        f0 = self.down0(_with_plane(rep, action))
        f1 = self.down1(_with_plane(f0, emb1))
        f2 = self.down2(_with_plane(f1, emb2))
        x = self.up1(self.up0(f2) + f1)
        return self.out(self.up2(x + f0))


class DSRNet(nn.Module):
    """One step of DSR-Net or a baseline: (tsdf, action map, history state) -> outputs."""

    coords: torch.Tensor  # (3, Y, X, Z) voxel coordinates / grid size: a buffer, not saved

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        self.channels_last = False  # feed the encoder channels_last_3d inputs (set with the weights' format)
        self.warp_kernel = FLOOR  # the history warp's kernel: set_warp_kernel()
        self._warp_compiled = False
        self._warp = forward_warp  # (features, flow, weight, eps, deterministic) -> warped; compile_warp() compiles it
        c = config.state_channels
        self.encoder = VolumeEncoder(1 + 3 + c, config.leaky_slope, config.width)
        self.decoder = FeatureDecoder(c, config.leaky_slope, config.width)
        self.mask_head = nn.Conv3d(c, config.num_slots, 1)
        self.motion_head = SE3Head(config) if config.motion == "se3" else FlowHead(config)
        grid = torch.stack(torch.meshgrid(*(torch.arange(g, dtype=torch.float32) for g in config.grid), indexing="ij"))
        self.register_buffer("coords", grid / torch.tensor(config.grid, dtype=torch.float32).view(3, 1, 1, 1),
                             persistent=False)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Official initialisation: Kaiming-normal conv weights, BatchNorm (1, 0), Xavier-normal MLP
        weights with zero biases; `init="zero-motion"` also zeroes the MLP's output layer."""
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.Conv3d)):
                nn.init.kaiming_normal_(m.weight)
            elif isinstance(m, (nn.BatchNorm2d, nn.BatchNorm3d)):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
            elif isinstance(m, nn.Linear):
                nn.init.xavier_normal_(m.weight)
                nn.init.zeros_(m.bias)
        if self.config.init == "zero-motion" and isinstance(self.motion_head, SE3Head):
            nn.init.zeros_(cast(nn.Linear, self.motion_head.mlp[-1]).weight)

    def to_channels_last(self) -> DSRNet:
        """channels_last_3d weights and inputs for the 3D convs (channels_last for the 2D ones)."""
        for m in self.modules():
            if isinstance(m, (nn.Conv3d, nn.Conv2d)):
                fmt = torch.channels_last_3d if isinstance(m, nn.Conv3d) else torch.channels_last
                m.weight.data = m.weight.data.contiguous(memory_format=fmt)
        self.channels_last = True
        return self

    def initial_state(self, batch: int, device) -> torch.Tensor:
        """The zero history (B, state_channels, D0, D1, D2) float32."""
        return torch.zeros(batch, self.config.state_channels, *self.config.grid, device=device)

    def forward(self, tsdf: torch.Tensor, action: torch.Tensor, state: torch.Tensor) -> dict[str, torch.Tensor]:
        """tsdf (B, D0, D1, D2) in [-1, 1]; action (B, 8, D0, D1) one-hot; state (B, C, D0, D1, D2).

        Returns mask_logits (B, K, ...), mask (softmax, fp32, background last), motion (B, 3, ...)
        fp32 in voxels (dy, dx, dz) and the representation (B, C, ...)."""
        out = self.represent(tsdf, state)
        out["motion"] = self.motion_of(out["representation"], out["mask"], action)
        return out

    def represent(self, tsdf: torch.Tensor, state: torch.Tensor) -> dict[str, torch.Tensor]:
        """The part of `forward` that does not see the action: representation, mask_logits and mask (softmax,
        fp32). The planning track runs it once per state and `motion_of` once per batch of candidate actions."""
        b = tsdf.shape[0]
        if tuple(tsdf.shape[1:]) != tuple(self.config.grid):
            raise ValueError(f"tsdf grid {tuple(tsdf.shape[1:])} differs from the model's {tuple(self.config.grid)}")
        if self.config.history == "none":
            state = torch.zeros_like(state)
        coords = self.coords.unsqueeze(0).expand(b, -1, -1, -1, -1).to(tsdf.dtype)
        x = torch.cat([tsdf.unsqueeze(1), coords, state.to(tsdf.dtype)], 1)
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last_3d)
        rep = self.decoder(*self.encoder(x))
        logits = self.mask_head(rep)
        with torch.autocast(tsdf.device.type, enabled=False):  # softmax, pivots and blending in fp32
            mask = torch.softmax(logits.float(), 1)
        return {"mask_logits": logits, "mask": mask, "representation": rep}

    def motion_of(self, rep: torch.Tensor, mask: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The motion (B, 3, ...) fp32 in voxels (dy, dx, dz) of actions (B, 8, D0, D1) from a representation
        and its mask (`represent`)."""
        if self.channels_last:
            action = action.contiguous(memory_format=torch.channels_last)
        if self.config.motion == "flow":
            return self.motion_head(rep, action).float()
        params = self.motion_head(rep, action)
        with torch.autocast(rep.device.type, enabled=False):
            params = params.float()
            rotations = euler_to_matrix(params[..., 3:], self.config.euler)
            pivots = soft_centroids(mask[:, :-1])
            return blended_motion(mask, rotations, params[..., :3], pivots)

    @torch.no_grad()
    def next_state(self, outputs: dict, gt_flow: torch.Tensor | None = None, gt_mask: torch.Tensor | None = None,
                   deterministic: bool = False) -> torch.Tensor:
        """The history fed to the next step (detached, fp32): the representation forward-warped by
        the predicted motion (dsr) or by ground-truth flow (gtwarp), unwarped (nowarp), or zero
        (single, 3dflow). Splat weights: the predicted foreground probability (1 - background)."""
        rep = outputs["representation"].detach().float()
        history = self.config.history
        if history == "none":
            return torch.zeros_like(rep)
        if history == "nowarp":
            return rep
        foreground = outputs["mask"][:, :-1].detach().float().sum(1)
        if history == "gtwarp":
            if gt_flow is None or (self.config.gtwarp_weight == "gt" and gt_mask is None):
                raise ValueError("gtwarp needs the ground-truth flow (and mask with gtwarp_weight='gt')")
            if self.config.gtwarp_weight == "gt" and gt_mask is not None:  # (not None: checked above)
                foreground = (gt_mask > 0).float()
            return self._warp(rep, gt_flow.float(), foreground, self.config.warp_eps, deterministic)
        return self._warp(rep, outputs["motion"].detach().float(), foreground, self.config.warp_eps, deterministic)

    def set_warp_kernel(self, kernel: str) -> DSRNet:
        """Warp the history with `kernel` (`warp.FLOOR`, ours, or `warp.OFFICIAL`, the authors' truncating
        kernel) from now on; ValueError for another name. Keeps a compiled warp compiled."""
        self.warp_kernel = check_kernel(kernel)
        self._warp = self._warp_function()
        return self

    def compile_warp(self) -> DSRNet:
        """Run the history warp through torch.compile (fused index arithmetic and atomic adds) when the
        network is on a GPU; on a CPU the eager warp stays (inductor's CPU backend rejects its scatter)."""
        if self.coords.device.type == "cuda":
            self._warp_compiled = True
            self._warp = self._warp_function()
        return self

    def _warp_function(self):
        """forward_warp with this network's kernel, compiled if compile_warp() asked for it."""
        warp = forward_warp if self.warp_kernel == FLOOR else functools.partial(forward_warp, kernel=self.warp_kernel)
        return torch.compile(warp, dynamic=False) if self._warp_compiled else warp
