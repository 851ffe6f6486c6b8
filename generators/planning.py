"""The planning track's simulator side (`dsr_bench.planning` has the rest, and never imports this module):
making planning tasks, the pybullet `SimEnvironment` plans run in (and the oracle's true next states), and running
plans (`plan_tasks`). The commands `dsr-bench generate-plan-tasks` and `dsr-bench plan` that call them live with the
generator's other commands in `generators.cli`.

A task: a scene generated as a sequence (`generators.episode.generate_episode`, the same seeding, so a task
is a pure function of its seed: bit for bit on any machine) with PLAN_STEPS pushes of the heuristic policy;
its first state is the start, its last the target. A plan restores the start in a fresh pybullet world from the
task file (the objects' solids and poses), so it never depends on the generator's world.
"""

from __future__ import annotations

import math
import os
import shlex
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from dsr_bench import __version__
from dsr_bench.atomic import check_writable, write_text
from dsr_bench.errors import UserError
from dsr_bench.parallel import run_in_order


# --- tasks ---------------------------------------------------------------------------------------------
class _Recording:
    """An object set that remembers the objects of its last `sample` (those of the accepted scene)."""

    def __init__(self, base):
        self.base, self.name, self.last = base, base.name, None

    def sample(self, rng, count):
        self.last = self.base.sample(rng, count)
        return self.last


def make_task(object_set, seed: int, name: str, pushes: int, objects: str, objects_per_scene: int,
              policy: str = "heuristic") -> tuple[dict[str, np.ndarray], dict]:
    """A task's arrays and attributes (`dsr_bench.planning.tasks`) from a seed: the scene and pushes of
    `generate_episode`, its first state the start and its last the target."""
    from dsr_bench.generators.episode import EpisodeConfig, generate_episode

    recording = _Recording(object_set)
    config = EpisodeConfig(objects=objects, steps=pushes, objects_per_scene=objects_per_scene, policy=policy)
    ep = generate_episode(config, recording, seed, name)
    a = ep.arrays
    arrays = {"start/object_poses": a["object_poses"][0], "start/mask_3d": a["mask_3d"][0],
              "target/object_poses": a["object_poses"][-1], "target/mask_3d": a["mask_3d"][-1],
              "reference/action": a["action"], "start/tsdf": a["tsdf"][0], "start/heightmap": a["heightmap"][0],
              "start/color": a["cameras/front/color"][0], "target/color": a["cameras/front/color"][-1]}
    for i, spec in enumerate(recording.last):
        for j, part in enumerate(spec.parts):
            arrays[f"objects/{i}/part_{j}/vertices"] = np.asarray(part.vertices, np.float64)
            arrays[f"objects/{i}/part_{j}/faces"] = np.asarray(part.faces, np.int64)
    attrs = {"name": name, "seed": int(seed), "num_objects": len(recording.last), "pushes": pushes,
             "objects": ep.attrs["objects"], "toolkit_version": __version__,
             "generator_args": {**config.as_attrs(), "scene_attempts": ep.scene_attempts}}
    return arrays, attrs


_WORKER: dict = {}


def _task_job(job: tuple) -> str:
    from dsr_bench.planning.tasks import write_task
    from dsr_bench.generators.objects import get_object_set

    out, name, seed, spec = job
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if _WORKER.get("set_name") != spec["objects"]:
        _WORKER["set"], _WORKER["set_name"] = get_object_set(spec["objects"]), spec["objects"]
    arrays, attrs = make_task(_WORKER["set"], seed, name, spec["pushes"], spec["objects"], spec["objects_per_scene"],
                              spec["policy"])
    attrs["task_set"], attrs["index"] = spec["name"], int(name.split("_")[-1])
    write_task(Path(out) / f"{name}.h5", arrays, attrs)
    return name


def generate_tasks(task_set: str, out: Path, workers: int = 1, num_tasks: int | None = None,
                   progress=None) -> dict:
    """Write the tasks of a named set into `out` (task_0000.h5, ...; existing complete tasks of the same seed are
    kept) and its manifest (tasks.json); return the manifest. `num_tasks`: only the first ones (a prefix)."""
    from dsr_bench.dataset.splits import sequence_seed
    from dsr_bench.planning.tasks import build_manifest, get_task_set, read_task, task_name, write_manifest

    spec = get_task_set(task_set)
    count = spec.num_tasks if num_tasks is None else num_tasks
    if not 1 <= count <= spec.num_tasks:
        raise UserError(f"--num-tasks {count}: must be 1..{spec.num_tasks} for {task_set}")
    check_writable(out)
    out.mkdir(parents=True, exist_ok=True)
    names = [task_name(i) for i in range(count)]
    jobs = []
    for i, name in enumerate(names):
        path, seed = out / f"{name}.h5", sequence_seed(spec.base_seed, i)
        if path.exists():
            if read_task(path).seed != seed:
                raise UserError(f"{path} is a task of another set or seed; use another --out or delete it")
            if progress:
                progress()
            continue
        jobs.append((str(out), name, seed, spec.__dict__))
    run_in_order(_task_job, jobs, max(1, workers), (lambda done, total: progress()) if progress else None)
    manifest = build_manifest(out, task_set, names)
    write_manifest(out, manifest)
    return manifest


