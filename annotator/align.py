"""Rigid alignment of object meshes to a fused RGB-D point cloud (numpy + scipy only).

- `kabsch`: the rigid transform of three or more picked point pairs (mesh <-> cloud), least squares.
- `sample_surface`: area-weighted surface samples with outward normals of a mesh, in its object frame.
- `visible_samples`: which posed samples a camera can see (front-facing, above the table, not hidden behind the
  measured depth), so coverage counts only surface the cameras could have measured.
- `icp`: point-to-plane ICP of the visible samples against a cloud crop (cKDTree correspondences, shrinking
  correspondence distance, Tukey weights, damped Gauss-Newton), with jump rejection against the start pose.
- `fit_score`: inlier RMSE, coverage of the visible samples, fitness of the crop, and the physical checks
  (`physical_problems`): no interpenetration with the other objects, resting on the table or on another object,
  no surface in front of what a camera measured (free space).
- `render_depth`: the z-depth of posed meshes in a camera (the other objects, as occluders of a view).
- `refinement`: how far a short ICP from a pose moves it and how much closer it brings the surface to the cloud (a
  pose a snap would improve is wrong); `sample_colours` / `colour_mismatch`: the colours the cameras saw at the
  surface samples, compared with those of the same samples at another step (a swapped identity).

Transforms are 4x4 object-to-world matrices; points (..., 3) are (x, y, z) metres in the world/table frame unless
stated; angles are radians.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from dsr_bench.errors import UserError
from dsr_bench.geometry import Camera, matrix_to_pose, rotation_angle  # noqa: F401 - matrix_to_pose: used as align.matrix_to_pose

#: Distance (m) within which a cloud point counts as lying on the mesh surface (sensor noise + calibration error).
INLIER_DISTANCE = 0.005
#: Initial correspondence distance (m) of ICP: the basin it converges from.
MAX_CORRESPONDENCE = 0.02
#: ICP results moving further than this from the start pose are rejected (m, rad).
MAX_JUMP_TRANSLATION = 0.03
MAX_JUMP_ROTATION = float(np.deg2rad(25.0))
#: Points below this height (m) belong to the table: left out of crops and of the visible samples.
TABLE_MARGIN = 0.003
#: A sample counts as hidden from a camera when the measured surface lies this much (m) in front of it.
OCCLUSION_TOLERANCE = 0.02
#: A sample counts for a camera only when its normal is turned at most about 81 degrees from the ray to the camera
#: (cosine above this): a face seen edge-on covers a few pixels whose depth is hardly measured (a box face at 85
#: degrees to one camera, whose other view another object hides, had half its samples without a cloud point).
MIN_VIEW_COSINE = 0.15
#: A sample counts as hidden by another object when that object's posed surface lies this much (m) in front of it
#: along the camera's ray (`View.occluders`): coverage counts only the surface no other object hides.
OCCLUDER_TOLERANCE = 0.002
#: Physical checks (`physical_problems`): two meshes may interpenetrate by at most this (m), measured by the
#: PENETRATION_COUNT-th deepest surface sample of one inside the other ...
PENETRATION_TOLERANCE = 0.005
PENETRATION_COUNT = 5
#: ... a mesh's lowest point may lie this far (m) below or above the table (z = 0) ...
TABLE_TOLERANCE = 0.005
#: ... or higher when it rests on another object: some surface sample within this distance (m) of that object's ...
SUPPORT_DISTANCE = 0.006
#: ... and the cameras may measure depth more than FREE_SPACE_TOLERANCE (m) behind at most FREE_SPACE_FRACTION of
#: the mesh's surface samples that face them and project onto measured pixels (they saw through the mesh there);
#: the measured depth of a pixel is the nearest in its 3 x 3 neighbourhood, so a silhouette's edge does not count.
FREE_SPACE_TOLERANCE = 0.01
FREE_SPACE_FRACTION = 0.1
FREE_SPACE_MIN_SAMPLES = 20
#: ... and every measured point near it must be explained: at most UNEXPLAINED_FRACTION of the cloud points within
#: UNEXPLAINED_REACH (m) of its posed surface (at least UNEXPLAINED_MIN_POINTS) may lie farther than
#: INLIER_DISTANCE from every posed mesh (its own and the other objects'): a wrong pose leaves the surface where the
#: object really is unexplained (true poses under the simulated sensor's noise: at most 2%; 10 mm off: 20%+; a
#: true pose beside a neighbour left 9 cm behind: 8%).
UNEXPLAINED_REACH = 0.01
UNEXPLAINED_FRACTION = 0.1
UNEXPLAINED_MIN_POINTS = 30
#: ... counting only points this high (m) above the table: its measured surface (depth noise, calibration error)
#: reaches a few millimetres above z = 0 (up to 4 mm seen beside a can: 12% of the points around it).
UNEXPLAINED_MIN_HEIGHT = 0.01
#: ... or, for an object lower than that (a phone lying flat, 7 mm high), above UNEXPLAINED_THIN_FRACTION of its
#: highest point and at least UNEXPLAINED_THIN_FLOOR (m): otherwise none of its measured surface would count.
UNEXPLAINED_THIN_FRACTION = 0.65
UNEXPLAINED_THIN_FLOOR = 0.004
#: ... and a snap would not improve it (`refinement`, only with `fit_score(refine=True)`): a short ICP of
#: REFINE_ITERATIONS steps from the pose may move it (the origin) at most REFINE_TRANSLATION (m) and
#: REFINE_ROTATION (rad) unless it brings the visible samples no closer than REFINE_GAIN (m, the mean distance to
#: the nearest cloud point, capped at REFINE_CAP m) to the cloud, and may turn it more than REFINE_TURN (rad) only
#: with a gain under REFINE_TURN_GAIN (m); the move is measured from the shift the other objects share (the
#: cameras' calibration error against the table frame moves a whole scene alike: `Session._shared_shift`). Set from
#: the true poses of `bench/bench_annotate_errors.py -n 3 --steps 5` (realistic sensor noise and calibration error):
#: with --seed 3 the refinement moved them at most 2.5 mm and 1.6 deg, with gains up to 0.26 mm; with --seed 4
#: (larger calibration errors; 4.5 mm before the shared shift is taken off) up to 4.2 mm and 3.4 deg, with gains up
#: to 0.59 mm (--seed 5, run after: 4.8 mm, 3.4 deg, 0.73 mm; 2 of its 72 flagged). Every wrong pose of 10 mm or 10
#: deg and more that the other checks missed with seeds 3 and 4 (10-20 deg turns, a mug turned 180 deg with its
#: handle on the wrong side, 10 mm shifts) is beyond them. A shift along a direction the cloud does not constrain
#: moves the pose without a gain.
REFINE_ITERATIONS = 15
#: The refinement iterates and measures its gain on a fixed random subset of at most this many samples: with 3000
#: (as `icp`) the three seeds flagged the same errors (but one) for 2.2 times its time (24 vs 11 ms a pose, seed 3).
REFINE_SAMPLES = 1000
REFINE_TRANSLATION = 0.0035
REFINE_ROTATION = float(np.deg2rad(4.0))
REFINE_GAIN = 0.00035
REFINE_TURN = float(np.deg2rad(6.0))
REFINE_TURN_GAIN = 0.00012
REFINE_CAP = 0.01
#: ... and its colours match those of another step (`colour_mismatch`, only with `fit_score(reference_colours=)`):
#: at most COLOUR_FRACTION of the surface samples seen at both (at least COLOUR_MIN_SAMPLES, each brighter than
#: COLOUR_MIN_BRIGHTNESS, 0..1) may differ in chromaticity (r, g, b over their sum) by more than COLOUR_DISTANCE
#: (L1); chromaticity does not change with shading. True poses of the simulated captures: at most 1% of the
#: samples differ; two cans of different colours swapped: all of them.
COLOUR_DISTANCE = 0.1
COLOUR_FRACTION = 0.3
COLOUR_MIN_SAMPLES = 30
COLOUR_MIN_BRIGHTNESS = 0.05
#: A fit is good when at least this fraction of the visible samples has a cloud point within INLIER_DISTANCE ...
MIN_COVERAGE = 0.65
#: ... and the inlier RMSE is at most this (m).
MAX_RMSE = 0.003
#: ICP needs at least this many correspondences.
MIN_CORRESPONDENCES = 30
#: Surface sampling density: spacing (m) between samples, and the bounds of the sample count.
SAMPLE_SPACING = 0.002
MIN_SAMPLES, MAX_SAMPLES = 500, 20000
#: Levenberg damping of each ICP step, relative to the mean curvature: holds still the directions the data do not
#: constrain (the spin of a can about its axis), where noise would otherwise turn the object.
ICP_DAMPING = 1e-3
#: ICP iterates on a fixed random subset of at most this many samples (scores use all).
ICP_SAMPLES = 3000


@dataclass
class FitScore:
    """How well a posed mesh matches the cloud.

    rmse: m, RMS point-to-plane distance (along the mesh normal) of the inlier correspondences (visible samples
    with a cloud point within the inlier distance); coverage: 0..1, fraction of the visible samples with such a
    point; fitness: 0..1, fraction of the cropped cloud points (around the object, table removed) within the
    inlier distance of the mesh; accepted: the fit (or the ICP result) passed its checks (coverage >= MIN_COVERAGE,
    RMSE <= MAX_RMSE; for ICP also no jump); reason: why not, or what the checks that ran measured (never empty:
    every verdict says why); visible: visible samples.
    """

    rmse: float
    coverage: float
    fitness: float
    accepted: bool
    reason: str
    visible: int = 0  # number of visible samples

    def __post_init__(self) -> None:
        if not str(self.reason).strip():  # every verdict says why: an empty reason is never stored or shown
            self.reason = "accepted (no check ran)" if self.accepted else "not accepted (no reason given)"

    def as_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> FitScore:
        return cls(float(d["rmse"]), float(d["coverage"]), float(d["fitness"]), bool(d["accepted"]), str(d["reason"]),
                   int(d.get("visible", 0)))

    def quality(self) -> float:
        """One number to rank fits by (higher is better): coverage minus RMSE in units of 2 cm."""
        rmse = float(self.rmse) if np.isfinite(self.rmse) else INLIER_DISTANCE
        return float(self.coverage) - rmse / 0.02


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


@dataclass
class IcpResult:
    """The outcome of `icp`: the final transform (4, 4) (the start transform when rejected), its score, the
    iterations run, how far it moved from the start (m, rad), and whether the result was kept (`applied`: no jump,
    enough correspondences; `score.accepted` says in addition whether the fit is good)."""

    transform: np.ndarray
    score: FitScore
    iterations: int
    translation: float
    rotation: float
    applied: bool = True


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


def sample_surface(vertices: np.ndarray, faces: np.ndarray, spacing: float = SAMPLE_SPACING,
                   seed: int = 0) -> SurfaceSamples:
    """Area-weighted random samples of a triangle mesh's surface with outward face normals.

    vertices (V, 3) m, faces (F, 3) int; the sample count is area / spacing^2 clipped to [MIN_SAMPLES,
    MAX_SAMPLES]; deterministic for a seed. A closed mesh with inward faces (negative volume) is flipped.
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
    count = int(np.clip(area.sum() / spacing**2, MIN_SAMPLES, MAX_SAMPLES))
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
    from annotator.images import clip_near
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


