"""Per-sequence statistics of simulated pushing sequences, and the resampling that compares two sets.

Pure numpy, no I/O: `bench/bench_fidelity.py` reads both generators' data into `Record`s and calls
`sequence_statistics` on each. Every statistic is one number per sequence (averaged over the pushes
or objects of that sequence, NaN where the sequence has nothing to average); `STATISTICS` holds
each one's definition, printed under the table and repeated in bench_fidelity.py's docstring.

Conventions: positions in metres (world frame), quaternions (x, y, z, w) as pybullet writes them,
actions [d, row, col] with direction angle d * pi / 4 in world xy, row along world y, col along
world x, cell = floor((p - bound_min) / 0.004); a push's start is its cell's centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dsr_bench.constants import GRID_BOUNDS, VOXEL_SIZE, WORKSPACE_CENTER
from dsr_bench.geometry import direction_vector, pixel_to_world, quat_to_matrix

#: An object moves in a push if its centre moves more than this (m, one voxel) ...
MOVE_TRANSLATION: float = 0.004
#: ... or it rotates by more than this (degrees).
MOVE_ROTATION_DEG: float = 2.0
#: The pushed object is the one whose centre is nearest to the segment from start + 0.02 m to start +
#: 0.12 m along the push direction (m).
PUSHED_SEGMENT: tuple[float, float] = (0.02, 0.12)
#: Points per axis of the lattice that stands for an object's points (statistic 5).
LATTICE: int = 5
CENTRE = np.asarray(WORKSPACE_CENTER, dtype=np.float64)

#: key -> (table label, definition). One row per key, in this order.
STATISTICS: dict[str, tuple[str, str]] = {
    "moving_per_push": (
        "objects moving per push",
        ("mean over pushes t of the number of objects whose pose change from t to t+1 moves the centre by "
         "> 4 mm (3D) or rotates it by > 2 deg (angle 2 acos|w| of q[t+1] * conj(q[t]))")),
    "multi_move_pct": (
        "pushes moving >= 2 objects (%)",
        "share of pushes in which >= 2 objects move (moving as in 'objects moving per push')"),
    "first_push_cos": (
        "first push: cos(dir, to centre)",
        ("mean over pushes that are the first push of the pushed object in the sequence of cos(angle) between "
         "the push direction and the xy direction from the object's centre before the push to (0.5, 0)")),
    "pushed_translation_cm": (
        "pushed object: translation (cm)",
        "mean over pushes of the 3D distance (cm) the pushed object's centre moves in its push"),
    "pushed_rotation_deg": (
        "pushed object: rotation (deg)",
        ("mean over pushes of the rotation angle (deg) of the pushed object in its push, 2 acos|w| of "
         "q[t+1] * conj(q[t])")),
    "point_displacement_vox": (
        "moving objects: point displacement (vox)",
        ("mean over (push, moving object) of the mean |displacement| (voxels of 4 mm) of a 5x5x5 lattice at "
         "the cell centres of a cube of side s, s^3 = voxels_per_object[t] * 0.004^3, centred on the object's "
         "origin in its body frame, moved from the pose at t to the pose at t+1")),
    "initial_distance_cm": (
        "distance from centre at t=0 (cm)",
        "mean over objects of the xy distance (cm) of the object's centre at t = 0 from (0.5, 0)"),
    "edge_pct": (
        "pushes ending with an object at the edge (%)",
        ("share of pushes after which some object's centre lies within s/2 of the grid's xy bounds "
         "(x in [0.244, 0.756], y in [-0.256, 0.256]) or outside them, s^3 = voxels_per_object[0] * 0.004^3")),
    "voxels_t0": (
        "voxels per object at t=0",
        "mean over objects of voxels_per_object[0] (voxels of mask_3d == k at t = 0)"),
    "tsdf_negative_pct": (
        "TSDF in (-1, 0) (%)",
        "mean over steps t < T of the share of TSDF voxels with -1 < v < 0"),
    "tsdf_near_pct": (
        "TSDF in [0, 1) (%)",
        "mean over steps t < T of the share of TSDF voxels with 0 <= v < 1"),
    "tsdf_free_pct": (
        "TSDF >= 1 (%)",
        "mean over steps t < T of the share of TSDF voxels with v >= 1"),
    "direction_resultant": (
        "push directions: mean resultant length",
        ("length of the mean of the unit push direction vectors (cos d pi/4, sin d pi/4) of the sequence's "
         "pushes (0: balanced, 1: all one way)")),
    "axis_direction_pct": (
        "pushes along the axes (d even) (%)",
        "share of pushes with an even direction index d (along +-x or +-y)"),
    "same_object_pct": (
        "same object as the previous push (%)",
        "share of pushes t >= 1 whose pushed object is the pushed object of push t-1"),
    "start_distance_cm": (
        "start distance to pushed object (cm)",
        ("mean over pushes of the xy distance (cm) from the push start (the action cell's centre) to the "
         "pushed object's centre before the push")),
}
#: How the pushed object of a push is found, the same on both sides (none is recorded in the reference).
PUSHED_OBJECT_RULE = ("pushed object: the object whose xy centre before the push is nearest to the segment from "
                      "start + 0.02 m to start + 0.12 m along the push direction (start = the action cell's centre)")


@dataclass(frozen=True)
class Record:
    """One sequence, reduced to what the statistics need (T pushes, N objects).

    positions (T+1, N, 3) m; quaternions (T+1, N, 4) (x, y, z, w); actions (T, 3) int [d, row, col];
    voxels_per_object (T+1, N) voxels of mask_3d == k (k = 1..N); tsdf_bands (T, 3) shares of TSDF
    voxels in (-1, 0), [0, 1) and >= 1 at steps t < T.
    """

    name: str
    positions: np.ndarray
    quaternions: np.ndarray
    actions: np.ndarray
    voxels_per_object: np.ndarray
    tsdf_bands: np.ndarray

    def __post_init__(self) -> None:
        T = len(self.actions)
        n = self.positions.shape[1] if self.positions.ndim == 3 else -1
        expected = {"positions": (T + 1, n, 3), "quaternions": (T + 1, n, 4), "actions": (T, 3),
                    "voxels_per_object": (T + 1, n), "tsdf_bands": (T, 3)}
        for field, shape in expected.items():
            got = np.shape(getattr(self, field))
            if got != shape or T < 1 or n < 1:
                raise ValueError(f"{self.name}: {field} has shape {got}, expected {shape} "
                                 f"(T = {T} pushes, N = {n} objects)")

    @property
    def num_pushes(self) -> int:
        return len(self.actions)


# --- geometry -----------------------------------------------------------------------------------


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of quaternions (..., 4) in (x, y, z, w) order."""
    ax, ay, az, aw = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion) of quaternions (..., 4), (x, y, z, w)."""
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([-q[..., :3], q[..., 3:]], axis=-1)


def rotation_angle(q_before: np.ndarray, q_after: np.ndarray) -> np.ndarray:
    """Angle (radians, 0..pi) of the relative rotation q_after * conj(q_before): 2 acos(|w|)."""
    a = np.asarray(q_after, dtype=np.float64)
    b = np.asarray(q_before, dtype=np.float64)
    rel = quat_multiply(a / np.linalg.norm(a, axis=-1, keepdims=True),
                        quat_conjugate(b / np.linalg.norm(b, axis=-1, keepdims=True)))
    return 2.0 * np.arccos(np.clip(np.abs(rel[..., 3]), 0.0, 1.0))


def push_starts(actions: np.ndarray) -> np.ndarray:
    """(T, 2) world xy (m) of the push starts: the centres of the actions' cells."""
    return pixel_to_world(np.asarray(actions)[:, 1:])


