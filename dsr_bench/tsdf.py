"""Projective TSDF of one depth image on the benchmark grid (vectorised numpy).

The official definition: every voxel centre is projected into the depth image; with
sdf = depth(pixel) - z_cam(voxel), the value is min(1, sdf / trunc) where sdf >= -trunc, and the
initial +1 elsewhere (behind the surface band, outside the image, or where depth is missing).
Values lie in [-1, 1]; occluded space reads like free space.
"""

from __future__ import annotations

import numpy as np

from dsr_bench.constants import GRID_SHAPE, TSDF_TRUNCATION
from dsr_bench.geometry import Camera, voxel_centers

_CENTERS_CACHE: dict[tuple[int, int, int], np.ndarray] = {}


def _centers(grid_shape: tuple[int, int, int]) -> np.ndarray:
    if grid_shape not in _CENTERS_CACHE:
        _CENTERS_CACHE[grid_shape] = voxel_centers(grid_shape).reshape(-1, 3)
    return _CENTERS_CACHE[grid_shape]


def integrate_tsdf(
    depth: np.ndarray,
    camera: Camera,
    truncation: float = TSDF_TRUNCATION,
    grid_shape: tuple[int, int, int] = GRID_SHAPE,
) -> np.ndarray:
    """TSDF (Y, X, Z) float32 in [-1, 1] from a z-depth image (H, W) in metres (0 = no return).

    Each voxel reads the depth of the pixel whose centre is nearest to its projection.
    """
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth image {depth.shape} does not match camera {camera.height}x{camera.width}")
    centers = _centers(grid_shape)
    world_to_cam = np.linalg.inv(camera.extrinsics)
    cam = centers @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    z = cam[:, 2]
    fx, fy = camera.intrinsics[0, 0], camera.intrinsics[1, 1]
    cx, cy = camera.intrinsics[0, 2], camera.intrinsics[1, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(cam[:, 0] / z * fx + cx)
        v = np.rint(cam[:, 1] / z * fy + cy)
    inside = (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    tsdf = np.ones(centers.shape[0], dtype=np.float32)
    idx = np.flatnonzero(inside)
    d = depth[v[idx].astype(np.int64), u[idx].astype(np.int64)]
    sdf = d - z[idx]
    keep = (d > 0) & (sdf >= -truncation)
    tsdf[idx[keep]] = np.minimum(1.0, sdf[keep] / truncation).astype(np.float32)
    return tsdf.reshape(grid_shape)
