"""The fit checks of a posed mesh, each a named result (`Check`): what it measured, the threshold it was held to,
whether it passed and why, in one line. `annotator.align.fit_score` runs them in order and builds its verdict
(`FitScore.checks`, `FitScore.accepted`, and the reason the window and the CLI show: `verdict_reason`).

- `fit_checks`: coverage and RMSE of the cloud fit (and whether there is a cloud and a visible surface at all);
- `physical_checks`: no interpenetration with the other objects, resting on the table or on another object, no
  surface in front of what a camera measured (free space);
- `unexplained_check`: the cloud around the object is explained by some posed mesh;
- `colour_check`: its colours match those of the same surface at another step (`sample_colours`, `colour_mismatch`);
- `annotator.moves`: a short ICP from the pose would not move it and fit the cloud clearly better
  (`refinement_checks`), and no slide along the table fits a thin object clearly better (`slide_check`).

CHECKS is the table of check names: each one's unit, how its value is compared with its threshold, and which field
of `annotator.thresholds.Thresholds` the threshold is. Points and transforms as in `annotator.fitting`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import NamedTuple

import numpy as np

from dsr_bench.annotator.fitting import SurfaceSamples, View, near_depth, pixels, posed_samples, visible_samples
from dsr_bench.annotator.thresholds import THRESHOLDS, Thresholds


class CheckKind(NamedTuple):
    """What a check name means: the unit of its value and threshold, when it passes (value `passes_when`
    threshold, where it applies), the Thresholds field its threshold comes from, and what it measures."""

    unit: str
    passes_when: str  # "<=", ">=", ">" or "<"
    threshold: str  # a field of Thresholds ("" where the threshold is measured, as for snap_quality)
    what: str


#: Every check of a verdict, by name.
CHECKS: dict[str, CheckKind] = {
    "cloud": CheckKind("points", ">=", "", "cloud points around the object (there are some)"),
    "visible": CheckKind("samples", ">=", "", "surface samples a camera could have measured (there are some)"),
    "coverage": CheckKind("fraction", ">=", "min_coverage", "visible samples with a cloud point within "
                                                            "inlier_distance"),
    "rmse": CheckKind("m", "<=", "max_rmse", "RMS point-to-plane distance of those samples (NaN: none)"),
    "interpenetration": CheckKind("m", "<=", "penetration_tolerance", "how deep it and another object (`about`) "
                                                                      "interpenetrate"),
    "sinks": CheckKind("m", "<=", "table_tolerance", "how far its lowest point lies below the table"),
    "floats": CheckKind("m", "<=", "table_tolerance", "how far its lowest point lies above the table (applies when "
                                                      "it rests on no other object)"),
    "free_space": CheckKind("fraction", "<=", "free_space_fraction", "of its camera-facing samples, those the "
                                                                     "cameras measured depth behind (applies with "
                                                                     "free_space_min_samples of them)"),
    "unexplained": CheckKind("fraction", "<=", "unexplained_fraction", "of the cloud within unexplained_reach of it, "
                                                                       "points no posed mesh explains (applies with "
                                                                       "unexplained_min_points of them)"),
    "colour": CheckKind("fraction", "<=", "colour_fraction", "of the samples seen at both steps, those of another "
                                                             "chromaticity (applies with colour_min_samples)"),
    "snap_move": CheckKind("m", "<=", "refine_gain", "how much closer a short ICP brings the surface to the cloud "
                                                     "(applies when it moves the pose beyond refine_translation or "
                                                     "refine_rotation)"),
    "snap_turn": CheckKind("m", "<=", "refine_turn_gain", "the same gain (applies when it turns the pose beyond "
                                                          "refine_turn)"),
    "slide": CheckKind("quality", "<=", "slide_gain", "how much better the best slide along the table fits the cloud "
                                                      "(FitScore.quality units; run for objects lower than "
                                                      "slide_max_height)"),
    "icp_cloud": CheckKind("points", ">=", "min_correspondences", "cloud points near the object for ICP"),
    "icp_correspondences": CheckKind("samples", ">=", "min_correspondences", "samples ICP matched to cloud points"),
    "icp_jump_translation": CheckKind("m", "<=", "max_jump_translation", "how far ICP moved the pose"),
    "icp_jump_rotation": CheckKind("rad", "<=", "max_jump_rotation", "how far ICP turned the pose"),
    "snap_quality": CheckKind("quality", ">", "", "the snapped pose's FitScore.quality against the start's"),
}
#: The physical checks: an accepted verdict says "physically possible" for them together.
PHYSICAL = ("interpenetration", "sinks", "floats", "free_space")


@dataclass(frozen=True)
class Check:
    """One check of a fit's verdict: which (`name`, a key of CHECKS), what it measured (`value`, in CHECKS' unit),
    the threshold it was held to, whether it passed, and why in one line (`reason`, pass or fail). `applies`: False
    where the check's condition does not hold (too few samples to tell, resting on another object, a move within
    the limits): it passes then, whatever its value. `about`: the other object of a pairwise check; `measured`:
    other values it measured, ((name, value), ...), in CHECKS' unit unless the name says."""

    name: str
    value: float
    threshold: float
    passed: bool
    reason: str
    applies: bool = True
    about: str = ""
    measured: tuple[tuple[str, float], ...] = ()

    def as_dict(self) -> dict:
        """JSON-able (NaN stays a float NaN)."""
        out = asdict(self)
        out["value"], out["threshold"] = float(self.value), float(self.threshold)
        out["measured"] = {k: float(v) for k, v in self.measured}
        return out


