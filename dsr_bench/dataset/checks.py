"""Per-sequence checks of `dsr-bench validate`: value ranges and the ground truth against itself (flow
recomputed from poses and amodal masks, flow zero off objects, amodal masks at t + 1 against the masks at t
moved by the flow, the TSDF's sign against the front depth image). A damaged file is a problem, never a crash.

Flow is checked by its source's own definition: ours is the exact rigid motion of each voxel's sample
point (`dsr_bench.geometry.groundtruth.rigid_scene_flow_3d`); the official release's (files imported with
`source` = `official-import`) is integer-valued, the difference of rounded voxel coordinates of the
object's solid points moved by its poses, which the release stores as read at other instants than the
flow's (see `rounding_excess` and OFFICIAL_POSE_DRIFT).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from dsr_bench.constants import FLOW_COMPONENTS, GRID_BOUNDS, GRID_SHAPE, NUM_DIRECTIONS, TSDF_TRUNCATION, VOXEL_SIZE
from dsr_bench.geometry import rotation_angle, transform_points, voxel_points
from dsr_bench.geometry.groundtruth import rigid_scene_flow_3d

#: Largest allowed difference (voxels) between stored flow and the rigid motion of the stored poses
#: (our own data; also the numerical slack added to the official release's allowance).
FLOW_TOLERANCE = 1e-3
#: Least fraction of negative TSDF voxels that must lie behind the depth image's surface (edges disagree).
TSDF_SIGN_AGREEMENT = 0.95
#: Least IoU between an object's amodal voxels at t + 1 and its voxels at t moved by the flow.
MASK_WARP_IOU = 0.9


def action_problems(actions: np.ndarray, shape: tuple[int, ...] = GRID_SHAPE[:2]) -> list[str]:
    """What is wrong with actions (T, 3) [direction, row, col] on a (Y, X) action map (none: [])."""
    a = np.asarray(actions)
    if a.ndim != 2 or a.shape[1] != 3 or not np.issubdtype(a.dtype, np.integer):
        return [f"action: {a.dtype} array of shape {a.shape}, expected (T, 3) integers [direction, row, col]"]
    out = []
    if a.size and (a[:, 0].min() < 0 or a[:, 0].max() >= NUM_DIRECTIONS):
        out.append(f"action: direction outside 0..{NUM_DIRECTIONS - 1} (values {a[:, 0].min()}..{a[:, 0].max()})")
    if a.size and (a[:, 1:].min() < 0 or a[:, 1].max() >= shape[0] or a[:, 2].max() >= shape[1]):
        out.append(f"action: row/col outside 0..{shape[0] - 1}" if shape[0] == shape[1]
                   else f"action: row/col outside the {shape[0]} x {shape[1]} map")
    return out


def _guard(problems: list[str], label: str, check: Callable[[], list[str]]) -> None:
    """Run one check; a read error (truncated chunk, bad data) becomes a problem, not a crash."""
    try:
        problems += check()
    except Exception as exc:  # noqa: BLE001 - anything a damaged file raises
        problems.append(f"{label}: unreadable data ({type(exc).__name__}: {exc})")


def _finite(name: str, a: np.ndarray) -> list[str]:
    return [] if np.all(np.isfinite(a)) else [f"{name}: {int(np.sum(~np.isfinite(a)))} values are NaN or inf"]


def _range_checks(seq, ok: set[str]) -> dict[str, Callable[[], list[str]]]:
    """Value-range checks of the fields whose shape and dtype are right."""
    n = seq.num_objects

    def tsdf():
        a = seq.read("tsdf")
        out = _finite("tsdf", a)
        if not out and (a.min() < -1 or a.max() > 1):
            out.append(f"tsdf: values in [{a.min():.3g}, {a.max():.3g}], expected [-1, 1]")
        return out

    def mask_3d():
        m = int(seq.read("mask_3d").max())
        return [f"mask_3d: instance id {m} > num_objects {n}"] if m > n else []

    def camera_mask(name):
        def check():
            m = int(seq.read(name).max())
            return [f"{name}: instance id {m} > num_objects {n}"] if m > n else []
        return check

    def poses():
        a = seq.read("object_poses")
        out = _finite("object_poses", a)
        if not out:
            norm = np.linalg.norm(a[..., 3:], axis=-1)
            if not np.allclose(norm, 1.0, atol=1e-4):
                out.append(f"object_poses: quaternion norms in [{norm.min():.4g}, {norm.max():.4g}], expected 1")
        return out

    def action():
        return action_problems(seq.read("action"))

    def visible():
        a = seq.read("visible_fraction")
        out = _finite("visible_fraction", a)
        if not out and (a.min() < 0 or a.max() > 1):
            out.append(f"visible_fraction: values in [{a.min():.3g}, {a.max():.3g}], expected [0, 1]")
        return out

    def finite(name):
        return lambda: _finite(name, seq.read(name))

    checks: dict[str, Callable[[], list[str]]] = {"tsdf": tsdf, "mask_3d": mask_3d, "object_poses": poses,
                                                  "action": action, "visible_fraction": visible}
    for name in ("scene_flow_3d", "push_start", "push_end", "heightmap"):
        checks[name] = finite(name)
    for cam in seq.cameras:
        checks[f"cameras/{cam}/mask"] = camera_mask(f"cameras/{cam}/mask")
        flow2d = f"cameras/{cam}/scene_flow_2d"
        checks[flow2d] = finite(flow2d)
    return {name: check for name, check in checks.items() if name in ok}


def _check_flow(seq) -> list[str]:
    """Stored flow against the rigid motion of the stored poses, and zero off objects; official imports
    by the release's own (rounded) definition, `_check_official_flow`."""
    if seq.attrs.get("source") == "official-import":
        return _check_official_flow(seq)
    problems: list[str] = []
    for t, poses, mask, flow in _flow_steps(seq, problems):
        err = float(np.abs(flow - rigid_scene_flow_3d(mask, poses[t], poses[t + 1])).max())
        if err > FLOW_TOLERANCE:
            problems.append(f"scene_flow_3d[{t}]: differs from the rigid motion of the stored poses by "
                            f"{err:.3g} voxels (tolerance {FLOW_TOLERANCE:g})")
    return problems


