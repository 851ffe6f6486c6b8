"""Annotation accuracy and effort on simulated captures with known poses: the annotator vs keyboard-only vs
keyboard + snap.

    python bench/bench_annotate.py --captures captures/bench -n 5 --steps 10 --seed 0 [--json out.json]

Generates the captures first where missing (`dsr-bench generate-captures`, realistic sensor noise and
calibration error), then annotates each capture with three simulated people and compares with truth.json. The
people decide from what the window shows (the fit score, coverage and status the Session reports, as the panel
prints them: `looks_wrong`), never from the true pose; only where their eye aims (the points they click, the
direction they nudge) comes from the truth, as a person's eye sees the scene.

1. The annotator (`annotator.session.Session`, the API the window drives): step 0, per object: pick mode (M)
   with three or four picked point pairs (`init_from_picks`), then one ICP snap (Space). A simulated person aims
   at well-spread surface points of the object they can see (mesh surface points whose true world position has a
   cloud point within 4 mm, farthest-point sampling) and clicks both sides with noise: on the cloud, the true
   position plus --click-noise-mm (3 mm) RMS 3D noise, snapped to the nearest cloud point (and so to the stored,
   slightly miscalibrated cloud); on the mesh, in the pick window that shows the mesh's offered surface samples
   (`annotator.keys.mesh_samples`) over about MESH_VIEW_PIXELS (700) pixels, the aimed point plus
   --mesh-click-px (10) pixels RMS in the view plane of a random view direction, snapped to the nearest offered
   sample. Steps 1..T: N (`go_to`: carry forward, snap what moved). After each, every object the window shows as
   poor (score not accepted) or unchecked (status 'initialised') is re-picked and snapped, at most --tries (2)
   times per object and step.
2. Keyboard-only (the paper's tool), a model of a person with nudge keys only (window sizes: 1 cm / 1 mm and
   5 / 1 degrees; one key per axis and sign, table axes, rotation about the object centre; a key toggles coarse /
   fine). Start pose: the object's pose the person gave at the previous step; at step 0 the mesh appears upright
   (identity rotation) at the workspace centre (0.5, 0) at its true height. The person is an ideal observer
   of the truth (no calibration error: this favours the keyboard) but sees a misalignment only when it displaces
   the mesh surface by more than --visible-mm (2 mm): a translation error along an axis > 2 mm, or a rotation
   error about an axis times the object's radius > 2 mm (rotation about a continuous symmetry axis is
   invisible). Greedy: press the key of the axis with the largest visible error, coarse while the error is at
   least 3/4 of a coarse step, else fine; stop when nothing visible remains or a press would not reduce the
   error. This is a lower bound on a real person's presses (an oracle never overshoots or hunts).
3. Keyboard + snap: the annotator without picks. Step 0: the same keyboard person nudges each object from its spawn
   pose only until no misalignment over --rough-mm (5 mm) shows, then snaps (Space). Steps 1..T: N; an object the
   window shows as poor or unchecked is nudged from its current pose (to --rough-mm, on a second try to
   --visible-mm) and snapped again, at most --tries times.

Effort, per sequence: clicks (2 per picked pair) and keys (nudges, coarse/fine toggles, M, Space, N; selecting
objects and closing pick windows not counted for any method), and their sum per object per step.

Errors per object and step against the true poses: translation (mm, of the mesh frame origin = centre of
mass), rotation (degrees; for objects with a continuous symmetry axis, the tilt of that axis; "raw": the full
rotation), ADD(-S) as a fraction of the object's diameter (ADD: mean distance of corresponding surface points;
for objects with a continuous symmetry axis ADD-S: mean distance of the posed surface samples to the true
surface), ADD-S for every object (blind to discrete symmetries such as a box turned by 180 degrees, which ADD
and the rotation error count), and the fraction of gross errors (over 10 mm or 10 degrees). Figures only, never
asserted; the seconds reported are the computer's, not the person's.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dsr_bench.annotator.align import matrix_to_pose, rotvec_to_matrix  # noqa: E402
from dsr_bench.geometry import pose_to_matrix  # noqa: E402

COARSE = (0.01, np.deg2rad(5.0))
FINE = (0.001, np.deg2rad(1.0))
PICK_VISIBLE = 0.004  # m: a surface point is pickable when a cloud point lies this close to its true position
PICK_MIN_HEIGHT = 0.005  # m above the table
WORKSPACE_SPAWN = (0.5, 0.0)
GROSS = (10.0, 10.0)  # mm, degrees: an error beyond either is a gross error (e.g. a box turned by 180 degrees)
MESH_VIEW_PIXELS = 700  # px: the pick window's view of a mesh spans about this many pixels across its diameter


# --- geometry helpers ----------------------------------------------------------------------------------------


def rotvec(matrix: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(matrix).as_rotvec()


def symmetry_axis(vertices: np.ndarray, faces: np.ndarray, samples: np.ndarray, tol: float = 5e-4) -> np.ndarray | None:
    """The object-frame axis (through the origin, the centre of mass) about which the mesh is continuously
    symmetric, among the object's x, y, z axes, or None: samples turned by several angles stay within `tol` m
    of the surface."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    for axis in np.eye(3)[::-1]:
        turned = [(samples @ rotvec_to_matrix(axis * np.deg2rad(a)).T).astype(np.float32) for a in (23.0, 71.0, 137.0)]
        dists = [scene.compute_distance(o3d.core.Tensor(t)).numpy().mean() for t in turned]
        if max(dists) < tol:
            return axis
    return None


