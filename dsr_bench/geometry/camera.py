"""Pinhole cameras: OpenCV axes (x right, y down, z forward), 4x4 camera-to-world extrinsics, pixel
(u, v) centres at integer coordinates, principal point (W / 2, H / 2), as in the official release.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dsr_bench.constants import CAMERA_HFOV, CAMERAS
from dsr_bench.geometry.transforms import apply_matrix, rigid_inverse, transform_points, vector_norm

#: The `convention` a sequence file's camera attributes state (`Camera.as_attrs`).
CAMERA_CONVENTION = "opencv, camera-to-world"


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: intrinsics (3x3, pixels) and camera-to-world extrinsics (4x4, OpenCV)."""

    name: str
    height: int
    width: int
    intrinsics: np.ndarray
    extrinsics: np.ndarray

    def as_attrs(self) -> dict:
        """The camera as a sequence file stores it under its `cameras` attribute (JSON: size, intrinsics,
        camera-to-world extrinsics, the convention); `Camera.from_attrs` reads it back."""
        return {"height": int(self.height), "width": int(self.width),
                "intrinsics": np.asarray(self.intrinsics).tolist(), "extrinsics": np.asarray(self.extrinsics).tolist(),
                "convention": CAMERA_CONVENTION}

    @classmethod
    def from_attrs(cls, name: str, spec: dict) -> Camera:
        """The camera `name` of a sequence file's `cameras` attribute (`as_attrs`'s dict)."""
        return cls(name, int(spec["height"]), int(spec["width"]), np.array(spec["intrinsics"]),
                   np.array(spec["extrinsics"]))

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
    return np.array([[1 / fx, -s / (fx * fy), (s * cy - cx * fy) / (fx * fy)],
                     [0.0, 1 / fy, -cy / fy],
                     [0.0, 0.0, 1.0]])


def pinhole_intrinsics(height: int, width: int, hfov: float = CAMERA_HFOV) -> np.ndarray:
    """3x3 intrinsics with focal length (W / 2) / tan(hfov / 2) and principal point (W/2, H/2)."""
    f = (width / 2) / math.tan(hfov / 2)  # glibc's tan: the same on every x86-64 CPU with FMA
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def resized_camera(camera, height: int, width: int) -> Camera:
    """The same camera at another image size (height, width): fx, skew and cx scale by width / camera.width, fy
    and cy by height / camera.height, so pixel centres stay at integer coordinates (pixel (u', v') of the new size
    looks along the ray of (u' W / W', v' H / H') of the old). `camera`: any object with name, height, width,
    intrinsics and extrinsics (a `Camera`, a capture's camera)."""
    k = np.asarray(camera.intrinsics, dtype=np.float64).copy()
    k[0, :] *= width / camera.width
    k[1, :] *= height / camera.height
    return Camera(camera.name, height, width, k, np.asarray(camera.extrinsics, dtype=np.float64))


def make_camera(name: str, height: int, width: int) -> Camera:
    """One of the benchmark's cameras ('front' or 'back') at a given image size."""
    if name not in CAMERAS:
        raise ValueError(f"unknown camera {name!r}; choose from {', '.join(CAMERAS)}")
    spec = CAMERAS[name]
    return Camera(
        name, height, width, pinhole_intrinsics(height, width), look_at(spec["eye"], spec["target"], spec["up"])
    )
