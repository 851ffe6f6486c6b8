"""The 2D track's networks (torch only): 2DFlow, SE3-Net and SE3Pose-Net on the front camera's image.

Inputs, at the network's resolution (h, w) = `ImageModelConfig.image_shape`:
  points (B, 3, h, w) world (x, y, z) metres, 0 where the camera has no return;
  valid  (B, 1, h, w) 1 where it has one;
  action (B, 3) int64 [d, v, u]: the push's direction and its start point's pixel (`image_data.action_pixels`).
The action carries what DSR-Net's does (the start point and the direction), mapped to the image plane and
concatenated with the image at the input of 2DFlow and SE3-Net (`action_maps`): the direction one-hot,
constant over the image, and the start point as a Gaussian bump around it plus each pixel's offset from it.
(DSR-Net's own encoding, a one-hot map with a single 1 at [d, v, u], did not train here: over 1,200 batches
both models' loss stayed at that of predicting no motion; docs/models.md, the 2D track.) SE3Pose-Net's masks
and poses see the image alone (its masks do not depend on the action, as in Byravan et al. 2018) and its
transition sees the push as a vector (u, v scaled to [-1, 1], one-hot d).

All three share one 2D U-Net (`Backbone`: 3 stride-2 levels, skip connections, BatchNorm, leaky ReLU).
Their outputs (`forward`) are the pieces `flow_at` turns into flow at any resolution:
  2dflow:     "flow" (B, 3, h, w) metres, world (x, y, z) components;
  se3net:     "masks" (B, K, h, w) softmax, "transforms" (B, K-1, 4, 4): object k's points move by
              x -> R_k (x - p_k) + p_k + t_k about the pivot p_k, its mask's mean point;
  se3posenet: "masks", "poses" and "next_poses" (B, K-1, 4, 4) object-to-world: each pose's origin is
              its mask's mean point plus a predicted offset; the transition predicts each object's change
              as a rotation about the pose's origin and a translation, in world axes (P' = [dR R | p + dt]),
              and points move by P' P^-1 (`rigid.flow_from_poses`).
The layers that output motions are zero-initialised: every model predicts no motion before training.
"""

from __future__ import annotations

from typing import cast

import torch
import torch.nn.functional as F
from torch import nn

from dsr_bench.constants import NUM_DIRECTIONS, WORKSPACE_CENTER
from dsr_bench.models import rigid
from dsr_bench.models.image_config import ImageModelConfig
from dsr_bench.models.se3 import euler_to_matrix

#: Scales of the motion outputs: a unit of output is 1 cm of translation, 0.1 rad of rotation.
TRANSLATION_SCALE = 0.01
ROTATION_SCALE = 0.1
#: Points enter the network centred on the workspace and in decimetres.
POINT_CENTER = (WORKSPACE_CENTER[0], WORKSPACE_CENTER[1], 0.0)
POINT_SCALE = 0.1


def _conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout),
                         nn.LeakyReLU(0.01, inplace=True))


def _zero(layer: nn.Module) -> None:
    """Zero a layer's weight and bias (a head's last layer: the network starts by predicting no motion)."""
    nn.init.zeros_(cast(torch.Tensor, layer.weight))
    nn.init.zeros_(cast(torch.Tensor, layer.bias))


class Backbone(nn.Module):
    """2D U-Net: (B, cin, h, w) -> features (B, width, h, w) and the bottleneck (B, 8 width, h/8, w/8)."""

    def __init__(self, cin: int, width: int):
        super().__init__()
        w = width
        self.down = nn.ModuleList([nn.Sequential(_conv(cin, w), _conv(w, w)),
                                   nn.Sequential(_conv(w, 2 * w, 2), _conv(2 * w, 2 * w)),
                                   nn.Sequential(_conv(2 * w, 4 * w, 2), _conv(4 * w, 4 * w)),
                                   nn.Sequential(_conv(4 * w, 8 * w, 2), _conv(8 * w, 8 * w))])
        self.up = nn.ModuleList([_conv(12 * w, 4 * w), _conv(6 * w, 2 * w), _conv(3 * w, w)])

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        skips = []
        for level in self.down:
            x = level(x)
            skips.append(x)
        bottleneck = x
        for conv, skip in zip(self.up, reversed(skips[:-1])):
            x = conv(torch.cat([F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False), skip], 1))
        return x, bottleneck