def _pixels(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The nearest pixel (u, v) (n,) int64, depth z (n,) m and whether it lies in front of the camera and inside its
    image (n,) bool, of world points (n, 3)."""
    uv, z = camera.project(points)
    u = np.rint(uv[:, 0]).astype(np.int64)
    v = np.rint(uv[:, 1]).astype(np.int64)
    return u, v, z, (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)


def visible_samples(points: np.ndarray, normals: np.ndarray, views: Sequence[View],
                    table_margin: float = TABLE_MARGIN, occlusion_tolerance: float = OCCLUSION_TOLERANCE) -> np.ndarray:
    """Which posed samples (S,) bool at least one camera could have measured.

    A sample counts for a camera when it faces the camera (its normal within the angle of MIN_VIEW_COSINE of the
    ray to the camera centre: a face seen edge-on is hardly measured), projects
    inside its image onto a pixel with a measurement, and that measurement is not more than
    `occlusion_tolerance` m in front of it (something else hides it), nor hidden by another object's posed surface
    (`View.occluders`, more than OCCLUDER_TOLERANCE m in front). Samples below `table_margin` m are left out
    (the table hides the contact surface), and so are samples outside the view's `bounds` (the cloud holds no
    point there: an object pushed partly off the grid). points, normals: (S, 3) world.
    """
    out = np.zeros(len(points), dtype=bool)
    above = points[:, 2] > table_margin
    for view in views:
        cam = view.camera
        centre = cam.extrinsics[:3, 3]
        ray = centre - points
        facing = np.einsum("ij,ij->i", normals, ray) > MIN_VIEW_COSINE * np.linalg.norm(ray, axis=1)
        cand = facing & above & ~out
        if view.bounds is not None:
            cand &= np.all((points >= view.bounds[0]) & (points <= view.bounds[1]), axis=1)
        if not cand.any():
            continue
        u, v, z, inside = _pixels(cam, points[cand])
        d = np.zeros(len(z))
        d[inside] = view.depth[v[inside], u[inside]]
        seen = inside & (d > 0) & (d >= z - occlusion_tolerance)
        if view.occluders is not None:
            seen[inside] &= view.occluders[v[inside], u[inside]] >= z[inside] - OCCLUDER_TOLERANCE
        idx = np.flatnonzero(cand)
        out[idx[seen]] = True
    return out


def crop_cloud(points: np.ndarray, centre: np.ndarray, radius: float, table_margin: float = TABLE_MARGIN) -> np.ndarray:
    """Cloud points (M, 3) within `radius` m of `centre` (3,) and above the table margin."""
    near = np.sum((points - centre) ** 2, axis=1) <= radius * radius
    return points[near & (points[:, 2] > table_margin)]


# --- physical checks -------------------------------------------------------------------------------------------


def _inside_depth(points: np.ndarray, surface: np.ndarray, normals: np.ndarray, tree) -> np.ndarray:
    """Per point (M, 3) its depth (m) below a posed surface (samples (S, 3) with outward normals (S, 3) and their
    cKDTree): minus the signed distance along the nearest sample's normal (<= 0 outside)."""
    _, j = tree.query(points)
    return -np.einsum("ij,ij->i", points - surface[j], normals[j])


