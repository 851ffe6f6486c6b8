"""How often the annotator flags a wrong pose, and how often it flags a right one (issue 32, part 1).

    python bench/bench_annotate_errors.py --captures captures/bench-errors -n 2 --steps 5 --seed 3 [--json out.json]
        [--set slide_gain=0.02 ...]

Generates the captures first where missing (`dsr-bench generate-captures`: realistic sensor noise and calibration
error), takes their true poses as the annotation (every one confirmed: the colour check compares a pose with the
object's colours at the nearest other step), and injects wrong poses one at a time (the other objects at their
true poses, unless the kind moves them too):

- translation: the object moved by 5, 10, 20, 50 or 100 mm in a random horizontal direction;
- rotation: turned by 5, 10, 20, 45, 90 or 180 degrees about its centre of mass, about a random axis (for an
  object with a continuous symmetry axis, an axis at right angles to it, so that the turn is an error);
- twin: turned by 180 degrees about its symmetry axis (a can) or about its vertical box axis (a box): a symmetric
  twin, which the cameras cannot tell from the right pose (reported, not counted as an error); so is any injected
  pose whose surface lies within TWIN_SURFACE_MM of the true surface (a can turned upside down); a twin whose
  surface lies farther (a box whose centre of mass is off its middle) is an error, twin_off;
- swap: the object and the nearest other object exchange poses (both moved); reported apart as swap_same_shape
  (not counted as an error) when the two have one shape, which geometry cannot tell apart;
- on_top: the object resting on the nearest other object (centred over it, its lowest point on that object's
  highest);
- left_behind: a carried pose left behind: the pose of the step before, for objects that moved (>= 10 mm or
  10 degrees) since.

A pose counts as flagged when the window would show it for a check (`Session.next_to_check`: its fit score, with
the other objects at their poses of the kind, is not accepted: coverage, RMSE, a physical check, the colours or
the refinement, `annotator.align.fit_score`). The error of a pose is its translation (mm) and its rotation up to a
continuous symmetry (deg) from the truth (`bench_annotate.pose_errors`); every kind is reported per size bucket of
that error. False alarms: the true
poses (as annotated) flagged under the captures' sensor noise. Every verdict carries its reason and its named checks
(`annotator.checks.Check`: name, value, threshold, pass or fail; in --json), so that thresholds can be judged from the
values; `--set NAME=VALUE` holds the poses to other thresholds (`annotator.thresholds.Thresholds`: tune on the seeds
kept for it, never on those reported as unseen). The cost of scoring a true pose (every check runs) is timed, and the
refinement's and the colour check's shares apart. Figures only, never asserted.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_annotate import ROOT, ObjectInfo, ensure_captures, pose_errors  # noqa: E402

sys.path.insert(0, str(ROOT))
from dsr_bench.annotator.align import matrix_to_pose, rotvec_to_matrix  # noqa: E402
from dsr_bench.geometry import pose_to_matrix  # noqa: E402

TRANSLATIONS_MM = (5, 10, 20, 50, 100)
ROTATIONS_DEG = (5, 10, 20, 45, 90, 180)
#: Error buckets (lower edges) of the report: translation (mm) and rotation (deg), whichever is larger in units of
#: these (10 mm counts as 10 deg).
BUCKETS = (0, 5, 10, 20, 50, 100)
AIM = 10.0  # mm or degrees: every error at least this large should be flagged
MOVED = (0.01, np.deg2rad(10.0))  # m, rad: an object moved since the step before (left_behind)
#: An injected pose whose surface lies within this (mm, 90th percentile of the distance of its surface samples to
#: the true surface) of the true surface is a symmetric twin (a can turned upside down), not an error.
TWIN_SURFACE_MM = 2.0
#: Injected kinds that geometry cannot tell from the truth: reported, not counted as errors.
NOT_ERRORS = ("twin", "swap_same_shape")


def turned(pose: np.ndarray, axis_world: np.ndarray, angle: float) -> np.ndarray:
    """Pose (7,) turned by `angle` rad about a world axis through its origin (the centre of mass)."""
    m = pose_to_matrix(pose)
    m[:3, :3] = rotvec_to_matrix(axis_world / np.linalg.norm(axis_world) * angle) @ m[:3, :3]
    return matrix_to_pose(m)


def shifted(pose: np.ndarray, shift: np.ndarray) -> np.ndarray:
    out = pose.copy()
    out[:3] += shift
    return out


def nearest_other(truth_t: np.ndarray, k: int) -> int:
    d = np.linalg.norm(truth_t[:, :2] - truth_t[k, :2], axis=1)
    d[k] = np.inf
    return int(np.argmin(d))


def on_top(session, truth_t: np.ndarray, k: int, j: int) -> np.ndarray:
    """Object k's pose moved to rest on object j: centred over j's top, its lowest point on j's highest."""
    mk, mj = pose_to_matrix(truth_t[k]), pose_to_matrix(truth_t[j])
    vk = session.capture.mesh(k)[0] @ mk[:3, :3].T + mk[:3, 3]
    vj = session.capture.mesh(j)[0] @ mj[:3, :3].T + mj[:3, 3]
    shift = np.zeros(3)
    shift[:2] = (vj[:, :2].min(0) + vj[:, :2].max(0)) / 2 - (vk[:, :2].min(0) + vk[:, :2].max(0)) / 2
    shift[2] = vj[:, 2].max() - vk[:, 2].min()
    return shifted(truth_t[k], shift)


