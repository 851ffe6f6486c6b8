"""Generating a dataset: many sequences in parallel, sharded, resumable, deterministic.

Sequence i of a run is a pure function of the run's arguments and `sequence_seed(seed, i)`, so the
arrays do not depend on `workers` or `shard`. Every file is written under a temporary name and
renamed when complete (`dsr_bench.atomic`), so a killed run (even kill -9) leaves only complete files
under final names; rerunning the same command skips them and finishes the rest. Shards may run at
the same time into one directory, on one host or several sharing it: a run removes only the
temporaries whose writer is provably gone, never a live writer's. The sequences of a run may also
run on a Ray cluster or a SLURM job array (`generate_dataset`'s engine, `dsr_bench.engines`), the
driver writing the manifest once they are all done.

Before any simulation a run checks that it can write in --out and that every file already named
like one of its sequences is a complete sequence of the same arguments (skipped); anything else
there (another file, another format, other arguments) is refused, never overwritten.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dsr_bench.constants import CAMERAS, MAX_OBJECTS_PER_SCENE, MODEL_CAMERA
from dsr_bench.dataset.splits import sequence_name, sequence_seed
from dsr_bench.atomic import check_writable, clean_temporaries, write_text
from dsr_bench.engines import Engine, LocalEngine
from dsr_bench.errors import UserError
from dsr_bench.generators.episode import EpisodeConfig


@dataclass(frozen=True)
class RunPlan:
    """What a `dsr-bench generate` invocation produces."""

    config: EpisodeConfig
    out: Path
    num_sequences: int
    seed: int
    split: str
    shard: tuple[int, int] = (0, 1)
    workers: int = 1

    def indices(self) -> list[int]:
        """Sequence indices of this shard (i, n): every index with index % n == i."""
        i, n = self.shard
        return [k for k in range(self.num_sequences) if k % n == i]

    def generator_args(self, index: int) -> dict:
        """The arguments recorded in sequence `index`'s file (independent of workers and shard)."""
        return {**self.config.as_attrs(), "base_seed": self.seed, "index": index, "split": self.split,
                "num_sequences": self.num_sequences}


@dataclass
class SequenceResult:
    name: str
    seconds: float
    bytes: int
    scene_attempts: int
    timings: dict[str, float]


def parse_shard(text: str) -> tuple[int, int]:
    """'i/n' -> (i, n) with 0 <= i < n."""
    try:
        i, n = (int(part) for part in text.split("/"))
    except ValueError:
        raise UserError(f"--shard {text!r} is not of the form i/n (e.g. 0/4)") from None
    if n < 1 or not 0 <= i < n:
        raise UserError(f"--shard {text!r}: need 0 <= i < n, e.g. 0/4 ... 3/4")
    return i, n