def _kth_deepest(depth: np.ndarray) -> float:
    """The PENETRATION_COUNT-th largest positive depth (m), 0 when fewer are inside."""
    depth = np.sort(depth[depth > 0])
    return float(depth[-PENETRATION_COUNT]) if len(depth) >= PENETRATION_COUNT else 0.0


def penetration_depth(a: SurfaceSamples, ta: np.ndarray, b: SurfaceSamples, tb: np.ndarray) -> float:
    """How deep (m) two posed meshes (samples, 4x4 transform each) interpenetrate: the PENETRATION_COUNT-th
    deepest surface sample of either inside the other (0 when apart)."""
    from scipy.spatial import cKDTree

    ca, cb = ta[:3, :3] @ a.centre + ta[:3, 3], tb[:3, :3] @ b.centre + tb[:3, 3]
    if np.linalg.norm(ca - cb) > a.radius + b.radius:
        return 0.0
    (pa, na), (pb, nb) = posed_samples(a, ta), posed_samples(b, tb)
    depth = 0.0
    for pts, centre, radius, surface, normals in ((pa, cb, b.radius, pb, nb), (pb, ca, a.radius, pa, na)):
        inside = np.sum((pts - centre) ** 2, axis=1) <= radius**2
        if inside.sum() >= PENETRATION_COUNT:
            depth = max(depth, _kth_deepest(_inside_depth(pts[inside], surface, normals, cKDTree(surface))))
    return depth


