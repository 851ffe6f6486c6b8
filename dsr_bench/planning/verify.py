"""The planning track never trusts its files: task files are checked against the toolkit's pin, plan files are
replayed in the simulator from their task's start, and every score is recomputed from verified arrays
(docs/planning.md, "What is verified").

  verify_tasks       a task directory: every task file read (its digests recomputed from its arrays, never read
                     from its attributes; a named set's seed derived from the set, never read), compared with the pin
                     this toolkit ships for its task set (`task_pins.json`); the set's checksum recomputed from the
                     files, never read from tasks.json
  plan_scores        one plan file: it must belong to its task (name, task file, task digest, the task's start and
                     target states) and equal its replay (`dsr_bench.planning.replay`: every state, candidate, choice
                     and stored score), and its scores are recomputed from the replayed final state
  recompute_results  a `dsr-bench plan --out DIR` directory: the results JSON recomputed, in exactly the format of
                     `dsr_bench.planning.results.build_results`, so a caller compares it field by field with
                     DIR/results.json
  check_results      schema, types, ranges and consistency of a planning results dict, one short phrase per problem
  differences        the fields where two results dicts differ

Recomputed: method and planner name and description (from the plan files), task_set, split, task_checksum,
split_checksum, pinned, plans_checksum, coverage, parameters candidates/seed/lambda/steps/margin/clear/masks (from the
plan files), every per-task score and every metric but tasks_per_minute. Replayed: every state of every plan (the
simulator is deterministic bit for bit), its candidates (from the seeds and the planner's stored masks), the push it
chose (from its costs and margin) and that push's cost (from its stored prediction). Self-reported (read from
results.json or, for seconds, the plan files, and never ranked on): per-task seconds and tasks_per_minute (timing),
planner weights and grid, parameters hardware and workers, command and date; toolkit_version must be this toolkit's.
Not recomputed (the planner's network is not run again): the costs of the candidates not chosen and the planner's
masks.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from dsr_bench.constants import NUM_DIRECTIONS
from dsr_bench.errors import UserError
from dsr_bench.jsonfile import UnreadableJSON, read_json
from dsr_bench.parallel import as_finished
from dsr_bench.planning.planners import OraclePlanner, RandomPlanner
from dsr_bench.planning.replay import Replay

SCORE_KEYS = ("iou", "iou_identity", "iou_occupancy", "start_iou", "start_iou_identity", "start_iou_occupancy")
#: the plan attributes that say how a plan was made (one run's plans share them)
RUN_KEYS = ("model", "checkpoint", "planner", "description", "candidates", "seed", "lambda", "margin", "clear", "masks")
#: the arrays a plan file must hold (`dsr_bench.planning.plans`; states/color only when the world renders one)
PLAN_ARRAYS = ("states/tsdf", "states/mask_3d", "states/object_poses", "target/mask_3d", "target/object_poses",
               "actions", "candidates", "costs", "chosen", "clear", "cost_position_mse", "cost_iou", "planner_masks",
               "predicted")
#: the planners whose plans are a function of the task and the seeds alone: model -> (planner name, description)
FIXED_PLANNERS = {"random": (RandomPlanner.name, RandomPlanner.description),
                  "oracle": (OraclePlanner.name, OraclePlanner.description)}
TASK_NAME = re.compile(r"task_\d{4}")
_HEX64 = re.compile(r"[0-9a-f]{64}")


def _show(text) -> str:
    """An untrusted name or value for a one-line message: a number as it is, anything else printable ASCII (at most
    60 characters)."""
    if isinstance(text, (int, float, np.number)) and not isinstance(text, (bool, np.bool_)):
        return str(_plain(text))
    text = str(text)
    return text if TASK_NAME.fullmatch(text) else ascii(text[:60])


@dataclass(frozen=True)
class VerifiedTasks:
    """A task directory as verified: names sorted, ground-truth digests recomputed from the task files' arrays,
    the set's checksum over them, whether it is this toolkit's pin, one warning line per task that is not."""

    task_dir: Path
    task_set: str
    names: tuple[str, ...]
    digests: dict
    checksum: str
    pinned: bool
    expected: int
    warnings: tuple[str, ...]

    def path(self, name: str) -> Path:
        return self.task_dir / f"{name}.h5"


def verify_tasks(tasks: str | Path) -> VerifiedTasks:
    """Read every task of a task directory (`--tasks`: a directory or a task set's name) and verify it against the
    pin. A task whose recomputed digest differs from the pin (or that the pin lacks) gives one warning and makes
    the directory unpinned; a damaged file, a file that says it is another task, or a malformed tasks.json is a
    UserError (one line)."""
    from dsr_bench.dataset.digests import GROUND_TRUTH_KEY, split_checksum
    from dsr_bench.dataset.splits import sequence_seed
    from dsr_bench.planning.tasks import TASK_SETS, pinned_checksums, pinned_tasks, read_task, resolve_tasks

    task_dir, manifest = resolve_tasks(tasks)
    fix = f"regenerate the tasks with `dsr-bench generate-plan-tasks --out {task_dir}` into an empty directory"
    task_set, entries = manifest.get("task_set"), manifest["tasks"]
    if not isinstance(task_set, str) or not entries:
        raise UserError(f"{task_dir}/tasks.json names no task set or lists no tasks; {fix}")
    names = [e["name"] for e in entries]
    for e in entries:
        if not TASK_NAME.fullmatch(e["name"]) or e.get("file") != f"{e['name']}.h5":
            raise UserError(f"{task_dir}/tasks.json: entry {_show(e['name'])} is not task_NNNN with its file "
                            f"task_NNNN.h5; {fix}")
    if len(set(names)) != len(names):
        raise UserError(f"{task_dir}/tasks.json lists a task twice; {fix}")
    pins = pinned_tasks(task_set)
    spec = TASK_SETS.get(task_set)
    listed = {e["name"]: e for e in entries}
    digests, warnings = {}, []
    for name in sorted(names):
        task = read_task(task_dir / f"{name}.h5")  # recomputes the digests from the arrays (a mismatch: UserError)
        if task.name != name:
            raise UserError(f"{task.path}: its name attribute says {_show(task.name)}, tasks.json lists it as {name} "
                            f"(an edited or misplaced file); {fix}")
        digests[name] = task.ground_truth_sha256
        # the seed seeds the candidates (`runner.run_plan`) but is no array: a named set's is derived, never believed
        if spec is not None and task.seed != sequence_seed(spec.base_seed, int(name.split("_")[1])):
            raise UserError(f"{task.path}: its seed attribute {_show(task.seed)} is not the seed of {task_set} {name} "
                            f"(an edited file); {fix}")
        if pins is not None and digests[name] != pins.get(name):
            why = "is not in" if name not in pins else "differs from"
            warnings.append(f"{task.path}: its ground truth (recomputed from its arrays) {why} the pin of "
                            f"{task_set} {name}: results on {task_dir} are not pinned (\"pinned\": false); delete "
                            f"it and run `dsr-bench generate-plan-tasks --tasks {task_set} --out {task_dir}`")
        elif pins is None and digests[name] != listed[name].get(GROUND_TRUTH_KEY):
            warnings.append(f"{task.path}: its ground truth (recomputed from its arrays) differs from its tasks.json "
                            "entry; scored as the file is")
    checksum = split_checksum(digests.items())
    pin = pinned_checksums().get(task_set)
    return VerifiedTasks(task_dir=task_dir, task_set=task_set, names=tuple(sorted(names)), digests=digests,
                         checksum=checksum, pinned=pin is not None and pin == checksum,
                         expected=spec.num_tasks if spec else len(names), warnings=tuple(warnings))


class PlanMismatch(UserError):
    """A plan file that is not a valid plan of its task: `problem` is the message without the fix (what a rerun of
    `dsr-bench plan`, which plans the task again, prints)."""

    def __init__(self, path: Path, problem: str):
        self.problem = f"{path}: {problem}"
        super().__init__(f"{self.problem}; rerun `dsr-bench plan` with the same options over its directory (it plans "
                         "such a task again)")


def plan_scores(path: str | Path, task, digest: str, replay: Replay, same: Mapping | None = None) -> tuple[dict, dict]:
    """The scores of a plan file (`dsr_bench.planning.results.score_plan` keys and `seconds`), recomputed from the
    final state of its replay and `task`'s start and target (a task read by `read_task`, `digest` its verified
    ground-truth digest), and the file's attributes. UserError (one line) unless the file is a plan of `task`
    (its name, task file, task digest, the task's start and target states), of the track's shapes, made, for each
    key of `same`, with that value (model, candidates, seed, ...), and equal to its replay in everything the
    replay determines (`replay`: the simulator's, `dsr_bench.planning.replay`); `PlanMismatch` for a plan file
    that is not. The stored scores are never taken for the recomputed ones."""
    from dsr_bench.constants import GRID_SHAPE
    from dsr_bench.planning.plans import read_plan
    from dsr_bench.planning.protocol import PLAN_STEPS
    from dsr_bench.planning.replay import replay_problem
    from dsr_bench.planning.results import score_plan

    path = Path(path)
    try:
        plan, attrs = read_plan(path)
    except UserError as exc:
        raise PlanMismatch(path, str(exc).split(": ", 1)[-1].split("; ", 1)[0]) from None
    except Exception as exc:  # noqa: BLE001 - whatever h5py raises on a damaged file
        raise PlanMismatch(path, f"unreadable plan file ({type(exc).__name__})") from None
    if path.stem != task.name or attrs.get("task") != task.name or attrs.get("task_file") != f"{task.name}.h5":
        raise PlanMismatch(path, f"a plan of {_show(attrs.get('task'))}, not of the task it is named for "
                                 f"({_show(path.stem)})")
    if attrs.get("task_ground_truth_sha256") != digest:
        raise PlanMismatch(path, f"made for another version of {task.name} (its task digest is not the task file's)")
    for key, value in (same or {}).items():
        if attrs.get(key) != value:
            raise PlanMismatch(path, f"made with {key} {_show(attrs.get(key))}, not {_show(value)}")
    missing = [name for name in PLAN_ARRAYS if name not in plan]
    if missing:
        raise PlanMismatch(path, f"a plan file without {missing[0]}")
    states, target, actions = plan["states/mask_3d"], plan["target/mask_3d"], plan["actions"]
    n = task.num_objects
    if states.shape != (PLAN_STEPS + 1,) + GRID_SHAPE or states.dtype != np.uint8 or int(states.max()) > n:
        raise PlanMismatch(path, f"states/mask_3d is not {PLAN_STEPS + 1} states of object ids 0..{n} on the grid")
    if actions.shape != (PLAN_STEPS, 3) or not np.issubdtype(actions.dtype, np.integer):
        raise PlanMismatch(path, f"actions is not {PLAN_STEPS} pushes (d, row, col)")
    if not np.array_equal(states[0], task.start_mask) or not np.array_equal(target, task.target_mask) or \
            not _equal(plan["target/object_poses"], task.arrays["target/object_poses"]):
        raise PlanMismatch(path, f"its start or target state is not {task.name}'s")
    if not all(_number(_plain(attrs.get(k))) for k in ("seed", "candidates", "clear", "margin", "lambda")) or \
            not all(float(attrs[k]).is_integer() for k in ("seed", "candidates", "clear")):
        raise PlanMismatch(path, "its seed, candidates, clear, margin or lambda attribute is not a number")
    seconds = attrs.get("seconds")
    if isinstance(seconds, (bool, np.bool_)) or not isinstance(seconds, (int, float, np.number)) or \
            not math.isfinite(float(seconds)) or float(seconds) < 0:
        raise PlanMismatch(path, "its seconds attribute is not a time")
    if np.any((actions[:, 0] < 0) | (actions[:, 0] >= NUM_DIRECTIONS)) or \
            np.any((actions[:, 1:] < 0) | (actions[:, 1:] >= np.array(GRID_SHAPE[:2]))):
        raise PlanMismatch(path, "actions is not a list of (direction 0..7, row, col) pushes on the grid")
    replayed = replay(task, actions)
    scores = score_plan(replayed[-1].mask_3d, task.start_mask, task.target_mask, n)
    problem = replay_problem(plan, attrs, task, replayed, scores)
    if problem:
        raise PlanMismatch(path, problem)
    scores["seconds"] = float(seconds)
    return scores, attrs


def _equal(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and bool(np.array_equal(a, b))


def _read_results_json(plans_dir: Path) -> dict:
    path = plans_dir / "results.json"
    fix = f"pass the --out directory of a finished `dsr-bench plan` run (rerun `dsr-bench plan ... --out {plans_dir}`)"
    if not plans_dir.is_dir():
        raise UserError(f"plans directory not found: {plans_dir}; {fix}")
    if not path.is_file():
        raise UserError(f"{plans_dir} has no results.json; {fix}")
    try:
        r = read_json(path)
    except UnreadableJSON as exc:
        raise UserError(f"{path}: unreadable results file ({exc}); {fix}") from None
    from dsr_bench.planning.results import RESULTS_FORMAT

    if not isinstance(r, dict) or r.get("format") != RESULTS_FORMAT or not isinstance(r.get("per_task"), dict):
        raise UserError(f"{path}: not a dsr-bench planning results file with per_task; {fix}")
    return r


def _replayed_scores(job: tuple[str, str, str]) -> tuple[str | None, dict]:
    """(None, scores) of one plan file replayed against its verified task (`plan_scores`), or (the one-line
    problem, {}): a worker's job of `recompute_results`."""
    from dsr_bench.planning.replay import load_simulator
    from dsr_bench.planning.tasks import read_task

    plan_path, task_path, digest = job
    try:
        task = read_task(task_path)
        if task.ground_truth_sha256 != digest:
            raise UserError(f"{task.path} changed while it was being verified; run again")
        return None, plan_scores(plan_path, task, digest, load_simulator())[0]
    except UserError as exc:
        return str(exc), {}


def recompute_results(plans_dir: Path, tasks: str | Path | None = None, workers: int = 1,
                      progress: Callable[[int, int], None] | None = None) -> dict:
    """The results of a `dsr-bench plan --out plans_dir` run recomputed from its plan files, each replayed in the
    simulator (`dsr_bench.planning.replay`; in `workers` processes, `progress(done, total)` per plan), and the
    verified tasks (`tasks`: a task directory or a task set's name, as `plan --tasks`; default: the task set
    results.json names, as data/<name>), in the format of `dsr_bench.planning.results.build_results`. results.json
    is read only for the self-reported fields (module doc). UserError (one line): an unreadable file, a plan file
    that is not a plan of its task or not its replay, a plan missing from or extra to results.json's per_task,
    plans that are not a prefix of the tasks (what --num-tasks plans) or not of one run."""
    from dsr_bench.planning.plans import read_plan_attrs
    from dsr_bench.planning.protocol import PLAN_STEPS
    from dsr_bench.planning.replay import load_simulator
    from dsr_bench.planning.results import build_results
    from dsr_bench.planning.tasks import TASK_SETS

    plans_dir = Path(plans_dir)
    submitted = _read_results_json(plans_dir)
    fix = f"rerun `dsr-bench plan` with the same options into {plans_dir}"
    if tasks is None:
        if submitted.get("task_set") not in TASK_SETS:
            raise UserError(f"{plans_dir}/results.json names no known task set; pass the task directory (tasks=)")
        tasks = submitted["task_set"]
    verified = verify_tasks(tasks)
    planned = sorted(p.stem for p in plans_dir.glob("*.h5"))
    for name in planned:
        if name not in verified.digests:
            raise UserError(f"{plans_dir}: {_show(name)}.h5 is not a task of {verified.task_dir} (an extra plan); "
                            f"remove it or {fix}")
    listed = sorted(str(k) for k in submitted["per_task"])
    for name in listed:
        if name not in planned:
            raise UserError(f"{plans_dir}: results.json scores {_show(name)} but its plan file is missing; {fix}")
    for name in planned:
        if name not in listed:
            raise UserError(f"{plans_dir}: {name}.h5 is not in results.json's per_task (an extra plan); remove it or "
                            f"{fix}")
    if not planned:
        raise UserError(f"{plans_dir}: no plan files; {fix}")
    if tuple(planned) != verified.names[: len(planned)]:
        missing = next(n for n in verified.names if n not in planned)
        raise UserError(f"{plans_dir}: plans of {len(planned)} tasks but not of {missing}: a partial run is a "
                        f"prefix of the tasks (--num-tasks); {fix}")
    load_simulator()  # a one-line error before any work when the simulator is missing
    run: dict[str, Any] | None = None
    for name in planned:  # one run's plans (their attributes alone, before the replays)
        try:
            attrs = read_plan_attrs(plans_dir / f"{name}.h5")
        except UserError as exc:
            raise PlanMismatch(plans_dir / f"{name}.h5", str(exc).split(": ", 1)[-1].split("; ", 1)[0]) from None
        this = {k: attrs.get(k) for k in RUN_KEYS}
        if run is None:
            run, first = this, name
        elif this != run:
            key = next(k for k in RUN_KEYS if this[k] != run[k])
            raise UserError(f"{plans_dir}: {name}.h5 was made with {key} {_show(this[key])}, {first}.h5 with "
                            f"{_show(run[key])}: not one run's plans; {fix}")
    jobs = [(str(plans_dir / f"{name}.h5"), str(verified.path(name)), verified.digests[name]) for name in planned]
    per_task: dict[str, dict] = {}
    for done, (position, outcome) in enumerate(as_finished(_replayed_scores, jobs, workers), 1):
        problem, scores = cast(tuple[str | None, dict], outcome)
        if problem is not None:  # the first problem found ends the work (the first by name, one worker)
            raise UserError(problem)
        per_task[planned[position]] = scores
        if progress is not None:
            progress(done, len(jobs))
    assert run is not None  # planned is not empty
    if not all(isinstance(run[k], str) for k in ("planner", "description")):
        raise UserError(f"{plans_dir}/{first}.h5: planner or description is not a string; {fix}")
    fixed = FIXED_PLANNERS.get(str(run["model"]))  # the reference planners' names and descriptions are theirs alone
    named = next((m for m, pair in FIXED_PLANNERS.items() if run["planner"] == pair[0]), None)
    if (fixed is not None and (run["planner"], run["description"]) != fixed) or (named is not None and
                                                                                 named != run["model"]):
        raise UserError(f"{plans_dir}/{first}.h5: its planner {_show(run['planner'])} was not made by the model "
                        f"{_show(run['model'])} it records; {fix}")
    submitted_planner = submitted.get("planner")
    planner = {**(submitted_planner if isinstance(submitted_planner, dict) else {}), "name": run["planner"],
               "description": run["description"]}
    reported = submitted.get("parameters")
    if not isinstance(reported, dict):
        reported = {}
    parameters = {"candidates": _plain(run["candidates"]), "seed": _plain(run["seed"]), "lambda": _plain(run["lambda"]),
                  "steps": PLAN_STEPS, "margin": _plain(run["margin"]), "clear": _plain(run["clear"]),
                  "masks": _plain(run["masks"]),
                  "hardware": reported.get("hardware"), "workers": reported.get("workers")}
    out = build_results(per_task, planner, {"task_set": verified.task_set, "checksum": verified.checksum},
                        verified.expected, [plans_dir / f"{name}.h5" for name in planned], submitted.get("command"),
                        parameters)
    out["date"] = submitted.get("date")  # self-reported; toolkit_version is this toolkit's (build_results)
    return out


def _plain(value):
    """An attribute read from HDF5 (numpy scalar) as the JSON value it was written from."""
    return value.item() if isinstance(value, np.generic) else value


def differences(recomputed: Mapping, submitted: Mapping, prefix: str = "") -> list[str]:
    """The dotted names of the fields where two results dicts differ (a missing or extra key counts)."""
    out = []
    for key in sorted(set(recomputed) | set(submitted), key=str):
        a, b, name = recomputed.get(key), submitted.get(key), f"{prefix}{key}"
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            out += differences(a, b, f"{name}.")
        elif key not in recomputed or key not in submitted or not _same(a, b):
            out.append(name)
    return out


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, bool) or isinstance(b, bool):  # true is not 1
        return type(a) is type(b) and a == b
    return a == b


# --- the results dict alone ---------------------------------------------------------------------------------
def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _iou(x) -> bool:
    return _number(x) and 0.0 <= x <= 1.0


def check_results(results: dict) -> list[str]:
    """Problems of a planning results dict (`dsr-bench plan`'s results.json), one short phrase each: schema and
    types, IoUs finite in [0, 1], metrics equal to the means of the per-task values, coverage consistent with
    per_task and partial, task_set known, task_checksum and split_checksum equal, `pinned` true exactly when the
    checksum is this toolkit's pin of task_set (another set's pin under its name is a problem), per_task keys a
    prefix of the set's task names. An empty list: nothing found (the scores still need `recompute_results`)."""
    from dsr_bench.planning.results import RESULTS_FORMAT
    from dsr_bench.planning.tasks import TASK_SETS, pinned_checksums, task_name

    if not isinstance(results, dict):
        return ["not a JSON object"]
    p = []
    if results.get("format") != RESULTS_FORMAT:
        p.append(f"format is not {RESULTS_FORMAT}")
    if results.get("version") != 1 or isinstance(results.get("version"), bool):
        p.append("version is not 1")
    for key in ("method", "task_set", "split", "task_checksum", "split_checksum", "plans_checksum", "command",
                "toolkit_version", "date"):
        if not isinstance(results.get(key), str):
            p.append(f"{key} is not a string")
    for key in ("task_checksum", "plans_checksum"):
        if isinstance(results.get(key), str) and not _HEX64.fullmatch(results[key]):
            p.append(f"{key} is not a SHA-256")
    planner = results.get("planner")
    if not isinstance(planner, dict) or planner.get("name") != results.get("method") or \
            not isinstance(planner.get("description"), str):
        p.append("planner is not an object with the method's name and a description")
    if not isinstance(results.get("parameters"), dict):
        p.append("parameters is not an object")
    task_set, checksum, pinned = results.get("task_set"), results.get("task_checksum"), results.get("pinned")
    spec = TASK_SETS.get(task_set) if isinstance(task_set, str) else None
    if spec is None:
        p.append("task_set is not a known task set")
    if results.get("split") != task_set:
        p.append("split differs from task_set")
    if results.get("split_checksum") != checksum:
        p.append("split_checksum differs from task_checksum")
    pins = pinned_checksums()
    if not isinstance(pinned, bool):
        p.append("pinned is not true or false")
    elif pinned and (task_set not in pins or checksum != pins[task_set]):
        p.append("pinned is true but task_checksum is not the pin of task_set")
    elif not pinned and task_set in pins and checksum == pins[task_set]:
        p.append("pinned is false but task_checksum is the pin of task_set")
    for other, pin in pins.items():
        if other != task_set and checksum == pin:
            p.append(f"task_checksum is the pin of {other}, not of {task_set}")
    p += _check_per_task(results.get("per_task"), spec, task_name)
    p += _check_metrics(results.get("metrics"), results.get("per_task"))
    cov, per_task = results.get("coverage"), results.get("per_task")
    keys = ("scored", "expected", "partial")
    if not isinstance(cov, dict) or set(cov) != set(keys) or not all(_number(cov[k]) and isinstance(cov[k], int)
                                                                      for k in keys[:2]) or \
            not isinstance(cov["partial"], bool):
        p.append("coverage is not {scored, expected, partial}")
    else:
        if isinstance(per_task, dict) and cov["scored"] != len(per_task):
            p.append("coverage scored is not the number of per_task entries")
        if spec is not None and cov["expected"] != spec.num_tasks:
            p.append("coverage expected is not the task set's size")
        if not 0 <= cov["scored"] <= cov["expected"]:
            p.append("coverage scored is not within 0..expected")
        if cov["partial"] != (cov["scored"] < cov["expected"]):
            p.append("coverage partial disagrees with scored < expected")
    return p


def _check_per_task(per_task, spec, task_name) -> list[str]:
    if not isinstance(per_task, dict):
        return ["per_task is not an object"]
    if not per_task:
        return ["per_task is empty"]
    p = []
    names = sorted(per_task, key=str)
    if spec is not None and names != [task_name(i) for i in range(min(len(names), spec.num_tasks))]:
        p.append("per_task keys are not a prefix of the task set's task names")
    for name in names:
        t = per_task[name]
        if not isinstance(t, dict) or not all(_iou(t.get(k)) for k in SCORE_KEYS):
            p.append(f"per_task {_show(name)}: an IoU missing, not a number or outside [0, 1]")
            continue
        per_object = t.get("iou_per_object")
        if not isinstance(per_object, list) or not per_object or not all(_iou(x) for x in per_object):
            p.append(f"per_task {_show(name)}: iou_per_object is not a list of IoUs")
        elif abs(float(np.mean(per_object)) - t["iou_identity"]) > 1e-12:
            p.append(f"per_task {_show(name)}: iou_identity is not the mean of iou_per_object")
        if "seconds" in t and not (_number(t["seconds"]) and t["seconds"] >= 0):
            p.append(f"per_task {_show(name)}: seconds is not a time")
        if set(t) - set(SCORE_KEYS) - {"iou_per_object", "seconds"}:
            p.append(f"per_task {_show(name)}: unknown keys")
    return p


def _check_metrics(metrics, per_task) -> list[str]:
    if not isinstance(metrics, dict):
        return ["metrics is not an object"]
    p = []
    valid = isinstance(per_task, dict) and per_task and all(
        isinstance(t, dict) and all(_iou(t.get(k)) for k in SCORE_KEYS) for t in per_task.values())
    for key in SCORE_KEYS + ("planning_iou",):
        if not _iou(metrics.get(key)):
            p.append(f"metrics {key} is not a number in [0, 1]")
        elif valid and abs(metrics[key] - float(np.mean([per_task[n][key.replace("planning_", "")]
                                                         for n in sorted(per_task, key=str)]))) > 1e-12:
            p.append(f"metrics {key} is not the mean of the per-task values")
    seconds = [t.get("seconds") for t in per_task.values()] if valid else []
    tpm = metrics.get("tasks_per_minute")
    if tpm is not None and not (_number(tpm) and tpm > 0):
        p.append("metrics tasks_per_minute is not a positive number or null")
    elif valid and all(_number(s) for s in seconds) and sum(seconds) > 0 and \
            (tpm is None or abs(tpm - 60.0 * len(seconds) / sum(seconds)) > 1e-9 * tpm):
        p.append("metrics tasks_per_minute disagrees with the per-task seconds")
    if set(metrics) - set(SCORE_KEYS) - {"planning_iou", "tasks_per_minute"}:
        p.append("metrics has unknown keys")
    return p
