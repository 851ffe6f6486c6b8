"""Planning tasks: the file format (one HDF5 file per task), its validated reader, task digests, the named
task sets and a task directory's manifest (tasks.json) with the set's checksum.

A task file (format "dsr-bench-plan-task", version 1) holds, all in the benchmark's conventions
(volumes (Y, X, Z) = (world y, world x, z), 128 x 128 x 48 voxels of 4 mm; poses (N, 7) = (x, y, z, qx,
qy, qz, qw) world metres; actions (d, row, col)):

  start/object_poses (N, 7) f8, start/mask_3d (Y, X, Z) u1     the start's full state           ground truth
  target/object_poses (N, 7) f8, target/mask_3d (Y, X, Z) u1   the target's full state          ground truth
  reference/action (3, 3) i8                                   the heuristic pushes that made it  ground truth
  objects/<i>/part_<j>/vertices (V, 3) f8, .../faces (F, 3) i8 each object's solid parts (object frame)
  start/tsdf (Y, X, Z) f4, start/heightmap (Y, X) f4           the start as the front camera sees it  observations
  start/color (H, W, 3) u1, target/color (H, W, 3) u1          front camera images (viewer)           observations

Root attributes: format, version, name, task_set, index, seed, num_objects, pushes, objects (JSON identities:
colour, mass, is_large, ...), generator_args (JSON), toolkit_version, and the digests (`task_digests`):
ground_truth_sha256, observations_sha256, content_sha256. The reader recomputes them: a file whose arrays do
not match its digests is refused (`UserError`, one line naming the file and the fix), and `Task.digests` holds the
recomputed ones. Digests a file carries prove nothing (a forger recomputes them): `dsr_bench.planning.verify`
compares the recomputed digests with the pin this toolkit ships (`task_pins.json`, `pinned_tasks`), and tasks.json
is never taken for the files it lists.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dsr_bench import __version__
from dsr_bench.atomic import atomic_path, write_text
from dsr_bench.constants import GRID_SHAPE, MAX_OBJECTS_PER_SCENE, NUM_DIRECTIONS
from dsr_bench.dataset.digests import GROUND_TRUTH_KEY, OBSERVATIONS_KEY, array_digest, split_checksum
from dsr_bench.errors import UserError
from dsr_bench.planning.protocol import PLAN_STEPS

TASK_FORMAT, TASK_VERSION = "dsr-bench-plan-task", 1
MANIFEST_FORMAT, MANIFEST_NAME = "dsr-bench-plan-tasks", "tasks.json"
PINS_FILE = Path(__file__).resolve().parent / "task_pins.json"
#: Arrays of the ground-truth group besides the objects' parts (what scores a plan).
GROUND_TRUTH_ARRAYS = ("start/object_poses", "start/mask_3d", "target/object_poses", "target/mask_3d",
                       "reference/action")
OBSERVATION_ARRAYS = ("start/tsdf", "start/heightmap", "start/color", "target/color")


@dataclass(frozen=True)
class TaskSet:
    """A named, reproducible set of planning tasks: task i comes from `sequence_seed(base_seed, i)`."""

    name: str
    objects: str
    num_tasks: int
    base_seed: int
    description: str
    pushes: int = PLAN_STEPS
    objects_per_scene: int = 4
    policy: str = "heuristic"


TASK_SETS: dict[str, TaskSet] = {s.name: s for s in (
    TaskSet("plan-novel-test", "procedural-novel", 100, 70_000,
            "The planning track's 100 tasks: novel objects (as procedural-novel-test), 3 heuristic pushes to the "
            "target"),
    TaskSet("plan-novel-mini", "procedural-novel", 4, 71_000, "Four planning tasks for a first look and the tests"),
    TaskSet("plan-val", "procedural", 50, 72_000,
            "Validation tasks on the training objects, for choosing a planner's settings (never reported as a "
            "result: the novel-object tasks of plan-novel-test are)"),
    TaskSet("plan-novel-replicate", "procedural-novel", 100, 73_000,
            "A second 100 novel-object tasks, made as plan-novel-test's, to replicate its results with planners and "
            "settings fixed before these tasks were made (never used to choose one; docs/planning.md)"),
    TaskSet("plan-novel-confirm", "procedural-novel", 1000, 74_000,
            "1,000 novel-object tasks, made as plan-novel-test's, to settle whether the learned planner fixed "
            "beforehand beats not pushing (stated before these tasks were made; docs/planning.md)"),
)}


def get_task_set(name: str) -> TaskSet:
    """The named task set, or a UserError listing the known names."""
    if name not in TASK_SETS:
        raise UserError(f"unknown task set {name!r}; choose one of: {', '.join(TASK_SETS)}")
    return TASK_SETS[name]


def task_name(index: int) -> str:
    """File stem of task `index`: task_0000, task_0001, ..."""
    return f"task_{index:04d}"


def is_ground_truth(name: str) -> bool:
    """Whether an array of a task file belongs to the ground-truth group."""
    return name in GROUND_TRUTH_ARRAYS or name.startswith("objects/")


def task_digests(arrays: Mapping[str, np.ndarray], objects: list[dict]) -> dict[str, str]:
    """{"ground_truth_sha256", "observations_sha256", "content_sha256"} of a task's arrays, as sequences'
    (`dsr_bench.dataset.digests`): each group the SHA-256 of its sorted "name:array digest" lines, the ground
    truth followed by the canonical JSON of the object identities."""
    groups = {GROUND_TRUTH_KEY: hashlib.sha256(), OBSERVATIONS_KEY: hashlib.sha256()}
    for name in sorted(arrays):
        key = GROUND_TRUTH_KEY if is_ground_truth(name) else OBSERVATIONS_KEY
        groups[key].update(f"{name}:{array_digest(name, arrays[name])}\n".encode())
    groups[GROUND_TRUTH_KEY].update(json.dumps(objects, sort_keys=True).encode())
    out = {key: h.hexdigest() for key, h in groups.items()}
    out["content_sha256"] = hashlib.sha256(f"{out[GROUND_TRUTH_KEY]}\n{out[OBSERVATIONS_KEY]}\n".encode()).hexdigest()
    return out


@dataclass
class Task:
    """A planning task as read from its file (arrays validated, digests checked)."""

    path: Path
    name: str
    seed: int
    arrays: dict[str, np.ndarray]
    objects: list[dict]
    parts: list[list[tuple[np.ndarray, np.ndarray]]]
    attrs: dict = field(default_factory=dict)
    #: the digests recomputed from the arrays on reading (`task_digests`), never the file's own attributes
    digests: dict = field(default_factory=dict)

    @property
    def num_objects(self) -> int:
        return len(self.objects)

    @property
    def target_mask(self) -> np.ndarray:
        return self.arrays["target/mask_3d"]

    @property
    def start_mask(self) -> np.ndarray:
        return self.arrays["start/mask_3d"]

    @property
    def ground_truth_sha256(self) -> str:
        """The ground-truth digest recomputed from the arrays (what the file says is checked against it)."""
        return str(self.digests.get(GROUND_TRUTH_KEY) or task_digests(self.arrays, self.objects)[GROUND_TRUTH_KEY])


def write_task(path: str | Path, arrays: Mapping[str, np.ndarray], attrs: Mapping) -> Path:
    """Write a task file atomically (`dsr_bench.atomic`); `attrs` holds at least name, seed and objects (a list
    of identities); the digests are added here."""
    import h5py

    path = Path(path)
    objects = list(attrs["objects"])
    out = {**attrs, **task_digests(arrays, objects), "format": TASK_FORMAT, "version": TASK_VERSION}
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        for name, value in sorted(arrays.items()):
            a = np.ascontiguousarray(value)
            big = a.size > 4096
            f.create_dataset(name, data=a, compression="gzip" if big else None, compression_opts=4 if big else None,
                             chunks=a.shape if big else None)
        for key, value in out.items():
            f.attrs[key] = json.dumps(value) if isinstance(value, (dict, list)) else value
    return path


def _fix(path: Path) -> str:
    return (f"regenerate it with `dsr-bench generate-plan-tasks --out {path.parent}` (with the same --tasks) or "
            "delete it")


def _expect(path: Path, name: str, a: np.ndarray, shape: tuple, dtype) -> None:
    if a.shape != shape or a.dtype != np.dtype(dtype):
        raise UserError(f"{path}: {name} is {a.dtype}{list(a.shape)}, expected {np.dtype(dtype)}{list(shape)}; "
                        f"{_fix(path)}")


def _check_arrays(path: Path, arrays: dict[str, np.ndarray], n: int) -> None:
    """Shapes, dtypes and ranges of a task's arrays (UserError naming the first problem)."""
    for key in ("start", "target"):
        _expect(path, f"{key}/object_poses", arrays[f"{key}/object_poses"], (n, 7), np.float64)
        _expect(path, f"{key}/mask_3d", arrays[f"{key}/mask_3d"], GRID_SHAPE, np.uint8)
        if not np.all(np.isfinite(arrays[f"{key}/object_poses"])):
            raise UserError(f"{path}: {key}/object_poses has NaN or inf; {_fix(path)}")
        if int(arrays[f"{key}/mask_3d"].max(initial=0)) > n:
            raise UserError(f"{path}: {key}/mask_3d has an object id above num_objects {n}; {_fix(path)}")
    _expect(path, "start/tsdf", arrays["start/tsdf"], GRID_SHAPE, np.float32)
    if not np.all(np.isfinite(arrays["start/tsdf"])):
        raise UserError(f"{path}: start/tsdf has NaN or inf; {_fix(path)}")
    action = arrays["reference/action"]
    if action.ndim != 2 or action.shape[1] != 3 or not np.issubdtype(action.dtype, np.integer) or \
            np.any((action[:, 0] < 0) | (action[:, 0] >= NUM_DIRECTIONS)) or \
            np.any((action[:, 1:] < 0) | (action[:, 1:] >= np.array(GRID_SHAPE[:2]))):
        raise UserError(f"{path}: reference/action is not a list of (direction 0..7, row, col) actions; {_fix(path)}")


