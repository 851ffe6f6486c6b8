"""Carrying poses forward to a step visited for the first time, and the searches for an object that moved: the
Session's third layer (`Carrying`, on `annotator.scoring.Scoring`).

An object the pusher passed, or whose carried pose fits the new cloud worse, is snapped (ICP); one that does not
converge is searched for along the push (`_search`: start poses along it, sideways and turned, screened in two passes
by a coarse fit, the best few snapped), then, if it left its place, over the cloud no other object explains
(`_search_landed`); the objects that did not move keep their pose exactly. `go_to` runs it for a new step,
`annotator.review.Reviewing.recarry` for the steps a fix left stale.
"""

from __future__ import annotations

import numpy as np

from dsr_bench.annotator import align
from dsr_bench.annotator.align import FitScore
from dsr_bench.annotator.scoring import Scoring
from dsr_bench.constants import RIG_PUSHER_RADIUS
from dsr_bench.geometry import matrix_to_pose, pose_to_matrix

#: Carry-forward: an object counts as moved when its carried pose's coverage drops by this much (fraction) ...
MOVED_COVERAGE_DROP = 0.1
#: ... or its RMSE grows by this much (m), or its fit fails, or the pusher passed within this distance (m) of it.
MOVED_RMSE_RISE = 0.001
PUSH_CONTACT_MARGIN = 0.01
#: A snap of an object the fit does not flag as moved is kept only if it moves it at least this much (m, rad).
MIN_SNAP_CHANGE = (0.001, float(np.deg2rad(0.5)))
#: Start-pose search for a moved object whose carried pose does not snap: steps along the push (m), sideways
#: offsets (m), yaw candidates (rad), and how many of the best-scoring starts get an ICP.
SEARCH_STEP = 0.01
SEARCH_LATERAL = (-0.04, -0.02, 0.0, 0.02, 0.04)
#: Inlier distance (m) of the coarse score that ranks the search's start poses.
SEARCH_INLIER = 0.015
#: Surface samples used to rank the search's start poses.
SEARCH_SAMPLES = 400
SEARCH_YAWS = tuple(np.deg2rad([0, 15, -15, 30, -30, 60, -60, 90, -90, 180]))
SEARCH_ICP_STARTS = 6
#: Ranking penalty of a start pose or result per half turn (pi rad) away from the carried pose, in quality units
#: (coverage fraction): among fits of nearly equal quality the least turned one wins.
TURN_PENALTY = 0.05
#: A moved object that the search along the push does not find is looked for where the step's cloud shows surface
#: that no other object explains (a can or bottle lying on its side rolls on after the push, often farther than the
#: push and across it): cloud points above the table farther than this (m) from every other object's surface ...
EXPLAINED_DISTANCE = 0.01
#: ... in SEARCH_STEP cells holding at least this many of them put the object's centre over the cell, at its carried
#: height, turned about the vertical by SEARCH_YAWS.
LANDING_MIN_POINTS = 3
#: Ranking penalty of such a start pose or result per metre away from the carried pose, in quality units: among
#: fits of nearly equal quality (the same shape elsewhere) the nearest one wins.
DISTANCE_PENALTY = 0.5
#: Start poses screened at once (bounds the memory of the vectorised screen).
SCREEN_CHUNK = 1000
#: The screen runs in two passes when there are more than SCREEN_KEEP start poses: every start with one in
#: SCREEN_COARSE of the SEARCH_SAMPLES samples, then the best SCREEN_KEEP (at least; SCREEN_KEEP_FRACTION of them
#: when more) with all; the SEARCH_ICP_STARTS best of the second pass get an ICP. On the simulated captures the
#: starts chosen are those of one full pass (checked on 4 captures, every search), at a third of its time.
SCREEN_COARSE = 3
SCREEN_KEEP = 60
SCREEN_KEEP_FRACTION = 0.12
#: Ranking penalty (quality units) of a search's ICP result whose fit is not accepted (e.g. a physical check
#: failed: it sits inside another object or in front of what a camera measured): the best physically valid fit wins.
REJECTED_PENALTY = 1.0


