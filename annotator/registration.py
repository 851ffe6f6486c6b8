"""Colour undistortion and depth registration of a RealSense recording's streams, in numpy (`annotator.bag` reads the
streams; docs/annotator.md, "RealSense recordings").

Colour is undistorted onto its own pinhole (fx, fy, cx, cy) (`undistortion_maps`) according to librealsense's
distortion model; depth is registered to it (`align_depth`): each depth pixel is back-projected with the depth
stream's intrinsics (and distortion), moved into the colour camera by the depth -> colour extrinsics, and splatted
over the colour pixels its footprint covers, the nearest surface winning (z-buffer); 0 = no depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dsr_bench.annotator.rig import undistort_maps
from dsr_bench.dataset.capture import CaptureCamera

#: librealsense's distortion models (`rs2_distortion_to_string`) this importer undistorts.
SUPPORTED_MODELS = ("None", "Brown Conrady", "Inverse Brown Conrady", "Modified Brown Conrady")
#: A depth pixel's footprint larger than this (colour pixels per axis) is dropped (a grazing or broken sample).
MAX_SPLAT = 8
#: Registration's z-buffer: candidates within SAME_SURFACE_M + SAME_SURFACE_REL x z (m) of a colour pixel's nearest
#: one are the same surface (a sloped table's neighbouring samples); anything further behind is hidden by it.
SAME_SURFACE_M, SAME_SURFACE_REL = 0.005, 0.01


@dataclass(frozen=True)
class StreamInfo:
    """A stream's sensor_msgs/CameraInfo: image width and height (px), intrinsics (3, 3) px, librealsense's distortion
    model name and its coefficients (5,) [k1, k2, p1, p2, k3]."""

    width: int
    height: int
    intrinsics: np.ndarray
    model: str
    coeffs: np.ndarray

    @property
    def distorted(self) -> bool:
        """Whether the coefficients bend rays at all (all-zero coefficients are a pinhole in every model)."""
        return self.model != "None" and bool(np.any(self.coeffs != 0))


# --- distortion ------------------------------------------------------------------------------------------------------


def _brown(xy: np.ndarray, c: np.ndarray, modified: bool) -> np.ndarray:
    """Brown-Conrady polynomial of normalised points (N, 2) with c = [k1, k2, p1, p2, k3]: OpenCV's (tangential terms
    of the original point) or librealsense's "Modified" form (tangential terms of the radially scaled point)."""
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    f = 1 + c[0] * r2 + c[1] * r2 * r2 + c[4] * r2 * r2 * r2
    tx, ty = (x * f, y * f) if modified else (x, y)
    return np.stack([x * f + 2 * c[2] * tx * ty + c[3] * (r2 + 2 * tx * tx),
                     y * f + 2 * c[3] * tx * ty + c[2] * (r2 + 2 * ty * ty)], 1)


def _invert(function, target: np.ndarray, iterations: int = 50, tolerance: float = 1e-12) -> np.ndarray:
    """Points p (N, 2) with function(p) = target (fixed-point iteration, until every point is within `tolerance`;
    the polynomials are near the identity)."""
    p = target.copy()
    for _ in range(iterations):
        error = function(p) - target
        if np.max(np.abs(error)) < tolerance:
            break
        p = p - error
    return p


def _raw_of_ideal(info: StreamInfo, xy: np.ndarray) -> np.ndarray:
    """Where ideal (pinhole) normalised points (N, 2) lie in the raw image, normalised."""
    c = info.coeffs
    if not info.distorted:
        return xy
    if info.model == "Inverse Brown Conrady":  # its polynomial maps raw -> ideal
        return _invert(lambda p: _brown(p, c, False), xy)
    return _brown(xy, c, info.model == "Modified Brown Conrady")


def ideal_rays(info: StreamInfo, pixels: np.ndarray) -> np.ndarray:
    """Normalised ideal rays (N, 2) (x/z, y/z) of raw pixels (N, 2) (u along columns, v along rows) of a stream."""
    k = info.intrinsics
    xy = (pixels - k[:2, 2]) / np.array([k[0, 0], k[1, 1]])
    c = info.coeffs
    if not info.distorted:
        return xy
    if info.model == "Inverse Brown Conrady":
        return _brown(xy, c, False)
    return _invert(lambda p: _brown(p, c, info.model == "Modified Brown Conrady"), xy)


