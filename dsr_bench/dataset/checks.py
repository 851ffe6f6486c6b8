"""Per-sequence checks of `dsr-bench validate`: value ranges and the ground truth against itself (flow
recomputed from poses and amodal masks, flow zero off objects, amodal masks at t + 1 against the masks at t
moved by the flow, the TSDF's sign against the front depth image). A damaged file is a problem, never a crash.

Flow is checked by its source's own definition: ours is the exact rigid motion of each voxel's sample
point (`dsr_bench.geometry.groundtruth.rigid_scene_flow_3d`); the official release's (files imported with
`source` = `official-import`) is integer-valued, the difference of rounded voxel coordinates of the
object's solid points (see `official_flow_bound`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from dsr_bench.constants import FLOW_COMPONENTS, GRID_BOUNDS, GRID_SHAPE, NUM_DIRECTIONS, TSDF_TRUNCATION, VOXEL_SIZE
from dsr_bench.geometry import rotation_angle

#: Largest allowed difference (voxels) between stored flow and the rigid motion of the stored poses
#: (our own data; also the numerical slack added to the official release's bound).
FLOW_TOLERANCE = 1e-3
#: Least fraction of negative TSDF voxels that must lie behind the depth image's surface (edges disagree).
TSDF_SIGN_AGREEMENT = 0.95
#: Least IoU between an object's amodal voxels at t + 1 and its voxels at t moved by the flow.
MASK_WARP_IOU = 0.9


def action_problems(actions: np.ndarray, shape: tuple[int, int] = GRID_SHAPE[:2]) -> list[str]:
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

    checks = {"tsdf": tsdf, "mask_3d": mask_3d, "object_poses": poses, "action": action,
              "visible_fraction": visible}
    for name in ("scene_flow_3d", "push_start", "push_end", "heightmap"):
        checks[name] = (lambda name=name: _finite(name, seq.read(name)))
    for cam in seq.cameras:
        checks[f"cameras/{cam}/mask"] = camera_mask(f"cameras/{cam}/mask")
        flow2d = f"cameras/{cam}/scene_flow_2d"
        checks[flow2d] = (lambda name=flow2d: _finite(name, seq.read(name)))
    return {name: check for name, check in checks.items() if name in ok}


def _check_flow(seq) -> list[str]:
    """Stored flow against the rigid motion of the stored poses, and zero off objects; official imports
    by the release's own (rounded) definition, `_check_official_flow`."""
    from dsr_bench.geometry.groundtruth import rigid_scene_flow_3d

    if seq.attrs.get("source") == "official-import":
        return _check_official_flow(seq)
    problems = []
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


def official_flow_bound(angle: float) -> float:
    """Largest difference (voxels, per component) between the official release's flow at a voxel and
    the rigid motion of the stored poses at that voxel's grid point, for a push that turns the object
    by `angle` radians.

    The release stores at voxel i the flow round(c') - round(c) of a solid point c of the object with
    round(c) = i, in voxel coordinates (c = (world - bound_min) / voxel size, so voxel i's grid point
    is bound_min + i * voxel size, the release's corner convention), where c' = R c + t is c moved by
    the push. With m(i) = (R - I) i + t the motion of the grid point:
        flow - m(i) = [(round(c') - c') - (round(c) - c)] + (R - I)(c - i).
    Each rounding moves a coordinate by at most 1/2, so the bracket is within 1 per component; c lies
    within half a voxel of i on each axis, |c - i| <= sqrt(3)/2, and the spectral norm of R - I is
    2 sin(angle / 2), so the second term is within sqrt(3) sin(angle / 2). The solid points themselves are not stored, so
    this is what can be checked: 1 voxel without rotation, at most 1 + sqrt(3) (a half turn).
    """
    return 1.0 + math.sqrt(3.0) * math.sin(min(abs(angle), math.pi) / 2)


