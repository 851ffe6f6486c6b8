"""Grid, pose and camera geometry shared by the generator, the readers, the metrics and the viewer.

Conventions (see DATASHEET.md):
- World frame: table plane z = 0, metres. Quaternions are (x, y, z, w), as in pybullet and the
  official release.
- Volumes are indexed (iy, ix, iz); voxel (iy, ix, iz) is sampled at its sample point
  bound_min + (index + VOXEL_SAMPLE_OFFSET) * VOXEL_SIZE, the voxel's lower corner as in the
  official release (TSDF, amodal masks and 3D flow alike).
- The workspace grid of actions and the heightmap (128 x 128 cells, row along y) is an image:
  cell (row, col) covers [bound_min + index * VOXEL_SIZE, + VOXEL_SIZE) and is sampled at its centre.
- Cameras use the OpenCV convention (x right, y down, z forward); an extrinsic is the 4x4
  camera-to-world transform; pixel (u, v) centres sit at integer coordinates and the principal
  point is (W / 2, H / 2), as in the official release.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dsr_bench.constants import CAMERA_HFOV, CAMERAS, GRID_BOUNDS, GRID_SHAPE, VOXEL_SAMPLE_OFFSET, VOXEL_SIZE

# --- Poses -------------------------------------------------------------------------------------


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


# --- The voxel grid ----------------------------------------------------------------------------


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


# --- Cameras -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: intrinsics (3x3, pixels) and camera-to-world extrinsics (4x4, OpenCV)."""

    name: str
    height: int
    width: int
    intrinsics: np.ndarray
    extrinsics: np.ndarray

    def ray_directions_world(self) -> np.ndarray:
        """World-frame ray directions (H, W, 3) with unit camera z (so t along a ray = z-depth)."""
        v, u = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
        pix = np.stack([u, v, np.ones_like(u)], axis=-1).astype(np.float64)
        return apply_matrix(self.extrinsics[:3, :3], apply_matrix(pinhole_inverse(self.intrinsics), pix))

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (..., 2) as (u, v) and z-depth (...,) of world points (..., 3)."""
        cam = transform_points(rigid_inverse(self.extrinsics), points_world)
        z = cam[..., 2]
        uv = cam[..., :2] / z[..., None] * np.diag(self.intrinsics)[:2] + self.intrinsics[:2, 2]
        return uv, z

    def backproject(self, depth: np.ndarray) -> np.ndarray:
        """World points (H, W, 3) of a z-depth image (H, W) in metres (invalid depth 0 -> NaN)."""
        pts = self.ray_directions_world() * depth[..., None] + self.extrinsics[:3, 3]
        pts[depth <= 0] = np.nan
        return pts


def look_at(eye, target, up) -> np.ndarray:
    """Camera-to-world 4x4 (OpenCV axes) of a camera at `eye` looking at `target`."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    forward = target - eye
    forward /= vector_norm(forward)
    right = np.cross(forward, up)
    right /= vector_norm(right)
    down = np.cross(forward, right)
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2], out[:3, 3] = right, down, forward, eye
    return out


def pinhole_inverse(intrinsics: np.ndarray) -> np.ndarray:
    """Closed-form inverse of intrinsics [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (no LAPACK, see `apply_matrix`)."""
    (fx, s, cx), (_, fy, cy) = np.asarray(intrinsics, dtype=np.float64)[:2]
    return np.array([[1 / fx, -s / (fx * fy), (s * cy - cx * fy) / (fx * fy)], [0.0, 1 / fy, -cy / fy], [0.0, 0.0, 1.0]])


def pinhole_intrinsics(height: int, width: int, hfov: float = CAMERA_HFOV) -> np.ndarray:
    """3x3 intrinsics with focal length (W / 2) / tan(hfov / 2) and principal point (W/2, H/2)."""
    f = (width / 2) / math.tan(hfov / 2)  # glibc's tan: the same on every x86-64 CPU with FMA
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def make_camera(name: str, height: int, width: int) -> Camera:
    """One of the benchmark's cameras ('front' or 'back') at a given image size."""
    if name not in CAMERAS:
        raise ValueError(f"unknown camera {name!r}; choose from {', '.join(CAMERAS)}")
    spec = CAMERAS[name]
    return Camera(
        name, height, width, pinhole_intrinsics(height, width), look_at(spec["eye"], spec["target"], spec["up"])
    )