def near_depth(depth: np.ndarray) -> np.ndarray:
    """Per pixel the nearest measured depth (m) of its 3 x 3 neighbourhood (inf where none is measured): depth
    (H, W) m, 0 = missing."""
    from scipy.ndimage import minimum_filter

    return minimum_filter(np.where(depth > 0, depth, np.inf), size=3, mode="nearest")


def free_space_fraction(points: np.ndarray, normals: np.ndarray, views: Sequence[View],
                        tolerance: float = FREE_SPACE_TOLERANCE) -> tuple[float, int]:
    """(fraction, count) of the posed samples (S, 3) world, normals (S, 3), that face a camera (cosine to the ray
    above 0.2), project onto a measured pixel and have the measured depth (nearest of its 3 x 3 pixels) more than
    `tolerance` m behind them: the camera saw through the mesh there. count: the samples tested (all views)."""
    bad = tested = 0
    for view in views:
        cam = view.camera
        ray = cam.extrinsics[:3, 3] - points
        cos = np.einsum("ij,ij->i", normals, ray) / np.maximum(np.linalg.norm(ray, axis=1), 1e-12)
        cand = cos > 0.2
        if not cand.any():
            continue
        u, v, z, inside = _pixels(cam, points[cand])
        d = (near_depth(view.depth) if view.near is None else view.near)[v[inside], u[inside]]
        measured = np.isfinite(d)
        tested += int(measured.sum())
        bad += int((d[measured] > z[inside][measured] + tolerance).sum())
    return (bad / tested if tested else 0.0), tested


def physical_problems(samples: SurfaceSamples, transform: np.ndarray,
                      neighbours: Sequence[tuple[str, SurfaceSamples, np.ndarray]], views: Sequence[View]) -> list[str]:
    """Why the mesh cannot physically be at `transform` (4, 4), as reason strings ([] when it can):

    - it interpenetrates another object (neighbours: (name, samples, 4x4 transform) of the others at this step)
      by more than PENETRATION_TOLERANCE (either object's samples inside the other);
    - its lowest point sinks more than TABLE_TOLERANCE below the table (z = 0), or floats more than that above it
      without resting on another object (a sample within SUPPORT_DISTANCE of it);
    - the cameras measured depth behind more than FREE_SPACE_FRACTION of its surface (`free_space_fraction`).
    """
    from scipy.spatial import cKDTree

    pts, nrm = posed_samples(samples, transform)
    centre = transform[:3, :3] @ samples.centre + transform[:3, 3]
    own_tree = None
    problems = []
    supported = False
    for name, other, other_t in neighbours:
        if not np.all(np.isfinite(other_t)):
            continue
        other_centre = other_t[:3, :3] @ other.centre + other_t[:3, 3]
        if np.linalg.norm(centre - other_centre) > samples.radius + other.radius + SUPPORT_DISTANCE:
            continue
        opts, onrm = posed_samples(other, other_t)
        # own samples near the other's surface: their distance to it (support) and their depth inside it
        near = np.sum((pts - other_centre) ** 2, axis=1) <= (other.radius + SUPPORT_DISTANCE) ** 2
        if not near.any():
            continue
        other_tree = cKDTree(opts)
        gap, j = other_tree.query(pts[near])
        supported |= bool((gap <= SUPPORT_DISTANCE).any())
        depth = _kth_deepest(-np.einsum("ij,ij->i", pts[near] - opts[j], onrm[j]))
        theirs = np.sum((opts - centre) ** 2, axis=1) <= samples.radius ** 2
        if theirs.sum() >= PENETRATION_COUNT:
            own_tree = cKDTree(pts) if own_tree is None else own_tree
            depth = max(depth, _kth_deepest(_inside_depth(opts[theirs], pts, nrm, own_tree)))
        if depth > PENETRATION_TOLERANCE:
            problems.append(f"interpenetrates {name} by {depth * 1000:.0f} mm")
    lowest_points = pts if samples.vertices is None else samples.vertices @ transform[:3, :3].T + transform[:3, 3]
    lowest = float(lowest_points[:, 2].min())
    if lowest < -TABLE_TOLERANCE:
        problems.append(f"sinks {-lowest * 1000:.0f} mm into the table")
    elif lowest > TABLE_TOLERANCE and not supported:
        problems.append(f"floats {lowest * 1000:.0f} mm above the table")
    fraction, tested = free_space_fraction(pts, nrm, views)
    if tested >= FREE_SPACE_MIN_SAMPLES and fraction > FREE_SPACE_FRACTION:
        problems.append(f"the cameras see through {fraction:.0%} of its surface")
    return problems