class VectorHead(nn.Module):
    """The bottleneck (B, C, h/8, w/8) -> a vector (B, out): two stride-2 convs, pooled to 4 x 5, two linear
    layers; the last zero-initialised."""

    def __init__(self, cin: int, hidden: int, out: int):
        super().__init__()
        self.convs = nn.Sequential(_conv(cin, cin, 2), _conv(cin, cin, 2), nn.AdaptiveAvgPool2d((4, 5)))
        self.mlp = nn.Sequential(nn.Flatten(), nn.Linear(cin * 20, hidden), nn.LeakyReLU(0.01, inplace=True),
                                 nn.Linear(hidden, out))
        _zero(self.mlp[-1])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.convs(x))


#: Channels of the action's image encoding (`action_maps`) and the start bump's width (a fraction of the image width).
ACTION_CHANNELS = NUM_DIRECTIONS + 3
ACTION_SIGMA = 1 / 20


def action_maps(action: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    """The push as images (B, 11, h, w) from actions (B, 3) = [d, v, u]: the direction one-hot, constant over
    the image (8 channels); the start point as a Gaussian bump exp(-r^2 / 2 s^2), s = w / 20 (r: the distance
    from (u, v) in pixels), and each pixel's offset from it, ((u' - u) / w, (v' - v) / w)."""
    b = len(action)
    h, w = shape
    v = torch.arange(h, device=action.device, dtype=torch.float32).view(1, h, 1)
    u = torch.arange(w, device=action.device, dtype=torch.float32).view(1, 1, w)
    du = (u - action[:, 2].view(b, 1, 1).float()) / w
    dv = (v - action[:, 1].view(b, 1, 1).float()) / w
    bump = torch.exp(-(du ** 2 + dv ** 2) / (2 * ACTION_SIGMA ** 2))
    direction = F.one_hot(action[:, 0], NUM_DIRECTIONS).float().view(b, NUM_DIRECTIONS, 1, 1)
    direction = direction.expand(b, NUM_DIRECTIONS, h, w)
    return torch.cat([direction, torch.stack([bump, du.expand(b, h, w), dv.expand(b, h, w)], 1)], 1)


def action_vectors(action: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    """(B, 10): the start pixel (u, v) scaled to [-1, 1], then the direction one-hot."""
    h, w = shape
    uv = torch.stack([action[:, 2] / (w - 1), action[:, 1] / (h - 1)], -1).float() * 2 - 1
    return torch.cat([uv, F.one_hot(action[:, 0], NUM_DIRECTIONS).float()], -1)


class ImageNet(nn.Module):
    """One of the 2D track's models, chosen by `config.name` (see the module docstring)."""

    def __init__(self, config: ImageModelConfig):
        super().__init__()
        self.config = config
        k, w = config.num_slots, config.width
        pose_model = config.name == "se3posenet"
        self.backbone = Backbone(4 if pose_model else 4 + ACTION_CHANNELS, w)
        if config.name == "2dflow":
            self.flow = nn.Conv2d(w, 3, 1)
            _zero(self.flow)
            return
        self.mask = nn.Conv2d(w, k, 1)
        if not pose_model:
            self.motion = VectorHead(8 * w, config.hidden, (k - 1) * 6)
            return
        self.pose = VectorHead(8 * w, config.hidden, (k - 1) * 6)
        self.transition = nn.Sequential(nn.Linear((k - 1) * 6 + 2 + NUM_DIRECTIONS, config.hidden),
                                        nn.LeakyReLU(0.01, inplace=True), nn.Linear(config.hidden, config.hidden),
                                        nn.LeakyReLU(0.01, inplace=True), nn.Linear(config.hidden, (k - 1) * 6))
        _zero(self.transition[-1])

    def encode(self, points: torch.Tensor, valid: torch.Tensor, action: torch.Tensor | None) -> tuple:
        center = torch.tensor(POINT_CENTER, device=points.device).view(1, 3, 1, 1)
        x = [(points - center) / POINT_SCALE * valid, valid]
        if action is not None:
            x.append(action_maps(action, points.shape[-2:]))
        return self.backbone(torch.cat(x, 1))

    def _masks(self, features: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Softmax masks (B, K, h, w); pixels without a point belong to the background."""
        masks = torch.softmax(self.mask(features).float(), 1)
        background = torch.zeros_like(masks)
        background[:, -1] = 1
        return masks * valid + background * (1 - valid)

    def poses(self, points: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """SE3Pose-Net's encoder: masks (B, K, h, w), pose parameters (B, K-1, 6) (origin metres, Euler
        radians) and poses (B, K-1, 4, 4) of one image."""
        features, bottleneck = self.encode(points, valid, None)
        masks = self._masks(features, valid)
        b, k = masks.shape[:2]
        raw = self.pose(bottleneck).float().view(b, k - 1, 6)
        flat = points.flatten(2).transpose(1, 2).float()
        origin = rigid.masked_centroids(flat, masks.flatten(2)) + raw[..., :3] * TRANSLATION_SCALE
        params = torch.cat([origin, raw[..., 3:]], -1)
        return masks, params, rigid.pose_matrices(params)

    def forward(self, points: torch.Tensor, valid: torch.Tensor, action: torch.Tensor) -> dict[str, torch.Tensor]:
        """The model's outputs for one step (see the module docstring)."""
        name = self.config.name
        if name == "2dflow":
            features, _ = self.encode(points, valid, action)
            return {"flow": self.flow(features).float() * TRANSLATION_SCALE * valid}
        if name == "se3net":
            features, bottleneck = self.encode(points, valid, action)
            masks = self._masks(features, valid)
            b, k = masks.shape[:2]
            raw = self.motion(bottleneck).float().view(b, k - 1, 6)
            pivots = rigid.masked_centroids(points.flatten(2).transpose(1, 2).float(), masks.flatten(2))
            transforms = rigid.about_pivots(euler_to_matrix(raw[..., 3:] * ROTATION_SCALE, "standard"),
                                            raw[..., :3] * TRANSLATION_SCALE, pivots)
            return {"masks": masks, "transforms": transforms}
        masks, params, poses = self.poses(points, valid)
        b, k = masks.shape[:2]
        delta = self.transition(torch.cat([_pose_features(params), action_vectors(action, points.shape[-2:])],
                                          -1)).float().view(b, k - 1, 6)
        turn = euler_to_matrix(delta[..., 3:] * ROTATION_SCALE, "standard")
        next_poses = rigid.homogeneous(turn @ poses[..., :3, :3],
                                       poses[..., :3, 3] + delta[..., :3] * TRANSLATION_SCALE)
        return {"masks": masks, "poses": poses, "next_poses": next_poses, "pose_params": params}


def _pose_features(params: torch.Tensor) -> torch.Tensor:
    """Pose parameters (B, K-1, 6) as the transition's input (B, 6 (K-1)): origins centred on the workspace
    in decimetres, angles in radians."""
    center = torch.tensor(POINT_CENTER, device=params.device)
    return torch.cat([(params[..., :3] - center) / POINT_SCALE, params[..., 3:]], -1).flatten(1)


def flow_at(out: dict[str, torch.Tensor], points: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Flow (B, 3, H, W) in metres, world (x, y, z) components, at the points (B, 3, H, W) of any resolution
    (the network's, or the full image): 2DFlow's flow and the SE3 models' masks are resized bilinearly to
    it, and the SE3 models' rigid motions applied to the points themselves. valid (B, 1, H, W)."""
    size = points.shape[-2:]
    if "flow" in out:
        flow = out["flow"]
        if flow.shape[-2:] != size:
            flow = F.interpolate(flow, size=size, mode="bilinear", align_corners=False)
        return flow * valid
    masks = out["masks"]
    if masks.shape[-2:] != size:
        masks = F.interpolate(masks, size=size, mode="bilinear", align_corners=False)
    b, k = masks.shape[:2]
    flat = points.flatten(2).transpose(1, 2).float()
    if "transforms" in out:
        flow = rigid.blended_flow(flat, masks.flatten(2), out["transforms"])
    else:
        flow = rigid.flow_from_poses(flat, masks.flatten(2), out["poses"], out["next_poses"])
    return flow.transpose(1, 2).reshape(b, 3, *size) * valid