def push_directions(actions: np.ndarray) -> np.ndarray:
    """(T, 2) unit push directions in world xy: (cos d pi/4, sin d pi/4)."""
    return direction_vector(np.asarray(actions, dtype=np.int64)[:, 0])


def segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (m) from points (..., 2) to the segments a-b (..., 2) (broadcast)."""
    ab = b - a
    s = np.clip(np.sum((points - a) * ab, -1) / np.maximum(np.sum(ab * ab, -1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(points - (a + s[..., None] * ab), axis=-1)


def pushed_objects(rec: Record) -> np.ndarray:
    """(T,) index of the pushed object of each push (see PUSHED_OBJECT_RULE)."""
    start, u = push_starts(rec.actions), push_directions(rec.actions)
    a = start + PUSHED_SEGMENT[0] * u
    b = start + PUSHED_SEGMENT[1] * u
    dist = segment_distance(rec.positions[:-1, :, :2], a[:, None], b[:, None])  # (T, N)
    return np.argmin(dist, axis=1)


def object_motion(rec: Record) -> tuple[np.ndarray, np.ndarray]:
    """(translation (T, N) m, rotation (T, N) degrees) of every object in every push (3D centre distance,
    relative rotation angle)."""
    translation = np.linalg.norm(rec.positions[1:] - rec.positions[:-1], axis=-1)
    rotation = np.degrees(rotation_angle(rec.quaternions[:-1], rec.quaternions[1:]))
    return translation, rotation


def moving(rec: Record) -> np.ndarray:
    """(T, N) bool: the object moves in the push (centre > 4 mm or rotation > 2 degrees)."""
    translation, rotation = object_motion(rec)
    return (translation > MOVE_TRANSLATION) | (rotation > MOVE_ROTATION_DEG)


def cube_side(voxels: np.ndarray) -> np.ndarray:
    """Side (m) of the cube whose volume is `voxels` voxels of 4 mm."""
    return np.cbrt(np.asarray(voxels, dtype=np.float64)) * VOXEL_SIZE


def lattice() -> np.ndarray:
    """(LATTICE^3, 3) cell centres of a LATTICE^3 lattice over the unit cube centred on 0: offsets in (-0.5, 0.5)."""
    g = (np.arange(LATTICE) + 0.5) / LATTICE - 0.5
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)


def point_displacement(rec: Record) -> np.ndarray:
    """(T, N) mean |displacement| (voxels) of each object's equal-volume cube lattice (side from
    voxels_per_object[t]) under its rigid motion from t to t+1."""
    side = cube_side(rec.voxels_per_object[:-1])  # (T, N)
    body = lattice()[None, None] * side[..., None, None]  # (T, N, P, 3)
    r0, r1 = quat_to_matrix(rec.quaternions[:-1]), quat_to_matrix(rec.quaternions[1:])  # (T, N, 3, 3)
    rotated = np.einsum("tnij,tnpj->tnpi", r1 - r0, body)
    disp = rotated + (rec.positions[1:] - rec.positions[:-1])[:, :, None]
    return np.linalg.norm(disp, axis=-1).mean(-1) / VOXEL_SIZE


def at_edge(rec: Record) -> np.ndarray:
    """(T,) bool: after push t some object's xy centre is within half its equal-volume cube side
    (from voxels_per_object[0]) of the grid's xy bounds, or outside them."""
    xy = rec.positions[1:, :, :2]  # (T, N, 2)
    margin = np.minimum(xy - GRID_BOUNDS[:2, 0], GRID_BOUNDS[:2, 1] - xy).min(-1)  # (T, N), < 0 outside
    half = cube_side(rec.voxels_per_object[0]) / 2  # (N,)
    return np.any(margin <= half, axis=-1)


