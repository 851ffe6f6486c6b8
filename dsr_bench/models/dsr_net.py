"""DSR-Net (paper appendix, official conventions) and its baselines in one network.

Input per step: TSDF (1), voxel coordinates / grid size (3) and the 8-channel state (the warped
representation of the previous step, zeros at t = 0 or without history): 12 channels on the grid.
Scene encoder (22 3D conv layers with skips) -> representation S_t (8 channels). Mask head: 1x1x1
conv to K channels, softmax, background last. Action encoder (2D convs) -> embeddings at 1/2 and
1/4 resolution. Motion: SE(3) head (8 strided 3D convs fed with the action and its embeddings, a
conv to a vector, an MLP) -> K - 1 transforms, blended by the masks around soft-centroid pivots;
or, for 3DFlow, a 3D conv decoder to per-voxel flow. Motion is in voxels along (D0, D1, D2).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from dsr_bench.models.config import ModelConfig
from dsr_bench.models.se3 import blended_motion, euler_to_matrix, soft_centroids, voxel_grid
from dsr_bench.models.warp import forward_warp


def conv3(cin: int, cout: int, stride: int, slope: float) -> nn.Sequential:
    return nn.Sequential(nn.Conv3d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm3d(cout),
                         nn.LeakyReLU(slope, inplace=True))


def conv2(cin: int, cout: int, stride: int, slope: float) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout),
                         nn.LeakyReLU(slope, inplace=True))


class ResBlock3d(nn.Module):
    def __init__(self, channels: int, slope: float):
        super().__init__()
        self.body = nn.Sequential(conv3(channels, channels, 1, slope), nn.Conv3d(channels, channels, 3, 1, 1, bias=False),
                                  nn.BatchNorm3d(channels))
        self.act = nn.LeakyReLU(slope, inplace=True)

    def forward(self, x):
        return self.act(x + self.body(x))


def _up(x: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, scale_factor=2, mode="trilinear", align_corners=False)


class SceneEncoder(nn.Module):
    """12 -> 8 channels: ten convs down (strides on 1, 2, 6, 10; skips after 1, 5, 9), two residual
    blocks, eight convs up (skips into 3, 5, 7; x2 trilinear after 1, 3, 5, 7)."""

    def __init__(self, cin: int, cout: int, slope: float):
        super().__init__()
        chans = [16, 32, 32, 32, 32, 64, 64, 64, 64, 128]
        strides = [2, 2, 1, 1, 1, 2, 1, 1, 1, 2]
        layers, prev = [], cin
        for ch, st in zip(chans, strides):
            layers.append(conv3(prev, ch, st, slope))
            prev = ch
        self.down = nn.ModuleList(layers)
        self.res = nn.Sequential(ResBlock3d(128, slope), ResBlock3d(128, slope))
        self.up = nn.ModuleList([
            conv3(128, 64, 1, slope), conv3(64, 64, 1, slope), conv3(64 + 64, 32, 1, slope), conv3(32, 32, 1, slope),
            conv3(32 + 32, 16, 1, slope), conv3(16, 16, 1, slope), conv3(16 + 16, 8, 1, slope),
        ])
        self.last = nn.Conv3d(8, cout, 3, 1, 1)

    def forward(self, x):
        skips = {}
        for i, layer in enumerate(self.down, start=1):
            x = layer(x)
            if i in (1, 5, 9):
                skips[i] = x
        x = self.res(x)
        u = self.up
        x = _up(u[0](x))
        x = u[1](x)
        x = _up(u[2](torch.cat([x, skips[9]], 1)))
        x = u[3](x)
        x = _up(u[4](torch.cat([x, skips[5]], 1)))
        x = u[5](x)
        x = _up(u[6](torch.cat([x, skips[1]], 1)))
        return self.last(x)


class ActionEncoder(nn.Module):
    """8 x Y x X one-hot action map -> embeddings (8 ch at 1/2, 16 ch at 1/4 resolution)."""

    def __init__(self, slope: float):
        super().__init__()
        self.a = nn.Sequential(conv2(8, 64, 2, slope), conv2(64, 64, 1, slope), conv2(64, 64, 1, slope),
                               conv2(64, 64, 1, slope))
        self.emb_half = nn.Conv2d(64, 8, 3, 1, 1)
        self.b = nn.Sequential(conv2(64, 128, 2, slope), conv2(128, 128, 1, slope), conv2(128, 128, 1, slope),
                               conv2(128, 128, 1, slope))
        self.emb_quarter = nn.Conv2d(128, 16, 3, 1, 1)

    def forward(self, action):
        h = self.a(action)
        return self.emb_half(h), self.emb_quarter(self.b(h))


def _halved(n: int, times: int) -> int:
    for _ in range(times):
        n = (n + 1) // 2
    return n


def _repeat_z(x2d: torch.Tensor, depth: int) -> torch.Tensor:
    return x2d.unsqueeze(-1).expand(-1, -1, -1, -1, depth)


class SE3Head(nn.Module):
    """Eight 3D convs (five strided) fed with the action and its two embeddings, a conv over the
    remaining volume to a 128-vector, and an MLP to (K - 1) x [translation (3), Euler angles (3)]."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        s, k = config.leaky_slope, config.num_slots
        self.c1 = conv3(config.state_channels + 8, 8, 2, s)
        self.c2 = conv3(8 + 8, 16, 2, s)
        self.c3 = conv3(16 + 16, 32, 2, s)
        self.rest = nn.Sequential(conv3(32, 32, 1, s), conv3(32, 32, 2, s), conv3(32, 64, 2, s), conv3(64, 128, 1, s),
                                  conv3(128, 128, 1, s))
        final = tuple(_halved(g, 5) for g in config.grid)  # five stride-2 convs (kernel 3, padding 1)
        self.to_vector = nn.Conv3d(128, 128, final)
        layers, prev = [], 128
        for _ in range(config.mlp_layers - 1):
            layers += [nn.Linear(prev, config.mlp_hidden), nn.LeakyReLU(s, inplace=True)]
            prev = config.mlp_hidden
        layers.append(nn.Linear(prev, 6 * (k - 1)))
        self.mlp = nn.Sequential(*layers)
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)
        self.k = k

    def forward(self, state, action, emb_half, emb_quarter):
        x = self.c1(torch.cat([state, _repeat_z(action, state.shape[-1])], 1))
        x = self.c2(torch.cat([x, _repeat_z(emb_half, x.shape[-1])], 1))
        x = self.c3(torch.cat([x, _repeat_z(emb_quarter, x.shape[-1])], 1))
        x = self.to_vector(self.rest(x)).flatten(1)
        return self.mlp(x).reshape(-1, self.k - 1, 6)


