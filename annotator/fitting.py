"""The geometry the fit checks stand on (numpy + scipy only): transforms, surface samples, the cameras' views and what
they could see, cloud crops, the coarse screen of candidate poses and one ICP step.

- `kabsch`: the rigid transform of three or more picked point pairs (mesh <-> cloud), least squares.
- `sample_surface`: area-weighted surface samples with outward normals of a mesh, in its object frame.
- `visible_samples`: which posed samples a camera can see (front-facing, above the table, not hidden behind the
  measured depth nor behind another object), so coverage counts only surface the cameras could have measured.
- `render_depth`: the z-depth of posed meshes in a camera (the other objects, as occluders of a view).
- `screen_quality`: a coarse fit of many candidate poses at once (ranking start poses, the slide check).
- `icp_step`: one damped point-to-plane Gauss-Newton step (`annotator.align.icp`, the refinement check).

Transforms are 4x4 object-to-world matrices; points (..., 3) are (x, y, z) metres in the world/table frame unless
stated; angles are radians. Thresholds: `annotator.thresholds`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dsr_bench.annotator.thresholds import THRESHOLDS, Thresholds
from dsr_bench.errors import UserError
from dsr_bench.geometry import Camera, rotation_angle


@dataclass(frozen=True)
class SurfaceSamples:
    """Surface samples of a mesh in its object frame: points (S, 3) m, unit outward normals (S, 3); centre (3,) of
    the bounding box and radius (m) of the bounding sphere about it; the mesh's vertices (V, 3) m (for its lowest
    point), or None (the samples stand in)."""

    points: np.ndarray
    normals: np.ndarray
    centre: np.ndarray
    radius: float
    vertices: np.ndarray | None = None


# --- transforms ------------------------------------------------------------------------------------------------


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of an axis-angle vector (3,) in radians."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(rotvec, dtype=np.float64).reshape(3)).as_matrix()


def pose_delta(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation rad) between two 4x4 transforms."""
    return float(np.linalg.norm(b[:3, 3] - a[:3, 3])), rotation_angle(a[:3, :3].T @ b[:3, :3])