# --- the world of a plan ---------------------------------------------------------------------------------
def task_objects(task) -> list:
    """ObjectSpec-like objects (parts, colour, mass) of a task, for `PushWorld` and `SceneRenderer`."""
    from dsr_bench.generators.objects.spec import Part

    return [SimpleNamespace(parts=tuple(Part(v, f) for v, f in parts), color=tuple(ident["color"]),
                            mass=float(ident["mass"]), is_large=bool(ident.get("is_large", False)))
            for parts, ident in zip(task.parts, task.objects)]


class SimEnvironment:
    """A task's world in pybullet (`generators.physics.PushWorld`) observed by `dsr_bench.render.SceneRenderer`:
    `reset(task)` builds it at the start poses, `step(action)` pushes and observes, `current_mask()` and
    `simulate(actions)` are the oracle's callbacks (true next states, the world restored after each)."""

    def __init__(self):
        self.world = self.renderer = None

    def close(self) -> None:
        if self.world is not None:
            self.world.close()
            self.world = None

    def reset(self, task):
        from dsr_bench.generators.physics import PushWorld
        from dsr_bench.render import create_renderer

        self.close()
        objects = task_objects(task)
        self.world = PushWorld(objects, poses=task.arrays["start/object_poses"])
        self.renderer = create_renderer(objects)
        return self._observe()

    def _observe(self):
        from dsr_bench.planning.runner import WorldState

        poses = self.world.poses()
        obs = self.renderer.observe(poses)
        return WorldState(tsdf=obs.tsdf, mask_3d=obs.mask_3d, object_poses=poses, color=obs.images["front"].color)

    def _push(self, action) -> None:
        from dsr_bench.geometry import pixel_to_world

        d, row, col = (int(x) for x in action)
        self.world.push(pixel_to_world(np.array([row, col])), d)

    def step(self, action):
        """Execute the push and observe. A push starts from a world built afresh at the objects' rest poses
        (`PushWorld.push`), as in the generator and in `simulate`: the executed push is the one that made the task's
        target when it is the reference's, and the oracle's prediction of it, bit for bit."""
        self._push(action)
        return self._observe()

    def current_mask(self) -> np.ndarray:
        return self.renderer.amodal_mask(self.world.poses())

    def simulate(self, actions: np.ndarray) -> np.ndarray:
        """The true next amodal masks (A, Y, X, Z) of pushes (A, 3), each from the current rest poses; the world is
        put back at them afterwards."""
        rest = self.world.rest_poses.copy()
        out = []
        try:
            for action in actions:
                self.world.rest_poses = rest.copy()
                self._push(action)
                out.append(self.renderer.amodal_mask(self.world.poses()))
        finally:
            self.world.restart(rest)
        return np.stack(out)


def replay_plan(task, actions: np.ndarray) -> list:
    """The states (`dsr_bench.planning.runner.WorldState`, PLAN_STEPS + 1) that pushes (S, 3) (d, row, col) give
    from `task`'s start in a fresh world: what `dsr-bench plan` (resuming) and `dsr_bench.planning.verify` compare a
    plan file's stored states with (registered as the `plan-replay` simulator, `dsr_bench.planning.replay`)."""
    env = SimEnvironment()
    try:
        return [env.reset(task)] + [env.step(action) for action in actions]
    finally:
        env.close()


# --- running plans ----------------------------------------------------------------------------------------
def _one_thread() -> None:
    """One thread per worker process (parallelism comes from --workers): torch's OpenMP threads spinning at their
    barriers on a loaded machine cost far more than they bring."""
    import sys

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


def _not_simulated(*args):
    raise RuntimeError("this planner only describes the run: its plans run in the workers' simulators")