def injections(session, truth: np.ndarray, infos: list, t: int, k: int, rng: np.random.Generator):
    """(kind, injected size label, {object: wrong pose}) of every error injected for object k at step t."""
    pose = truth[t, k]
    for mm in TRANSLATIONS_MM:
        a = rng.uniform(0, 2 * np.pi)
        yield "translation", f"{mm} mm", {k: shifted(pose, mm / 1000 * np.array([np.cos(a), np.sin(a), 0.0]))}
    sym = infos[k].axis
    m = pose_to_matrix(pose)
    for deg in ROTATIONS_DEG:
        axis = rng.normal(size=3)
        if sym is not None:
            s = m[:3, :3] @ sym
            axis -= (axis @ s) * s
        yield "rotation", f"{deg} deg", {k: turned(pose, axis, np.deg2rad(deg))}
    if sym is not None:
        yield "twin", "180 deg", {k: turned(pose, m[:3, :3] @ sym, np.pi)}
    else:
        up = int(np.argmax(np.abs(m[2, :3])))  # the box axis nearest the vertical
        yield "twin", "180 deg", {k: turned(pose, m[:3, up], np.pi)}
    j = nearest_other(truth[t], k)
    yield "swap", "", {k: truth[t, j].copy(), j: truth[t, k].copy()}
    yield "on_top", "", {k: on_top(session, truth[t], k, j)}
    if t > 0:
        moved_t, moved_r = (float(np.linalg.norm(truth[t, k, :3] - truth[t - 1, k, :3])),
                            np.deg2rad(pose_errors(truth[t - 1, k], pose, infos[k])["rotation_deg"]))
        if moved_t >= MOVED[0] or moved_r >= MOVED[1]:
            yield "left_behind", "", {k: truth[t - 1, k].copy()}


def check_costs(session, t: int, k: int, truth_t: np.ndarray) -> dict[str, float]:
    """Seconds to score object k's true pose at step t (`Session._fit`, every check), and of that the refinement
    (`align.refinement`) and the colour check (`align.sample_colours` + `colour_mismatch`), timed apart."""
    from dsr_bench.annotator import align

    others = [(i, truth_t[i]) for i in range(len(truth_t)) if i != k]
    start = time.perf_counter()
    session._fit(k, t, truth_t[k], others)
    fit = time.perf_counter() - start
    transform = pose_to_matrix(truth_t[k])
    samples = session.samples(k)
    views, checks = session._context(k, t, others)
    crop = session._crop(t, transform, samples)
    start = time.perf_counter()
    align.refinement(samples, transform, crop, views, limits=session.limits)
    refine = time.perf_counter() - start
    start = time.perf_counter()
    if checks["reference_colours"] is not None:
        align.colour_check(*align.posed_samples(samples, transform), views, checks["reference_colours"],
                           session.limits)
    colour = time.perf_counter() - start
    return {"fit_s": fit, "refine_s": refine, "colour_s": colour}


def flagged(session, t: int, poses: dict[int, np.ndarray], truth_t: np.ndarray) -> tuple[bool, str, list[dict]]:
    """(whether any object given a pose in `poses` (the others at their true poses) would be shown for a check,
    why, the checks): the reasons of the scores that were not accepted, or, when every one was, what each accepted
    score's checks measured ("accepted: object 1: rmse ..."), so that a miss says what let it through (never
    empty); the checks of every score, each `Check.as_dict` with its object (numbered from 1)."""
    scene = {i: truth_t[i] for i in range(len(truth_t))} | poses
    refused, accepted, checks = [], [], []
    for i, pose in poses.items():
        score = session._fit(i, t, pose, [(o, p) for o, p in scene.items() if o != i])
        (accepted if score.accepted else refused).append(f"object {i + 1}: {score.reason}")
        checks += [{"object": i + 1, **c.as_dict()} for c in score.checks]
    if refused:
        return True, "; ".join(refused), checks
    return False, "accepted: " + "; ".join(accepted), checks