def read_task(path: str | Path) -> Task:
    """Read and check a task file: format, version, arrays (shapes, dtypes, ranges) and digests. Any problem is a
    UserError of one line naming the file and the fix."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise UserError(f"task file not found: {path}; generate the tasks with `dsr-bench generate-plan-tasks "
                        f"--tasks plan-novel-test --out {path.parent}`")
    try:
        with h5py.File(path, "r") as f:
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
            if attrs.get("format") != TASK_FORMAT:
                raise UserError(f"{path}: not a dsr-bench planning task (format {attrs.get('format')!r}); {_fix(path)}")
            if attrs.get("version") != TASK_VERSION:
                raise UserError(f"{path}: task format version {attrs.get('version')}, this toolkit reads "
                                f"{TASK_VERSION}; {_fix(path)}")
            arrays: dict[str, np.ndarray] = {}
            f.visititems(lambda name, obj: arrays.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    except UserError:
        raise
    except Exception as exc:  # noqa: BLE001 - whatever h5py raises on a damaged file
        raise UserError(f"{path}: unreadable task file ({type(exc).__name__}: {' '.join(str(exc).split())[:120]}); "
                        f"{_fix(path)}") from None
    try:
        objects = json.loads(attrs["objects"])
        n = int(attrs["num_objects"])
        seed = int(attrs["seed"])
        missing = [a for a in GROUND_TRUTH_ARRAYS + ("start/tsdf",) if a not in arrays]
    except (KeyError, TypeError, ValueError):
        raise UserError(f"{path}: a task file without its objects, num_objects or seed attributes; "
                        f"{_fix(path)}") from None
    if missing:
        raise UserError(f"{path}: missing arrays {', '.join(missing)}; {_fix(path)}")
    if not isinstance(objects, list) or len(objects) != n or not 1 <= n <= MAX_OBJECTS_PER_SCENE:
        raise UserError(f"{path}: {n} objects but {len(objects) if isinstance(objects, list) else '?'} identities; "
                        f"{_fix(path)}")
    _check_arrays(path, arrays, n)
    digests = task_digests(arrays, objects)
    for key in (GROUND_TRUTH_KEY, OBSERVATIONS_KEY):
        if digests[key] != attrs.get(key):
            raise UserError(f"{path}: its arrays do not match its {key} (a damaged or edited file); {_fix(path)}")
    parts = []
    for i in range(n):
        k, obj = 0, []
        while f"objects/{i}/part_{k}/vertices" in arrays:
            obj.append((arrays[f"objects/{i}/part_{k}/vertices"], arrays[f"objects/{i}/part_{k}/faces"]))
            k += 1
        if not obj:
            raise UserError(f"{path}: object {i} has no solid parts; {_fix(path)}")
        parts.append(obj)
    return Task(path=path, name=str(attrs.get("name", path.stem)), seed=seed, arrays=arrays, objects=objects,
                parts=parts, attrs=attrs, digests=digests)


# --- task directories --------------------------------------------------------------------------------------
def build_manifest(task_dir: str | Path, task_set: str, names: list[str]) -> dict:
    """The manifest of a task directory: per task its file's SHA-256 and digests (read from the file, checked by
    `read_task`), and the set's checksum over the sorted (name, ground-truth digest) pairs."""
    from dsr_bench.dataset.manifest import file_sha256

    task_dir = Path(task_dir)
    entries = []
    for name in names:
        task = read_task(task_dir / f"{name}.h5")
        entries.append({"name": name, "file": f"{name}.h5", "sha256": file_sha256(task.path),
                        GROUND_TRUTH_KEY: task.ground_truth_sha256,
                        OBSERVATIONS_KEY: task.digests[OBSERVATIONS_KEY]})
    return {"format": MANIFEST_FORMAT, "version": 1, "task_set": task_set, "toolkit_version": __version__,
            "tasks": entries, "checksum": split_checksum((e["name"], e[GROUND_TRUTH_KEY]) for e in entries)}


