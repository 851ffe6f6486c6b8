"""Fit scores of a session's poses: the crop of the cloud around an object, the views with the other objects as
occluders, the keywords of the checks (`annotator.align.fit_score`, `annotator.checks`: the neighbours, whether they
are all the other objects, the colours of a checked step, the thresholds), the shift the other objects share under
the refinement, the scores themselves and ICP from a start pose.

`Scoring` is the Session's second layer (after `annotator.session_core.SessionCore`); every verdict the window, the
CLI and the benchmark show comes from `_fit` (a pose) or `_icp` (a snap).
"""

from __future__ import annotations

import numpy as np

from dsr_bench.annotator import align
from dsr_bench.annotator.align import FitScore
from dsr_bench.annotator.checks import penetration_depth
from dsr_bench.annotator.session_core import SessionCore
from dsr_bench.geometry import pose_to_matrix

#: Crop radius around an object: its bounding sphere plus this margin (m).
CROP_MARGIN = 0.03
#: Occluder depth renders kept in memory (one per step and set of the other objects' poses).
OCCLUDER_CACHE = 64


def _nan_score(d: dict | None) -> FitScore | None:
    """The FitScore of a stored score dict; None when there is none or it is not a whole score (then refitted)."""
    if d is None:
        return None
    try:
        return FitScore.from_dict({k: (float("nan") if v is None else v) for k, v in d.items()})
    except (KeyError, TypeError, ValueError):
        return None