def plan_from_arguments(*, objects: str | None = None, num_sequences: int | None = None, out: Path | None = None,
                        split: str | None = None, seed: int | None = None, steps: int | None = None,
                        objects_per_scene: int | None = None, policy: str | None = None, cameras: str = MODEL_CAMERA,
                        workers: int = 1, shard: str = "0/1", object_root: Path | None = None,
                        sleep_at_rest: bool = False) -> RunPlan:
    """The run that `dsr-bench generate`'s arguments ask for (None: not given). A named `split` fixes the object
    set, size, seed, steps, objects per scene and policy (giving any of them too is refused) and --out defaults
    to data/<split>; without it --objects, --num-sequences and --out are needed and the rest take their defaults
    (seed 0, DEFAULT_STEPS, DEFAULT_OBJECTS_PER_SCENE, the heuristic policy). `cameras`: names of
    `constants.CAMERAS`, comma-separated, MODEL_CAMERA among them ('front' or 'front,back'); `shard`: 'i/n'.
    `sleep_at_rest`: objects sleep through each push until touched (faster; refused with a split, whose pinned
    bytes are made without it). The plan is not checked yet (`check_plan`, `prepare_run`)."""
    from dsr_bench.constants import DEFAULT_OBJECTS_PER_SCENE, DEFAULT_STEPS
    from dsr_bench.dataset.splits import get_split

    if split is not None:
        spec = get_split(split)
        given = {"--objects": objects, "--num-sequences": num_sequences, "--seed": seed, "--steps": steps,
                 "--objects-per-scene": objects_per_scene, "--policy": policy}
        clash = [flag for flag, value in given.items() if value is not None]
        if sleep_at_rest:
            raise UserError(f"--split {split} with --sleep-at-rest: a split's sequences are made (and pinned) "
                            "with every object awake; drop --sleep-at-rest, or generate your own "
                            "--objects/--out data with it")
        if clash:
            raise UserError(f"--split {split} fixes {', '.join(clash)}; drop them or generate without --split")
        objects, num_sequences, seed = spec.objects, spec.num_sequences, spec.base_seed
        steps, objects_per_scene, policy = spec.steps, spec.objects_per_scene, spec.policy
        out = out or Path("data") / split
    else:
        if objects is None or num_sequences is None or out is None:
            missing = [flag for flag, value in (("--objects SET", objects), ("--num-sequences N", num_sequences),
                                                ("--out DIR", out)) if value is None]
            raise UserError(f"missing {' and '.join(missing)}: give {'it' if len(missing) == 1 else 'them'}, or a "
                            f"named --split instead{_needs_meshes(objects, object_root)}")
        seed = 0 if seed is None else seed
        steps = DEFAULT_STEPS if steps is None else steps
        objects_per_scene = DEFAULT_OBJECTS_PER_SCENE if objects_per_scene is None else objects_per_scene
        policy = policy or "heuristic"
    config = EpisodeConfig(objects=objects, steps=steps, objects_per_scene=objects_per_scene, policy=policy,
                           cameras=tuple(c.strip() for c in cameras.split(",") if c.strip()),
                           object_root=str(object_root) if object_root else None,
                           sleep_at_rest=sleep_at_rest)
    return RunPlan(config=config, out=Path(out), num_sequences=num_sequences, seed=seed, split=split or "all",
                   shard=parse_shard(shard), workers=workers)


def _needs_meshes(objects: str | None, object_root: Path | None) -> str:
    """'; ShapeNet also needs --object-root ...' when `objects` is a mesh set read from the user's copy and
    neither --object-root nor its environment variable names one ('' otherwise)."""
    from dsr_bench.generators.objects.external import ENV, SOURCES

    if objects not in ENV or object_root is not None or os.environ.get(ENV[objects]):
        return ""
    return (f"; --objects {objects} also needs --object-root PATH (or ${ENV[objects]}), your copy of "
            f"{SOURCES[objects]}")


def check_scene_arguments(num_sequences: int, steps: int, objects_per_scene: int) -> None:
    """Reject a bad --num-sequences, --steps or --objects-per-scene (of sequences and of captures)."""
    if num_sequences < 1:
        raise UserError(f"--num-sequences {num_sequences}: must be at least 1")
    if steps < 1:
        raise UserError(f"--steps {steps}: must be at least 1")
    if not 1 <= objects_per_scene <= MAX_OBJECTS_PER_SCENE:
        raise UserError(f"--objects-per-scene {objects_per_scene}: must be 1..{MAX_OBJECTS_PER_SCENE}")


def check_plan(plan: RunPlan) -> None:
    """Reject bad arguments before anything is written."""
    cfg = plan.config
    check_scene_arguments(plan.num_sequences, cfg.steps, cfg.objects_per_scene)
    if cfg.policy not in ("heuristic", "random"):
        raise UserError(f"--policy {cfg.policy!r}: choose heuristic or random")
    bad = [c for c in cfg.cameras if c not in CAMERAS]
    if bad or MODEL_CAMERA not in cfg.cameras:
        raise UserError(f"--cameras {','.join(cfg.cameras)!r}: use {MODEL_CAMERA} or {','.join(CAMERAS)}")
    if plan.workers < 1:
        raise UserError(f"--workers {plan.workers}: must be at least 1")
    check_writable(plan.out)