def unexplained_fraction(samples: SurfaceSamples, transform: np.ndarray, crop: np.ndarray,
                         neighbours: Sequence[tuple[str, SurfaceSamples, np.ndarray]]) -> tuple[float, int]:
    """(fraction, count) of the cloud crop's points (M, 3) within UNEXPLAINED_REACH m of the posed mesh's surface
    samples and UNEXPLAINED_MIN_HEIGHT m above the table (lower for a thin object: UNEXPLAINED_THIN_FRACTION of
    its highest point, at least UNEXPLAINED_THIN_FLOOR) that lie farther than INLIER_DISTANCE from its samples
    and from every neighbour's (name, samples, 4x4 transform); count: the points tested. Only the band around
    the object's own surface counts, so that a wrong neighbour a little farther away does not flag it."""
    from scipy.spatial import cKDTree

    pts = posed_samples(samples, transform)[0]
    top = float((pts if samples.vertices is None else samples.vertices @ transform[:3, :3].T + transform[:3, 3])[:, 2]
                .max())
    high = crop[crop[:, 2] > min(UNEXPLAINED_MIN_HEIGHT, max(UNEXPLAINED_THIN_FLOOR, UNEXPLAINED_THIN_FRACTION * top))]
    if len(high) == 0:
        return 0.0, 0
    own, _ = cKDTree(pts).query(high, distance_upper_bound=UNEXPLAINED_REACH)
    near = high[np.isfinite(own)]
    unexplained = own[np.isfinite(own)] > INLIER_DISTANCE
    if not unexplained.any():
        return 0.0, len(near)
    centre = transform[:3, :3] @ samples.centre + transform[:3, 3]
    loose = near[unexplained]
    for _, other, other_t in neighbours:
        other_centre = other_t[:3, :3] @ other.centre + other_t[:3, 3]
        reach = samples.radius + UNEXPLAINED_REACH + other.radius
        if not np.all(np.isfinite(other_t)) or np.linalg.norm(other_centre - centre) > reach:
            continue
        d, _ = cKDTree(posed_samples(other, other_t)[0]).query(loose, distance_upper_bound=INLIER_DISTANCE)
        loose = loose[~np.isfinite(d)]
        if len(loose) == 0:
            break
    return len(loose) / len(near), len(near)


def sample_colours(points: np.ndarray, normals: np.ndarray, views: Sequence[View],
                   tolerance: float = INLIER_DISTANCE) -> np.ndarray:
    """The colour (S, 3) 0..1 the cameras saw at each posed sample (points, normals (S, 3) world): the mean over the
    views that see it (`visible_samples`, one view at a time) with their measured depth within `tolerance` m of it
    (so the pixel shows this surface, not another in front or behind); NaN rows where no view with a colour image
    (`View.color`) does."""
    total = np.zeros((len(points), 3))
    count = np.zeros(len(points))
    for view in views:
        if view.color is None:
            continue
        seen = visible_samples(points, normals, [view])
        if not seen.any():
            continue
        idx = np.flatnonzero(seen)
        u, v, z, inside = _pixels(view.camera, points[idx])
        idx, u, v, z = idx[inside], u[inside], v[inside], z[inside]
        close = np.abs(view.depth[v, u] - z) <= tolerance
        idx, u, v = idx[close], u[close], v[close]
        colour = np.asarray(view.color[v, u], dtype=np.float64)
        total[idx] += colour / 255.0 if np.asarray(view.color).dtype == np.uint8 else colour
        count[idx] += 1
    out = np.full((len(points), 3), np.nan)
    seen_any = count > 0
    out[seen_any] = total[seen_any] / count[seen_any, None]
    return out


def colour_mismatch(observed: np.ndarray, reference: np.ndarray) -> tuple[float, int]:
    """(fraction, count) of the samples seen in both colour sets (S, 3) 0..1 (`sample_colours`: NaN rows unseen)
    and brighter than COLOUR_MIN_BRIGHTNESS (mean of r, g, b) in both, whose chromaticity (r, g, b over their sum)
    differs by more than COLOUR_DISTANCE (L1); count: those compared."""
    both = np.all(np.isfinite(observed), 1) & np.all(np.isfinite(reference), 1)
    both &= (np.nan_to_num(observed).mean(1) > COLOUR_MIN_BRIGHTNESS) \
        & (np.nan_to_num(reference).mean(1) > COLOUR_MIN_BRIGHTNESS)
    if not both.any():
        return 0.0, 0
    a, b = observed[both], reference[both]
    diff = np.abs(a / a.sum(1, keepdims=True) - b / b.sum(1, keepdims=True)).sum(1)
    return float((diff > COLOUR_DISTANCE).mean()), int(both.sum())