def shape_difference_mm(infos: list, a: int, b: int) -> float:
    """How far (mm) objects a and b differ in shape: the larger over both of the 90th percentile of the distance of
    one's surface samples to the other's surface, in their object frames (each at the other's pose)."""
    return max(float(np.percentile(infos[j].surface_distance(infos[i].samples), 90)) * 1000
               for i, j in ((a, b), (b, a)))


def bucket(err: dict) -> int:
    size = max(err["translation_mm"], err["rotation_deg"])
    return max(b for b in BUCKETS if size >= b)


def run_capture(path: Path, work: Path, rng: np.random.Generator, steps: list[int] | None = None,
                limits=None) -> tuple[list[dict], list[dict]]:
    """(injected errors, correct poses) of one capture (at `steps`, default every step), each a dict with its kind,
    error, whether flagged, why (`flagged`: never an empty reason) and its checks; `limits`: the thresholds
    (`annotator.thresholds.Thresholds`, default today's)."""
    from dsr_bench.annotator.session import Session

    session = Session.open(path, work)
    if limits is not None:
        session.limits = limits
    truth = session.capture.truth_poses()
    # the annotation: every true pose confirmed (the colour check compares each pose with the object's colours at
    # the nearest other confirmed step, `Session._reference_colours`)
    session._commit("confirm", {(t, k): (truth[t, k], "confirmed", None) for t in range(len(truth))
                                for k in range(session.num_objects)})
    infos = [ObjectInfo(*session.capture.mesh(k)) for k in range(session.num_objects)]
    wrong, right = [], []
    for t in (range(len(truth)) if steps is None else steps):
        for k in range(session.num_objects):
            flag, why, checks = flagged(session, t, {k: truth[t, k]}, truth[t])
            right.append({"capture": path.name, "step": t, "object": k, "flagged": flag, "reason": why,
                          "checks": checks, **check_costs(session, t, k, truth[t])})
            for kind, size, poses in injections(session, truth, infos, t, k, rng):
                err = pose_errors(poses[k], truth[t, k], infos[k])
                if err["off_p90_mm"] < TWIN_SURFACE_MM and len(poses) == 1:
                    kind = "twin"  # e.g. a can turned upside down: its surface is where it was
                elif kind == "twin":
                    kind = "twin_off"  # a box whose turned surface is not quite where it was: an error
                elif kind == "swap":
                    shape_mm = shape_difference_mm(infos, *poses)
                    err["shape_difference_mm"] = shape_mm
                    if shape_mm < TWIN_SURFACE_MM:
                        kind = "swap_same_shape"  # two objects of one shape: only their appearance tells them apart
                flag, why, checks = flagged(session, t, poses, truth[t])
                wrong.append({"capture": path.name, "step": t, "object": k, "kind": kind, "injected": size,
                              "translation_mm": err["translation_mm"], "rotation_deg": err["rotation_deg"],
                              "surface_p90_mm": err["off_p90_mm"],
                              "shape_difference_mm": err.get("shape_difference_mm"),
                              "bucket": bucket(err), "flagged": flag, "reason": why, "checks": checks})
    session.close()
    return wrong, right