def needs_writing(path: Path, expected: dict, recorded: Callable[[Path], object], different: str,
                  overwrite: bool = False) -> bool:
    """Resumption, one rule for every output of a run (sequence files, capture directories): True when `path`
    is to be written (absent, or `overwrite`), False when it is complete and was made with the same arguments
    (skip it). `recorded(path)` reads the arguments an existing output was made with, comparable with
    `expected`, and raises UserError (one line naming the output and the fix) when it is not one of ours; other
    arguments raise UserError(`different`): an existing output is never overwritten without `overwrite`."""
    if overwrite or not (path.exists() or path.is_symlink()):
        return True
    if recorded(path) != expected:
        raise UserError(different)
    return False


def _sequence_arguments(args: dict, seed: int) -> dict:
    """The arguments that define a generated sequence file, as compared on resumption (`needs_writing`)."""
    if isinstance(args, dict):  # where the meshes live may differ between machines
        args = {k: v for k, v in args.items() if k != "object_root"}
    return {"generator_args": args, "seed": seed}


def recorded_sequence_arguments(path: Path) -> dict:
    """`_sequence_arguments` of an existing sequence file; UserError (naming the file and the fix) when it is not
    a dsr-bench sequence of this schema made by `dsr-bench generate`."""
    import json

    import h5py

    from dsr_bench.constants import FORMAT_NAME, READABLE_SCHEMA_VERSIONS, SCHEMA_VERSION

    fix = "move it away or use another --out"
    if not path.is_file():
        raise UserError(f"{path} exists and is not a file; {fix}")
    try:
        with h5py.File(path, "r") as f:
            attrs = dict(f.attrs)
    except Exception:  # noqa: BLE001 - whatever h5py raises: it is not an HDF5 file we can read
        raise UserError(f"{path} is not a dsr-bench sequence (not a readable HDF5 file); {fix}") from None
    fmt = attrs.get("format")
    if isinstance(fmt, bytes):
        fmt = fmt.decode(errors="replace")
    if fmt != FORMAT_NAME:
        raise UserError(f"{path} is not a dsr-bench sequence (format attribute {fmt!r}); {fix}")
    if attrs.get("schema_version") not in READABLE_SCHEMA_VERSIONS:  # an older schema of the same arrays is kept
        raise UserError(f"{path} was written by another dsr-bench version (schema {attrs.get('schema_version')}, "
                        f"this one writes {SCHEMA_VERSION}); {fix}")
    try:
        args = json.loads(attrs["generator_args"])
        seed = int(attrs["seed"])
    except (KeyError, TypeError, ValueError):
        raise UserError(f"{path} is a dsr-bench sequence not made by `dsr-bench generate` (no generator "
                        f"arguments); {fix}") from None
    return _sequence_arguments(args, seed)


def _clean_partials(out: Path) -> None:
    """Remove the temporaries of abandoned writers (killed runs); keep live writers' (other shards)."""
    clean_temporaries(out, "seq_*.h5")
    if (out / "splits").is_dir():
        clean_temporaries(out / "splits", "*.txt")


# --- worker side -------------------------------------------------------------------------------
_WORKER: dict = {}


def _init_worker(objects: str, object_root: str | None) -> None:
    from dsr_bench.generators.objects import get_object_set

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    _WORKER["set"] = get_object_set(objects, object_root)
    _WORKER["key"] = (objects, object_root)


def _generate_one(plan: RunPlan, index: int) -> SequenceResult:
    from dsr_bench.dataset.sequence import write_sequence
    from dsr_bench.generators.episode import generate_episode

    start = time.perf_counter()
    name = sequence_name(index)
    episode = generate_episode(plan.config, _WORKER["set"], sequence_seed(plan.seed, index), name,
                               generator_args=plan.generator_args(index))
    path = write_sequence(plan.out / f"{name}.h5", episode.arrays, episode.attrs, episode.meshes)
    return SequenceResult(name, time.perf_counter() - start, path.stat().st_size, episode.scene_attempts,
                          episode.timings)