def _mean(values: np.ndarray) -> float:
    """Mean of the finite values; NaN if there are none."""
    values = np.asarray(values, dtype=np.float64).ravel()
    values = values[np.isfinite(values)]
    return float(values.mean()) if values.size else float("nan")


# --- per-sequence statistics ------------------------------------------------------------------------


def sequence_statistics(rec: Record) -> dict[str, float]:
    """Every statistic of STATISTICS for one sequence (NaN where the sequence has nothing to average)."""
    T = rec.num_pushes
    steps = np.arange(T)
    pushed = pushed_objects(rec)
    translation, rotation = object_motion(rec)
    moves = (translation > MOVE_TRANSLATION) | (rotation > MOVE_ROTATION_DEG)
    u = push_directions(rec.actions)
    before = rec.positions[:-1, :, :2]  # (T, N, 2)
    pushed_xy = before[steps, pushed]  # (T, 2)

    _, first = np.unique(pushed, return_index=True)  # pushes that are an object's first push
    to_centre = CENTRE - pushed_xy[first]
    norm = np.linalg.norm(to_centre, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_first = np.sum(u[first] * to_centre, -1) / norm

    displacement = point_displacement(rec)
    bands = np.asarray(rec.tsdf_bands, dtype=np.float64)
    return {
        "moving_per_push": _mean(moves.sum(1)),
        "multi_move_pct": 100 * _mean(moves.sum(1) >= 2),
        "first_push_cos": _mean(cos_first),
        "pushed_translation_cm": 100 * _mean(translation[steps, pushed]),
        "pushed_rotation_deg": _mean(rotation[steps, pushed]),
        "point_displacement_vox": _mean(displacement[moves]),
        "initial_distance_cm": 100 * _mean(np.linalg.norm(rec.positions[0, :, :2] - CENTRE, axis=-1)),
        "edge_pct": 100 * _mean(at_edge(rec)),
        "voxels_t0": _mean(rec.voxels_per_object[0]),
        "tsdf_negative_pct": 100 * _mean(bands[:, 0]),
        "tsdf_near_pct": 100 * _mean(bands[:, 1]),
        "tsdf_free_pct": 100 * _mean(bands[:, 2]),
        "direction_resultant": float(np.linalg.norm(u.mean(0))),
        "axis_direction_pct": 100 * _mean(rec.actions[:, 0] % 2 == 0),
        "same_object_pct": 100 * _mean(pushed[1:] == pushed[:-1]) if T >= 2 else float("nan"),
        "start_distance_cm": 100 * _mean(np.linalg.norm(push_starts(rec.actions) - pushed_xy, axis=-1)),
    }


def statistics_table(records: list[Record]) -> dict[str, np.ndarray]:
    """key -> (S,) per-sequence values of every statistic over `records`."""
    rows = [sequence_statistics(r) for r in records]
    return {key: np.array([row[key] for row in rows], dtype=np.float64) for key in STATISTICS}


def tsdf_bands(tsdf: np.ndarray) -> np.ndarray:
    """(..., 3) shares of voxels of TSDF volumes (..., Y, X, Z) in (-1, 0), [0, 1) and >= 1."""
    v = np.asarray(tsdf)
    axes = (-3, -2, -1)
    return np.stack([np.mean((v > -1) & (v < 0), axis=axes), np.mean((v >= 0) & (v < 1), axis=axes),
                     np.mean(v >= 1, axis=axes)], axis=-1)


def voxel_counts(mask_3d: np.ndarray, num_objects: int) -> np.ndarray:
    """(num_objects,) voxels of mask_3d == k for k = 1..num_objects."""
    ids = np.asarray(mask_3d).ravel()
    return np.bincount(ids[(ids > 0) & (ids <= num_objects)].astype(np.int64), minlength=num_objects + 1)[1:]


# --- resampling -------------------------------------------------------------------------------------


def bootstrap_interval(values: np.ndarray, n_boot: int, rng: np.random.Generator,
                       level: float = 0.95) -> tuple[float, float, float]:
    """(mean, low, high): the mean of the finite per-sequence values and the percentile interval of the
    means of `n_boot` resamples of whole sequences with replacement (NaN for no values)."""
    x = np.asarray(values, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return float("nan"), float("nan"), float("nan")
    means = x[rng.integers(0, x.size, size=(n_boot, x.size))].mean(1)
    tail = 100 * (1 - level) / 2
    low, high = np.percentile(means, [tail, 100 - tail])
    return float(x.mean()), float(low), float(high)


def permutation_pvalue(a: np.ndarray, b: np.ndarray, n_perm: int, rng: np.random.Generator) -> float:
    """Two-sided p-value of the difference of means of the finite values of a and b, by `n_perm` random
    reassignments of the pooled sequences to the two sides: (1 + #{|diff*| >= |diff|}) / (1 + n_perm)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    if a.size == 0 or b.size == 0:
        return float("nan")
    pooled = np.concatenate([a, b])
    observed = abs(a.mean() - b.mean())
    perms = rng.permuted(np.broadcast_to(pooled, (n_perm, pooled.size)), axis=1)
    diffs = np.abs(perms[:, :a.size].mean(1) - perms[:, a.size:].mean(1))
    tol = 1e-12 * max(1.0, float(np.abs(pooled).max()))  # equal means up to rounding count as as extreme
    return float((1 + np.count_nonzero(diffs >= observed - tol)) / (1 + n_perm))


def paired_difference(a: np.ndarray, b: np.ndarray, n_perm: int, rng: np.random.Generator) -> dict:
    """The mean of the per-sequence differences a - b over sequences where both are finite (the same sequences
    made two ways), its standard error, n, and the two-sided sign-flip permutation p-value ((1 + #{|mean*| >=
    |mean|}) / (1 + n_perm), each difference's sign flipped at random)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    d = (a - b)[np.isfinite(a) & np.isfinite(b)]
    if d.size == 0:
        return {"mean": float("nan"), "se": float("nan"), "n": 0, "p": float("nan")}
    observed = abs(d.mean())
    signs = rng.choice(np.array([-1.0, 1.0]), size=(n_perm, d.size))
    flipped = np.abs((signs * d).mean(1))
    tol = 1e-12 * max(1.0, float(np.abs(d).max()))
    p = float((1 + np.count_nonzero(flipped >= observed - tol)) / (1 + n_perm))
    se = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else float("nan")
    return {"mean": float(d.mean()), "se": se, "n": int(d.size), "p": p}
