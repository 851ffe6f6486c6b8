"""Rigid alignment of object meshes to a fused RGB-D point cloud, and the verdict on a pose (numpy + scipy only).

- `fit_score`: the verdict on a posed mesh (`FitScore`): inlier RMSE, coverage of the visible samples, fitness of
  the crop, and the checks that decide whether it is accepted, each a named result (`annotator.checks.Check`: its
  value, its threshold, pass or fail and a one-line reason), run in order: the cloud fit (coverage, RMSE), the
  physical checks (no interpenetration, resting on the table or another object, no free space seen through it),
  the cloud around it explained, its colours against another step, a short ICP that would not improve it, and
  for a thin object no slide along the table that fits clearly better (`annotator.moves`).
- `icp`: point-to-plane ICP of the visible samples against a cloud crop (cKDTree correspondences, shrinking
  correspondence distance, Tukey weights, damped Gauss-Newton), with jump rejection against the start pose.

The thresholds are one frozen dataclass, `annotator.thresholds.Thresholds` (`THRESHOLDS`: today's), passed as
`limits`; the geometry (transforms, surface samples, the views and what they see) is `annotator.fitting`, the
checks `annotator.checks`; both are re-exported here (`align.kabsch`, `align.View`, `align.refinement`, ...), the
names the session, the window and the tests use. Transforms are 4x4 object-to-world matrices; points (..., 3) are
(x, y, z) metres in the world/table frame unless stated; angles are radians.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields

import numpy as np

from dsr_bench.annotator.checks import (CHECKS, Check, colour_check, colour_mismatch,  # noqa: F401 - re-exported
                                        fit_checks, free_space_fraction, holds, lowest_point, penetration_depth,
                                        physical_checks, sample_colours, unexplained_check, unexplained_fraction,
                                        verdict_reason)
from dsr_bench.annotator.fitting import (SurfaceSamples, View, crop_cloud, icp_step, icp_subset,  # noqa: F401
                                         kabsch, near_depth, pose_delta, posed_samples, render_depth,
                                         rotvec_to_matrix, sample_surface, screen_quality, visible_samples)
from dsr_bench.annotator.moves import Refinement, refinement, refinement_checks, slide_check, slide_gain  # noqa: F401
from dsr_bench.annotator.thresholds import THRESHOLDS, Thresholds
from dsr_bench.geometry import matrix_to_pose  # noqa: F401 - matrix_to_pose: used as align.matrix_to_pose


@dataclass
class FitScore:
    """How well a posed mesh matches the cloud, and the verdict.

    rmse: m, RMS point-to-plane distance (along the mesh normal) of the inlier correspondences (visible samples
    with a cloud point within the inlier distance); coverage: 0..1, fraction of the visible samples with such a
    point; fitness: 0..1, fraction of the cropped cloud points (around the object, table removed) within the
    inlier distance of the mesh; accepted: the fit (or the ICP result) passed its checks; reason: why not, or what
    the checks that ran measured (never empty: every verdict says why; `checks.verdict_reason` of the checks, or the
    refusal of ICP or of a snap, `refused`); visible: visible samples; checks: the checks that ran, in order
    (`annotator.checks.Check`; kept in memory only: a stored score, `as_dict`, holds the reason).
    """

    rmse: float
    coverage: float
    fitness: float
    accepted: bool
    reason: str
    visible: int = 0  # number of visible samples
    checks: tuple[Check, ...] = field(default=(), compare=False, repr=False)

    def __post_init__(self) -> None:
        if not str(self.reason).strip():  # every verdict says why: an empty reason is never stored or shown
            self.reason = "accepted (no check ran)" if self.accepted else "not accepted (no reason given)"

    def as_dict(self) -> dict:
        """The stored score (state, journal, the export's provenance): every field but the checks."""
        out = {}
        for f in fields(self):
            if f.name != "checks":
                v = getattr(self, f.name)
                out[f.name] = float(v) if isinstance(v, (float, np.floating)) else v
        return out

    @classmethod
    def from_dict(cls, d: dict) -> FitScore:
        return cls(float(d["rmse"]), float(d["coverage"]), float(d["fitness"]), bool(d["accepted"]), str(d["reason"]),
                   int(d.get("visible", 0)))

    def quality(self) -> float:
        """One number to rank fits by (higher is better): coverage minus RMSE in units of 2 cm."""
        rmse = float(self.rmse) if np.isfinite(self.rmse) else THRESHOLDS.inlier_distance
        return float(self.coverage) - rmse / 0.02

    def check(self, name: str) -> list[Check]:
        """The checks of that name that ran (CHECKS; several for a pairwise check), in order."""
        return [c for c in self.checks if c.name == name]

    def failed(self) -> list[Check]:
        """The checks that failed, in order."""
        return [c for c in self.checks if not c.passed]

    def refused(self, *checks: Check) -> FitScore:
        """This score refused by ICP or a snap (`checks`: theirs, at least one failed): not accepted, the refusal as
        the reason, the checks appended to this score's."""
        reason = "; ".join(dict.fromkeys(c.reason for c in checks if not c.passed))
        return FitScore(self.rmse, self.coverage, self.fitness, False, reason, self.visible, self.checks + checks)


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


def fit_score(samples: SurfaceSamples, transform: np.ndarray, crop: np.ndarray, views: Sequence[View],
              inlier_distance: float | None = None, tree=None, with_fitness: bool = True,
              neighbours: Sequence[tuple[str, SurfaceSamples, np.ndarray]] | None = None,
              explain: bool = False, refine: bool = False, reference_colours: np.ndarray | None = None,
              shared_shift: Callable[[], np.ndarray | None] | None = None,
              limits: Thresholds = THRESHOLDS) -> FitScore:
    """Score of the mesh at `transform` (4, 4) against a cloud crop (M, 3) (see FitScore), with its checks
    (`annotator.checks`), accepted when every one passes: coverage and RMSE (`fit_checks`; within `inlier_distance`,
    default the limits'); with `neighbours` (the other objects: name, samples, 4x4 transform) the physical checks
    (`physical_checks`) and, with `explain` (they are all the other objects of the scene), the cloud around it
    explained (`unexplained_check`). When all of these pass, more: with `reference_colours` (S, 3)
    (`sample_colours` of the same samples at another step, NaN unseen) the colours (`colour_check`), and with
    `refine` a short ICP from the pose may not improve it (`annotator.moves.refinement`, `refinement_checks`;
    `shared_shift`, called only then: the shift the scene's other objects share, or None) and, for an object lower
    than slide_max_height, no slide along the table may fit clearly better (`slide_check`); each runs only when
    every check before it passed. `tree`: a cKDTree of `crop` to reuse; `with_fitness=False` skips the fitness
    (reported as NaN), for fast screening; `limits`: the thresholds."""
    from scipy.spatial import cKDTree

    inlier_distance = limits.inlier_distance if inlier_distance is None else inlier_distance
    pts, nrm = posed_samples(samples, transform)
    vis = visible_samples(pts, nrm, views, limits)
    nvis = int(vis.sum())
    if len(crop) == 0 or nvis == 0:
        early = fit_checks(len(crop), nvis, 0.0, float("nan"), limits)
        return FitScore(float("nan"), 0.0, 0.0, False, verdict_reason(early), nvis, tuple(early))
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
    checks = fit_checks(len(crop), nvis, coverage, rmse, limits)
    if neighbours is not None:
        checks += physical_checks(samples, transform, neighbours, views, limits)
        if explain:
            checks.append(unexplained_check(samples, transform, crop, neighbours, limits))
    if all(c.passed for c in checks) and reference_colours is not None:
        checks.append(colour_check(pts, nrm, views, reference_colours, limits))
    if all(c.passed for c in checks) and refine:
        shared = None if shared_shift is None else shared_shift()
        checks += refinement_checks(refinement(samples, transform, crop, views, tree, shared=shared, limits=limits),
                                    limits)
        if all(c.passed for c in checks):
            slide = slide_check(samples, transform, tree, views, limits)
            checks += [] if slide is None else [slide]
    accepted = all(c.passed for c in checks)
    return FitScore(rmse, coverage, fitness, accepted, verdict_reason(checks), nvis, tuple(checks))


def icp(samples: SurfaceSamples, crop: np.ndarray, start: np.ndarray, views: Sequence[View], *,
        max_correspondence: float | None = None, inlier_distance: float | None = None,
        iterations: int = 40, max_translation: float | None = None,
        max_rotation: float | None = None, tree=None,
        neighbours: Sequence[tuple[str, SurfaceSamples, np.ndarray]] | None = None, explain: bool = False,
        reference_colours: np.ndarray | None = None, limits: Thresholds = THRESHOLDS) -> IcpResult:
    """Point-to-plane ICP of the mesh's visible samples against a cloud crop (M, 3), from `start` (4, 4).

    Each iteration matches the visible posed samples to their nearest cloud points within a correspondence
    distance that shrinks from `max_correspondence` to 2 x `inlier_distance`, weights residuals along the sample
    normals with Tukey's biweight, and takes one damped Gauss-Newton step (rotation about the matched samples'
    centroid). The result is rejected (transform = start, its score `refused` by the failed check: "icp_cloud",
    "icp_correspondences", "icp_jump_translation" / "icp_jump_rotation") when it moved more than `max_translation`
    m or `max_rotation` rad from the start, or found too few correspondences. Unset limits are `limits`'.
    `neighbours`, `explain`, `reference_colours`: the other objects (name, samples, 4x4 transform), for the
    score's physical checks, whether they are all of them, and the colours to compare with (`fit_score`; the
    result is not checked with `refine`: ICP has converged there).
    """
    from scipy.spatial import cKDTree

    max_correspondence = limits.max_correspondence if max_correspondence is None else max_correspondence
    inlier_distance = limits.inlier_distance if inlier_distance is None else inlier_distance
    max_translation = limits.max_jump_translation if max_translation is None else max_translation
    max_rotation = limits.max_jump_rotation if max_rotation is None else max_rotation
    start = np.asarray(start, dtype=np.float64)
    checks: dict = {"neighbours": neighbours, "explain": explain, "reference_colours": reference_colours,
                    "limits": limits}
    least = limits.min_correspondences
    if len(crop) < least:
        score = fit_score(samples, start, crop, views, inlier_distance, **checks)
        refusal = Check("icp_cloud", len(crop), least, False,
                        f"only {len(crop)} cloud points near the object: move it onto its points")
        return IcpResult(start, score.refused(refusal), 0, 0.0, 0.0, False)
    tree = cKDTree(crop) if tree is None else tree
    fit_samples = icp_subset(samples, limits.icp_samples)
    current = start.copy()
    dist = max_correspondence
    floor = 2 * inlier_distance
    it = 0
    for it in range(1, iterations + 1):
        step, small, matched = icp_step(fit_samples, current, crop, tree, views, dist, limits)
        if step is None:
            score = fit_score(samples, start, crop, views, inlier_distance, tree, **checks)
            refusal = Check("icp_correspondences", matched, least, False,
                            f"only {matched} mesh points have cloud points within {dist * 100:.1f} cm: "
                            "nudge the object onto its points and snap again", measured=(("distance_m", dist),))
            return IcpResult(start, score.refused(refusal), it, 0.0, 0.0, False)
        current = step @ current
        if small and dist <= floor:
            break
        dist = max(floor, dist * 0.75)
    moved_t, moved_r = pose_delta(start, current)
    if moved_t > max_translation or moved_r > max_rotation:
        score = fit_score(samples, start, crop, views, inlier_distance, tree, **checks)
        why = (f"rejected jump: ICP moved the object {moved_t * 100:.1f} cm and {np.rad2deg(moved_r):.0f} deg "
               f"(limits {max_translation * 100:.0f} cm, {np.rad2deg(max_rotation):.0f} deg); nudge it closer "
               "and snap again")
        jumps = (Check("icp_jump_translation", moved_t, max_translation, not moved_t > max_translation, why),
                 Check("icp_jump_rotation", moved_r, max_rotation, not moved_r > max_rotation, why))
        return IcpResult(start, score.refused(*jumps), it, moved_t, moved_r, False)
    score = fit_score(samples, current, crop, views, inlier_distance, tree, **checks)
    return IcpResult(current, score, it, moved_t, moved_r)