def holds(check: Check) -> bool:
    """Whether the check passes by its rule in CHECKS (not applying, or its value compared with its threshold):
    what `check.passed` says."""
    if not check.applies:
        return True
    value, threshold = check.value, check.threshold
    return bool({"<=": value <= threshold, ">=": value >= threshold, ">": value > threshold,
                 "<": value < threshold}[CHECKS[check.name].passes_when])


def _unique(reasons) -> list[str]:
    out: list[str] = []
    for reason in reasons:
        if reason not in out:
            out.append(reason)
    return out


def verdict_reason(checks: Sequence[Check]) -> str:
    """The one-line reason of a verdict, built from its checks: the failed checks' reasons, or, when every check
    passed, what they measured ("rmse 1.2 mm, coverage 86%; physically possible; 6% of ... unaccounted for; ...")."""
    failed = [c.reason for c in checks if not c.passed]
    if failed:
        return "; ".join(_unique(failed))
    by_name = {c.name: c for c in checks}
    parts = [", ".join(by_name[n].reason for n in ("rmse", "coverage") if n in by_name)]
    if any(c.name in PHYSICAL for c in checks):
        parts.append("physically possible")
    parts += _unique(c.reason for c in checks if c.name not in PHYSICAL + ("cloud", "visible", "rmse", "coverage"))
    return "; ".join(p for p in parts if p)


# --- the cloud fit ---------------------------------------------------------------------------------------------------


def fit_checks(crop_points: int, visible: int, coverage: float, rmse: float,
               limits: Thresholds = THRESHOLDS) -> list[Check]:
    """The checks of the cloud fit: a cloud around the object and a visible surface (the others only with both),
    coverage at least min_coverage, RMSE (m, NaN without inliers) at most max_rmse."""
    out = [Check("cloud", crop_points, 1, crop_points > 0, "no cloud points around the object" if crop_points == 0
                 else f"{crop_points} cloud points around the object")]
    if crop_points == 0:
        return out
    out.append(Check("visible", visible, 1, visible > 0, "no surface of the mesh is visible to a camera" if not visible
                     else f"{visible} surface samples visible to a camera"))
    if not visible:
        return out
    ok = coverage >= limits.min_coverage
    out.append(Check("coverage", coverage, limits.min_coverage, ok, f"coverage {coverage:.0%}" if ok else
                     f"coverage {coverage:.0%} < {limits.min_coverage:.0%}"))
    ok = bool(np.isfinite(rmse)) and not rmse > limits.max_rmse
    out.append(Check("rmse", rmse, limits.max_rmse, ok, f"rmse {rmse * 1000:.1f} mm" if ok else
                     f"rmse {rmse * 1000:.1f} mm > {limits.max_rmse * 1000:.1f} mm"))
    return out