def kabsch(source: np.ndarray, target: np.ndarray, min_spread: float = 0.005) -> np.ndarray:
    """Rigid transform (4, 4) T minimising sum |T source_k - target_k|^2 (Kabsch/Umeyama without scale).

    source, target: (k, 3) matched points, k >= 3, metres (e.g. mesh points in the object frame and picked cloud
    points in the world). Raises UserError for fewer than 3 pairs or picks that (nearly) lie on one line
    (second spread of either set below `min_spread` m), which leave a rotation undetermined.
    """
    src = np.asarray(source, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    if len(src) != len(dst):
        raise UserError(f"picked {len(src)} mesh points but {len(dst)} cloud points: pick them in pairs")
    if len(src) < 3:
        raise UserError(f"picked {len(src)} point pairs: pick at least 3 pairs (mesh <-> cloud) to place an object")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise UserError("picked points contain NaN or inf: pick points on the mesh and on measured cloud points")
    cs, cd = src.mean(0), dst.mean(0)
    a, b = src - cs, dst - cd
    for name, pts in (("mesh", a), ("cloud", b)):
        spread = np.linalg.svd(pts, compute_uv=False) / np.sqrt(len(pts))
        if spread[1] < min_spread:
            raise UserError(f"the picked {name} points lie almost on one line (spread {spread[1] * 1000:.1f} mm across "
                            f"it): pick 3 or more points spread over the object, not in a row")
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = cd - rot @ cs
    return out


# --- surface samples ---------------------------------------------------------------------------------------------


def sample_surface(vertices: np.ndarray, faces: np.ndarray, spacing: float = THRESHOLDS.sample_spacing,
                   seed: int = 0, limits: Thresholds = THRESHOLDS) -> SurfaceSamples:
    """Area-weighted random samples of a triangle mesh's surface with outward face normals.

    vertices (V, 3) m, faces (F, 3) int; the sample count is area / spacing^2 clipped to [limits.min_samples,
    limits.max_samples]; deterministic for a seed. A closed mesh with inward faces (negative volume) is flipped.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    tri = v[f]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    doubled = np.linalg.norm(cross, axis=1)
    keep = doubled > 1e-14
    tri, cross, doubled = tri[keep], cross[keep], doubled[keep]
    if len(tri) == 0:
        raise UserError("mesh has no triangles with area: check the mesh file")
    volume = float(np.einsum("ij,ij->i", tri[:, 0], cross).sum() / 6.0)
    sign = -1.0 if volume < 0 else 1.0
    normals = sign * cross / doubled[:, None]
    area = doubled / 2
    count = int(np.clip(area.sum() / spacing**2, limits.min_samples, limits.max_samples))
    rng = np.random.default_rng(seed)
    which = rng.choice(len(tri), size=count, p=area / area.sum())
    r1, r2 = rng.random((2, count))
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    points = np.einsum("ij,ijk->ik", w, tri[which])
    lo, hi = v.min(0), v.max(0)
    centre = (lo + hi) / 2
    radius = float(np.linalg.norm(v - centre, axis=1).max())
    return SurfaceSamples(points, normals[which], centre, radius, v)


def posed_samples(samples: SurfaceSamples, transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points and normals (S, 3) of the samples at a 4x4 object-to-world transform."""
    rot, t = transform[:3, :3], transform[:3, 3]
    return samples.points @ rot.T + t, samples.normals @ rot.T


@dataclass(frozen=True)
class View:
    """A calibrated camera and its measured z-depth (H, W) in metres (0 = missing), for visibility tests;
    `occluders`: the z-depth (H, W) m of the other objects' posed meshes in this camera (inf where none,
    `render_depth`), or None (no other objects known); `bounds`: the box (2, 3) (lowest, highest x, y, z, m) outside
    which the cloud holds no points (`Capture.cloud` keeps the grid's), or None; `color`: the colour image (H, W, 3)
    uint8 of this camera, or None."""

    camera: Camera
    depth: np.ndarray
    occluders: np.ndarray | None = None
    bounds: np.ndarray | None = None  # (2, 3) lowest and highest (x, y, z) m of the cloud's points (it is cut there)
    near: np.ndarray | None = None  # `near_depth(depth)`, computed once (None: computed where needed)
    color: np.ndarray | None = None  # the colour image (H, W, 3) uint8 (or float 0..1), for `sample_colours`

    def with_occluders(self, occluders: np.ndarray | None) -> View:
        """This view with another occluder depth (H, W) m (or None)."""
        from dataclasses import replace

        return replace(self, occluders=occluders)


def render_depth(camera: Camera, meshes: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Z-depth (H, W) m of posed meshes in a camera (the nearest surface per pixel centre, inf where none).

    meshes: (vertices (V, 3) world m, faces (F, 3)) each; rasterised exactly (`dsr_bench.render.raster`), the part
    in front of the camera (`annotator.images.clip_near`)."""
    from dsr_bench.annotator.images import clip_near
    from dsr_bench.geometry import rigid_inverse, transform_points
    from dsr_bench.render.raster import nearest, perspective_depth, rasterize

    h, w = camera.height, camera.width
    out = np.full(h * w, np.inf)
    to_camera = rigid_inverse(camera.extrinsics)
    k = np.asarray(camera.intrinsics, np.float64)
    for vertices, faces in meshes:
        if len(faces) == 0 or not np.all(np.isfinite(vertices)):
            continue
        points, front = clip_near(transform_points(to_camera, np.asarray(vertices, np.float64)), faces)
        uv = points[:, :2] / points[:, 2:3] * np.diag(k)[:2] + k[:2, 2]
        frags = rasterize(uv, front, h, w)
        if len(frags.sample) == 0:
            continue
        depth, _ = nearest(frags, perspective_depth(frags, front, points[:, 2]), h * w)
        np.minimum(out, depth, out=out)
    return out.reshape(h, w)


def pixels(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The nearest pixel (u, v) (n,) int64, depth z (n,) m and whether it lies in front of the camera and inside its
    image (n,) bool, of world points (n, 3)."""
    uv, z = camera.project(points)
    u = np.rint(uv[:, 0]).astype(np.int64)
    v = np.rint(uv[:, 1]).astype(np.int64)
    return u, v, z, (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)


def visible_samples(points: np.ndarray, normals: np.ndarray, views: Sequence[View],
                    limits: Thresholds = THRESHOLDS) -> np.ndarray:
    """Which posed samples (S,) bool at least one camera could have measured.

    A sample counts for a camera when it faces the camera (its normal within the angle of `limits.min_view_cosine`
    of the ray to the camera centre: a face seen edge-on is hardly measured), projects inside its image onto a pixel
    with a measurement, and that measurement is not more than `limits.occlusion_tolerance` m in front of it
    (something else hides it), nor hidden by another object's posed surface (`View.occluders`, more than
    `limits.occluder_tolerance` m in front). Samples below `limits.table_margin` m are left out (the table hides the
    contact surface), and so are samples outside the view's `bounds` (the cloud holds no
    point there: an object pushed partly off the grid). points, normals: (S, 3) world.
    """
    out = np.zeros(len(points), dtype=bool)
    above = points[:, 2] > limits.table_margin
    for view in views:
        cam = view.camera
        centre = cam.extrinsics[:3, 3]
        ray = centre - points
        facing = np.einsum("ij,ij->i", normals, ray) > limits.min_view_cosine * np.linalg.norm(ray, axis=1)
        cand = facing & above & ~out
        if view.bounds is not None:
            cand &= np.all((points >= view.bounds[0]) & (points <= view.bounds[1]), axis=1)
        if not cand.any():
            continue
        u, v, z, inside = pixels(cam, points[cand])
        d = np.zeros(len(z))
        d[inside] = view.depth[v[inside], u[inside]]
        seen = inside & (d > 0) & (d >= z - limits.occlusion_tolerance)
        if view.occluders is not None:
            seen[inside] &= view.occluders[v[inside], u[inside]] >= z[inside] - limits.occluder_tolerance
        idx = np.flatnonzero(cand)
        out[idx[seen]] = True
    return out


def crop_cloud(points: np.ndarray, centre: np.ndarray, radius: float,
               table_margin: float = THRESHOLDS.table_margin) -> np.ndarray:
    """Cloud points (M, 3) within `radius` m of `centre` (3,) and above the table margin."""
    near = np.sum((points - centre) ** 2, axis=1) <= radius * radius
    return points[near & (points[:, 2] > table_margin)]


def near_depth(depth: np.ndarray) -> np.ndarray:
    """Per pixel the nearest measured depth (m) of its 3 x 3 neighbourhood (inf where none is measured): depth
    (H, W) m, 0 = missing."""
    from scipy.ndimage import minimum_filter

    return minimum_filter(np.where(depth > 0, depth, np.inf), size=3, mode="nearest")


# --- screening and ICP steps ---------------------------------------------------------------------------------------


def screen_quality(samples: SurfaceSamples, transforms: np.ndarray, tree, views: Sequence[View],
                   inlier_distance: float, min_visible: int = 20, limits: Thresholds = THRESHOLDS) -> np.ndarray:
    """Coarse quality (C,) of the samples at each of C candidate transforms (C, 4, 4) against a cloud's cKDTree,
    in one vectorised pass (for ranking start poses): coverage within `inlier_distance` minus the inliers' RMS
    distance in units of 2 cm (as `FitScore.quality`); -1 where fewer than `min_visible` samples are visible."""
    transforms = np.asarray(transforms, dtype=np.float64)
    count, size = len(transforms), len(samples.points)
    rot, t = transforms[:, :3, :3], transforms[:, :3, 3]
    rot_t = np.ascontiguousarray(rot.transpose(0, 2, 1))
    pts = (np.matmul(samples.points[None], rot_t) + t[:, None]).reshape(-1, 3)
    nrm = np.matmul(samples.normals[None], rot_t).reshape(-1, 3)
    vis = visible_samples(pts, nrm, views, limits)
    idx = np.flatnonzero(vis)
    d, _ = tree.query(pts[idx], distance_upper_bound=inlier_distance)
    ok = np.isfinite(d)
    hit = np.zeros(count * size, dtype=bool)
    hit[idx[ok]] = True
    sq = np.zeros(count * size)
    sq[idx[ok]] = d[ok] ** 2
    nvis = vis.reshape(count, size).sum(1)
    nhit = hit.reshape(count, size).sum(1)
    cov = nhit / np.maximum(nvis, 1)
    rms = np.sqrt(sq.reshape(count, size).sum(1) / np.maximum(nhit, 1))
    rms = np.where(nhit > 0, rms, inlier_distance)
    return np.where(nvis >= min_visible, cov - rms / 0.02, -1.0)


def _tukey(r: np.ndarray, c: float) -> np.ndarray:
    w = (1 - (r / c) ** 2) ** 2
    return np.where(np.abs(r) < c, w, 0.0)


def icp_subset(samples: SurfaceSamples, count: int = THRESHOLDS.icp_samples) -> SurfaceSamples:
    """A fixed random subset of at most `count` of the samples (all of them when fewer), for ICP's iterations."""
    if len(samples.points) <= count:
        return samples
    keep = np.random.default_rng(0).choice(len(samples.points), count, replace=False)
    return SurfaceSamples(samples.points[keep], samples.normals[keep], samples.centre, samples.radius)


def icp_step(samples: SurfaceSamples, current: np.ndarray, crop: np.ndarray, tree, views: Sequence[View],
             dist: float, limits: Thresholds = THRESHOLDS) -> tuple[np.ndarray | None, bool, int]:
    """One damped Gauss-Newton point-to-plane step of the samples at `current` (4, 4) against the cloud crop (M, 3)
    (its cKDTree `tree`), matching within `dist` m: (the step (4, 4) to apply on the left, or None when fewer than
    `limits.min_correspondences` samples matched; whether the step is negligible; the matched count)."""
    pts, nrm = posed_samples(samples, current)
    vis = visible_samples(pts, nrm, views, limits)
    d, j = tree.query(pts[vis], distance_upper_bound=dist)
    ok = np.isfinite(d)
    if ok.sum() < limits.min_correspondences:
        return None, False, int(ok.sum())
    p, n = pts[vis][ok], nrm[vis][ok]
    q = crop[j[ok]]
    r = np.einsum("ij,ij->i", p - q, n)
    w = _tukey(r, max(dist, 1e-6))
    centroid = p.mean(0)
    jac = np.hstack([np.cross(p - centroid, n), n])
    a = jac.T @ (w[:, None] * jac)
    damping = limits.icp_damping * max(float(np.trace(a)), 1e-12) / 6
    x = np.linalg.solve(a + damping * np.eye(6), -jac.T @ (w * r))
    rot = rotvec_to_matrix(x[:3])
    step = np.eye(4)
    step[:3, :3] = rot
    step[:3, 3] = centroid - rot @ centroid + x[3:]
    small = bool(np.linalg.norm(x[3:]) < 1e-5 and np.linalg.norm(x[:3]) < 1e-4)
    return step, small, int(ok.sum())