def write_manifest(task_dir: str | Path, manifest: Mapping) -> Path:
    """Write TASK_DIR/tasks.json atomically."""
    return write_text(Path(task_dir) / MANIFEST_NAME, json.dumps(manifest, indent=1, sort_keys=True) + "\n")


def load_manifest(task_dir: str | Path) -> dict:
    """TASK_DIR/tasks.json, checked for its format (UserError naming the file and the fix otherwise)."""
    task_dir = Path(task_dir)
    path = task_dir / MANIFEST_NAME
    fix = f"generate the tasks with `dsr-bench generate-plan-tasks --tasks plan-novel-test --out {task_dir}`"
    if not task_dir.is_dir():
        raise UserError(f"task directory not found: {task_dir}; {fix}")
    if not path.is_file():
        raise UserError(f"{task_dir} has no {MANIFEST_NAME} (not a task directory, or its generation did not finish); "
                        f"{fix}")
    try:
        manifest = json.loads(path.read_text())
        ok = manifest.get("format") == MANIFEST_FORMAT and all(
            isinstance(e.get("name"), str) and isinstance(e.get(GROUND_TRUTH_KEY), str) for e in manifest["tasks"])
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError, KeyError, TypeError):
        ok = False
    if not ok:
        raise UserError(f"{path}: not a dsr-bench task manifest; {fix}")
    return manifest


