"""The voxel grid and the workspace grid: sample points, world <-> voxel and cell coordinates, push
directions.

Volumes are indexed (iy, ix, iz); voxel (iy, ix, iz) is sampled at bound_min + (index +
VOXEL_SAMPLE_OFFSET) * VOXEL_SIZE, its lower corner as in the official release (TSDF, amodal masks
and 3D flow alike). The workspace grid of actions and the heightmap (128 x 128 cells, row along y)
is an image: cell (row, col) covers [bound_min + index * VOXEL_SIZE, + VOXEL_SIZE) and is sampled at
its centre.
"""

from __future__ import annotations

import numpy as np

from dsr_bench.constants import GRID_BOUNDS, GRID_SHAPE, VOXEL_SAMPLE_OFFSET, VOXEL_SIZE


def axis_samples(axis: int, count: int | None = None) -> np.ndarray:
    """Sample coordinates (metres) of the voxels along world axis 0 (x), 1 (y) or 2 (z), increasing."""
    n = GRID_SHAPE[[1, 0, 2][axis]] if count is None else count
    return GRID_BOUNDS[axis, 0] + (np.arange(n) + VOXEL_SAMPLE_OFFSET) * VOXEL_SIZE


def voxel_points(grid_shape: tuple[int, int, int] = GRID_SHAPE) -> np.ndarray:
    """World coordinates (x, y, z) of every voxel's sample point, shape (*grid_shape, 3), metres."""
    yy, xx, zz = np.meshgrid(axis_samples(1, grid_shape[0]), axis_samples(0, grid_shape[1]),
                             axis_samples(2, grid_shape[2]), indexing="ij")
    return np.stack([xx, yy, zz], axis=-1)


def voxel_points_of(indices_yxz: np.ndarray) -> np.ndarray:
    """World sample points (M, 3) in (x, y, z) metres of integer voxel indices (M, 3) in (iy, ix, iz)."""
    idx = np.asarray(indices_yxz)[:, [1, 0, 2]].astype(np.float64)
    return GRID_BOUNDS[:, 0] + (idx + VOXEL_SAMPLE_OFFSET) * VOXEL_SIZE


def world_to_voxel(points_xyz: np.ndarray) -> np.ndarray:
    """Continuous voxel coordinates (iy, ix, iz) of world points (..., 3) in (x, y, z) metres.

    A voxel's sample point maps to its integer index; round(coordinate) is the nearest voxel.
    """
    p = np.asarray(points_xyz, dtype=np.float64)
    v = (p - GRID_BOUNDS[:, 0]) / VOXEL_SIZE - VOXEL_SAMPLE_OFFSET
    return v[..., [1, 0, 2]]


def voxel_to_world(voxel_yxz: np.ndarray) -> np.ndarray:
    """World points (x, y, z) metres of continuous voxel coordinates (..., 3) in (iy, ix, iz)."""
    v = np.asarray(voxel_yxz, dtype=np.float64)[..., [1, 0, 2]]
    return GRID_BOUNDS[:, 0] + (v + VOXEL_SAMPLE_OFFSET) * VOXEL_SIZE


def world_to_pixel(xy: np.ndarray) -> np.ndarray:
    """(row, col) workspace-grid cells (int) of world points (..., 2) in (x, y) metres."""
    xy = np.asarray(xy, dtype=np.float64)
    col = np.floor((xy[..., 0] - GRID_BOUNDS[0, 0]) / VOXEL_SIZE).astype(np.int64)
    row = np.floor((xy[..., 1] - GRID_BOUNDS[1, 0]) / VOXEL_SIZE).astype(np.int64)
    return np.stack([row, col], axis=-1)


def pixel_to_world(row_col: np.ndarray) -> np.ndarray:
    """World (x, y) metres of the centres of workspace-grid cells (..., 2) in (row, col)."""
    rc = np.asarray(row_col, dtype=np.float64)
    x = GRID_BOUNDS[0, 0] + (rc[..., 1] + 0.5) * VOXEL_SIZE
    y = GRID_BOUNDS[1, 0] + (rc[..., 0] + 0.5) * VOXEL_SIZE
    return np.stack([x, y], axis=-1)


#: (cos, sin) of d * pi / 4 for d = 0..7, exact: 0, +-1 and +-sqrt(1/2) (IEEE sqrt is correctly rounded; numpy's
#: cos and sin are not the same function on every instruction set, and cos(pi / 2) is 6e-17, not 0).
_S = float(np.sqrt(0.5))
_DIRECTIONS = np.array([[1.0, 0.0], [_S, _S], [0.0, 1.0], [-_S, _S], [-1.0, 0.0], [-_S, -_S], [0.0, -1.0], [_S, -_S]])


def direction_vector(direction: int | np.ndarray) -> np.ndarray:
    """Unit push direction(s) (..., 2) in world (x, y) for direction index d in 0..7: angle d * pi / 4."""
    d = np.asarray(direction)
    if not np.issubdtype(d.dtype, np.integer) or np.any((d < 0) | (d > 7)):
        raise ValueError(f"push directions are integers 0..7, got {direction!r}")
    return _DIRECTIONS[d]