class Scoring(SessionCore):
    """The fit scores of a session's poses (see the module docstring)."""

    def _crop(self, step: int, transform: np.ndarray, samples: align.SurfaceSamples, extra: float = 0.0) -> np.ndarray:
        """The step's cloud points (M, 3) within the object's bounding sphere at `transform` (4, 4) plus CROP_MARGIN
        and `extra` m, above the table."""
        points = self.cloud(step)[0]
        centre = transform[:3, :3] @ samples.centre + transform[:3, 3]
        return align.crop_cloud(points, centre, samples.radius + CROP_MARGIN + extra, self.limits.table_margin)

    def _others(self, obj: int, step: int) -> list[tuple[int, np.ndarray]]:
        """(object, pose (7,)) of the other objects posed at a step in the state."""
        return [(k, p) for k in range(self.num_objects) if k != obj and (p := self.state.pose(step, k)) is not None]

    def _context(self, obj: int, step: int, others: list[tuple[int, np.ndarray]] | None = None,
                 colours: bool = True) -> tuple[list[align.View], dict]:
        """(views, keywords) to score object `obj` at a step with: the step's views with the other objects' posed
        meshes as occluders (`align.View.occluders`), and the keywords of `align.fit_score` / `align.icp` for the
        physical checks: `neighbours`, those objects as (name, samples, 4x4 transform), `explain`, whether
        they are all the other objects (then the cloud around the object must be explained),
        `reference_colours`, the object's colours at another checked step (`_reference_colours`; None without
        `colours`), and `limits`, the session's thresholds. others: (object, pose (7,)) of the other objects
        (default: the state's)."""
        others = self._others(obj, step) if others is None else [(k, p) for k, p in others if k != obj]
        others = [(k, np.asarray(p, dtype=np.float64)) for k, p in others if np.all(np.isfinite(p))]
        views = self._views(step)
        key = (step, tuple((k, p.tobytes()) for k, p in sorted(others, key=lambda e: e[0])))
        if key not in self._occluders:
            meshes = []
            for k, p in others:
                v, f = self.capture.mesh(k)
                m = pose_to_matrix(p)
                meshes.append((np.asarray(v, np.float64) @ m[:3, :3].T + m[:3, 3], f))
            self._occluders[key] = [align.render_depth(view.camera, meshes) if meshes else None for view in views]
            while len(self._occluders) > OCCLUDER_CACHE:
                self._occluders.popitem(last=False)
        self._occluders.move_to_end(key)
        views = [view.with_occluders(occ) for view, occ in zip(views, self._occluders[key])]
        neighbours = [(f"object {k + 1} ({self.capture.objects[k].name})", self.samples(k), pose_to_matrix(p))
                      for k, p in others]
        return views, {"neighbours": neighbours, "explain": len({k for k, _ in others}) == self.num_objects - 1,
                       "reference_colours": self._reference_colours(obj, step) if colours else None,
                       "limits": self.limits}

    def _reference_colours(self, obj: int, step: int) -> np.ndarray | None:
        """The colours (S, 3) 0..1 the cameras saw at object `obj`'s surface samples (`align.sample_colours`, NaN
        unseen) at the nearest other step (the earlier of two) where its pose is confirmed, or snapped with an
        accepted score, or None when there is none; cached per step and pose."""
        checked = [s for s in range(self.num_steps + 1) if s != step and (
            self.state.status[s, obj] == "confirmed" or (self.state.status[s, obj] == "snapped"
                                                         and (self.state.scores[s][obj] or {}).get("accepted")))]
        if not checked:
            return None
        ref = min(checked, key=lambda s: (abs(s - step), s))
        pose = self.state.pose(ref, obj)
        assert pose is not None  # a checked status has a pose
        key = (obj, ref, pose.tobytes())
        if key not in self._colours:
            views, _ = self._context(obj, ref, colours=False)
            self._colours[key] = align.sample_colours(*align.posed_samples(self.samples(obj), pose_to_matrix(pose)),
                                                      views, limits=self.limits)
            while len(self._colours) > OCCLUDER_CACHE:
                self._colours.popitem(last=False)
        return self._colours[key]

    def _fit(self, obj: int, step: int, pose: np.ndarray, others: list[tuple[int, np.ndarray]] | None = None
             ) -> FitScore:
        """Fit score of object `obj` at `pose` (7,) at a step, occlusion-aware and with the physical checks against
        the other objects (`others`: (object, pose); default: the state's poses at the step), the colours of a
        checked step (`_reference_colours`) and the refinement (a snap may not improve it beyond the shift the
        other objects share: `align.refinement`, `_shared_shift`)."""
        transform = pose_to_matrix(pose)
        samples = self.samples(obj)
        views, checks = self._context(obj, step, others)
        posed = self._others(obj, step) if others is None else others
        return align.fit_score(samples, transform, self._crop(step, transform, samples), views, refine=True,
                               shared_shift=lambda: self._shared_shift(obj, step, posed), **checks)

    def _shared_shift(self, obj: int, step: int, others: list[tuple[int, np.ndarray]]) -> np.ndarray | None:
        """The shift (3,) m that the refinement (`align.refinement`, the step's views without occluders) gives the
        objects other than `obj` at their poses (`others`: (object, pose)), the median per axis; None with fewer
        than 2 of them. Every object of a step shares the cameras' calibration error against the table frame (3-4 mm
        in some simulated captures), so only a move beyond it says a pose is wrong. Cached per step, object and
        pose."""
        shifts = []
        for k, p in others:
            pose = np.asarray(p, dtype=np.float64)
            if k == obj or not np.all(np.isfinite(pose)):
                continue
            key = (step, k, pose.tobytes())
            if key not in self._shifts:
                m, samples = pose_to_matrix(pose), self.samples(k)
                self._shifts[key] = align.refinement(samples, m, self._crop(step, m, samples), self._views(step),
                                                     limits=self.limits).shift
                while len(self._shifts) > OCCLUDER_CACHE:
                    self._shifts.popitem(last=False)
            shifts.append(self._shifts[key])
        return np.median(np.asarray(shifts), axis=0) if len(shifts) >= 2 else None

    def score(self, obj: int, step: int | None = None) -> FitScore:
        """Fit score of object `obj`'s current pose at a step (default the current one) against its cloud."""
        obj, step = self._check_obj(obj), self._step(step)
        pose = self.state.pose(step, obj)
        if pose is None:
            return FitScore(float("nan"), 0.0, 0.0, False, "unset")
        return self._fit(obj, step, pose)

    def stored_score(self, obj: int, step: int | None = None) -> FitScore | None:
        """The score recorded with the object's last change at a step (None if never scored)."""
        return _nan_score(self.state.scores[self._step(step)][self._check_obj(obj)])

    def _icp(self, obj: int, step: int, start: np.ndarray, extra_crop: float = 0.0,
             others: list[tuple[int, np.ndarray]] | None = None, **kwargs) -> align.IcpResult:
        """ICP of object `obj` at a step from `start` (4, 4), scored against the other objects (`others`:
        (object, pose); default: the state's poses at the step)."""
        samples = self.samples(obj)
        crop = self._crop(step, start, samples, extra_crop)
        views, checks = self._context(obj, step, others)
        return align.icp(samples, crop, start, views, **checks, **kwargs)

    def _interpenetrating(self, step: int) -> dict[int, int]:
        """{object: another object it interpenetrates by more than the limits' penetration_tolerance} at a step,
        from the poses as they are now (geometry only: cheap enough to run on every look)."""
        posed = [(k, pose_to_matrix(p)) for k in range(self.num_objects) if (p := self.state.pose(step, k)) is not None]
        out: dict[int, int] = {}
        for x, (a, ta) in enumerate(posed):
            for b, tb in posed[x + 1:]:
                depth = penetration_depth(self.samples(a), ta, self.samples(b), tb, self.limits)
                if depth > self.limits.penetration_tolerance:
                    out.setdefault(a, b)
                    out.setdefault(b, a)
        return out