def _planner(model: str, env: SimEnvironment, checkpoint: str | None, device: str, masks: str):
    from dsr_bench.planning.planners import make_planner

    if model == "oracle":
        return make_planner("oracle", (env.current_mask, env.simulate))
    key = (model, checkpoint, device, masks)
    if _WORKER.get("planner_key") != key:
        _WORKER["planner"] = make_planner(model, checkpoint=Path(checkpoint) if checkpoint else None, device=device,
                                          masks=masks)
        _WORKER["planner_key"] = key
    return _WORKER["planner"]


def _plan_job(job: tuple) -> tuple[str, dict, str | None]:
    """(name, scores, a warning line or None) of one task: an existing plan file of the same run is replayed and
    rescored (`dsr_bench.planning.verify.plan_scores`), anything else is planned (again)."""
    from dsr_bench.planning.plans import plan_arrays, write_plan
    from dsr_bench.planning.runner import run_plan
    from dsr_bench.planning.results import score_plan
    from dsr_bench.planning.tasks import read_task

    task_path, out, model, checkpoint, device, candidates, seed, batch, name, ground_truth, margin, masks = job
    task = read_task(task_path)  # the digests recomputed from its arrays
    if task.name != name or task.ground_truth_sha256 != ground_truth:
        raise UserError(f"{task_path} changed after it was verified (another process writing the tasks?); run again")
    done, note = _finished(Path(out) / f"{name}.h5", task, model, checkpoint, candidates, seed, margin, masks)
    if done is not None:
        return name, done, None
    _one_thread()
    env = SimEnvironment()
    try:
        planner = _planner(model, env, checkpoint, device, masks)
        start = time.perf_counter()
        record = run_plan(task, planner, env, candidates, seed=seed, batch=batch, margin=margin, clear=_clear())
        seconds = time.perf_counter() - start
    finally:
        env.close()
    arrays = plan_arrays(task, record)
    scores = score_plan(arrays["states/mask_3d"][-1], arrays["states/mask_3d"][0], task.target_mask, task.num_objects)
    scores["seconds"] = seconds
    attrs = {"task": task.name, "task_file": task.path.name, "task_ground_truth_sha256": task.ground_truth_sha256,
             "model": model, "checkpoint": str(checkpoint or ""), "planner": planner.name,
             "description": planner.description, "candidates": candidates, "seed": seed, "lambda": _lambda(),
             "margin": margin, "clear": _clear(), "masks": masks, **scores}
    write_plan(Path(out) / f"{name}.h5", arrays, attrs)
    return name, scores, note


def _steps() -> int:
    from dsr_bench.planning.protocol import PLAN_STEPS

    return PLAN_STEPS


def _finished(path: Path, task, model: str, checkpoint: str | None, candidates: int,
              seed: int, margin: float, masks: str) -> tuple[dict | None, str | None]:
    """(scores, None) of an existing plan file of this task made with the same planner, checkpoint, candidates, seed,
    lambda, margin, clear candidates and masks (a rerun resumes): its executed pushes replayed from the verified
    task's start and every stored state compared with the replay (`dsr_bench.planning.replay`), the scores
    recomputed from the replayed final state, never read from its attributes. (None, None) when there is no such
    file or it is another run's (planned again, the file replaced); (None, a warning line) when the file is not a
    valid plan of its task or not its replay (planned again too)."""
    from dsr_bench.planning.plans import read_plan_attrs
    from dsr_bench.planning.verify import PlanMismatch, plan_scores

    if not path.is_file():
        return None, None
    same = {"model": model, "checkpoint": str(checkpoint or ""), "candidates": candidates, "seed": seed,
            "lambda": _lambda(), "margin": margin, "clear": _clear(), "masks": masks}
    try:
        attrs = read_plan_attrs(path)
    except UserError as exc:
        return None, f"{' '.join(str(exc).split('; ')[:1])}: planned again"
    made = {**attrs, "model": attrs.get("model", attrs.get("planner")), "checkpoint": attrs.get("checkpoint", "")}
    if any(made.get(k) != v for k, v in same.items()):
        return None, None  # another run's plan (other options): replaced, as always
    try:
        return plan_scores(path, task, task.ground_truth_sha256, replay_plan)[0], None
    except PlanMismatch as exc:
        return None, f"{exc.problem}: planned again"


def _lambda() -> float:
    from dsr_bench.planning.protocol import COST_LAMBDA

    return COST_LAMBDA


def _clear() -> int:
    from dsr_bench.planning.protocol import CLEAR_CANDIDATES

    return CLEAR_CANDIDATES


