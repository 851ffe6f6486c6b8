"""The checks that move a pose and look whether it fits the cloud clearly better there (a wrong pose that the cloud
fit, the physical checks and the colours all accept): `refinement` / `refinement_checks` (a short ICP from the pose:
"snap_move", "snap_turn") and `slide_gain` / `slide_check` (a thin object slid along the table: "slide"). Each
returns named results (`annotator.checks.Check`); `annotator.align.fit_score` runs them last, when every other check
passed. Thresholds: `annotator.thresholds` (refine_*, slide_*).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dsr_bench.annotator.checks import Check, lowest_point
from dsr_bench.annotator.fitting import (SurfaceSamples, View, icp_step, icp_subset, pose_delta, posed_samples,
                                         screen_quality, visible_samples)
from dsr_bench.annotator.thresholds import THRESHOLDS, Thresholds


@dataclass
class Refinement:
    """What a short ICP from a pose did (`refinement`): how far it moved the pose (m, the origin, less the shift
    the whole scene shares when one is given, along the table only for an object resting on it; rad), how much
    closer (m) it brought the visible samples to the cloud (mean distance to the nearest cloud point, capped at
    refine_cap, before minus after; negative when it fits worse), the origin's shift (3,) m itself, and whether the
    object rests on the table (`resting`: its lowest point within refine_resting_height of it) with the vertical
    part of its move (m, less the shared shift's) that was left out for it."""

    translation: float
    rotation: float
    gain: float
    shift: np.ndarray
    resting: bool = False
    vertical: float = 0.0

    def improves(self, limits: Thresholds = THRESHOLDS) -> bool:
        """Whether a snap would improve the pose: it moves more than refine_translation or refine_rotation and
        gains more than refine_gain, or turns more than refine_turn and gains more than refine_turn_gain (the
        checks of `refinement_checks` fail)."""
        return not all(c.passed for c in refinement_checks(self, limits))


def refinement_checks(moved: Refinement, limits: Thresholds = THRESHOLDS) -> list[Check]:
    """"snap_move": a move beyond refine_translation or refine_rotation gains at most refine_gain; "snap_turn": a
    turn beyond refine_turn gains at most refine_turn_gain (`Refinement`: the move of a short ICP; for an object
    resting on the table the move along it)."""
    t, r, gain = moved.translation, moved.rotation, moved.gain
    measured = (("translation", t), ("rotation", r), ("vertical", moved.vertical), ("resting", float(moved.resting)))
    moves = t > limits.refine_translation or r > limits.refine_rotation
    turns = r > limits.refine_turn
    fails = [moves and gain > limits.refine_gain, turns and gain > limits.refine_turn_gain]
    along = " along the table" if moved.resting else ""
    if any(fails):
        reason = (f"a snap would move it {t * 1000:.0f} mm{along}, {np.rad2deg(r):.0f} deg and fit {gain * 1000:.1f} "
                  "mm closer")
    else:
        reason = (f"a snap would move it {t * 1000:.1f} mm{along}, {np.rad2deg(r):.1f} deg and fit "
                  f"{gain * 1000:.2f} mm closer (within limits)")
    return [Check("snap_move", gain, limits.refine_gain, not fails[0], reason, applies=moves, measured=measured),
            Check("snap_turn", gain, limits.refine_turn_gain, not fails[1], reason, applies=turns, measured=measured)]


def _capped_distance(samples: SurfaceSamples, transform: np.ndarray, tree, views: Sequence[View],
                     limits: Thresholds = THRESHOLDS) -> float:
    """Mean distance (m) of the visible posed samples to their nearest cloud point (cKDTree), capped at refine_cap
    (refine_cap when none is visible)."""
    pts, nrm = posed_samples(samples, transform)
    vis = visible_samples(pts, nrm, views, limits)
    if not vis.any():
        return limits.refine_cap
    d, _ = tree.query(pts[vis], distance_upper_bound=limits.refine_cap)
    return float(np.minimum(d, limits.refine_cap).mean())


def refinement(samples: SurfaceSamples, transform: np.ndarray, crop: np.ndarray, views: Sequence[View],
               tree=None, iterations: int | None = None, shared: np.ndarray | None = None,
               limits: Thresholds = THRESHOLDS) -> Refinement:
    """Run `iterations` (default refine_iterations) ICP steps (as `align.icp`: the correspondence distance shrinking
    from max_correspondence to 2 x inlier_distance, no jump limits) of refine_samples of the samples from
    `transform` (4, 4) against the cloud crop (M, 3) and report how far the pose moved and how much closer the
    surface came to the cloud (`Refinement`); a wrong pose that the other checks cannot tell (a 10 degree turn; a
    mug turned 180 degrees, its handle where it is not) moves towards the cloud and fits it better, a true pose
    moves by the noise and gains nothing. `shared`: the shift (3,) m that the refinement gives the other objects of
    the scene (the cameras' calibration error against the table frame moves them all alike); the translation is
    measured from it. For an object resting on the table (its lowest point within refine_resting_height of z = 0)
    only the move along the table counts: the table fixes its height (the floats / sinks checks refuse a wrong one),
    and the measured surface of a thin or concave object (a phone lying flat, a sofa's seat) lies a few millimetres
    off its true height under the sensor's noise."""
    from scipy.spatial import cKDTree

    tree = cKDTree(crop) if tree is None else tree
    subset = icp_subset(samples, limits.refine_samples)
    current = np.asarray(transform, dtype=np.float64)
    dist, floor = limits.max_correspondence, 2 * limits.inlier_distance
    for _ in range(limits.refine_iterations if iterations is None else iterations):
        step, small, _ = icp_step(subset, current, crop, tree, views, dist, limits)
        if step is None:
            break
        current = step @ current
        if small and dist <= floor:
            break
        dist = max(floor, dist * 0.75)
    shift = current[:3, 3] - np.asarray(transform, dtype=np.float64)[:3, 3]
    moved_r = pose_delta(transform, current)[1]
    delta = shift if shared is None else shift - shared
    resting = abs(lowest_point(samples, np.asarray(transform, dtype=np.float64))) <= limits.refine_resting_height
    moved_t = float(np.linalg.norm(delta[:2] if resting else delta))
    gain = (_capped_distance(subset, transform, tree, views, limits)
            - _capped_distance(subset, current, tree, views, limits))
    return Refinement(moved_t, moved_r, gain, shift, resting, float(delta[2]))


def height(samples: SurfaceSamples, transform: np.ndarray) -> float:
    """The vertical extent (m) of the mesh at `transform` (4, 4) (of its vertices, else of its samples)."""
    points = samples.points if samples.vertices is None else samples.vertices
    return float(np.ptp((points @ np.asarray(transform)[:3, :3].T)[:, 2]))


def slide_gain(samples: SurfaceSamples, transform: np.ndarray, tree, views: Sequence[View],
               limits: Thresholds = THRESHOLDS) -> tuple[float, float, float, float]:
    """(gain, distance m, quality at the pose, quality slid) of the best slide of the mesh at `transform` (4, 4)
    along the table (slide_distances in slide_directions directions): `screen_quality` (coverage within
    inlier_distance less the RMS distance in units of 2 cm) of refine_samples of its samples against the cloud's
    cKDTree `tree`, slid minus at the pose."""
    subset = icp_subset(samples, limits.refine_samples)
    angles = np.arange(limits.slide_directions) * (2 * np.pi / limits.slide_directions)
    moves = [(d, d * np.array([np.cos(a), np.sin(a), 0.0])) for d in limits.slide_distances for a in angles]
    starts = np.repeat(np.asarray(transform, np.float64)[None], len(moves) + 1, axis=0)
    for i, (_, move) in enumerate(moves):
        starts[i + 1, :3, 3] += move
    quality = screen_quality(subset, starts, tree, views, limits.inlier_distance, limits=limits)
    best = int(np.argmax(quality[1:]))
    return float(quality[1 + best] - quality[0]), moves[best][0], float(quality[0]), float(quality[1 + best])


def slide_check(samples: SurfaceSamples, transform: np.ndarray, tree, views: Sequence[View],
                limits: Thresholds = THRESHOLDS) -> Check | None:
    """"slide", for an object lower than slide_max_height (a phone lying flat: ICP slides it along the table
    without fitting much closer, and its few millimetres of side leave little cloud unexplained): no slide along
    the table fits the cloud better than the pose by more than slide_gain (`slide_gain`); None for a taller object
    (not run)."""
    tall = height(samples, transform)
    if tall >= limits.slide_max_height:
        return None
    gain, distance, before, after = slide_gain(samples, transform, tree, views, limits)
    ok = not gain > limits.slide_gain
    reason = (f"no slide along the table fits better (best {gain:+.3f} at {distance * 1000:.0f} mm)" if ok else
              f"sliding it {distance * 1000:.0f} mm along the table fits the cloud better (quality {before:.2f} -> "
              f"{after:.2f})")
    return Check("slide", gain, limits.slide_gain, ok, reason, measured=(
        ("distance_m", distance), ("quality", before), ("slid_quality", after), ("height_m", tall)))
