"""What the annotator tells a person to do next: the panel's opening message and its "next:" line, each object
described in words (name, colour, shape), and the "wrong object" check of a fit that landed on another object's
points.

No window here (testable without a display): `annotator.keys.Controller` sets the messages from these after every
key, and the window shows them in its panel. Everything reads the Session's state; only `wrong_object` fits
anything (after a pick or a snap, never per frame), and `next_hint` reads statuses alone, so it costs nothing per
key.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dsr_bench.geometry import pose_to_matrix

#: "wrong object" when more than this fraction of the cloud points a pose explains (within the session's
#: limits.inlier_distance of its surface) lie as close to another object's posed surface: the fit sits on that
#: object's points ...
SHARED_POINTS_FRACTION = 0.5
#: ... counted only with at least this many explained points.
MIN_EXPLAINED_POINTS = 30
#: An unplaced object's mesh fits the points of a poor fit better by at least this much (`FitScore.quality`:
#: coverage less RMSE in units of 2 cm) and is accepted there: the points are that object's.
BETTER_QUALITY = 0.15
#: Turns about the vertical tried for an unplaced object's mesh on a poor fit's points (degrees), in each of its
#: resting orientations (upright, on either side), and offsets of its centre (m) from the points' centre.
WRONG_YAWS = tuple(range(0, 360, 30))
WRONG_OFFSETS = (-0.01, 0.0, 0.01)
#: ICPs run per unplaced object from its best-screened starts.
WRONG_ICP_STARTS = 2

#: Hue ranges (degrees, upper ends) of the colour names used to describe an object.
_HUES = ((15, "red"), (45, "orange"), (70, "yellow"), (165, "green"), (195, "cyan"), (255, "blue"), (290, "purple"),
         (330, "pink"), (360, "red"))


def colour_name(rgb) -> str | None:
    """A plain name of an RGB colour (0..1): "green", "dark red", "grey", ...; None when it is not 3 numbers."""
    try:
        r, g, b = (float(c) for c in rgb)
    except (TypeError, ValueError):
        return None
    hi, lo = max(r, g, b), min(r, g, b)
    if not np.isfinite([r, g, b]).all():
        return None
    if hi < 0.15:
        return "black"
    if hi - lo < 0.15 * hi + 0.03:
        return "white" if hi > 0.8 else "grey"
    if hi == r:
        hue = (60 * (g - b) / (hi - lo)) % 360
    elif hi == g:
        hue = 60 * (b - r) / (hi - lo) + 120
    else:
        hue = 60 * (r - g) / (hi - lo) + 240
    name = next(n for top, n in _HUES if hue < top)
    return f"dark {name}" if hi < 0.4 else name


def describe(session, obj: int) -> str:
    """Object `obj` in words for the messages, numbered from 1 as the panel: "object 1, can_0 (a green can)";
    the colour and shape are those of its identity (a simulated capture's), when it has them."""
    item = session.capture.objects[obj]
    identity = item.identity if isinstance(item.identity, dict) else {}
    colour = colour_name(identity.get("color"))
    kind = identity.get("category") if isinstance(identity.get("category"), str) else None
    words = " ".join(w for w in (colour, kind) if w)
    if words:
        article = "an" if words[0] in "aeiou" else "a"
        words = f" ({article} {words})"
    return f"object {obj + 1}, {item.name}{words}"


def export_command(session) -> str:
    """The commands that export this annotation and validate the file (`dsr-bench annotate ... --export`)."""
    capture = _short(session.capture.path)
    out = f"{session.capture.name}.h5"
    work = "" if Path(session.work_dir).resolve() == (Path(session.capture.path) / "annotation").resolve() else \
        f" --work {_short(session.work_dir)}"
    return f"dsr-bench annotate {capture}{work} --export {out}, then dsr-bench validate {out}"


def _short(path) -> str:
    """A path as short as it reads: relative to the working directory when inside it."""
    path = Path(path).resolve()
    try:
        rel = os.path.relpath(path)
    except ValueError:
        return str(path)
    return rel if not rel.startswith("..") else str(path)


def opening_message(session) -> str:
    """The message line when the window opens: a fresh annotation says what the work is; a resumed one where it
    stands."""
    s = session
    steps = s.num_steps + 1
    posed = np.isfinite(s.state.poses[..., 0])
    if not posed.any():
        return f"new: place the {s.num_objects} objects at step 0, then N carries them to steps 1..{s.num_steps}"
    done = sum(all(x in ("snapped", "confirmed") for x in s.status(t)) for t in range(steps))
    return f"resumed {s.capture.name} at step {s.step}: {done} of {steps} steps done (every change is saved)"


def next_hint(session) -> str:
    """The panel's "next:" line: what to do now, from the statuses (the selected object's first, then the current
    step's, then the steps to visit or check, then the export)."""
    s = session
    statuses, sel = s.status(), s.selected
    n = s.num_objects
    unset = [i for i in range(n) if statuses[i] == "unset"]
    unchecked = [i for i in range(n) if statuses[i] == "initialised"]
    if sel in unset:
        return (f"next: find {describe(s, sel)} in the images; M, shift+click 3+ points on it in the cloud, Q, "
                "then the same on its mesh, Q")
    if sel in unchecked:
        return (f"next: Space snaps {s.capture.objects[sel].name} onto the cloud; if it is far off its points, place "
                "it again (M) or nudge it there (D A W S E Q; G: 1 cm steps); Enter confirms a pose you checked by eye")
    if unset:
        k = min(unset, key=lambda i: (i - sel) % n)
        return f"next: press {k + 1} to select {describe(s, k)}, not placed yet, then M to place it"
    if unchecked:
        k = min(unchecked, key=lambda i: (i - sel) % n)
        return f"next: press {k + 1} to select {describe(s, k)}, placed but not checked, and snap it (Space)"
    if s.step < s.num_steps:
        return (f"next: step {s.step} is done: N goes to step {s.step + 1} (the poses are carried forward and the "
                "objects that moved are snapped)")
    left = s.unchecked()
    if left:
        step, obj, status = left[0]
        if not s.visited(step):
            return f"next: step {step} is not visited yet: P / N go there"
        return f"next: B jumps to what is left to check (step {step}, object {obj + 1}: {status})"
    return (f"next: all {s.num_steps + 1} steps are done: Esc quits (everything is saved); export with "
            f"{export_command(s)}")


def undo_hint(session, obj: int) -> str:
    """The "next:" line after a "wrong object?" warning."""
    name = session.capture.objects[obj].name
    return f"next: Z undoes (until {name} is unset), then pick {name}'s own points (see 'objects')"


def wrong_object(session, obj: int, other_shapes: bool = True) -> str | None:
    """"wrong object? ..." when object `obj`'s pose at the current step lies on another object's points, else None:

    - on a placed object's points: more than SHARED_POINTS_FRACTION of the cloud points its pose explains are as
      close to another object's posed surface (at least MIN_EXPLAINED_POINTS of them);
    - on points of another object's colour, when the objects' identities give their colours (`_coloured_like`);
    - with `other_shapes` (after a snap: the pose is the best its own mesh fits there), on an unplaced object's
      points, when its fit is poor: that object's mesh, tried on the same points (upright and on either side,
      turned about the vertical, resting on the table; the best screened starts snapped with ICP), fits them with
      an accepted score better by BETTER_QUALITY.
    """
    from scipy.spatial import cKDTree

    from dsr_bench.annotator import align

    s = session
    step = s.step
    pose = s.state.pose(step, obj)
    if pose is None:
        return None
    m = pose_to_matrix(pose)
    samples = s.samples(obj)
    crop = s._crop(step, m, samples)
    own = align.posed_samples(samples, m)[0]
    d, _ = cKDTree(own).query(crop, distance_upper_bound=s.limits.inlier_distance) if len(crop) else (np.zeros(0), None)
    explained = crop[np.isfinite(d)]
    if len(explained) >= MIN_EXPLAINED_POINTS:
        for k, other in s._others(obj, step):
            theirs = align.posed_samples(s.samples(k), pose_to_matrix(other))[0]
            dk, _ = cKDTree(theirs).query(explained, distance_upper_bound=s.limits.inlier_distance)
            shared = float(np.isfinite(dk).mean())
            if shared > SHARED_POINTS_FRACTION:
                return f"wrong object? {shared:.0%} of its points are those of {describe(s, k)}, placed there"
    coloured = _coloured_like(s, obj, step, m)
    if coloured is not None:
        k, seen = coloured
        return f"wrong object? its points have the colour of {describe(s, k)} ({seen} seen)"
    score = s.stored_score(obj) or s.score(obj)
    if not other_shapes or score.accepted:
        return None
    blob = crop[np.linalg.norm(crop - (m[:3, :3] @ samples.centre + m[:3, 3]), axis=1) <= samples.radius]
    if len(blob) < s.limits.min_correspondences:
        return None
    best = None
    for k in range(s.num_objects):
        if k == obj or s.state.pose(step, k) is not None:
            continue
        found = _fit_elsewhere(s, k, obj, step, blob)
        if found is not None and found.accepted and found.quality() > score.quality() + BETTER_QUALITY \
                and (best is None or found.quality() > best[1].quality()):
            best = (k, found)
    if best is None:
        return None
    k, found = best
    return (f"wrong object? its points fit {describe(s, k)} better (coverage {found.coverage:.0%} against "
            f"{score.coverage:.0%})")


def _chromaticity(rgb) -> np.ndarray | None:
    """r, g, b over their sum (3,) of an RGB colour, or None when it is not 3 finite numbers with a sum."""
    try:
        c = np.asarray(rgb, np.float64).reshape(3)
    except (TypeError, ValueError):
        return None
    return c / c.sum() if np.all(np.isfinite(c)) and c.sum() > 0 else None


def _coloured_like(session, obj: int, step: int, transform: np.ndarray) -> tuple[int, int] | None:
    """(another object k, surface samples seen) when the colours the cameras saw on object `obj`'s surface at
    `transform` (4, 4) (`align.sample_colours`, median chromaticity of at least the session's limits'
    colour_min_samples samples) are farther than colour_distance from its own identity colour and at most half as
    far from object k's; None otherwise, or when the objects' identities carry no colour (a simulated capture's do)."""
    from dsr_bench.annotator import align

    s = session
    own = [_chromaticity(o.identity.get("color") if isinstance(o.identity, dict) else None)
           for o in s.capture.objects]
    if own[obj] is None or all(c is None for k, c in enumerate(own) if k != obj):
        return None
    colours = align.sample_colours(*align.posed_samples(s.samples(obj), transform), s._views(step))
    seen = np.all(np.isfinite(colours), axis=1) & (np.nan_to_num(colours).mean(1) > s.limits.colour_min_brightness)
    if seen.sum() < s.limits.colour_min_samples:
        return None
    observed = np.median(colours[seen] / colours[seen].sum(1, keepdims=True), axis=0)
    mine = float(np.abs(observed - own[obj]).sum())
    others = [(float(np.abs(observed - c).sum()), k) for k, c in enumerate(own) if k != obj and c is not None]
    best, k = min(others)
    return (k, int(seen.sum())) if mine > s.limits.colour_distance and best <= mine / 2 else None


def _fit_elsewhere(session, k: int, obj: int, step: int, blob: np.ndarray):
    """The best accepted-first FitScore of object k's mesh snapped (ICP) onto the cloud points `blob` (M, 3) that
    object `obj`'s pose covers, from starts resting on the table (upright and on either side, WRONG_YAWS, centred
    over the points' centre within WRONG_OFFSETS); object `obj` is left out of the others (it sits there). None
    when no ICP converged."""
    from scipy.spatial import cKDTree

    from dsr_bench.annotator import align
    from dsr_bench.annotator.carry import _best_starts, _rank

    s = session
    samples = s.samples(k)
    vertices = samples.vertices if samples.vertices is not None else samples.points
    centre_xy = blob[:, :2].mean(0)
    starts = []
    for base in (np.eye(3), align.rotvec_to_matrix(np.array([np.pi / 2, 0, 0])),
                 align.rotvec_to_matrix(np.array([0, np.pi / 2, 0]))):
        for yaw in WRONG_YAWS:
            rot = align.rotvec_to_matrix(np.array([0.0, 0.0, np.deg2rad(yaw)])) @ base
            low = float((vertices @ rot.T)[:, 2].min())
            box = rot @ samples.centre
            for dx in WRONG_OFFSETS:
                for dy in WRONG_OFFSETS:
                    cand = np.eye(4)
                    cand[:3, :3] = rot
                    cand[:3, 3] = [centre_xy[0] + dx - box[0], centre_xy[1] + dy - box[1], -low]
                    starts.append(cand)
    others = [(i, p) for i, p in s._others(k, step) if i != obj]
    views, checks = s._context(k, step, others, colours=False)
    near = align.crop_cloud(s.cloud(step)[0], blob.mean(0), samples.radius + 0.05)
    if len(near) < s.limits.min_correspondences:
        return None
    tree = cKDTree(near)
    best = None
    for i in _best_starts(samples, np.stack(starts), np.zeros(len(starts)), tree, views)[:WRONG_ICP_STARTS]:
        result = align.icp(samples, s._crop(step, starts[i], samples), starts[i], views, **checks)
        if result.applied and (best is None or _rank(result.score) > _rank(best)):
            best = result.score
    return best
