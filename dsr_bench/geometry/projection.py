"""A volume's scene flow read at world points: how a 3D prediction is scored on the 2D track.

The paper scores DSR-Net on the 2D track by reading its 3D flow at the surface point each front-camera
pixel sees (`cameras/front/points`): `flow_at_points` interpolates the flow trilinearly over the voxels
around each point, using only the voxels the predicted mask labels as object.
"""

from __future__ import annotations

import numpy as np

from dsr_bench.constants import GRID_SHAPE, VOXEL_SIZE
from dsr_bench.geometry.grid import world_to_voxel


def flow_at_points(motion: np.ndarray, mask: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Scene flow (H, W, 3) float32 in metres, components (dy, dx, dz), at world points.

    motion: (3, 128, 128, 48) flow in voxels, components (dy, dx, dz), volume axes (y, x, z), on the
    benchmark's grid (`GRID_SHAPE`, sampled at the voxels' lower corners). mask: (128, 128, 48) object
    slots, 0 empty. points: (H, W, 3) world (x, y, z) metres, NaN where a pixel has no return.
    Each point gets the trilinear interpolation of `motion` over the 8 voxels around it, weighted over
    the voxels `mask` labels (> 0) only (weights renormalised over those); 0 where none of them is
    labelled with a positive weight, where the point is NaN, or outside the grid.
    """
    motion, mask, points = np.asarray(motion), np.asarray(mask), np.asarray(points)
    if motion.shape != (3,) + GRID_SHAPE:
        raise ValueError(f"motion must be (3, {', '.join(map(str, GRID_SHAPE))}) voxels (dy, dx, dz), "
                         f"got {motion.shape}")
    if mask.shape != GRID_SHAPE:
        raise ValueError(f"mask must be ({', '.join(map(str, GRID_SHAPE))}), got {mask.shape}")
    if points.ndim < 1 or points.shape[-1] != 3:
        raise ValueError(f"points must be (..., 3) world (x, y, z) metres, got {points.shape}")
    out_shape = points.shape[:-1] + (3,)
    coords = world_to_voxel(points.reshape(-1, 3))  # (N, 3) continuous (iy, ix, iz)
    finite = np.all(np.isfinite(coords), axis=1)
    coords = np.where(finite[:, None], coords, -2.0)  # NaN -> outside the grid: no corner in bounds
    base = np.floor(coords)
    frac = coords - base
    base = base.astype(np.int64)
    shape = np.array(GRID_SHAPE)
    total = np.zeros((len(coords), 3), np.float64)
    weights = np.zeros(len(coords), np.float64)
    labelled = mask > 0
    for corner in np.ndindex(2, 2, 2):  # the 8 voxels around each point (a loop over corners, not pixels)
        offset = np.array(corner)
        idx = base + offset
        inside = finite & np.all((idx >= 0) & (idx < shape), axis=1)
        iy, ix, iz = (np.where(inside, idx[:, a], 0) for a in range(3))
        w = np.prod(np.where(offset == 1, frac, 1.0 - frac), axis=1)
        w = np.where(inside & labelled[iy, ix, iz], w, 0.0)
        weights += w
        total += w[:, None] * motion[:, iy, ix, iz].T.astype(np.float64)
    flow = np.divide(total, weights[:, None], out=np.zeros_like(total), where=weights[:, None] > 0)
    return (flow * VOXEL_SIZE).astype(np.float32).reshape(out_shape)