# --- scores and ICP ------------------------------------------------------------------------------------------------


def fit_score(samples: SurfaceSamples, transform: np.ndarray, crop: np.ndarray, views: Sequence[View],
              inlier_distance: float = INLIER_DISTANCE, tree=None, with_fitness: bool = True,
              neighbours: Sequence[tuple[str, SurfaceSamples, np.ndarray]] | None = None,
              explain: bool = False, refine: bool = False, reference_colours: np.ndarray | None = None,
              shared_shift: Callable[[], np.ndarray | None] | None = None) -> FitScore:
    """Score of the mesh at `transform` (4, 4) against a cloud crop (M, 3) (see FitScore); accepted when the
    coverage is at least MIN_COVERAGE, the RMSE at most MAX_RMSE and, when `neighbours` (the other objects:
    name, samples, 4x4 transform) are given, no physical check fails (`physical_problems`) and at most
    UNEXPLAINED_FRACTION of the cloud around it is explained by no object (`unexplained_fraction`; only with
    `explain`: when the neighbours are all the other objects of the scene). When all of these pass, two more
    checks: with `reference_colours` (S, 3) (`sample_colours` of the same samples at another step, NaN unseen),
    at most COLOUR_FRACTION of the samples seen at both may have changed colour (`colour_mismatch`), and with
    `refine`, a short ICP from the pose may not improve it (`refinement`, `Refinement.improves`; `shared_shift`,
    called only then: the shift the scene's other objects share, or None). `tree`: a
    cKDTree of `crop` to reuse; `with_fitness=False` skips the fitness (reported as NaN), for fast screening."""
    from scipy.spatial import cKDTree

    pts, nrm = posed_samples(samples, transform)
    vis = visible_samples(pts, nrm, views)
    nvis = int(vis.sum())
    if len(crop) == 0 or nvis == 0:
        why = "no cloud points around the object" if len(crop) == 0 else "no surface of the mesh is visible to a camera"
        return FitScore(float("nan"), 0.0, 0.0, False, why, nvis)
    tree = cKDTree(crop) if tree is None else tree
    d, j = tree.query(pts[vis], distance_upper_bound=inlier_distance)
    inl = np.isfinite(d)
    coverage = float(inl.mean())
    # RMSE along the sample normals (point-to-plane): the surface misfit, not the spacing of the cloud's points
    along = np.einsum("ij,ij->i", pts[vis][inl] - crop[j[inl]], nrm[vis][inl])
    rmse = float(np.sqrt(np.mean(along**2))) if inl.any() else float("nan")
    fitness = float("nan")
    if with_fitness:
        d_back, _ = cKDTree(pts).query(crop, distance_upper_bound=inlier_distance)
        fitness = float(np.isfinite(d_back).mean())
    problems = []
    passed = []  # what each check that ran measured, for the reason of an accepted fit
    if coverage < MIN_COVERAGE:
        problems.append(f"coverage {coverage:.0%} < {MIN_COVERAGE:.0%}")
    if not np.isfinite(rmse) or rmse > MAX_RMSE:
        problems.append(f"rmse {rmse * 1000:.1f} mm > {MAX_RMSE * 1000:.1f} mm")
    if neighbours is not None:
        problems += physical_problems(samples, transform, neighbours, views)
        passed.append("physically possible")
        unexplained, count = unexplained_fraction(samples, transform, crop, neighbours) if explain else (0.0, 0)
        if count >= UNEXPLAINED_MIN_POINTS and unexplained > UNEXPLAINED_FRACTION:
            problems.append(f"{unexplained:.0%} of the cloud around it is explained by no object")
        elif explain:
            passed.append(f"{unexplained:.0%} of {count} cloud points around it unaccounted for")
    if not problems and reference_colours is not None:
        changed, compared = colour_mismatch(sample_colours(pts, nrm, views), reference_colours)
        if compared >= COLOUR_MIN_SAMPLES and changed > COLOUR_FRACTION:
            problems.append(f"{changed:.0%} of its surface has another colour than at the reference step "
                            "(another object?)")
        else:
            passed.append(f"colours {changed:.0%} changed of {compared} samples seen at the reference step")
    if not problems and refine:
        shared = None if shared_shift is None else shared_shift()
        moved = refinement(samples, transform, crop, views, tree, shared=shared)
        if moved.improves():
            problems.append(f"a snap would move it {moved.translation * 1000:.0f} mm, "
                            f"{np.rad2deg(moved.rotation):.0f} deg and fit {moved.gain * 1000:.1f} mm closer")
        else:
            passed.append(f"a snap would move it {moved.translation * 1000:.1f} mm, {np.rad2deg(moved.rotation):.1f} "
                          f"deg and fit {moved.gain * 1000:.2f} mm closer (within limits)")
    reason = "; ".join(problems) if problems else "; ".join([f"rmse {rmse * 1000:.1f} mm, coverage {coverage:.0%}"]
                                                             + passed)
    return FitScore(rmse, coverage, fitness, not problems, reason, nvis)