def undistortion_maps(info: StreamInfo) -> tuple[np.ndarray, np.ndarray] | None:
    """OpenCV remap tables (H, W) float32 x, y: for each pixel of the undistorted image (same fx, fy, cx, cy, no
    distortion) where it lies in the raw one; None when the stream needs no undistortion. OpenCV's own model
    ("Brown Conrady") goes through `annotator.rig.undistort_maps`."""
    if not info.distorted:
        return None
    if info.model == "Brown Conrady":
        camera = CaptureCamera("stream", info.height, info.width, info.intrinsics, np.eye(4), 0.001)
        return undistort_maps(camera, info.coeffs)
    k = info.intrinsics
    v, u = np.mgrid[0:info.height, 0:info.width].astype(np.float64)
    xy = (np.stack([u.ravel(), v.ravel()], 1) - k[:2, 2]) / np.array([k[0, 0], k[1, 1]])
    raw = _raw_of_ideal(info, xy) * np.array([k[0, 0], k[1, 1]]) + k[:2, 2]
    shape = (info.height, info.width)
    return raw[:, 0].reshape(shape).astype(np.float32), raw[:, 1].reshape(shape).astype(np.float32)


# --- depth registration ----------------------------------------------------------------------------------------------


def _project(points: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) (u, v) of camera-frame points (N, 3) m through the pinhole k (3, 3)."""
    return points[:, :2] / points[:, 2:] * [k[0, 0], k[1, 1]] + k[:2, 2]


def align_depth(depth_m: np.ndarray, corner_rays: np.ndarray, depth_to_color: np.ndarray, color_k: np.ndarray,
                color_shape: tuple[int, int]) -> np.ndarray:
    """Depth (Hd, Wd) m (0 = none) of the depth stream registered to the undistorted colour image: (Hc, Wc) z-depth
    m in the colour camera, 0 = no depth.

    corner_rays: (Hd + 1, Wd + 1, 2) the depth pixels' corner rays (`Recording.depth_corner_rays`); depth_to_color
    4x4 m; color_k (3, 3) px of the pinhole colour image, color_shape (Hc, Wc). Each depth pixel's two opposite
    corners (at its depth) are moved into the colour camera and projected; the colour pixels between them (rounded,
    inclusive, as librealsense's align) are candidates for the z of the pixel's centre point in the colour camera.
    Per colour pixel a z-buffer keeps the nearest surface (candidates further than SAME_SURFACE behind the nearest
    are hidden) and, of its candidates, the one whose centre projects closest to the pixel (taking the nearest z
    outright would bias sloped surfaces towards the camera)."""
    hc, wc = color_shape
    rows, cols = np.nonzero(depth_m > 0)
    z = depth_m[rows, cols]
    rot, t = depth_to_color[:3, :3], depth_to_color[:3, 3]

    def to_color(rays: np.ndarray) -> np.ndarray:  # (N, 3) m in the colour camera of the rays (N, 2) at depth z
        x, y = rays[:, 0] * z, rays[:, 1] * z
        return np.stack([rot[i, 0] * x + rot[i, 1] * y + rot[i, 2] * z + t[i] for i in range(3)], 1)

    a, b = to_color(corner_rays[rows, cols]), to_color(corner_rays[rows + 1, cols + 1])
    centre = (a + b) / 2  # the transform is affine and both corners lie at the pixel's depth
    ok = (a[:, 2] > 0) & (b[:, 2] > 0)
    ua = np.floor(_project(a[ok], color_k) + 0.5).astype(np.int64)
    ub = np.floor(_project(b[ok], color_k) + 0.5).astype(np.int64)
    uc, zc = _project(centre[ok], color_k), centre[ok, 2]
    lo, hi = np.minimum(ua, ub), np.maximum(ua, ub)
    keep = np.all(lo >= 0, 1) & (hi[:, 0] < wc) & (hi[:, 1] < hc) & np.all(hi - lo < MAX_SPLAT, 1)
    lo, hi, uc, zc = lo[keep], hi[keep], uc[keep], zc[keep]
    span = (hi - lo).max(0) + 1 if len(zc) else np.zeros(2, np.int64)
    indices, values, misses = [], [], []
    for du in range(int(span[0])):  # a few offsets within a footprint, each vectorised over all pixels
        for dv in range(int(span[1])):
            inside = (lo[:, 0] + du <= hi[:, 0]) & (lo[:, 1] + dv <= hi[:, 1])
            u, v = lo[inside, 0] + du, lo[inside, 1] + dv
            indices.append(v * wc + u)
            values.append(zc[inside])
            misses.append((uc[inside, 0] - u) ** 2 + (uc[inside, 1] - v) ** 2)
    out = np.zeros(hc * wc)
    if not indices:
        return out.reshape(hc, wc)
    index, value, miss = np.concatenate(indices), np.concatenate(values), np.concatenate(misses)
    nearest = np.full(hc * wc, np.inf)
    np.minimum.at(nearest, index, value)  # the z-buffer
    front = value <= nearest[index] * (1 + SAME_SURFACE_REL) + SAME_SURFACE_M
    index, value, miss = index[front], value[front], miss[front]
    closest = np.full(hc * wc, np.inf)
    np.minimum.at(closest, index, miss)
    best = miss == closest[index]
    out[index[best]] = value[best]  # ties (equally near centres) are equally good
    return out.reshape(hc, wc)
