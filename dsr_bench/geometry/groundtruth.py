"""Ground truth derived from object poses: rigid 3D and 2D scene flow (numpy only).

Used by the generator, the annotator's export and `dsr-bench validate` (which recomputes flow from
the stored poses and amodal masks), so every producer and checker shares one definition.
"""

from __future__ import annotations

import numpy as np

from dsr_bench.constants import VOXEL_SIZE
from dsr_bench.geometry import relative_motion, transform_points, voxel_points_of


def rigid_scene_flow_3d(mask_t: np.ndarray, poses_t: np.ndarray, poses_next: np.ndarray,
                        out: np.ndarray | None = None) -> np.ndarray:
    """3D scene flow (3, Y, X, Z) float32 in voxels, components (dy, dx, dz).

    mask_t: amodal instance ids (Y, X, Z) at t (0 empty, i + 1 = object i); poses_t, poses_next:
    (N, 7) world poses at t and t + 1. Each object's voxels move with the object's rigid motion,
    evaluated at their sample points (`dsr_bench.geometry.voxel_points_of`); empty voxels get 0. `out`, if
    given, must be zeros; it is filled in place and returned.
    """
    flow = np.zeros((3,) + mask_t.shape, dtype=np.float32) if out is None else out
    flat = np.flatnonzero(mask_t)
    labels = mask_t.reshape(-1)[flat]
    indices = np.stack(np.unravel_index(flat, mask_t.shape), axis=1)
    flow_flat = flow.reshape(3, -1)
    for i in range(poses_t.shape[0]):
        sel = labels == i + 1
        if not sel.any():
            continue
        motion = relative_motion(poses_t[i], poses_next[i])
        points = voxel_points_of(indices[sel])
        moved = transform_points(motion, points)
        disp = (moved - points)[:, [1, 0, 2]] / VOXEL_SIZE
        flow_flat[:, flat[sel]] = disp.T.astype(np.float32)
    return flow


def rigid_scene_flow_2d(points: np.ndarray, mask_2d: np.ndarray, poses_t: np.ndarray,
                        poses_next: np.ndarray) -> np.ndarray:
    """2D scene flow (H, W, 3) float32 in metres, components (dy, dx, dz).

    points: world points (H, W, 3) seen at t (NaN where no return); mask_2d: visible instance ids
    (H, W). Background and missing pixels get 0.
    """
    flow = np.zeros(points.shape, dtype=np.float32)
    for i in range(poses_t.shape[0]):
        sel = mask_2d == i + 1
        if not sel.any():
            continue
        motion = relative_motion(poses_t[i], poses_next[i])
        p = points[sel].astype(np.float64)
        disp = transform_points(motion, p) - p
        flow[sel] = disp[:, [1, 0, 2]].astype(np.float32)
    return flow