def screen_quality(samples: SurfaceSamples, transforms: np.ndarray, tree, views: Sequence[View],
                    inlier_distance: float, min_visible: int = 20) -> np.ndarray:
    """Coarse quality (C,) of the samples at each of C candidate transforms (C, 4, 4) against a cloud's cKDTree,
    in one vectorised pass (for ranking start poses): coverage within `inlier_distance` minus the inliers' RMS
    distance in units of 2 cm (as `FitScore.quality`); -1 where fewer than `min_visible` samples are visible."""
    transforms = np.asarray(transforms, dtype=np.float64)
    count, size = len(transforms), len(samples.points)
    rot, t = transforms[:, :3, :3], transforms[:, :3, 3]
    rot_t = np.ascontiguousarray(rot.transpose(0, 2, 1))
    pts = (np.matmul(samples.points[None], rot_t) + t[:, None]).reshape(-1, 3)
    nrm = np.matmul(samples.normals[None], rot_t).reshape(-1, 3)
    vis = visible_samples(pts, nrm, views)
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


def _icp_subset(samples: SurfaceSamples, count: int = ICP_SAMPLES) -> SurfaceSamples:
    """A fixed random subset of at most `count` of the samples (all of them when fewer), for ICP's iterations."""
    if len(samples.points) <= count:
        return samples
    keep = np.random.default_rng(0).choice(len(samples.points), count, replace=False)
    return SurfaceSamples(samples.points[keep], samples.normals[keep], samples.centre, samples.radius)


def _icp_step(samples: SurfaceSamples, current: np.ndarray, crop: np.ndarray, tree, views: Sequence[View],
              dist: float) -> tuple[np.ndarray | None, bool, int]:
    """One damped Gauss-Newton point-to-plane step of the samples at `current` (4, 4) against the cloud crop (M, 3)
    (its cKDTree `tree`), matching within `dist` m: (the step (4, 4) to apply on the left, or None when fewer than
    MIN_CORRESPONDENCES samples matched; whether the step is negligible; the matched count)."""
    pts, nrm = posed_samples(samples, current)
    vis = visible_samples(pts, nrm, views)
    d, j = tree.query(pts[vis], distance_upper_bound=dist)
    ok = np.isfinite(d)
    if ok.sum() < MIN_CORRESPONDENCES:
        return None, False, int(ok.sum())
    p, n = pts[vis][ok], nrm[vis][ok]
    q = crop[j[ok]]
    r = np.einsum("ij,ij->i", p - q, n)
    w = _tukey(r, max(dist, 1e-6))
    centroid = p.mean(0)
    jac = np.hstack([np.cross(p - centroid, n), n])
    a = jac.T @ (w[:, None] * jac)
    damping = ICP_DAMPING * max(float(np.trace(a)), 1e-12) / 6
    x = np.linalg.solve(a + damping * np.eye(6), -jac.T @ (w * r))
    rot = rotvec_to_matrix(x[:3])
    step = np.eye(4)
    step[:3, :3] = rot
    step[:3, 3] = centroid - rot @ centroid + x[3:]
    small = bool(np.linalg.norm(x[3:]) < 1e-5 and np.linalg.norm(x[:3]) < 1e-4)
    return step, small, int(ok.sum())


@dataclass
class Refinement:
    """What a short ICP from a pose did (`refinement`): how far it moved the pose (m, the origin, less the shift
    the whole scene shares when one is given; rad), how much closer (m) it brought the visible samples to the cloud
    (mean distance to the nearest cloud point, capped at REFINE_CAP, before minus after; negative when it fits
    worse), and the origin's shift (3,) m itself."""

    translation: float
    rotation: float
    gain: float
    shift: np.ndarray

    def improves(self) -> bool:
        """Whether a snap would improve the pose: it moves more than REFINE_TRANSLATION or REFINE_ROTATION and
        gains more than REFINE_GAIN, or turns more than REFINE_TURN and gains more than REFINE_TURN_GAIN."""
        moved = self.translation > REFINE_TRANSLATION or self.rotation > REFINE_ROTATION
        return (moved and self.gain > REFINE_GAIN) or (self.rotation > REFINE_TURN and self.gain > REFINE_TURN_GAIN)


def _capped_distance(samples: SurfaceSamples, transform: np.ndarray, tree, views: Sequence[View]) -> float:
    """Mean distance (m) of the visible posed samples to their nearest cloud point (cKDTree), capped at REFINE_CAP
    (REFINE_CAP when none is visible)."""
    pts, nrm = posed_samples(samples, transform)
    vis = visible_samples(pts, nrm, views)
    if not vis.any():
        return REFINE_CAP
    d, _ = tree.query(pts[vis], distance_upper_bound=REFINE_CAP)
    return float(np.minimum(d, REFINE_CAP).mean())