def _flow_steps(seq, problems: list[str]):
    """(t, poses, mask_3d[t], scene_flow_3d[t]) for every push, reporting flow outside every object into
    `problems` on the way (zero there by every source's definition)."""
    poses = seq.read("object_poses")
    for t in range(seq.num_steps):
        mask = seq.read("mask_3d", t)
        flow = seq.read("scene_flow_3d", t)
        outside = np.count_nonzero(np.any(flow[:, mask == 0] != 0, axis=0))
        if outside:
            problems.append(f"scene_flow_3d[{t}]: {outside} voxels outside every object have non-zero flow")
        yield t, poses, mask, flow


#: Official imports: how far (voxels, per axis) the release's stored poses may place an object's points from where
#: the poses its flow was computed from place them. The authors' generator reads the poses for the flow at other
#: instants than the ones it stores (the old ones just before a step's images are rendered, the new ones once the
#: robot is home; the stored ones after the rendering and, for t + 1, after the TSDF fusion and the file writing)
#: while its physics thread keeps stepping the settling objects. Recorded from their generator
#: (columbia-ai-robotics/dsr, cube, pybullet 3.2.7), 30 sequences, 1,200 object-pushes: the stored poses place
#: the points up to 0.44 voxels from the ones used and put the flow up to 0.21 voxels off its rounding (the
#: poses used give it exactly); a pose 1 cm off is 2.5 voxels.
OFFICIAL_POSE_DRIFT = 0.5


def official_rotation(quat_xyzw: np.ndarray) -> np.ndarray:
    """The rotation (3, 3) the authors' generator gives a stored orientation (x, y, z, w): it turns the quaternion
    into roll, pitch and yaw as pybullet's getEulerFromQuaternion does (where |sin(pitch)| >= 0.99999, pitch is set
    to +-pi/2 and roll to 0, up to 0.26 degrees from the quaternion's own rotation) and builds
    Rz(yaw) Ry(pitch) Rx(roll) from them."""
    x, y, z, w = (float(v) for v in quat_xyzw)
    sin_pitch = 2.0 * (w * y - x * z)
    if abs(sin_pitch) >= 0.99999:
        sign = 1.0 if sin_pitch > 0 else -1.0
        roll, pitch, yaw = 0.0, sign * math.pi / 2, 2.0 * math.atan2(-sign * x, sign * y)
    else:
        roll = math.atan2(2.0 * (w * x + y * z), w * w - x * x - y * y + z * z)
        pitch = math.asin(sin_pitch)
        yaw = math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def official_motion(pose_from: np.ndarray, pose_to: np.ndarray) -> np.ndarray:
    """World-frame 4x4 motion of an object's points between two stored poses (7,), the authors' way: each pose
    places the points by `official_rotation` and its position."""
    rot_from, rot_to = official_rotation(pose_from[3:]), official_rotation(pose_to[3:])
    rot = rot_to @ rot_from.T
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = np.asarray(pose_to[:3], np.float64) - rot @ np.asarray(pose_from[:3], np.float64)
    return out


