"""Rigid transforms: quaternions (x, y, z, w), poses (x, y, z, qx, qy, qz, qw), 4x4 matrices, in metres.

Every product is written element-wise in a fixed order (no BLAS), so the ground truth computed from
poses is the same bits on every CPU.
"""

from __future__ import annotations

import numpy as np


def quat_to_matrix(quat_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from unit quaternions (..., 4) in (x, y, z, w) order."""
    q = np.asarray(quat_xyzw, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rot = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return rot.reshape(q.shape[:-1] + (3, 3))


def pose_to_matrix(pose: np.ndarray) -> np.ndarray:
    """4x4 transforms (..., 4, 4) from poses (..., 7) = (x, y, z, qx, qy, qz, qw), metres."""
    pose = np.asarray(pose, dtype=np.float64)
    out = np.zeros(pose.shape[:-1] + (4, 4))
    out[..., :3, :3] = quat_to_matrix(pose[..., 3:7])
    out[..., :3, 3] = pose[..., :3]
    out[..., 3, 3] = 1.0
    return out


def matrix_to_pose(transform: np.ndarray) -> np.ndarray:
    """Pose (7,) = (x, y, z, qx, qy, qz, qw), metres, of a rigid 4x4 transform (qw >= 0); the inverse of
    `pose_to_matrix` (up to the quaternion's sign)."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(np.asarray(transform)[:3, :3]).as_quat()
    if q[3] < 0:
        q = -q
    return np.concatenate([np.asarray(transform)[:3, 3], q]).astype(np.float64)


# Ground truth must be identical on every x86-64 machine: numpy's `@`, `np.dot` and `np.linalg` go
# through OpenBLAS / LAPACK, whose kernels (chosen per CPU at run time) sum in different orders. The
# small products below are written as element-wise operations in a fixed order instead (IEEE-exact
# on every instruction set), so a pinned split reproduces bit for bit across CPUs.


def apply_matrix(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """matrix (3, 3) times each point (..., 3), i.e. `points @ matrix.T`, in a fixed summation order."""
    m = np.asarray(matrix, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    return p[..., 0:1] * m[:, 0] + p[..., 1:2] * m[:, 1] + p[..., 2:3] * m[:, 2]


def dot_last(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot product over the last axis (broadcast), summed left to right without BLAS (see `apply_matrix`)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    out = a[..., 0] * b[..., 0]
    for i in range(1, max(a.shape[-1], b.shape[-1])):
        out = out + a[..., i] * b[..., i]
    return out


def rotation_angle(rotation: np.ndarray) -> float:
    """Angle (radians, 0..pi) of a 3x3 rotation matrix."""
    cos = (rotation[0, 0] + rotation[1, 1] + rotation[2, 2] - 1.0) / 2.0
    return float(np.arccos(np.clip(cos, -1.0, 1.0)))


def vector_norm(v: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis, without BLAS (see `apply_matrix`)."""
    v = np.asarray(v, dtype=np.float64)
    return np.sqrt(np.sum(v * v, axis=-1))


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points (..., 3), metres."""
    return apply_matrix(transform[:3, :3], points) + transform[:3, 3]


def rigid_inverse(transform: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform: (R^T, -R^T t)."""
    out = np.eye(4)
    rt = np.asarray(transform, dtype=np.float64)[:3, :3].T
    out[:3, :3] = rt
    out[:3, 3] = -apply_matrix(rt, transform[:3, 3])
    return out


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The 4x4 product a @ b of two affine transforms, in a fixed summation order."""
    out = np.eye(4)
    out[:3, :3] = apply_matrix(a[:3, :3], np.asarray(b, dtype=np.float64)[:3, :3].T).T
    out[:3, 3] = apply_matrix(a[:3, :3], b[:3, 3]) + a[:3, 3]
    return out


def relative_motion(pose_from: np.ndarray, pose_to: np.ndarray) -> np.ndarray:
    """The world-frame 4x4 rigid motion T with T @ pose_from = pose_to (poses as (7,))."""
    return compose(pose_to_matrix(pose_to), rigid_inverse(pose_to_matrix(pose_from)))
