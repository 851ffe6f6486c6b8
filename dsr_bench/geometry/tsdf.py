"""Projective TSDF of one depth image on the benchmark grid (vectorised numpy).

The official definition: every voxel's sample point (its lower corner, `bound_min + index *
VOXEL_SIZE`, as the official fusion code's `vol_origin + voxel * voxel_size`) is projected into the
depth image and reads the pixel nearest to its projection; with sdf = depth(pixel) - z_cam(voxel),
the value is min(1, sdf / trunc) where sdf >= -trunc, and the initial +1 elsewhere (behind the
surface band, outside the image, or where depth is missing). Values lie in [-1, 1]; occluded space
reads like free space.
"""

from __future__ import annotations

import numpy as np

from dsr_bench.cache import FrozenCache, camera_key
from dsr_bench.constants import GRID_SHAPE, TSDF_TRUNCATION
from dsr_bench.geometry import Camera, rigid_inverse, transform_points, voxel_points

#: Voxel projections per (camera, grid): they depend on nothing else, and computing them costs more
#: than integrating several depth images, so every ProjectiveTSDF of the same camera shares them.
_PROJECTIONS = FrozenCache(8)


def _projection(camera: Camera, grid_shape: tuple[int, int, int]) -> tuple[np.ndarray, ...]:
    """(voxels, z, pixels, inverse, counts, *grouped): the voxels whose centre projects into the
    image (flat indices, ascending), their camera z, the distinct image pixels they read (flat,
    ascending), per voxel the index of its pixel among those, the number of voxels of each pixel;
    then the same voxels grouped by pixel (stable): their flat index, z, pixel index and z in
    float32. Cached; the arrays are read-only."""
    return _PROJECTIONS.get(camera_key(camera) + (tuple(grid_shape),), lambda: _project(camera, grid_shape))