def plan_tasks(model: str, tasks: str, out: Path, candidates: int, workers: int = 1, seed: int = 0,
               checkpoint: Path | None = None, device: str = "cpu", num_tasks: int | None = None,
               batch: int | None = None, progress=None, warn=None, margin: float | None = None,
               masks: str = "model") -> dict:
    """Run a planner on a task directory (or a named set's data/<name>), write one plan file per task and
    OUT/results.json; return the results (`dsr_bench.planning.results.build_results`). The tasks are verified first
    (`dsr_bench.planning.verify.verify_tasks`: a task that differs from the pin is one line to `warn` and makes
    the results unpinned). Plan files already in `out` made for the same task with the same planner, candidates
    and seed are kept, replayed and rescored (a rerun resumes); an invalid one (or one its replay contradicts) is
    planned again with a line to `warn`. `margin`: what an object push's predicted cost must beat the best clear
    push's by (`dsr_bench.planning.runner.choose`; default the planner's own: PLAN_MARGIN for a learned model, 0 for
    the oracle). `masks`: a learned planner's masks of the current state, its network's ("model") or the objects its
    TSDF shows ("observed", `dsr_bench.planning.observed`)."""
    import json

    from dsr_bench.planning.planners import make_planner, planner_members
    from dsr_bench.planning.protocol import DEFAULT_BATCH
    from dsr_bench.planning.results import build_results
    from dsr_bench.planning.verify import verify_tasks

    planner_members(model, checkpoint)  # a one-line error for a name that is not a planner, before anything runs
    if candidates < 1:
        raise UserError(f"--candidates {candidates}: must be at least 1")
    if workers < 1:
        raise UserError(f"--workers {workers}: must be at least 1")
    if margin is not None and not (math.isfinite(margin) and margin >= 0):
        raise UserError(f"--margin {margin}: must be a finite number >= 0 (cost units; the default "
                        "is the planner's own)")
    verified = verify_tasks(tasks)  # before anything is written
    warn = warn or (lambda line: None)
    for line in verified.warnings:
        warn(line)
    names = verified.names[: num_tasks] if num_tasks else verified.names
    _one_thread()
    describe = make_planner(model, (_not_simulated, _not_simulated), masks=masks) if model in ("random", "oracle") \
        else make_planner(model, checkpoint=checkpoint, device=device, masks=masks)  # fails fast on bad options
    if model not in ("random", "oracle"):  # in this process, the workers' planner (workers=1) is this one
        _WORKER["planner"] = describe
        _WORKER["planner_key"] = (model, str(checkpoint) if checkpoint else None, device, masks)
    margin = float(describe.margin if margin is None else margin)
    check_writable(out)
    out.mkdir(parents=True, exist_ok=True)
    batch = batch or DEFAULT_BATCH
    jobs = [(str(verified.path(name)), str(out), model, str(checkpoint) if checkpoint else None, device, candidates,
             seed, batch, name, verified.digests[name], margin, masks) for name in names]
    outcomes = run_in_order(_plan_job, jobs, workers, (lambda done, total: progress()) if progress else None)
    per_task = {}
    for name, scores, note in outcomes:
        per_task[name] = scores
        if note:
            warn(note)
    others = sorted(p.name for p in out.glob("*.h5") if p.stem not in per_task)
    if others:
        warn(f"{out} also holds {', '.join(others[:3])}{' ...' if len(others) > 3 else ''}, plans this run did not "
             "make: the directory is not one run's (`dsr_bench.planning.verify.recompute_results` refuses it); "
             "remove them")
    command = shlex.join(["dsr-bench", "plan", "--model", model, "--tasks", str(tasks), "--out", str(out),
                          "--candidates", str(candidates), "--seed", str(seed), "--margin", repr(margin)]
                         + (["--num-tasks", str(num_tasks)] if num_tasks else [])
                         + (["--checkpoint", str(checkpoint)] if checkpoint else [])
                         + (["--masks", masks] if masks != "model" else []))
    planner = {"name": describe.name, "description": describe.description}
    if getattr(describe, "weights", None):
        planner["weights"] = describe.weights
    if getattr(describe, "grid", None):
        planner["grid"] = [int(g) for g in describe.grid]
    parameters = {"candidates": candidates, "seed": seed, "lambda": _lambda(), "steps": _steps(), "margin": margin,
                  "clear": _clear(), "masks": masks,
                  "hardware": f"{os.cpu_count()} CPU cores", "workers": workers}
    # the checksum recomputed from the task files (tasks.json is never trusted); a prefix of a named set is partial
    out_results = build_results(per_task, planner, {"task_set": verified.task_set, "checksum": verified.checksum},
                                verified.expected, [out / f"{name}.h5" for name in per_task], command, parameters)
    write_text(out / "results.json", json.dumps(out_results, indent=1, sort_keys=True) + "\n")
    return out_results