def refinement(samples: SurfaceSamples, transform: np.ndarray, crop: np.ndarray, views: Sequence[View],
               tree=None, iterations: int = REFINE_ITERATIONS, shared: np.ndarray | None = None) -> Refinement:
    """Run `iterations` ICP steps (as `icp`: the correspondence distance shrinking from MAX_CORRESPONDENCE to
    2 x INLIER_DISTANCE, no jump limits) of REFINE_SAMPLES of the samples from `transform` (4, 4) against the cloud
    crop (M, 3) and report how far the pose moved and how much closer the surface came to the cloud (`Refinement`);
    a wrong pose that the other checks cannot tell (a 10 degree turn; a mug turned 180 degrees, its handle where it
    is not) moves towards the cloud and fits it better, a true pose moves by the noise and gains nothing.
    `shared`: the shift (3,) m that the refinement gives the other objects of the scene (the cameras' calibration
    error against the table frame moves them all alike); the translation is measured from it."""
    from scipy.spatial import cKDTree

    tree = cKDTree(crop) if tree is None else tree
    subset = _icp_subset(samples, REFINE_SAMPLES)
    current = np.asarray(transform, dtype=np.float64)
    dist, floor = MAX_CORRESPONDENCE, 2 * INLIER_DISTANCE
    for _ in range(iterations):
        step, small, _ = _icp_step(subset, current, crop, tree, views, dist)
        if step is None:
            break
        current = step @ current
        if small and dist <= floor:
            break
        dist = max(floor, dist * 0.75)
    shift = current[:3, 3] - np.asarray(transform, dtype=np.float64)[:3, 3]
    moved_r = pose_delta(transform, current)[1]
    moved_t = float(np.linalg.norm(shift if shared is None else shift - shared))
    gain = _capped_distance(subset, transform, tree, views) - _capped_distance(subset, current, tree, views)
    return Refinement(moved_t, moved_r, gain, shift)


def icp(samples: SurfaceSamples, crop: np.ndarray, start: np.ndarray, views: Sequence[View], *,
        max_correspondence: float = MAX_CORRESPONDENCE, inlier_distance: float = INLIER_DISTANCE,
        iterations: int = 40, max_translation: float = MAX_JUMP_TRANSLATION,
        max_rotation: float = MAX_JUMP_ROTATION, tree=None,
        neighbours: Sequence[tuple[str, SurfaceSamples, np.ndarray]] | None = None, explain: bool = False,
        reference_colours: np.ndarray | None = None) -> IcpResult:
    """Point-to-plane ICP of the mesh's visible samples against a cloud crop (M, 3), from `start` (4, 4).

    Each iteration matches the visible posed samples to their nearest cloud points within a correspondence
    distance that shrinks from `max_correspondence` to 2 x `inlier_distance`, weights residuals along the sample
    normals with Tukey's biweight, and takes one damped Gauss-Newton step (rotation about the matched samples'
    centroid). The result is rejected (transform = start, score.accepted False, reason given) when it moved more
    than `max_translation` m or `max_rotation` rad from the start, or found too few correspondences.
    `neighbours`, `explain`, `reference_colours`: the other objects (name, samples, 4x4 transform), for the
    score's physical checks, whether they are all of them, and the colours to compare with (`fit_score`; the
    result is not checked with `refine`: ICP has converged there).
    """
    from scipy.spatial import cKDTree

    start = np.asarray(start, dtype=np.float64)
    checks: dict = {"neighbours": neighbours, "explain": explain, "reference_colours": reference_colours}
    if len(crop) < MIN_CORRESPONDENCES:
        score = fit_score(samples, start, crop, views, inlier_distance, **checks)
        score.accepted, score.reason = False, f"only {len(crop)} cloud points near the object: move it onto its points"
        return IcpResult(start, score, 0, 0.0, 0.0, False)
    tree = cKDTree(crop) if tree is None else tree
    fit_samples = _icp_subset(samples)
    current = start.copy()
    dist = max_correspondence
    floor = 2 * inlier_distance
    it = 0
    for it in range(1, iterations + 1):
        step, small, matched = _icp_step(fit_samples, current, crop, tree, views, dist)
        if step is None:
            score = fit_score(samples, start, crop, views, inlier_distance, tree, **checks)
            score.accepted = False
            score.reason = (f"only {matched} mesh points have cloud points within {dist * 100:.1f} cm: "
                            "nudge the object onto its points and snap again")
            return IcpResult(start, score, it, 0.0, 0.0, False)
        current = step @ current
        if small and dist <= floor:
            break
        dist = max(floor, dist * 0.75)
    moved_t, moved_r = pose_delta(start, current)
    if moved_t > max_translation or moved_r > max_rotation:
        score = fit_score(samples, start, crop, views, inlier_distance, tree, **checks)
        score.accepted = False
        score.reason = (f"rejected jump: ICP moved the object {moved_t * 100:.1f} cm and {np.rad2deg(moved_r):.0f} deg "
                        f"(limits {max_translation * 100:.0f} cm, {np.rad2deg(max_rotation):.0f} deg); nudge it closer "
                        "and snap again")
        return IcpResult(start, score, it, moved_t, moved_r, False)
    score = fit_score(samples, current, crop, views, inlier_distance, tree, **checks)
    return IcpResult(current, score, it, moved_t, moved_r)