def report(wrong: list[dict], right: list[dict]) -> dict:
    """Recall per kind and error bucket, false alarms, and whether the aims are met; printed as a table."""
    table: dict = defaultdict(lambda: [0, 0])
    for e in wrong:
        key = (e["kind"], e["injected"] if e["kind"] in ("translation", "rotation") else "", e["bucket"])
        table[key][0] += int(e["flagged"])
        table[key][1] += 1
    print(f"{'kind':<12} {'injected':>9} {'error >=':>9} {'flagged':>8} {'of':>5} {'recall':>7}")
    rows = []
    order = {k: i for i, k in enumerate(("translation", "rotation", "swap", "on_top", "left_behind", "twin_off",
                                         "twin", "swap_same_shape"))}

    def sort_key(item: tuple) -> tuple:
        (kind, injected, b), _ = item
        return order[kind], float(injected.split()[0]) if injected else 0.0, b

    for (kind, injected, b), (hit, n) in sorted(table.items(), key=sort_key):
        print(f"{kind:<12} {injected:>9} {b:>9} {hit:>8} {n:>5} {hit / n:>7.0%}")
        rows.append({"kind": kind, "injected": injected, "error_at_least": b, "flagged": hit, "count": n})
    errors = [e for e in wrong if e["kind"] not in NOT_ERRORS and max(e["translation_mm"], e["rotation_deg"]) >= AIM]
    missed = [e for e in errors if not e["flagged"]]
    alarms = [e for e in right if e["flagged"]]
    unexplained = [e for e in wrong + right if not str(e.get("reason", "")).strip()]
    recall = 1 - len(missed) / max(len(errors), 1)
    false_alarms = len(alarms) / max(len(right), 1)
    print(f"errors of >= {AIM:.0f} mm or deg ({', '.join(NOT_ERRORS)} left out): {len(errors) - len(missed)} of "
          f"{len(errors)} flagged (recall {recall:.1%}; aim 100% {'met' if not missed else 'NOT met'}); false alarms "
          f"on true poses: {len(alarms)} of {len(right)} ({false_alarms:.1%}; aim < 5% "
          f"{'met' if false_alarms < 0.05 else 'NOT met'}); verdicts without a reason: {len(unexplained)}")
    for e in missed[:12]:
        shape = f", shapes {e['shape_difference_mm']:.1f} mm apart" if e.get("shape_difference_mm") is not None else ""
        print(f"  missed: {e['capture']} step {e['step']} object {e['object'] + 1} {e['kind']} {e['injected']} "
              f"({e['translation_mm']:.0f} mm, {e['rotation_deg']:.0f} deg{shape}): {e['reason']}")
    for e in alarms[:10]:
        print(f"  false alarm: {e['capture']} step {e['step']} object {e['object'] + 1}: {e['reason']}")
    costs = {key: float(np.mean([e[key] for e in right])) * 1000 for key in ("fit_s", "refine_s", "colour_s")}
    print(f"scoring a true pose (every check runs): {costs['fit_s']:.0f} ms on average, of which the refinement "
          f"{costs['refine_s']:.0f} ms and the colour check {costs['colour_s']:.1f} ms")
    return {"rows": rows, "recall_at_aim": recall, "errors_at_aim": len(errors), "missed": missed,
            "false_alarm_rate": false_alarms, "correct_poses": len(right), "false_alarms": alarms,
            "true_pose_scoring_ms": costs, "verdicts_without_reason": len(unexplained)}


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--captures", type=Path, default=Path("captures/bench-errors"), help="capture directory")
    parser.add_argument("-n", "--num", type=int, default=2, help="captures")
    parser.add_argument("--steps", type=int, default=5, help="pushes per capture")
    parser.add_argument("--objects-per-scene", type=int, default=4)
    parser.add_argument("--objects", default="procedural")
    parser.add_argument("--noise", default="realistic")
    parser.add_argument("--seed", type=int, default=3, help="captures' base seed; also seeds the injected errors")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures as JSON here")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="hold the poses to another threshold (a field of annotator.thresholds.Thresholds; a "
                             "tuple as 0.01,0.02); repeatable")
    return parser.parse_args()


def thresholds(settings: list[str]):
    """The thresholds with the --set NAME=VALUE settings applied (`Thresholds.replaced`)."""
    from dsr_bench.annotator.thresholds import THRESHOLDS

    pairs = dict(s.split("=", 1) for s in settings if "=" in s)
    if len(pairs) != len(settings):
        raise SystemExit(f"--set takes NAME=VALUE, got {settings}")
    try:
        return THRESHOLDS.replaced(pairs)
    except ValueError as exc:
        raise SystemExit(f"--set: {exc}") from None


def main() -> None:
    args = parse_args()
    limits = thresholds(args.set)
    paths = ensure_captures(args)
    start = time.perf_counter()
    wrong, right = [], []
    with tempfile.TemporaryDirectory(prefix="bench_annotate_errors_") as tmp:
        for i, path in enumerate(paths):
            w, r = run_capture(path, Path(tmp) / path.name, np.random.default_rng([args.seed, i]), limits=limits)
            wrong += w
            right += r
            print(f"{path.name}: {len(w)} injected errors, {len(r)} true poses ({time.perf_counter() - start:.0f} s)",
                  file=sys.stderr)
    print(f"bench_annotate_errors: {len(paths)} captures x {args.steps} pushes ({args.objects}, "
          f"{args.objects_per_scene} objects, noise {args.noise}, seed {args.seed}"
          f"{'; thresholds set: ' + ', '.join(args.set) if args.set else ''}); "
          f"{time.perf_counter() - start:.0f} s of scoring")
    out = report(wrong, right)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        tmp_json = args.json.with_name(args.json.name + ".tmp")
        tmp_json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, **out,
                                        "errors": wrong, "true_poses": right}, indent=1))
        tmp_json.replace(args.json)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