# --- physical checks -------------------------------------------------------------------------------------------------


def _inside_depth(points: np.ndarray, surface: np.ndarray, normals: np.ndarray, tree) -> np.ndarray:
    """Per point (M, 3) its depth (m) below a posed surface (samples (S, 3) with outward normals (S, 3) and their
    cKDTree): minus the signed distance along the nearest sample's normal (<= 0 outside)."""
    _, j = tree.query(points)
    return -np.einsum("ij,ij->i", points - surface[j], normals[j])


def _kth_deepest(depth: np.ndarray, count: int) -> float:
    """The count-th largest positive depth (m), 0 when fewer are inside."""
    depth = np.sort(depth[depth > 0])
    return float(depth[-count]) if len(depth) >= count else 0.0


def penetration_depth(a: SurfaceSamples, ta: np.ndarray, b: SurfaceSamples, tb: np.ndarray,
                      limits: Thresholds = THRESHOLDS) -> float:
    """How deep (m) two posed meshes (samples, 4x4 transform each) interpenetrate: the penetration_count-th
    deepest surface sample of either inside the other (0 when apart)."""
    from scipy.spatial import cKDTree

    count = limits.penetration_count
    ca, cb = ta[:3, :3] @ a.centre + ta[:3, 3], tb[:3, :3] @ b.centre + tb[:3, 3]
    if np.linalg.norm(ca - cb) > a.radius + b.radius:
        return 0.0
    (pa, na), (pb, nb) = posed_samples(a, ta), posed_samples(b, tb)
    depth = 0.0
    for pts, centre, radius, surface, normals in ((pa, cb, b.radius, pb, nb), (pb, ca, a.radius, pa, na)):
        inside = np.sum((pts - centre) ** 2, axis=1) <= radius**2
        if inside.sum() >= count:
            depth = max(depth, _kth_deepest(_inside_depth(pts[inside], surface, normals, cKDTree(surface)), count))
    return depth


def free_space_fraction(points: np.ndarray, normals: np.ndarray, views: Sequence[View],
                        tolerance: float = THRESHOLDS.free_space_tolerance) -> tuple[float, int]:
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
        u, v, z, inside = pixels(cam, points[cand])
        d = (near_depth(view.depth) if view.near is None else view.near)[v[inside], u[inside]]
        measured = np.isfinite(d)
        tested += int(measured.sum())
        bad += int((d[measured] > z[inside][measured] + tolerance).sum())
    return (bad / tested if tested else 0.0), tested


def lowest_point(samples: SurfaceSamples, transform: np.ndarray) -> float:
    """Height (m) of the mesh's lowest point at `transform` (4, 4) (of its vertices, else of its samples)."""
    points = samples.points if samples.vertices is None else samples.vertices
    return float((points @ transform[:3, :3].T + transform[:3, 3])[:, 2].min())