def _separating_axes(rot: np.ndarray) -> np.ndarray:
    """Unit axes (K, 3) that separate an axis-aligned cube from a cube turned by `rot` (rows: its edge
    directions) whenever anything does: both cubes' face normals and the cross products of their edges."""
    faces = [*np.eye(3), *rot]
    cross = [np.cross(a, b) for a in np.eye(3) for b in rot]
    axes = faces + [c / np.linalg.norm(c) for c in cross if np.linalg.norm(c) > 1e-9]
    return np.array(axes)


def rounding_excess(indices_yxz: np.ndarray, flow_yxz: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """Per voxel (M,): how far (voxels, per axis) a point of voxel i moved by the world `motion` (4x4) falls
    short of making the flow f the release's round(c') - round(c); <= 0 where some point does.

    In voxel coordinates (c = (world - bound_min) / voxel size, x, y, z) a solid point c with round(c) = i
    lies in the cube of half-side 1/2 around i, the motion maps it to c' = R c + u, and round(c') = i + f
    means c' lies in the cube of half-side 1/2 around i + f. So f is possible exactly when the motion maps
    some point of the first cube into the second, and within a shift s per axis when it maps one into the
    cube of half-side 1/2 + s. Pulled back by the motion the second cube is a turned cube (centre
    g = R^T (i + f - u), edges along R's rows); two cubes meet unless an axis L among their face normals
    and edge cross products separates them: |(g - i) . L| > |L|_1 / 2 + (1/2 + s) |R L|_1. The least s
    is the largest (|(g - i) . L| - |L|_1 / 2) / |R L|_1 - 1/2 over those axes.
    indices_yxz (M, 3) voxel indices (iy, ix, iz); flow_yxz (M, 3) components (dy, dx, dz).
    """
    rot = motion[:3, :3]
    shift = (rot @ GRID_BOUNDS[:, 0] + motion[:3, 3] - GRID_BOUNDS[:, 0]) / VOXEL_SIZE
    start = np.asarray(indices_yxz, np.float64)[:, [1, 0, 2]]
    target = start + np.asarray(flow_yxz, np.float64)[:, [1, 0, 2]]
    offset = (target - shift) @ rot - start  # R^T (i + f - u) - i, as rows
    axes = _separating_axes(rot)
    reach = np.abs(offset @ axes.T) - 0.5 * np.abs(axes).sum(axis=1)
    return (reach / np.abs(axes @ rot.T).sum(axis=1)).max(axis=1) - 0.5


def _grid_point_motion(indices_yxz: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """Rigid motion (M, 3) in voxels (dy, dx, dz) of the official grid points (bound_min + i * voxel
    size) of voxel indices (M, 3) in (iy, ix, iz)."""
    points = GRID_BOUNDS[:, 0] + indices_yxz[:, [1, 0, 2]].astype(np.float64) * VOXEL_SIZE
    return ((transform_points(motion, points) - points) / VOXEL_SIZE)[:, [1, 0, 2]]


def _official_flow_hint(idx: np.ndarray, got: np.ndarray, motion: np.ndarray, others: dict[int, np.ndarray]) -> str:
    """What a flow that fails the official check would pass as: sign flipped, two components swapped, or
    another (moving) object's motion (empty if none)."""
    names = FLOW_COMPONENTS.split(",")
    limit = OFFICIAL_POSE_DRIFT + FLOW_TOLERANCE
    if rounding_excess(idx, -got, motion).max() <= limit:
        return "; it matches with the sign flipped"
    for a, b in ((0, 1), (0, 2), (1, 2)):
        swapped = got.copy()
        swapped[:, [a, b]] = got[:, [b, a]]
        if rounding_excess(idx, swapped, motion).max() <= limit:
            return f"; it matches with {names[a]} and {names[b]} swapped"
    still = np.zeros_like(got)
    for obj, other in others.items():  # an object that stayed still matches any zero flow: no hint from it
        if rounding_excess(idx, got, other).max() <= limit < rounding_excess(idx, still, other).max():
            return f"; it matches object {obj}'s motion (flow of the wrong object?)"
    return ""


def _check_official_flow(seq) -> list[str]:
    """Official flow by the release's definition: integer-valued, zero off objects, and at each voxel of object k
    a difference of rounded voxel coordinates of a point of that voxel moved by k's stored poses the authors' way
    (`official_motion`), within OFFICIAL_POSE_DRIFT (+ FLOW_TOLERANCE) voxels per axis (`rounding_excess`)."""
    names = FLOW_COMPONENTS.split(",")
    limit = OFFICIAL_POSE_DRIFT + FLOW_TOLERANCE
    problems: list[str] = []
    for t, poses, mask, flow in _flow_steps(seq, problems):
        fractional = flow != np.rint(flow)
        if fractional.any():
            c, y, x, z = np.argwhere(fractional)[0]
            count = np.count_nonzero(fractional.any(axis=0))
            problems.append(f"scene_flow_3d[{t}]: {count} voxels hold non-integer flow (e.g. {names[c]} = "
                            f"{float(flow[c, y, x, z]):g} at voxel (y, x, z) = ({y}, {x}, {z})); the official "
                            "release's flow is a difference of rounded voxel coordinates, so integer-valued")
        motions = {k: official_motion(poses[t, k - 1], poses[t + 1, k - 1]) for k in range(1, seq.num_objects + 1)}
        for k, motion in motions.items():
            idx = np.argwhere(mask == k)
            if len(idx) == 0:
                continue
            got = flow[:, idx[:, 0], idx[:, 1], idx[:, 2]].T.astype(np.float64)
            excess = rounding_excess(idx, got, motion)
            if excess.max() <= limit:
                continue
            j = int(np.argmax(excess))
            moved = ", ".join(f"{round(v, 2) + 0.0:.2f}" for v in _grid_point_motion(idx[j:j + 1], motion)[0])
            hint = _official_flow_hint(idx, got, motion, {o: m for o, m in motions.items() if o != k})
            problems.append(
                f"scene_flow_3d[{t}]: object {k}: {np.count_nonzero(excess > limit)} of {len(idx)} voxels hold a flow "
                f"that no point of the voxel moved by the object's stored poses rounds to (a "
                f"{math.degrees(rotation_angle(motion[:3, :3])):.1f}-degree turn): up to {excess[j]:.2f} voxels off "
                f"(allowance {OFFICIAL_POSE_DRIFT:g} for the instants the release reads its poses at), e.g. "
                f"({', '.join(names)}) = ({', '.join(f'{v:g}' for v in got[j])}) at voxel (y, x, z) = "
                f"{tuple(int(v) for v in idx[j])}, whose grid point moves by ({moved})"
                f"{hint}")
    return problems


#: Below this many voxels inside the grid at both steps an object is not compared (an edge effect).
MIN_WARP_VOXELS = 64


def mask_warp_iou(mask_t: np.ndarray, flow_t: np.ndarray, mask_next: np.ndarray, obj: int) -> float | None:
    """Voxel-tolerant IoU of object `obj`'s voxels at t + 1 with its voxels at t moved by the flow.

    mask_t, mask_next: (Y, X, Z) ids; flow_t: (3, Y, X, Z) voxels (dy, dx, dz). Moved voxel centres
    are rounded to voxels (those leaving the grid are dropped). A voxel of either set matches if the
    other set has a voxel within one voxel (26-neighbourhood): rounding a rotated solid's voxels
    leaves holes and doubles that a plain IoU would count (it drops to ~0.6 for valid 30-degree
    turns). Returns (matched voxels of both sets) / (voxels of both sets), or None if there is nothing
    to compare: the object has no voxel at t (it is outside the grid: pushes are never undone, so an
    object may leave the grid and come back), or fewer than MIN_WARP_VOXELS in the grid's interior at
    both steps. Voxels on the grid's side faces are left out (the faces cut a solid that crosses them,
    and rounding decides which side a voxel there falls on), and so is the part of the object at
    t + 1 that was outside the grid at t.
    """
    from scipy import ndimage

    src = np.argwhere(mask_t == obj)
    if len(src) == 0:
        return None
    shape = np.array(mask_t.shape)
    exact = src + flow_t[:, src[:, 0], src[:, 1], src[:, 2]].T
    moved = np.rint(exact).astype(np.int64)
    moved = moved[np.all((moved >= 0) & (moved < shape), axis=1)]
    target = np.argwhere(mask_next == obj)
    if len(src) >= 4 and len(target):  # leave out the part that entered the grid: it had no voxels at t
        rotation, shift = _rigid_fit(src.astype(np.float64), exact)
        before = (target - shift) @ rotation  # R^T (x - t), row vectors
        target = target[np.all((before >= -0.5) & (before < shape - 0.5), axis=1)]
    # the grid's side faces (y, x) cut a solid that crosses them, and rounding decides which side a voxel
    # there falls on: compare the interior only
    inner = np.array([1, 1, 0]), shape - np.array([1, 1, 0])
    moved = moved[np.all((moved >= inner[0]) & (moved < inner[1]), axis=1)]
    target = target[np.all((target >= inner[0]) & (target < inner[1]), axis=1)]
    if len(moved) < MIN_WARP_VOXELS and len(target) < MIN_WARP_VOXELS:
        return None  # (almost) nothing of the object left inside the grid to compare
    if len(moved) == 0 or len(target) == 0:
        return 0.0
    both = np.concatenate([moved, target])
    lo = both.min(0) - 1
    box = tuple(both.max(0) - lo + 2)
    warped, truth = np.zeros(box, bool), np.zeros(box, bool)
    warped[tuple((moved - lo).T)] = True
    truth[tuple((target - lo).T)] = True
    cube = np.ones((3, 3, 3), bool)
    matched = np.count_nonzero(warped & ndimage.binary_dilation(truth, cube))
    matched += np.count_nonzero(truth & ndimage.binary_dilation(warped, cube))
    return matched / (np.count_nonzero(warped) + np.count_nonzero(truth))


def _rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation R (3, 3) and shift t (3,) minimising |R a_i + t - b_i| over point pairs (Kabsch)."""
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rotation = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rotation, cb - rotation @ ca


def _check_mask_warp(seq) -> list[str]:
    problems = []
    for t in range(seq.num_steps):
        mask_t, flow_t, mask_next = seq.read("mask_3d", t), seq.read("scene_flow_3d", t), seq.read("mask_3d", t + 1)
        for obj in range(1, seq.num_objects + 1):
            iou = mask_warp_iou(mask_t, flow_t, mask_next, obj)
            if iou is not None and iou < MASK_WARP_IOU:
                problems.append(f"mask_3d[{t + 1}]: object {obj} overlaps its voxels at {t} moved by the flow "
                                f"with IoU {iou:.2f} (within a voxel) < {MASK_WARP_IOU}")
    return problems


def _check_tsdf_sign(seq, camera: str = "front") -> list[str]:
    """Voxels with tsdf < 0 must lie behind the depth image's surface, within the truncation."""
    problems = []
    cam = seq.camera(camera)
    centres = voxel_points()
    for t in range(seq.num_steps + 1):
        tsdf = seq.read("tsdf", t)
        depth = seq.read(f"cameras/{camera}/depth", t)
        neg = centres[tsdf < 0]
        if len(neg) == 0:
            continue
        uv, z = cam.project(neg)
        # at the stored image's resolution a pixel spans ~3 mm, so a voxel agrees when any of the four pixels
        # around its projection has a surface in front of it (edges of objects alias otherwise), with 6 mm slack
        u0, v0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = np.zeros(len(neg), dtype=bool)
        for du in (0, 1):
            for dv in (0, 1):
                d = depth[np.clip(v0 + dv, 0, cam.height - 1), np.clip(u0 + du, 0, cam.width - 1)]
                behind = z - d
                ok |= (d > 0) & (behind > -0.006) & (behind < TSDF_TRUNCATION + 0.012)
        agree = float(np.mean(ok))
        if agree < TSDF_SIGN_AGREEMENT:
            problems.append(f"tsdf[{t}]: only {agree:.0%} of negative voxels lie behind the {camera} depth "
                            f"image's surface (expected >= {TSDF_SIGN_AGREEMENT:.0%})")
    return problems


def content_problems(seq, ok: set[str], check_gt: bool = True) -> list[str]:
    """Problems of an open sequence's values: ranges of the datasets in `ok` (those whose shape and dtype are
    right, `dsr_bench.dataset.validate.schema_problems`) and, with `check_gt` and the ranges right, the ground
    truth's consistency (flow, mask warp, TSDF sign). A read error is a problem, never an exception."""
    problems: list[str] = []
    range_problems: list[str] = []
    for name, check in _range_checks(seq, ok).items():
        _guard(range_problems, name, check)
    problems += range_problems
    if check_gt:
        gt_ready = not range_problems and {"mask_3d", "scene_flow_3d", "object_poses"} <= ok
        if gt_ready:
            _guard(problems, "scene_flow_3d", lambda: _check_flow(seq))
            _guard(problems, "mask_3d", lambda: _check_mask_warp(seq))
        if not range_problems and "tsdf" in ok and "cameras/front/depth" in ok:
            _guard(problems, "tsdf", lambda: _check_tsdf_sign(seq))
    return problems