def _grid_point_motion(indices_yxz: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """Rigid motion (M, 3) in voxels (dy, dx, dz) of the official grid points (bound_min + i * voxel
    size) of voxel indices (M, 3) in (iy, ix, iz)."""
    from dsr_bench.geometry import transform_points

    points = GRID_BOUNDS[:, 0] + indices_yxz[:, [1, 0, 2]].astype(np.float64) * VOXEL_SIZE
    return ((transform_points(motion, points) - points) / VOXEL_SIZE)[:, [1, 0, 2]]


def _official_flow_hint(got: np.ndarray, expected: np.ndarray, bound: float,
                        others: dict[int, tuple[np.ndarray, float]]) -> str:
    """What a flow that fails the official check would match: sign flipped, two components swapped,
    or another object's motion (empty if none)."""
    names = FLOW_COMPONENTS.split(",")
    limit = bound + FLOW_TOLERANCE
    if np.abs(-got - expected).max() <= limit:
        return "; it matches with the sign flipped"
    for a, b in ((0, 1), (0, 2), (1, 2)):
        swapped = got.copy()
        swapped[:, [a, b]] = got[:, [b, a]]
        if np.abs(swapped - expected).max() <= limit:
            return f"; it matches with {names[a]} and {names[b]} swapped"
    for obj, (motion, other_bound) in others.items():
        if np.abs(got - motion).max() <= other_bound + FLOW_TOLERANCE:
            return f"; it matches object {obj}'s motion (flow of the wrong object?)"
    return ""


def _check_official_flow(seq) -> list[str]:
    """Official flow by the release's definition: integer-valued, zero off objects, and at each voxel of
    object k within `official_flow_bound(angle)` (+ FLOW_TOLERANCE) of the rigid motion of k's stored
    poses at the voxel's grid point, per component."""
    from dsr_bench.geometry import relative_motion

    names = FLOW_COMPONENTS.split(",")
    problems = []
    for t, poses, mask, flow in _flow_steps(seq, problems):
        fractional = flow != np.rint(flow)
        if fractional.any():
            c, y, x, z = np.argwhere(fractional)[0]
            count = np.count_nonzero(fractional.any(axis=0))
            problems.append(f"scene_flow_3d[{t}]: {count} voxels hold non-integer flow (e.g. {names[c]} = "
                            f"{float(flow[c, y, x, z]):g} at voxel (y, x, z) = ({y}, {x}, {z})); the official "
                            "release's flow is a difference of rounded voxel coordinates, so integer-valued")
        motions = {k: relative_motion(poses[t, k - 1], poses[t + 1, k - 1]) for k in range(1, seq.num_objects + 1)}
        for k, motion in motions.items():
            idx = np.argwhere(mask == k)
            if len(idx) == 0:
                continue
            got = flow[:, idx[:, 0], idx[:, 1], idx[:, 2]].T.astype(np.float64)
            expected = _grid_point_motion(idx, motion)
            angle = rotation_angle(motion[:3, :3])
            bound = official_flow_bound(angle)
            err = np.abs(got - expected)
            if err.max() <= bound + FLOW_TOLERANCE:
                continue
            bad = np.count_nonzero((err > bound + FLOW_TOLERANCE).any(axis=1))
            j, c = np.unravel_index(np.argmax(err), err.shape)
            others = {o: (_grid_point_motion(idx, m), official_flow_bound(rotation_angle(m[:3, :3])))
                      for o, m in motions.items() if o != k}
            hint = _official_flow_hint(got, expected, bound, others)
            problems.append(
                f"scene_flow_3d[{t}]: object {k}: {bad} of {len(idx)} voxels differ from the rounded rigid motion "
                f"of its stored poses by more than the release's rounding allows ({bound:.2f} voxels at this "
                f"push's {math.degrees(angle):.1f}-degree turn): up to {err[j, c]:.3g} (e.g. {names[c]} = "
                f"{got[j, c]:g}, expected {round(expected[j, c], 2) + 0.0:.2f}, at voxel (y, x, z) = "
                f"{tuple(int(v) for v in idx[j])})"
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
    shape = tuple(both.max(0) - lo + 2)
    warped, truth = np.zeros(shape, bool), np.zeros(shape, bool)
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
    from dsr_bench.geometry import voxel_points

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