def physical_checks(samples: SurfaceSamples, transform: np.ndarray,
                    neighbours: Sequence[tuple[str, SurfaceSamples, np.ndarray]], views: Sequence[View],
                    limits: Thresholds = THRESHOLDS) -> list[Check]:
    """Whether the mesh can physically be at `transform` (4, 4), one check each:

    - "interpenetration", per neighbour near it (neighbours: (name, samples, 4x4 transform) of the other objects at
      this step): they interpenetrate by at most penetration_tolerance (either object's samples inside the other);
    - "sinks" / "floats": its lowest point lies at most table_tolerance below the table (z = 0), and at most that
      above it unless it rests on another object (a sample within support_distance of it);
    - "free_space": the cameras measured depth behind at most free_space_fraction of its surface.
    """
    from scipy.spatial import cKDTree

    pts, nrm = posed_samples(samples, transform)
    centre = transform[:3, :3] @ samples.centre + transform[:3, 3]
    own_tree = None
    out = []
    supported = False
    tolerance, count = limits.penetration_tolerance, limits.penetration_count
    for name, other, other_t in neighbours:
        if not np.all(np.isfinite(other_t)):
            continue
        other_centre = other_t[:3, :3] @ other.centre + other_t[:3, 3]
        if np.linalg.norm(centre - other_centre) > samples.radius + other.radius + limits.support_distance:
            continue
        opts, onrm = posed_samples(other, other_t)
        # own samples near the other's surface: their distance to it (support) and their depth inside it
        near = np.sum((pts - other_centre) ** 2, axis=1) <= (other.radius + limits.support_distance) ** 2
        if not near.any():
            continue
        other_tree = cKDTree(opts)
        gap, j = other_tree.query(pts[near])
        supported |= bool((gap <= limits.support_distance).any())
        depth = _kth_deepest(-np.einsum("ij,ij->i", pts[near] - opts[j], onrm[j]), count)
        theirs = np.sum((opts - centre) ** 2, axis=1) <= samples.radius ** 2
        if theirs.sum() >= count:
            own_tree = cKDTree(pts) if own_tree is None else own_tree
            depth = max(depth, _kth_deepest(_inside_depth(opts[theirs], pts, nrm, own_tree), count))
        ok = not depth > tolerance
        out.append(Check("interpenetration", depth, tolerance, ok, f"interpenetrates {name} by {depth * 1000:.0f} mm"
                         + ("" if not ok else f" (within {tolerance * 1000:.0f} mm)"), about=name))
    lowest = lowest_point(samples, transform)
    table = limits.table_tolerance
    ok = not lowest < -table
    out.append(Check("sinks", -lowest, table, ok, f"sinks {-lowest * 1000:.0f} mm into the table" if not ok else
                     f"its lowest point {lowest * 1000:.1f} mm from the table"))
    ok = not (lowest > table and not supported)
    out.append(Check("floats", lowest, table, ok, f"floats {lowest * 1000:.0f} mm above the table" if not ok else
                     ("rests on another object" if supported else f"its lowest point {lowest * 1000:.1f} mm from "
                                                                  "the table"), applies=not supported))
    fraction, tested = free_space_fraction(pts, nrm, views, limits.free_space_tolerance)
    applies = tested >= limits.free_space_min_samples
    ok = not (applies and fraction > limits.free_space_fraction)
    out.append(Check("free_space", fraction, limits.free_space_fraction, ok,
                     f"the cameras see through {fraction:.0%} of its surface" if not ok else
                     f"the cameras see through {fraction:.0%} of {tested} samples", applies=applies,
                     measured=(("tested", float(tested)),)))
    return out


# --- the cloud around it ---------------------------------------------------------------------------------------------


def unexplained_fraction(samples: SurfaceSamples, transform: np.ndarray, crop: np.ndarray,
                         neighbours: Sequence[tuple[str, SurfaceSamples, np.ndarray]],
                         limits: Thresholds = THRESHOLDS) -> tuple[float, int]:
    """(fraction, count) of the cloud crop's points (M, 3) within unexplained_reach m of the posed mesh's surface
    samples and unexplained_min_height m above the table (lower for a thin object: unexplained_thin_fraction of
    its highest point, at least unexplained_thin_floor) that lie farther than inlier_distance from its samples
    and from every neighbour's (name, samples, 4x4 transform); count: the points tested. Only the band around
    the object's own surface counts, so that a wrong neighbour a little farther away does not flag it."""
    from scipy.spatial import cKDTree

    pts = posed_samples(samples, transform)[0]
    top = float((pts if samples.vertices is None else samples.vertices @ transform[:3, :3].T + transform[:3, 3])[:, 2]
                .max())
    floor = min(limits.unexplained_min_height, max(limits.unexplained_thin_floor,
                                                   limits.unexplained_thin_fraction * top))
    high = crop[crop[:, 2] > floor]
    if len(high) == 0:
        return 0.0, 0
    own, _ = cKDTree(pts).query(high, distance_upper_bound=limits.unexplained_reach)
    near = high[np.isfinite(own)]
    unexplained = own[np.isfinite(own)] > limits.inlier_distance
    if not unexplained.any():
        return 0.0, len(near)
    centre = transform[:3, :3] @ samples.centre + transform[:3, 3]
    loose = near[unexplained]
    for _, other, other_t in neighbours:
        other_centre = other_t[:3, :3] @ other.centre + other_t[:3, 3]
        reach = samples.radius + limits.unexplained_reach + other.radius
        if not np.all(np.isfinite(other_t)) or np.linalg.norm(other_centre - centre) > reach:
            continue
        d, _ = cKDTree(posed_samples(other, other_t)[0]).query(loose, distance_upper_bound=limits.inlier_distance)
        loose = loose[~np.isfinite(d)]
        if len(loose) == 0:
            break
    return len(loose) / len(near), len(near)