class FlowHead(nn.Module):
    """3DFlow: per-voxel flow from the representation and the action (3D conv decoder)."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        s = config.leaky_slope
        self.net = nn.Sequential(conv3(config.state_channels + 8, 32, 1, s), conv3(32, 32, 1, s), conv3(32, 16, 1, s),
                                 nn.Conv3d(16, 3, 3, 1, 1))

    def forward(self, state, action):
        return self.net(torch.cat([state, _repeat_z(action, state.shape[-1])], 1))


class DSRNet(nn.Module):
    """One step of DSR-Net or a baseline: (tsdf, action map, history state) -> outputs."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        c = config.state_channels
        self.encoder = SceneEncoder(1 + 3 + c, c, config.leaky_slope)
        self.mask_head = nn.Conv3d(c, config.num_slots, 1)
        self.action_encoder = ActionEncoder(config.leaky_slope)
        self.motion_head = SE3Head(config) if config.motion == "se3" else FlowHead(config)
        self.register_buffer("coords", voxel_grid(config.grid, "cpu") /
                             torch.tensor(config.grid, dtype=torch.float32).view(3, 1, 1, 1), persistent=False)

    def initial_state(self, batch: int, device) -> torch.Tensor:
        """The zero history (B, state_channels, D0, D1, D2)."""
        return torch.zeros(batch, self.config.state_channels, *self.config.grid, device=device)

    def forward(self, tsdf: torch.Tensor, action: torch.Tensor, state: torch.Tensor) -> dict[str, torch.Tensor]:
        """tsdf (B, D0, D1, D2); action (B, 8, D0, D1); state (B, C, D0, D1, D2). Returns mask_logits
        (B, K, ...), mask (softmax, fp32), motion (B, 3, ...) in voxels and the representation."""
        b = tsdf.shape[0]
        if self.config.history == "none":
            state = torch.zeros_like(state)
        coords = self.coords.unsqueeze(0).expand(b, -1, -1, -1, -1).to(tsdf.dtype)
        rep = self.encoder(torch.cat([tsdf.unsqueeze(1), coords, state], 1))
        logits = self.mask_head(rep)
        mask = torch.softmax(logits.float(), 1)
        if self.config.motion == "flow":
            motion = self.motion_head(rep, action).float()
        else:
            emb_half, emb_quarter = self.action_encoder(action)
            params = self.motion_head(rep, action, emb_half, emb_quarter).float()
            rotations = euler_to_matrix(params[..., 3:], self.config.euler)
            pivots = soft_centroids(mask[:, :-1])
            motion = blended_motion(mask, rotations, params[..., :3], pivots)
        return {"mask_logits": logits, "mask": mask, "motion": motion, "representation": rep}

    def next_state(self, outputs: dict, gt_flow: torch.Tensor | None = None, gt_mask: torch.Tensor | None = None,
                   deterministic: bool = False) -> torch.Tensor:
        """The history fed to the next step (detached): warped by the predicted motion (dsr), by
        ground truth (gtwarp), unwarped (nowarp) or zero (single, 3dflow)."""
        rep = outputs["representation"].detach().float()
        history = self.config.history
        if history == "none":
            return torch.zeros_like(rep)
        if history == "nowarp":
            return rep
        if history == "gtwarp":
            if gt_flow is None or gt_mask is None:
                raise ValueError("gtwarp needs the ground-truth flow and mask")
            return forward_warp(rep, gt_flow.float(), (gt_mask > 0).float(), self.config.warp_eps, deterministic)
        foreground = outputs["mask"][:, :-1].detach().sum(1)
        return forward_warp(rep, outputs["motion"].detach(), foreground, self.config.warp_eps, deterministic)