def sequence_job(job: tuple[RunPlan, int]) -> SequenceResult:
    """Generate and write sequence `index` of `plan`, job = (plan, index), in whichever process runs it (this one, a
    local worker, a Ray worker, a SLURM array task): the object set is loaded once per process."""
    plan, index = job
    if _WORKER.get("key") != (plan.config.objects, plan.config.object_root):
        _init_worker(plan.config.objects, plan.config.object_root)
    return _generate_one(plan, index)


def prepare_run(plan: RunPlan) -> tuple[list[int], list[str]]:
    """Check everything (arguments, meshes, existing files) before any work; return (indices to
    generate, names already complete). Creates the output directory and removes abandoned partial
    files (never those of a shard running at the same time)."""
    from dsr_bench.generators.objects import get_object_set

    check_plan(plan)
    get_object_set(plan.config.objects, plan.config.object_root)  # fails fast on missing meshes
    todo, skipped, refused = [], [], []
    for index in plan.indices():
        path = plan.out / f"{sequence_name(index)}.h5"
        expected = _sequence_arguments(plan.generator_args(index), sequence_seed(plan.seed, index))
        try:
            writing = needs_writing(path, expected, recorded_sequence_arguments, f"{path} was generated with "
                                    "different arguments; use another --out or delete the directory")
        except UserError as exc:  # every file in the way is named, not only the first
            refused.append((path.name, str(exc)))
            continue
        if writing:
            todo.append(index)
        else:
            skipped.append(path.stem)
    if refused:
        others = [name for name, _ in refused[1:]]
        more = (f" (also {', '.join(others[:5])}" + (f" and {len(others) - 5} more" if len(others) > 5 else "") + ")"
                if others else "")
        raise UserError(f"{len(refused)} existing file(s) in --out cannot be resumed: {refused[0][1]}{more}")
    try:
        plan.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {plan.out}: cannot create the directory ({exc.strerror or exc}); choose a "
                        "writable --out") from None
    _clean_partials(plan.out)
    return todo, skipped


def generate_dataset(plan: RunPlan, todo: list[int], progress: Callable[[SequenceResult], None] | None = None,
                     engine: Engine | None = None) -> list[SequenceResult]:
    """Generate the sequences `todo` (indices from `prepare_run`) and return their results in the order of `todo`;
    `progress(result)` is called as each sequence is written. `engine` (`dsr_bench.engines`) says where they run:
    a Ray cluster, a SLURM array; None: `plan.workers` processes on this machine. Each sequence is the same array
    for array wherever it runs (`sequence_seed`); the workers write into `plan.out` (made absolute for them)."""
    import multiprocessing as mp

    engine = engine or LocalEngine(plan.workers, mp.get_context("spawn"))
    plan = replace(plan, out=plan.out.absolute())
    results: list = [None] * len(todo)
    for position, result in engine.as_finished(sequence_job, [(plan, index) for index in todo],
                                               describe=lambda job: sequence_name(job[1])):
        results[position] = result
        if progress:
            progress(result)
    return results


def finalize_dataset(plan: RunPlan) -> dict | None:
    """Write splits/<split>.txt and manifest.json once every sequence of the run exists; else None."""
    from dsr_bench.dataset.manifest import build_manifest, write_manifest

    names = [sequence_name(i) for i in range(plan.num_sequences)]
    if not all((plan.out / f"{n}.h5").exists() for n in names):
        return None
    split_dir = plan.out / "splits"
    split_dir.mkdir(exist_ok=True)
    write_text(split_dir / f"{plan.split}.txt", "".join(f"{n}\n" for n in names))
    manifest = build_manifest(plan.out)
    write_manifest(plan.out, manifest)
    return manifest


def summarize(results: list[SequenceResult]) -> dict[str, float]:
    """Aggregate timings of generated sequences (seconds per sequence, bytes per step...)."""
    if not results:
        return {}
    secs = np.array([r.seconds for r in results])
    out = {"sequences": len(results), "mean_seconds": float(secs.mean()),
           "total_bytes": int(sum(r.bytes for r in results)),
           "mean_scene_attempts": float(np.mean([r.scene_attempts for r in results]))}
    for key in results[0].timings:
        out[f"mean_{key}_seconds"] = float(np.mean([r.timings[key] for r in results]))
    return out
