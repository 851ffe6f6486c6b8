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



class ProjectiveTSDF:
    """TSDF integration for one fixed camera: voxel projections are computed once, then each depth
    image costs one gather and a few vector operations."""

    def __init__(self, camera: Camera, truncation: float = TSDF_TRUNCATION,
                 grid_shape: tuple[int, int, int] = GRID_SHAPE):
        self.camera, self.truncation, self.grid_shape = camera, truncation, grid_shape
        centers = voxel_centers(grid_shape).reshape(-1, 3)
        world_to_cam = np.linalg.inv(camera.extrinsics)
        cam = centers @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
        z = cam[:, 2]
        fx, fy = camera.intrinsics[0, 0], camera.intrinsics[1, 1]
        cx, cy = camera.intrinsics[0, 2], camera.intrinsics[1, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.rint(cam[:, 0] / z * fx + cx)
            v = np.rint(cam[:, 1] / z * fy + cy)
        inside = (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        self._voxels = np.flatnonzero(inside)
        self._pixels = (v[inside].astype(np.int64) * camera.width + u[inside].astype(np.int64))
        self._z = z[inside]

    def __call__(self, depth: np.ndarray) -> np.ndarray:
        """TSDF (Y, X, Z) float32 in [-1, 1] from a z-depth image (H, W) in metres (0 = no return).

        Each voxel reads the depth of the pixel whose centre is nearest to its projection.
        """
        if depth.shape != (self.camera.height, self.camera.width):
            raise ValueError(f"depth image {depth.shape} does not match camera {self.camera.height}x{self.camera.width}")
        d = depth.reshape(-1)[self._pixels]
        sdf = d - self._z
        keep = (d > 0) & (sdf >= -self.truncation)
        tsdf = np.ones(int(np.prod(self.grid_shape)), dtype=np.float32)
        tsdf[self._voxels[keep]] = np.minimum(1.0, sdf[keep] / self.truncation)
        return tsdf.reshape(self.grid_shape)


def integrate_tsdf(
    depth: np.ndarray,
    camera: Camera,
    truncation: float = TSDF_TRUNCATION,
    grid_shape: tuple[int, int, int] = GRID_SHAPE,
) -> np.ndarray:
    """TSDF (Y, X, Z) float32 in [-1, 1] from a z-depth image (H, W) in metres (0 = no return)."""
    return ProjectiveTSDF(camera, truncation, grid_shape)(depth)