def _rank(score: FitScore) -> float:
    """Rank of a fit among a search's results: its quality, less REJECTED_PENALTY when it is not accepted."""
    return score.quality() - (0.0 if score.accepted else REJECTED_PENALTY)


def _screen(samples: align.SurfaceSamples, starts: np.ndarray, tree, views: list[align.View],
            min_visible: int = 20) -> np.ndarray:
    """`align.screen_quality` (C,) of start poses (C, 4, 4), SCREEN_CHUNK at a time."""
    return np.concatenate([align.screen_quality(samples, starts[k:k + SCREEN_CHUNK], tree, views, SEARCH_INLIER,
                                                min_visible) for k in range(0, len(starts), SCREEN_CHUNK)])


def _best_starts(samples: align.SurfaceSamples, starts: np.ndarray, penalties: np.ndarray, tree,
                 views: list[align.View]) -> np.ndarray:
    """Indices of the SEARCH_ICP_STARTS start poses (C, 4, 4) of best screened quality (`align.screen_quality` of
    SEARCH_SAMPLES of the object's surface samples, against a cKDTree of the cloud) less `penalties` (C,), best
    first, ties in index order; over SCREEN_KEEP starts in two passes (see SCREEN_COARSE)."""
    every = max(1, len(samples.points) // SEARCH_SAMPLES)
    screen = align.SurfaceSamples(samples.points[::every], samples.normals[::every], samples.centre, samples.radius)
    keep = np.arange(len(starts))
    if len(starts) > SCREEN_KEEP:
        coarse = align.SurfaceSamples(screen.points[::SCREEN_COARSE], screen.normals[::SCREEN_COARSE],
                                      samples.centre, samples.radius)
        first = _screen(coarse, starts, tree, views, max(1, 20 // SCREEN_COARSE)) - penalties
        count = max(SCREEN_KEEP, int(SCREEN_KEEP_FRACTION * len(starts)))
        keep = np.sort(np.argsort(-first, kind="stable")[:count])
    quality = _screen(screen, starts[keep], tree, views) - penalties[keep]
    return keep[np.argsort(-quality, kind="stable")[:SEARCH_ICP_STARTS]]


def _same_poses(a: list[tuple[int, np.ndarray]], b: list[tuple[int, np.ndarray]]) -> bool:
    """Whether two lists of (object, pose) hold the same objects at exactly the same poses."""
    return len(a) == len(b) and all(i == j and np.array_equal(p, q) for (i, p), (j, q) in zip(a, b))


class Carrying(Scoring):
    """Carrying poses to a new step, and the searches (see the module docstring)."""

    def go_to(self, step: int) -> list[int]:
        """Make `step` current. A step not visited before gets the poses of the nearest earlier visited step
        carried forward, and only the objects that moved are snapped (ICP; a start-pose search along the push
        when the carried pose does not converge; then, for an object that left its place and is still not snapped,
        a search over the cloud that no other object explains, e.g. a lying can that rolled on across the push).
        Returns the objects whose pose the snapping changed.

        Moving to a visited step only moves the cursor (not an undoable action); visiting a new step is one.
        """
        step = self._check_step(step)
        self._writable()
        if self.state.visited[step]:
            if step != self.state.step:
                self.state.step = step
                self.state.count("step")
                self._save("cursor")
            return []
        source = max(s for s in range(step) if self.state.visited[s])
        carries = {obj: (source, pose, None, None) for obj in range(self.num_objects)
                   if (pose := self.state.pose(source, obj)) is not None}
        changes, snapped = self._carry_objects(step, carries)
        self._commit("step", changes, cursor=step, visit=[step])
        return snapped

    def _carry_objects(self, step: int, carries: dict) -> tuple[dict, list[int]]:
        """Carry objects to `step`: carries {obj: (source step, source pose, source score or None, source status or
        None)} (None: the state's). Returns the changes {(step, obj): (pose, status, score dict, (source, source
        pose))} and the objects whose pose the snapping changed. Objects not carried keep their pose at `step`.

        The objects the pusher passed go first, each scored without the pushed ones not carried yet (their poses
        here are unknown), and the others stay still as hypotheses, scored against the new poses (an object that
        moved in front of a still one hides part of it); once every object has a pose, each is scored again
        against the others' final poses: a moved object whose new pose now fits (accepted, about as well covered
        as at the source) is snapped, and an object whose pose is not accepted (another object now hides it, or
        it interpenetrates one) is carried again against them."""
        current = {k: p for k in range(self.num_objects)
                   if k not in carries and (p := self.state.pose(step, k)) is not None}
        current.update({obj: c[1] for obj, c in carries.items()})
        pushed = {o for o in carries if self._near_push(o, carries[o][1], carries[o][0], step)}
        order = sorted(carries, key=lambda o: (o not in pushed, o))
        results, used = {}, {}
        for obj in order:
            source, pose, before, src_status = carries[obj]
            # the objects the pusher passed that are not carried yet have no pose here yet: left out
            pending = {k for k in pushed if k not in results}
            used[obj] = self._others_of(obj, {k: p for k, p in current.items() if k not in pending})
            results[obj] = self._carry(obj, source, step, pose, before, src_status, used[obj])
            current[obj] = results[obj][0]
        for obj in order:
            new_pose, status, score, moved = results[obj]
            others = self._others_of(obj, current)
            if _same_poses(others, used[obj]):
                continue  # scored against these poses already
            final = self._fit(obj, step, new_pose, others)
            source, pose, before, src_status = carries[obj]
            if final.accepted and (status == "snapped" or moved):
                before = before or self._fit(obj, source, pose)
                if status == "snapped" or final.coverage >= before.coverage - MOVED_COVERAGE_DROP:
                    results[obj] = (new_pose, "snapped", final, moved)  # its fit holds against the final poses
                    continue
            results[obj] = self._carry(obj, source, step, pose, before, src_status, others)
            current[obj] = results[obj][0]
        changes, snapped = {}, []
        for obj in sorted(results):
            new_pose, status, score, moved = results[obj]
            changes[(step, obj)] = (new_pose, status, score.as_dict(), (carries[obj][0], carries[obj][1]))
            if moved:
                snapped.append(obj)
        # once every object near its push has its new pose: an object that left its place and was not found near
        # the push is looked for where the cloud shows surface that no other object explains
        for obj in [k for (_, k), change in changes.items() if change[1] != "snapped"]:
            others = self._others_of(obj, {k: change[0] for (_, k), change in changes.items()} |
                                     {k: p for k, p in current.items() if k not in carries})
            source, pose, before, _ = carries[obj]
            landed = self._land(obj, source, step, pose, others, before)
            if landed is not None:
                changes[(step, obj)] = (landed[0], "snapped", landed[1].as_dict(), (source, pose))
                snapped = sorted(set(snapped) | {obj})
        return changes, snapped

    @staticmethod
    def _others_of(obj: int, poses: dict) -> list[tuple[int, np.ndarray]]:
        """(object, pose) of the entries of {object: pose} other than `obj`."""
        return [(k, np.asarray(p, dtype=np.float64)) for k, p in sorted(poses.items()) if k != obj]

    def _near_push(self, obj: int, pose: np.ndarray, source: int, step: int) -> bool:
        """Whether the pusher passed within its radius + PUSH_CONTACT_MARGIN of the object (xy) between steps."""
        pts, _ = align.posed_samples(self.samples(obj), pose_to_matrix(pose))
        pts = pts[:, :2]
        for a, b in self.capture.pushes_world[source:step, :, :2]:
            ab = b - a
            u = np.clip(((pts - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
            d = np.linalg.norm(pts - (a + u[:, None] * ab), axis=1)
            if d.min() < RIG_PUSHER_RADIUS + PUSH_CONTACT_MARGIN:
                return True
        return False

    def _carry(self, obj: int, source: int, step: int, pose: np.ndarray, before: FitScore | None = None,
               src_status: str | None = None, others: list[tuple[int, np.ndarray]] | None = None
               ) -> tuple[np.ndarray, str, FitScore, bool]:
        """(pose, status, score, moved) of an object carried from `source` to `step`; `before` / `src_status`: the
        source's score and status (default: scored now against the source's other objects, and the state's status);
        `others`: (object, pose) of the other objects at `step` (default: the state's). Coverage counts only the
        surface no other object hides, at both steps, so an object that another one moved in front of keeps its
        coverage; a pose that fails a physical check is not accepted."""
        before = before or self._fit(obj, source, pose)
        carried = self._fit(obj, step, pose, others)
        src_status = str(self.state.status[source, obj]) if src_status is None else src_status
        checked = src_status in ("snapped", "confirmed")
        rmse_before = before.rmse if np.isfinite(before.rmse) else 0.0
        dropped = (not carried.accepted or carried.coverage < before.coverage - MOVED_COVERAGE_DROP
                   or not np.isfinite(carried.rmse) or carried.rmse > rmse_before + MOVED_RMSE_RISE)
        if not dropped and not self._near_push(obj, pose, source, step):
            return pose, ("snapped" if checked else "initialised"), carried, False
        start = pose_to_matrix(pose)
        result = self._icp(obj, step, start, others=others)

        def good(r: align.IcpResult) -> bool:  # accepted, and about as well covered as at the source step
            return r.applied and r.score.accepted and r.score.coverage >= before.coverage - MOVED_COVERAGE_DROP

        if not dropped:
            # near the push but the fit did not change: keep the carried pose unless a good ICP fit clearly moves it
            moved_t, moved_r = align.pose_delta(start, result.transform)
            if not good(result) or (moved_t < MIN_SNAP_CHANGE[0] and moved_r < MIN_SNAP_CHANGE[1]):
                return pose, ("snapped" if checked else "initialised"), carried, False
            return matrix_to_pose(result.transform), "snapped", result.score, True
        if not good(result):
            searched = self._search(obj, source, step, start, others)
            if searched is not None and (not result.applied or _rank(searched.score) > _rank(result.score)):
                result = searched
        if good(result):
            return matrix_to_pose(result.transform), "snapped", result.score, True
        if result.applied and _rank(result.score) > _rank(carried):
            return matrix_to_pose(result.transform), "initialised", result.score, True
        carried.reason = f"moved, not snapped: {result.score.reason}"
        return pose, "initialised", carried, False

    def _search(self, obj: int, source: int, step: int, start: np.ndarray,
                others: list[tuple[int, np.ndarray]] | None = None) -> align.IcpResult | None:
        """Best kept ICP result from start poses along the push direction (the pushes between `source` and
        `step`, `capture.pushes_world`), sideways and turned about z; `others`: (object, pose) of the other objects
        at `step` (occluders, and the physical checks: the best physically valid fit wins)."""
        pushes = self.capture.pushes_world[source:step]
        samples = self.samples(obj)
        vec = pushes[-1, 1, :2] - pushes[-1, 0, :2]
        length = float(np.linalg.norm(vec))
        direction = vec / length if length > 1e-6 else np.array([1.0, 0.0])
        side = np.array([-direction[1], direction[0]])
        reach = float(sum(np.linalg.norm(p[1, :2] - p[0, :2]) for p in pushes)) + 0.03
        wide = self._crop(step, start, samples, extra=reach)
        if len(wide) < self.limits.min_correspondences:
            return None
        from scipy.spatial import cKDTree

        tree = cKDTree(wide)
        views, checks = self._context(obj, step, others)
        centre = start[:3, :3] @ samples.centre + start[:3, 3]
        starts, turns = [], []
        for along in np.arange(0.0, reach + 1e-9, SEARCH_STEP):
            for lateral in SEARCH_LATERAL:
                for yaw in SEARCH_YAWS:
                    rz = align.rotvec_to_matrix(np.array([0.0, 0.0, yaw]))
                    cand = np.eye(4)
                    cand[:3, :3] = rz @ start[:3, :3]
                    shift = np.zeros(3)
                    shift[:2] = along * direction + lateral * side
                    cand[:3, 3] = rz @ (start[:3, 3] - centre) + centre + shift
                    starts.append(cand)
                    turns.append(abs(yaw))
        # among equally good fits prefer the least turn: a symmetric object's turned twin fits as well but would
        # give the wrong motion (flow)
        best_starts = _best_starts(samples, np.stack(starts), TURN_PENALTY * np.asarray(turns) / np.pi, tree, views)
        best, best_rank = None, -np.inf
        for k in best_starts:
            cand = starts[k]
            result = align.icp(samples, self._crop(step, cand, samples), cand, views, **checks)
            rank = _rank(result.score) - TURN_PENALTY * align.pose_delta(start, result.transform)[1] / np.pi
            if result.applied and rank > best_rank:
                best, best_rank = result, rank
        return best

    def _land(self, obj: int, source: int, step: int, pose: np.ndarray, others: list[tuple[int, np.ndarray]],
              before: FitScore | None = None) -> tuple[np.ndarray, FitScore] | None:
        """(pose, score) of an object that left its place (its carried pose lost MOVED_COVERAGE_DROP of its
        coverage) found by `_search_landed` with a good fit (accepted, about as well covered as at `source`), or
        None. `others`: (object, pose) of the other objects at `step`; `before`: the source's score (default the
        state's)."""
        before = before or self._fit(obj, source, pose)
        carried = self._fit(obj, step, pose, others)
        if carried.coverage >= before.coverage - MOVED_COVERAGE_DROP:
            return None  # still (partly) where it was: not free to go looking elsewhere
        result = self._search_landed(obj, step, pose_to_matrix(pose), others)
        if result is None or not (result.applied and result.score.accepted
                                  and result.score.coverage >= before.coverage - MOVED_COVERAGE_DROP):
            return None
        return matrix_to_pose(result.transform), result.score

    def _search_landed(self, obj: int, step: int, start: np.ndarray,
                       others: list[tuple[int, np.ndarray]]) -> align.IcpResult | None:
        """Best kept ICP result from start poses over the step's unexplained surface: cloud points above the table
        farther than EXPLAINED_DISTANCE from every other object's surface at its pose (`others`: (object, pose)),
        binned in SEARCH_STEP cells (at least LANDING_MIN_POINTS points); the object's centre goes over each cell
        at its carried height, turned about the vertical by SEARCH_YAWS. Finds an object wherever it went (a can
        lying on its side rolls on across the push); ties go to the least turn, then to the nearest."""
        from scipy.spatial import cKDTree

        above = self.cloud(step)[0]
        above = points = above[above[:, 2] > self.limits.table_margin]
        if others and len(points):
            surfaces = np.vstack([align.posed_samples(self.samples(k), pose_to_matrix(p))[0] for k, p in others])
            d, _ = cKDTree(surfaces).query(points, distance_upper_bound=EXPLAINED_DISTANCE)
            points = points[~np.isfinite(d)]
        if len(points) < self.limits.min_correspondences:
            return None
        cells, counts = np.unique(np.floor(points[:, :2] / SEARCH_STEP).astype(np.int64), axis=0, return_counts=True)
        cells = cells[counts >= LANDING_MIN_POINTS]
        if len(cells) == 0:
            return None
        samples = self.samples(obj)
        centre = start[:3, :3] @ samples.centre + start[:3, 3]
        xy = (cells + 0.5) * SEARCH_STEP
        starts, penalties = [], []
        for yaw in SEARCH_YAWS:
            rot = align.rotvec_to_matrix(np.array([0.0, 0.0, yaw])) @ start[:3, :3]
            for x, y in xy:
                cand = np.eye(4)
                cand[:3, :3] = rot
                cand[:3, 3] = np.array([x, y, centre[2]]) - rot @ samples.centre
                starts.append(cand)
                penalties.append(TURN_PENALTY * abs(yaw) / np.pi + DISTANCE_PENALTY * np.hypot(x - centre[0],
                                                                                               y - centre[1]))
        tree = cKDTree(above)
        views, checks = self._context(obj, step, others)
        best, best_rank = None, -np.inf
        for k in _best_starts(samples, np.stack(starts), np.asarray(penalties), tree, views):
            result = align.icp(samples, self._crop(step, starts[k], samples), starts[k], views, **checks)
            moved_t, turned = align.pose_delta(start, result.transform)
            rank = _rank(result.score) - TURN_PENALTY * turned / np.pi - DISTANCE_PENALTY * moved_t
            if result.applied and rank > best_rank:
                best, best_rank = result, rank
        return best