def _project(camera: Camera, grid_shape: tuple[int, int, int]) -> tuple[np.ndarray, ...]:
    points = voxel_points(grid_shape).reshape(-1, 3)
    cam = transform_points(rigid_inverse(camera.extrinsics), points)
    z = cam[:, 2]
    fx, fy = camera.intrinsics[0, 0], camera.intrinsics[1, 1]
    cx, cy = camera.intrinsics[0, 2], camera.intrinsics[1, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(cam[:, 0] / z * fx + cx)
        v = np.rint(cam[:, 1] / z * fy + cy)
    inside = (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    voxels = np.flatnonzero(inside)
    pixels_of_voxels = v[inside].astype(np.int64) * camera.width + u[inside].astype(np.int64)
    # np.unique(pixels_of_voxels, return_inverse=True) without its sort: pixel ids are bounded by the image
    present = np.bincount(pixels_of_voxels, minlength=camera.height * camera.width) > 0
    pixels = np.flatnonzero(present)
    inverse = (np.cumsum(present) - 1)[pixels_of_voxels].astype(np.intp)
    z_in = np.ascontiguousarray(z[inside])
    # the voxels grouped by pixel (stable), for the band search of `ProjectiveTSDF.from_pixel_depths`
    order = np.argsort(inverse, kind="stable")
    counts = np.bincount(inverse, minlength=len(pixels))
    grouped = (voxels[order], z_in[order], inverse[order], z_in[order].astype(np.float32))
    return (voxels, z_in, pixels, inverse, counts) + grouped


class ProjectiveTSDF:
    """TSDF integration for one fixed camera: voxel projections are computed once (per process and
    camera), then each depth image costs one gather and a few vector operations."""

    def __init__(self, camera: Camera, truncation: float = TSDF_TRUNCATION,
                 grid_shape: tuple[int, int, int] = GRID_SHAPE):
        ny, nx, nz = grid_shape  # a tuple, whatever sequence was given
        self.camera, self.truncation, self.grid_shape = camera, truncation, (ny, nx, nz)
        (_, self._z, self._pixels, _, self._counts,
         self._g_voxels, self._g_z, self._g_pixel, self._g_z32) = _projection(camera, self.grid_shape)
        # float32 error of |d - z| where |d - z| <= trunc: a few float32 ulps of z_max + trunc
        z_max = float(self._z.max()) if len(self._z) else 0.0
        self._margin = 1e-5 + 1e-6 * (z_max + truncation)
        self._offsets = np.cumsum(self._counts) - self._counts  # each pixel's first grouped voxel

    @property
    def pixels(self) -> np.ndarray:
        """Flat indices (ascending) of the only image pixels the TSDF reads: a renderer needs depth
        there alone (see `from_pixel_depths`)."""
        return self._pixels

    def __call__(self, depth: np.ndarray) -> np.ndarray:
        """TSDF (Y, X, Z) float32 in [-1, 1] from a z-depth image (H, W) in metres (0 = no return).

        Each voxel reads the depth of the pixel whose centre is nearest to its projection.
        """
        if depth.shape != (self.camera.height, self.camera.width):
            raise ValueError(f"depth image {depth.shape} does not match camera "
                             f"{self.camera.height}x{self.camera.width}")
        return self.from_pixel_depths(np.asarray(depth).reshape(-1)[self._pixels])

    def from_pixel_depths(self, pixel_depth: np.ndarray) -> np.ndarray:
        """The TSDF of a depth image given only at `pixels` (same order), z-depth in metres (0 = none);
        identical to calling the TSDF on the full image.

        A voxel differs from +1 only where its pixel has depth d > 0 and |d - z| <= trunc (from
        d - z >= trunc follows (d - z) / trunc >= 1). A float32 pass finds a superset of those
        voxels (|d - z| <= trunc + margin, the margin 10 um plus 1e-6 of the farthest voxel's z:
        over 16 times float32's rounding there), and only they are computed, with the definition's
        float64 arithmetic; every other voxel is exactly +1.
        """
        pixel_depth = np.asarray(pixel_depth)
        if pixel_depth.shape != self._pixels.shape:
            raise ValueError(f"{pixel_depth.shape} depths given for {len(self._pixels)} TSDF pixels")
        if pixel_depth.dtype != np.float64:  # the definition computes in float64 (as from a float64 image)
            pixel_depth = pixel_depth.astype(np.float64)
        trunc = self.truncation
        with np.errstate(invalid="ignore", over="ignore"):
            seen = np.where(pixel_depth > 0, pixel_depth, -np.inf).astype(np.float32)  # -inf: never near
            gap = np.repeat(seen, self._counts)
            gap -= self._g_z32
            np.abs(gap, out=gap)
            near = np.flatnonzero(gap <= np.float32(trunc + self._margin))
        sdf = pixel_depth[self._g_pixel[near]] - self._g_z[near]
        keep = sdf >= -trunc
        tsdf = np.ones(int(np.prod(self.grid_shape)), dtype=np.float32)
        tsdf[self._g_voxels[near[keep]]] = np.minimum(1.0, sdf[keep] / trunc)
        return tsdf.reshape(self.grid_shape)

    def update_pixels(self, base: np.ndarray, pixel_depth: np.ndarray, changed: np.ndarray) -> np.ndarray:
        """The TSDF of `pixel_depth` (as `from_pixel_depths`) given `base`, the TSDF of a depth image
        that differs from it only at the pixels flagged in `changed` (bool over `pixels`): a voxel's
        value depends on its own pixel's depth alone, so only the voxels of changed pixels are
        recomputed (with the definition's float64 arithmetic) and the rest are copied from `base`."""
        pixel_depth = np.asarray(pixel_depth, dtype=np.float64)
        if pixel_depth.shape != self._pixels.shape or changed.shape != self._pixels.shape:
            raise ValueError(f"depths and flags must be given for the {len(self._pixels)} TSDF pixels")
        tsdf = np.array(base, dtype=np.float32).reshape(-1)
        index = np.flatnonzero(changed)
        if len(index) == 0:
            return tsdf.reshape(self.grid_shape)
        counts = self._counts[index]
        total = int(counts.sum())
        # positions of the changed pixels' voxels in the grouped order (runs of consecutive positions)
        pos = np.repeat(self._offsets[index] - np.cumsum(counts) + counts, counts) + np.arange(total)
        d = np.repeat(pixel_depth[index], counts)
        sdf = d - self._g_z[pos]
        keep = (d > 0) & (sdf >= -self.truncation)
        with np.errstate(invalid="ignore"):
            tsdf[self._g_voxels[pos]] = np.where(keep, np.minimum(1.0, sdf / self.truncation), 1.0)
        return tsdf.reshape(self.grid_shape)


def integrate_tsdf(
    depth: np.ndarray,
    camera: Camera,
    truncation: float = TSDF_TRUNCATION,
    grid_shape: tuple[int, int, int] = GRID_SHAPE,
) -> np.ndarray:
    """TSDF (Y, X, Z) float32 in [-1, 1] from a z-depth image (H, W) in metres (0 = no return)."""
    return ProjectiveTSDF(camera, truncation, grid_shape)(depth)