def pinned_checksums() -> dict[str, str]:
    """{task set: its pinned checksum} of the sets pinned in this toolkit (task_pins.json)."""
    if not PINS_FILE.is_file():
        return {}
    return {name: pin["checksum"] for name, pin in json.loads(PINS_FILE.read_text())["task_sets"].items()}


def pinned_tasks(task_set: str) -> dict[str, str] | None:
    """{task name: its pinned ground-truth digest} of a task set pinned in this toolkit, None if it is not."""
    if not PINS_FILE.is_file():
        return None
    pin = json.loads(PINS_FILE.read_text())["task_sets"].get(task_set)
    return None if pin is None else {name: d["ground_truth"] for name, d in pin["tasks"].items()}


def pin_task_set(manifest: Mapping) -> Path:
    """Record a task directory's checksum and per-task digests as the pin of its set (task_pins.json)."""
    pins: dict[str, Any] = (json.loads(PINS_FILE.read_text()) if PINS_FILE.is_file()
                            else {"format": "dsr-bench-task-pins", "version": 1, "task_sets": {}})
    pins["task_sets"][manifest["task_set"]] = {
        "checksum": manifest["checksum"],
        "tasks": {e["name"]: {"ground_truth": e[GROUND_TRUTH_KEY], "observations": e[OBSERVATIONS_KEY]}
                  for e in manifest["tasks"]}}
    text = json.dumps(pins, sort_keys=True, separators=(",", ":")).replace('},"task_', '},\n"task_') + "\n"
    return write_text(PINS_FILE, text)


def resolve_tasks(tasks: str | Path) -> tuple[Path, dict]:
    """A task directory from --tasks (a directory, or a task set's name: data/<name>) and its manifest (untrusted:
    `dsr_bench.planning.verify.verify_tasks` checks the files against the pin)."""
    path = Path(tasks)
    if not path.is_dir() and str(tasks) in TASK_SETS:
        path = Path("data") / str(tasks)
    return path, load_manifest(path)