def unexplained_check(samples: SurfaceSamples, transform: np.ndarray, crop: np.ndarray,
                      neighbours: Sequence[tuple[str, SurfaceSamples, np.ndarray]],
                      limits: Thresholds = THRESHOLDS) -> Check:
    """"unexplained": at most unexplained_fraction of the cloud around the mesh is explained by no posed mesh
    (`unexplained_fraction`; applies with at least unexplained_min_points points)."""
    fraction, count = unexplained_fraction(samples, transform, crop, neighbours, limits)
    applies = count >= limits.unexplained_min_points
    ok = not (applies and fraction > limits.unexplained_fraction)
    return Check("unexplained", fraction, limits.unexplained_fraction, ok,
                 f"{fraction:.0%} of {count} cloud points around it unaccounted for" if ok else
                 f"{fraction:.0%} of the cloud around it is explained by no object", applies=applies,
                 measured=(("points", float(count)),))


# --- colours ---------------------------------------------------------------------------------------------------------


def sample_colours(points: np.ndarray, normals: np.ndarray, views: Sequence[View],
                   tolerance: float = THRESHOLDS.inlier_distance, limits: Thresholds = THRESHOLDS) -> np.ndarray:
    """The colour (S, 3) 0..1 the cameras saw at each posed sample (points, normals (S, 3) world): the mean over the
    views that see it (`visible_samples`, one view at a time) with their measured depth within `tolerance` m of it
    (so the pixel shows this surface, not another in front or behind); NaN rows where no view with a colour image
    (`View.color`) does."""
    total = np.zeros((len(points), 3))
    count = np.zeros(len(points))
    for view in views:
        if view.color is None:
            continue
        seen = visible_samples(points, normals, [view], limits)
        if not seen.any():
            continue
        idx = np.flatnonzero(seen)
        u, v, z, inside = pixels(view.camera, points[idx])
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


def colour_mismatch(observed: np.ndarray, reference: np.ndarray, limits: Thresholds = THRESHOLDS
                    ) -> tuple[float, int]:
    """(fraction, count) of the samples seen in both colour sets (S, 3) 0..1 (`sample_colours`: NaN rows unseen)
    and brighter than colour_min_brightness (mean of r, g, b) in both, whose chromaticity (r, g, b over their sum)
    differs by more than colour_distance (L1); count: those compared."""
    both = np.all(np.isfinite(observed), 1) & np.all(np.isfinite(reference), 1)
    both &= (np.nan_to_num(observed).mean(1) > limits.colour_min_brightness) \
        & (np.nan_to_num(reference).mean(1) > limits.colour_min_brightness)
    if not both.any():
        return 0.0, 0
    a, b = observed[both], reference[both]
    diff = np.abs(a / a.sum(1, keepdims=True) - b / b.sum(1, keepdims=True)).sum(1)
    return float((diff > limits.colour_distance).mean()), int(both.sum())


def colour_check(points: np.ndarray, normals: np.ndarray, views: Sequence[View], reference: np.ndarray,
                 limits: Thresholds = THRESHOLDS) -> Check:
    """"colour": at most colour_fraction of the posed samples (points, normals (S, 3)) seen both here and at the
    reference step (`reference`: `sample_colours` there) changed chromaticity (applies with colour_min_samples)."""
    changed, compared = colour_mismatch(sample_colours(points, normals, views, limits=limits), reference, limits)
    applies = compared >= limits.colour_min_samples
    ok = not (applies and changed > limits.colour_fraction)
    return Check("colour", changed, limits.colour_fraction, ok,
                 f"colours {changed:.0%} changed of {compared} samples seen at the reference step" if ok else
                 f"{changed:.0%} of its surface has another colour than at the reference step (another object?)",
                 applies=applies, measured=(("compared", float(compared)),))