class ObjectInfo:
    """What the errors and the simulated users need of one object: surface samples (object frame), diameter (m),
    radius about the centre of mass (m), continuous symmetry axis (object frame) or None."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import trimesh
        from scipy.spatial import ConvexHull
        from scipy.spatial.distance import pdist

        mesh = trimesh.Trimesh(vertices, faces, process=False)
        self.samples = np.asarray(trimesh.sample.sample_surface_even(mesh, 1500, seed=0)[0], dtype=np.float64)
        hull = vertices[ConvexHull(vertices).vertices]
        self.diameter = float(pdist(hull).max())
        self.radius = float(np.linalg.norm(vertices, axis=1).max())
        self.axis = symmetry_axis(vertices, faces, self.samples)
        self._vertices, self._faces = vertices, faces
        self._scene = None

    def surface_distance(self, points: np.ndarray) -> np.ndarray:
        """Distance (m) of object-frame points (M, 3) to the mesh surface."""
        import open3d as o3d

        if self._scene is None:
            self._scene = o3d.t.geometry.RaycastingScene()
            self._scene.add_triangles(o3d.core.Tensor(self._vertices.astype(np.float32)),
                                      o3d.core.Tensor(self._faces.astype(np.uint32)))
        return self._scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy().astype(np.float64)


def pose_errors(est: np.ndarray, true: np.ndarray, info: ObjectInfo) -> dict[str, float]:
    """Translation (mm), rotation (deg, raw and symmetry-aware) and ADD / ADD-S over the diameter of one pose."""
    me, mt = pose_to_matrix(est), pose_to_matrix(true)
    rel = me[:3, :3].T @ mt[:3, :3]
    raw = float(np.rad2deg(np.linalg.norm(rotvec(rel))))
    if info.axis is not None:
        u, v = me[:3, :3] @ info.axis, mt[:3, :3] @ info.axis
        rot = float(np.rad2deg(np.arccos(np.clip(u @ v, -1.0, 1.0))))
    else:
        rot = raw
    pe = info.samples @ me[:3, :3].T + me[:3, 3]
    pt = info.samples @ mt[:3, :3].T + mt[:3, 3]
    add = float(np.linalg.norm(pe - pt, axis=1).mean())
    closest = info.surface_distance((pe - mt[:3, 3]) @ mt[:3, :3])  # to the true surface, in its object frame
    adds = float(closest.mean())
    trans = 1000 * float(np.linalg.norm(me[:3, 3] - mt[:3, 3]))
    return {"translation_mm": trans, "rotation_deg": rot, "rotation_raw_deg": raw,
            "add": (adds if info.axis is not None else add) / info.diameter, "add_s": adds / info.diameter,
            "gross": float(trans > GROSS[0] or rot > GROSS[1]), "off_p90_mm": 1000 * float(np.percentile(closest, 90))}


# --- the annotator, driven like a person would ---------------------------------------------------------------------


def _view_plane_noise(rng: np.random.Generator, sigma: float, count: int) -> np.ndarray:
    """(count, 3) offsets of RMS length `sigma` (m) in the image plane of a random view direction: where a click
    lands beside the point aimed at."""
    out = np.zeros((count, 3))
    for k in range(count):
        view = rng.normal(size=3)
        view /= np.linalg.norm(view)
        a = np.cross(view, [1.0, 0.0, 0.0] if abs(view[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(view, a)
        out[k] = (rng.normal(0.0, sigma / np.sqrt(2), 2) @ np.stack([a, b]))
    return out


class MeshClicks:
    """Where the person's clicks on the rendered mesh land: the pick window shows the mesh's surface samples
    (`annotator.keys.mesh_samples`, the points the tool offers) filling a MESH_VIEW_PIXELS-pixel view; a click
    aimed at a surface point lands `px` RMS pixels beside it in the view plane and picks the nearest offered
    sample (the tool's own snap to the mesh surface)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, diameter: float, px: float):
        from scipy.spatial import cKDTree

        from dsr_bench.annotator.keys import mesh_samples

        self.points = mesh_samples(vertices, faces)
        self.tree = cKDTree(self.points)
        self.sigma = px * diameter / MESH_VIEW_PIXELS

    def click(self, rng: np.random.Generator, aimed: np.ndarray) -> np.ndarray:
        """Object-frame points (k, 3) the person picks when aiming at `aimed` (k, 3)."""
        _, idx = self.tree.query(aimed + _view_plane_noise(rng, self.sigma, len(aimed)))
        return self.points[idx]


def simulate_picks(rng: np.random.Generator, info: ObjectInfo, mesh: MeshClicks, true_pose: np.ndarray,
                   cloud: np.ndarray, tree, click_noise: float) -> tuple[np.ndarray, np.ndarray]:
    """k = 3 or 4 picked pairs: mesh points (k, 3) object frame, cloud points (k, 3) world (see the docstring)."""
    m = pose_to_matrix(true_pose)
    world = info.samples @ m[:3, :3].T + m[:3, 3]
    dist, _ = tree.query(world)
    pickable = np.flatnonzero((dist < PICK_VISIBLE) & (world[:, 2] > PICK_MIN_HEIGHT))
    if len(pickable) < 3:
        pickable = np.argsort(dist)[:50]
    k = int(rng.integers(3, 5))
    chosen = [int(rng.choice(pickable))]
    for _ in range(k - 1):  # farthest-point sampling: well spread
        d = np.min(np.linalg.norm(world[pickable][:, None] - world[chosen][None], axis=2), axis=1)
        chosen.append(int(pickable[int(np.argmax(d))]))
    clicks = world[chosen] + rng.normal(0.0, click_noise / np.sqrt(3), (k, 3))
    _, nearest = tree.query(clicks)
    return mesh.click(rng, info.samples[chosen]), cloud[nearest]


def looks_wrong(session, obj: int) -> bool:
    """What the window shows makes the person fix the object: its fit score (the Session's, as the panel shows it)
    is poor, or it is not snapped / confirmed (the panel says 'initialised': carried but not re-fitted). Never the
    true pose."""
    score = session.stored_score(obj) or session.score(obj)
    return not score.accepted or session.status()[obj] not in ("snapped", "confirmed")


def annotate_with_session(capture_dir: Path, work: Path, infos: list[ObjectInfo], meshes: list[MeshClicks],
                          truth: np.ndarray, rng: np.random.Generator, click_noise: float, tries: int) -> dict:
    """Poses (T+1, N, 7), action counts, clicks and keys of the annotator driven by a simulated person."""
    from scipy.spatial import cKDTree

    from dsr_bench.annotator.session import Session

    session = Session.open(capture_dir, work_dir=work)
    effort = {"clicks": 0, "keys": 0, "repicks": 0}

    def place(obj: int, step: int) -> None:
        cloud = session.cloud(step)[0]
        mesh_pts, cloud_pts = simulate_picks(rng, infos[obj], meshes[obj], truth[step, obj], cloud, cKDTree(cloud),
                                             click_noise)
        session.init_from_picks(obj, mesh_pts, cloud_pts)
        session.snap(obj)
        effort["clicks"] += 2 * len(mesh_pts)
        effort["keys"] += 2  # M (pick mode), Space (snap); closing the two pick windows (Q) not counted

    start = time.perf_counter()
    for step in range(session.num_steps + 1):
        if step == 0:
            for obj in range(session.num_objects):
                place(obj, 0)
        else:
            session.go_to(step)
            effort["keys"] += 1  # N
        for obj in range(session.num_objects):
            for _ in range(tries):
                if not looks_wrong(session, obj):
                    break
                place(obj, step)
                effort["repicks"] += 1
    seconds = time.perf_counter() - start
    poses = np.stack([session.poses(s) for s in range(session.num_steps + 1)])
    return {"poses": poses, "actions": session.action_counts, **effort, "seconds": seconds}


def snap_from_truth(cap, truth: np.ndarray) -> np.ndarray:
    """Poses (T+1, N, 7) of one ICP snap started at the true pose: the floor the cloud allows (its sensor noise and
    calibration error), reached by no user action."""
    from dsr_bench.annotator import align

    out = truth.copy()
    samples = [align.sample_surface(*cap.mesh(k), seed=k) for k in range(cap.num_objects)]
    for t in range(cap.num_observations):
        cloud = cap.cloud(t)[0]
        views = [align.View(c.camera, cap.depth(t, n)) for n, c in cap.cameras.items()]
        for k, smp in enumerate(samples):
            start = pose_to_matrix(truth[t, k])
            crop = align.crop_cloud(cloud, start[:3, :3] @ smp.centre + start[:3, 3], smp.radius + 0.03)
            result = align.icp(smp, crop, start, views)
            if result.applied:
                out[t, k] = matrix_to_pose(result.transform)
    return out


# --- keyboard only --------------------------------------------------------------------------------------------------


def keyboard_annotate(start: np.ndarray, target: np.ndarray, info: ObjectInfo, visible: float,
                      mode: list[str], max_presses: int = 5000) -> tuple[np.ndarray, int]:
    """The keyboard-only person's pose (7,) and key presses from `start` towards `target` (see the docstring).
    `mode` (one-element list, 'fine' or 'coarse') is the window's coarse/fine state, kept across objects."""
    cur, tgt = pose_to_matrix(start), pose_to_matrix(target)
    presses = 0
    for _ in range(max_presses):
        e_t = tgt[:3, 3] - cur[:3, 3]
        if info.axis is not None:
            u, v = cur[:3, :3] @ info.axis, tgt[:3, :3] @ info.axis
            cross = np.cross(u, v)
            angle = np.arctan2(np.linalg.norm(cross), u @ v)
            e_r = cross / max(np.linalg.norm(cross), 1e-12) * angle
        else:
            e_r = rotvec(tgt[:3, :3] @ cur[:3, :3].T)  # table-frame rotation taking cur to target
        shown = np.concatenate([np.abs(e_t), np.abs(e_r) * info.radius])  # surface displacement, m
        shown[shown <= visible] = 0.0
        if not shown.any():
            break
        k = int(np.argmax(shown))
        kind, axis = divmod(k, 3)
        err = (e_t if kind == 0 else e_r)[axis]
        size = COARSE[kind] if abs(err) >= 0.75 * COARSE[kind] else FINE[kind]
        if abs(err) <= size / 2:  # a press would not reduce the error
            break
        want = "coarse" if size == COARSE[kind] else "fine"
        if mode[0] != want:
            mode[0] = want
            presses += 1
        delta = np.sign(err) * size
        if kind == 0:
            cur[axis, 3] += delta
        else:
            vec = np.zeros(3)
            vec[axis] = delta
            centre = cur[:3, 3].copy()  # rotate about the object centre (the mesh frame origin: centre of mass)
            cur[:3, :3] = rotvec_to_matrix(vec) @ cur[:3, :3]
            cur[:3, 3] = centre
        presses += 1
    return matrix_to_pose(cur), presses


def annotate_with_keyboard(truth: np.ndarray, infos: list[ObjectInfo], visible: float) -> dict:
    """Keyboard-only: poses (T+1, N, 7) and key presses (T+1, N) of the nudging oracle (see the docstring)."""
    steps, n = truth.shape[:2]
    poses = np.zeros_like(truth)
    presses = np.zeros((steps, n), dtype=np.int64)
    mode = ["fine"]
    for t in range(steps):
        for obj in range(n):
            start = spawn_pose(truth[0, obj]) if t == 0 else poses[t - 1, obj]
            poses[t, obj], presses[t, obj] = keyboard_annotate(start, truth[t, obj], infos[obj], visible, mode)
    return {"poses": poses, "presses": presses, "keys": int(presses.sum()) + steps - 1}


def spawn_pose(true_pose: np.ndarray) -> np.ndarray:
    """Where the mesh appears before anyone moves it: upright at the workspace centre, at its true height."""
    return np.array([*WORKSPACE_SPAWN, true_pose[2], 0.0, 0.0, 0.0, 1.0])


def annotate_with_keys_and_snap(capture_dir: Path, work: Path, infos: list[ObjectInfo], truth: np.ndarray,
                                rough: float, visible: float, tries: int) -> dict:
    """Keyboard + snap: the annotator (Session) without picks. Step 0: the keyboard oracle nudges each object from
    its spawn pose until no misalignment over `rough` m shows, then snaps (Space). Steps 1..T: N (carry forward,
    snap what moved); an object the window shows as wrong (`looks_wrong`) is nudged from its current pose (to
    `rough`, then on later tries to `visible`) and snapped again, at most `tries` times."""
    from dsr_bench.annotator.session import Session

    session = Session.open(capture_dir, work_dir=work)
    mode, keys = ["fine"], 0

    def nudge_and_snap(obj: int, step: int, start: np.ndarray, threshold: float) -> int:
        pose, presses = keyboard_annotate(start, truth[step, obj], infos[obj], threshold, mode)
        session.place(obj, pose_to_matrix(pose))  # where the person's key presses moved the mesh
        session.snap(obj)
        return presses + 1  # + Space

    start_time = time.perf_counter()
    for step in range(session.num_steps + 1):
        if step == 0:
            for obj in range(session.num_objects):
                keys += nudge_and_snap(obj, 0, spawn_pose(truth[0, obj]), rough)
        else:
            session.go_to(step)
            keys += 1  # N
        for obj in range(session.num_objects):
            for attempt in range(tries):
                if not looks_wrong(session, obj):
                    break
                keys += nudge_and_snap(obj, step, session.poses()[obj], rough if attempt == 0 else visible)
    seconds = time.perf_counter() - start_time
    poses = np.stack([session.poses(s) for s in range(session.num_steps + 1)])
    return {"poses": poses, "actions": session.action_counts, "keys": keys, "clicks": 0, "seconds": seconds}


# --- the benchmark ---------------------------------------------------------------------------------------------------


def ensure_captures(args) -> list[Path]:
    from dsr_bench.cli import main

    rc = main(["generate-captures", "--out", str(args.captures), "-n", str(args.num), "--steps", str(args.steps),
               "--objects-per-scene", str(args.objects_per_scene), "--seed", str(args.seed), "--objects",
               args.objects, "--noise", args.noise])
    if rc != 0:
        raise SystemExit(rc)
    from dsr_bench.dataset.splits import sequence_name

    return [args.captures / sequence_name(i) for i in range(args.num)]


def summarise(errors: list[dict]) -> dict[str, float]:
    keys = ("translation_mm", "rotation_deg", "rotation_raw_deg", "add", "add_s", "gross")
    out = {f"mean_{k}": float(np.mean([e[k] for e in errors])) for k in keys}
    out["median_translation_mm"] = float(np.median([e["translation_mm"] for e in errors]))
    out["p90_translation_mm"] = float(np.percentile([e["translation_mm"] for e in errors], 90))
    out["median_rotation_deg"] = float(np.median([e["rotation_deg"] for e in errors]))
    return out


METHODS = ("annotator", "keyboard", "keyboard+snap", "floor")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--captures", type=Path, default=Path("captures/bench"), help="capture directory")
    parser.add_argument("-n", "--num", type=int, default=5, help="captures")
    parser.add_argument("--steps", type=int, default=10, help="pushes per capture")
    parser.add_argument("--objects-per-scene", type=int, default=4)
    parser.add_argument("--objects", default="procedural")
    parser.add_argument("--noise", default="realistic")
    parser.add_argument("--seed", type=int, default=0, help="captures' base seed; also seeds the simulated clicks")
    parser.add_argument("--click-noise-mm", type=float, default=3.0, help="RMS 3D noise of a cloud-side click")
    parser.add_argument("--mesh-click-px", type=float, default=10.0,
                        help=f"RMS noise (pixels of a {MESH_VIEW_PIXELS}-pixel view of the mesh) of a mesh-side click")
    parser.add_argument("--tries", type=int, default=2, help="fixes per object and step the person tries at most")
    parser.add_argument("--rough-mm", type=float, default=5.0,
                        help="keyboard + snap: the person snaps once no misalignment over this shows")
    parser.add_argument("--visible-mm", type=float, default=2.0, help="smallest misalignment a keyboard user sees")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures as JSON here")
    return parser.parse_args()


def run_capture(args, path: Path, index: int, tmp: Path) -> dict:
    """Every method on one capture: a row of errors, summaries and effort."""
    from dsr_bench.dataset.capture import load_capture
    from dsr_bench.generators.capture import calibration_error

    cap = load_capture(path)
    truth = cap.truth_poses()
    infos = [ObjectInfo(*cap.mesh(k)) for k in range(cap.num_objects)]
    meshes = [MeshClicks(*cap.mesh(k), infos[k].diameter, args.mesh_click_px) for k in range(cap.num_objects)]
    rng = np.random.default_rng([args.seed, index])
    runs = {"annotator": annotate_with_session(path, tmp / f"{cap.name}-picks", infos, meshes, truth, rng,
                                               args.click_noise_mm / 1000, args.tries),
            "keyboard": annotate_with_keyboard(truth, infos, args.visible_mm / 1000),
            "keyboard+snap": annotate_with_keys_and_snap(path, tmp / f"{cap.name}-keys", infos, truth,
                                                         args.rough_mm / 1000, args.visible_mm / 1000, args.tries),
            "floor": {"poses": snap_from_truth(cap, truth), "keys": 0, "clicks": 0}}
    per_step_obj = cap.num_observations * cap.num_objects
    row = {"capture": cap.name, "objects": cap.num_objects, "steps": cap.num_observations,
           "categories": [o.identity.get("category", "?") for o in cap.objects],
           "symmetric": [info.axis is not None for info in infos],
           "calibration_error": {n: dict(zip(("translation_mm", "rotation_deg"), (1000 * a, b)))
                                 for n, (a, b) in ((n, calibration_error(c, cap.truth_calibration()[n]))
                                                   for n, c in cap.cameras.items())}, "errors": {}}
    for method, run in runs.items():
        errs = [pose_errors(run["poses"][t, k], truth[t, k], infos[k]) | {"step": t, "object": k}
                for t in range(cap.num_observations) for k in range(cap.num_objects)]
        row["errors"][method] = errs
        effort = {"clicks": int(run.get("clicks", 0)), "keys": int(run.get("keys", 0))}
        effort["per_object_step"] = (effort["clicks"] + effort["keys"]) / per_step_obj
        row[method] = summarise(errs) | effort | {k: run[k] for k in ("actions", "repicks", "seconds") if k in run}
    a, k, ks = row["annotator"], row["keyboard"], row["keyboard+snap"]
    print(f"{cap.name}: annotator {a['mean_translation_mm']:.2f} mm {a['mean_rotation_deg']:.2f} deg "
          f"({a['clicks']} clicks, {a['keys']} keys, {a['repicks']} re-picks); keyboard {k['mean_translation_mm']:.2f} "
          f"mm ({k['keys']} keys); keyboard+snap {ks['mean_translation_mm']:.2f} mm ({ks['keys']} keys)",
          file=sys.stderr)
    return row


def print_table(args, rows: list[dict], overall: dict) -> None:
    """The per-capture and overall table."""
    header = (f"{'capture':<10} {'method':<14} {'trans mm':>9} {'rot deg':>8} {'raw rot':>8} {'ADD(-S)/d':>10} "
              f"{'ADD-S/d':>8} {'gross':>6} {'clicks':>7} {'keys':>7} {'/obj/step':>10}")
    print(f"bench_annotate: {len(rows)} captures x {args.steps} pushes ({args.objects}, {args.objects_per_scene} "
          f"objects, noise {args.noise}, seed {args.seed}); clicks: cloud side {args.click_noise_mm} mm RMS, mesh side "
          f"{args.mesh_click_px} px RMS of a {MESH_VIEW_PIXELS} px view; keyboard visibility {args.visible_mm} mm, "
          f"keyboard+snap snaps at {args.rough_mm} mm; {args.tries} tries per fix; means over objects and steps "
          "(clicks and keys: per sequence)")
    print(header)
    print("-" * len(header))
    for r in rows + [{"capture": "all", **overall}]:
        for method in METHODS:
            s = r[method]
            print(f"{r['capture']:<10} {method:<14} {s['mean_translation_mm']:>9.2f} {s['mean_rotation_deg']:>8.2f} "
                  f"{s['mean_rotation_raw_deg']:>8.2f} {s['mean_add']:>10.3f} {s['mean_add_s']:>8.3f} "
                  f"{s['mean_gross']:>6.1%} {s['clicks']:>7.1f} {s['keys']:>7.1f} {s['per_object_step']:>10.2f}")


def main() -> None:
    args = parse_args()
    paths = ensure_captures(args)
    with tempfile.TemporaryDirectory(prefix="bench_annotate_") as tmp:
        rows = [run_capture(args, path, i, Path(tmp)) for i, path in enumerate(paths)]
    n_obj_steps = sum(r["objects"] * r["steps"] for r in rows)
    overall = {}
    for method in METHODS:
        errs = [e for r in rows for e in r["errors"][method]]
        clicks, keys = (sum(r[method][x] for r in rows) for x in ("clicks", "keys"))
        overall[method] = summarise(errs) | {"clicks": clicks / len(rows), "keys": keys / len(rows),
                                             "per_object_step": (clicks + keys) / n_obj_steps}
        good = [e for e in errs if not e["gross"]]
        overall[method] |= {"gross_count": len(errs) - len(good), "object_steps": len(errs)}
        if good:
            overall[method] |= {
                "mean_translation_mm_without_gross": float(np.mean([e["translation_mm"] for e in good])),
                "mean_rotation_deg_without_gross": float(np.mean([e["rotation_deg"] for e in good]))}
    overall["annotator"]["repicks"] = sum(r["annotator"]["repicks"] for r in rows) / len(rows)
    for method in ("annotator", "keyboard+snap"):  # Session actions (pick, snap, step, ...), as the issue counts them
        total = sum(sum(r[method]["actions"].values()) for r in rows)
        overall[method] |= {"actions_per_sequence": total / len(rows), "actions_per_object_step": total / n_obj_steps}
    print_table(args, rows, overall)
    for method in METHODS:
        o = overall[method]
        if "mean_translation_mm_without_gross" in o:
            print(f"{method}: {o['gross_count']} gross errors of {o['object_steps']} object-steps; without them "
                  f"{o['mean_translation_mm_without_gross']:.2f} mm, {o['mean_rotation_deg_without_gross']:.2f} deg")
    a = overall["annotator"]
    ok = [a["mean_translation_mm"] < 3.0, a["mean_rotation_deg"] < 2.0, a["actions_per_object_step"] <= 2.0]
    print(f"annotator: {a['repicks']:.1f} re-picks and {a['actions_per_sequence']:.1f} Session actions (pick, snap, "
          f"step, ...) per sequence, {a['actions_per_object_step']:.2f} per object per step; issue target: mean "
          f"translation < 3 mm {'met' if ok[0] else 'NOT met'}, mean rotation < 2 deg {'met' if ok[1] else 'NOT met'}, "
          f"<= 2 actions per object per step {'met' if ok[2] else 'NOT met'}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "overall": overall,
                                         "captures": rows}, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
