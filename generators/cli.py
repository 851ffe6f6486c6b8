"""The generator's `dsr-bench` commands, registered through the `dsr_bench.commands` entry point: `generate`
(pushing sequences), `generate-captures` (simulated two-camera RGB-D captures, the annotator's input), and the
planning track's `generate-plan-tasks` and `plan` (`generators.planning` makes the tasks and runs the plans)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dsr_bench.engine_options import (RayAddress, Slurm, SlurmLocal, SlurmLogs, SlurmPartition, SlurmTasks,
                                         SlurmTime)
from dsr_bench.constants import CAMERAS, MODEL_CAMERA, PLAN_MARGIN
from dsr_bench.engines import engine_from_options, slurm_options_given
from dsr_bench.errors import UserError
from dsr_bench.planning.tasks import TASK_SETS
from dsr_bench.generators.objects import OBJECT_SET_NAMES

OBJECT_SETS_HELP = " | ".join(OBJECT_SET_NAMES)
TASK_SETS_HELP = " | ".join(f"{s.name} ({s.num_tasks} tasks, {s.objects} objects)" for s in TASK_SETS.values())


def generate(
    objects: Optional[str] = typer.Option(None, "--objects", help=f"Object set: {OBJECT_SETS_HELP}."),
    num_sequences: Optional[int] = typer.Option(None, "--num-sequences", "-n", help="Sequences to generate."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Dataset directory (default data/<split> with "
                                       "--split; required otherwise)."),
    split: Optional[str] = typer.Option(None, "--split", help="A named benchmark split (sets objects, size, seed)."),
    seed: Optional[int] = typer.Option(None, "--seed", help="Base seed; sequence i uses a seed derived from it and i."),
    steps: Optional[int] = typer.Option(None, "--steps", help="Pushes per sequence (default 10)."),
    objects_per_scene: Optional[int] = typer.Option(None, "--objects-per-scene", help="Objects per scene, 1-5 "
                                                    "(default 4)."),
    policy: Optional[str] = typer.Option(None, "--policy", help="heuristic (the paper's) or random."),
    cameras: str = typer.Option(MODEL_CAMERA, "--cameras", help=f"{MODEL_CAMERA}, or {','.join(CAMERAS)} for the rig's "
                                "second view."),
    workers: Optional[int] = typer.Option(None, "--workers", "-w", help="Parallel worker processes (default 1; "
                                          "with --ray local the CPUs of its Ray, with --slurm those of each task)."),
    shard: Optional[str] = typer.Option(None, "--shard", help="Generate only shard i of n (i/n), e.g. in a SLURM "
                                        "array written by hand (--ray and --slurm shard the run themselves)."),
    object_root: Optional[Path] = typer.Option(None, "--object-root", help="Your copy of the meshes, needed by "
                                               "shapenet (ShapeNetCore v2, from https://shapenet.org) and ycb (from "
                                               "https://www.ycbbenchmarks.com/); else $DSR_BENCH_SHAPENET / "
                                               "$DSR_BENCH_YCB."),
    sleep_at_rest: bool = typer.Option(False, "--sleep-at-rest", help="Objects sleep through each push "
                                       "until something touches them (Bullet's deactivation: a quarter less CPU "
                                       "time, the pushes alike, docs/performance.md): for your own training "
                                       "data, not with --split."),
    ray: RayAddress = None,
    slurm: Slurm = False,
    slurm_partition: SlurmPartition = None,
    slurm_time: SlurmTime = None,
    slurm_tasks: SlurmTasks = None,
    slurm_logs: SlurmLogs = None,
    slurm_local: SlurmLocal = False,
) -> None:
    """Simulate pushing sequences (pybullet) and write them with ground truth, a manifest and splits: here, on a Ray
    cluster (--ray) or in a SLURM job array (--slurm), with the same arrays whichever."""
    from rich.console import Console
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)
    from rich.table import Table

    from dsr_bench.generators.run import finalize_dataset, generate_dataset, plan_from_arguments, prepare_run, summarize

    console = Console(stderr=True)
    plan = plan_from_arguments(objects=objects, num_sequences=num_sequences, out=out, split=split, seed=seed,
                               steps=steps, objects_per_scene=objects_per_scene, policy=policy, cameras=cameras,
                               workers=1 if workers is None else workers, shard=shard or "0/1",
                               object_root=object_root, sleep_at_rest=sleep_at_rest)
    if shard is not None and (ray is not None or slurm):
        raise UserError(f"--shard {shard} with {'--ray' if ray is not None else '--slurm'}: the engine splits the run "
                        "itself; drop --shard")
    slurm_given = slurm_options_given(slurm_partition, slurm_time, slurm_tasks, slurm_logs, slurm_local)
    engine = engine_from_options(ray, slurm, workers, slurm_given, "dsr-bench-generate", output=plan.out)
    total = len(plan.indices())
    todo, skipped = prepare_run(plan)
    with Progress(TextColumn("[bold]generate"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), TextColumn("ETA"),
                  TimeRemainingColumn(), console=console, transient=False) as bar:
        task = bar.add_task("sequences", total=total, completed=len(skipped), rate="")
        done: list[float] = []

        def advance(result) -> None:
            done.append(result.seconds)
            elapsed = bar.tasks[task].elapsed or 1e-9
            bar.update(task, advance=1, rate=f"{len(done) / elapsed * 60:.1f} seq/min")

        results = generate_dataset(plan, todo, progress=advance, engine=engine)
        bar.update(task, completed=total)
    manifest = finalize_dataset(plan)
    stats = summarize(results)
    table = Table(title=f"dsr-bench generate: {plan.out}", show_header=False)
    table.add_row("object set / policy", f"{plan.config.objects} / {plan.config.policy}")
    table.add_row("shard", f"{plan.shard[0]}/{plan.shard[1]}: {total} of {plan.num_sequences} sequences")
    table.add_row("generated / already present", f"{len(results)} / {len(skipped)}")
    if engine is not None:
        table.add_row("ran on", engine.label)
    if stats:
        table.add_row("seconds per sequence (per worker)", f"{stats['mean_seconds']:.2f}")
        table.add_row("  physics / render", f"{stats['mean_physics_seconds']:.2f} / {stats['mean_render_seconds']:.2f}")
        table.add_row("MB per step on disk", f"{stats['total_bytes'] / len(results) / plan.config.steps / 1e6:.2f}")
    if manifest is not None:
        from dsr_bench.dataset.manifest import split_digest

        table.add_row("split file", f"splits/{plan.split}.txt")
        table.add_row("split checksum", split_digest(manifest, plan.split))
    else:
        table.add_row("manifest",
                      "not written yet: other shards missing; run `dsr-bench manifest DIR` when all are done")
    console.print(table)


def generate_captures(
    out: Path = typer.Option(..., "--out", "-o", help="Directory to write captures/seq_0000/, seq_0001/, ... into."),
    num: int = typer.Option(1, "--num-sequences", "-n", help="Captures to generate."),
    objects: str = typer.Option("procedural", "--objects", help=f"Object set: {OBJECT_SETS_HELP}."),
    steps: int = typer.Option(10, "--steps", help="Pushes per capture (T; T + 1 steps of images)."),
    objects_per_scene: int = typer.Option(4, "--objects-per-scene", help="Objects per scene, 1-5."),
    seed: int = typer.Option(0, "--seed", help="Base seed; capture i uses a seed derived from it and i."),
    noise: str = typer.Option("realistic", "--noise", help="Sensor model: realistic (RealSense-like depth noise, "
                                                           "missing pixels, calibration error) or none."),
    object_root: Optional[Path] = typer.Option(None, "--object-root", help="Mesh root for shapenet / ycb."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace captures that already exist."),
    workers: int = typer.Option(1, "--workers", "-w", help="Parallel worker processes (the captures are the same "
                                                          "with any number)."),
) -> None:
    """Simulate pushing sequences and write them as captures: colour + 16-bit depth PNGs of the front and back
    cameras, a calibration with small errors, actions, object meshes, and the true poses kept aside in truth.json."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from dsr_bench.generators.capture import CapturePlan, generate_captures as run, prepare_captures

    plan = CapturePlan(out=out, num=num, objects=objects, steps=steps, objects_per_scene=objects_per_scene, seed=seed,
                       noise=noise, object_root=str(object_root) if object_root else None, overwrite=overwrite)
    jobs = prepare_captures(plan)
    console = Console(stderr=True)
    with Progress(TextColumn("[bold]generate-captures"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.description}"), TimeElapsedColumn(), console=console) as bar:
        task = bar.add_task("", total=num, completed=len(jobs.skipped))
        run(plan, jobs, started=lambda name: bar.update(task, description=name),
            finished=lambda name: bar.update(task, advance=1), workers=max(1, workers))
    console.print(f"{out}: {len(jobs.todo)} captures written, {len(jobs.skipped)} already present "
                  f"({objects}, {steps} pushes, {objects_per_scene} objects, noise {noise})")


def generate_plan_tasks(
    tasks: str = typer.Option("plan-novel-test", "--tasks",
                              help=f"Task set: {TASK_SETS_HELP}."),
    out: Path | None = typer.Option(None, "--out", "-o", help="Directory to write (default data/<task set>)."),
    workers: int = typer.Option(1, "--workers", "-w", help="Parallel worker processes."),
    num_tasks: int | None = typer.Option(None, "--num-tasks", "-n", help="Only the first N tasks of the set."),
    pin: bool = typer.Option(False, "--pin", hidden=True, help="Maintainers: record the complete set's checksum "
                             "and task digests in dsr_bench/planning/task_pins.json."),
) -> None:
    """Simulate planning tasks (start scene + 3 heuristic pushes -> target) and write them with tasks.json."""
    from rich.progress import Progress

    from dsr_bench.planning.tasks import get_task_set, pinned_checksums
    from dsr_bench.generators.planning import generate_tasks

    spec = get_task_set(tasks)
    out = out or Path("data") / tasks
    with Progress(transient=True) as bar:
        job = bar.add_task(f"generate-plan-tasks {tasks}", total=num_tasks or spec.num_tasks)
        manifest = generate_tasks(tasks, out, workers, num_tasks, progress=lambda: bar.advance(job))
    if pin:
        from dsr_bench.planning.tasks import pin_task_set

        if num_tasks not in (None, spec.num_tasks):
            raise UserError("--pin needs the complete set: drop --num-tasks")
        typer.echo(f"pinned {tasks} in {pin_task_set(manifest)}")
    pinned = pinned_checksums().get(tasks)
    state = ("matches the pin" if pinned == manifest["checksum"] else "differs from the pin" if pinned and not num_tasks
             else "not pinned" if not pinned else "a prefix of the set (not comparable with the pin)")
    typer.echo(f"{out}: {len(manifest['tasks'])} tasks of {tasks}; checksum {manifest['checksum']} ({state})")


def plan(
    model: str = typer.Option(..., "--model", help="random | oracle | dsr | single | nowarp | 3dflow, or learned "
                              "models separated by commas (3dflow,single,dsr): an ensemble moving the first's "
                              "objects by the mean of their motions."),
    tasks: str = typer.Option("plan-novel-test", "--tasks", help="Task directory, or a task set's name "
                              "(data/<name>)."),
    out: Path = typer.Option(..., "--out", "-o", help="Directory for the plan files and results.json."),
    candidates: int = typer.Option(100, "--candidates", "-c", help="Candidate actions per step (the paper: 100)."),
    workers: int = typer.Option(1, "--workers", "-w", help="Parallel worker processes (one task each)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the candidate sampling (with each task's seed)."),
    checkpoint: Path | None = typer.Option(None, "--checkpoint", help="A learned model's checkpoint (default: "
                                              "the shipped CPU-track weights)."),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda (learned models)."),
    num_tasks: int | None = typer.Option(None, "--num-tasks", "-n", help="Only the first N tasks (partial "
                                            "results)."),
    margin: float | None = typer.Option(None, "--margin", help="Push an object only when its predicted cost beats "
                                        f"the best clear push's by this (default: {PLAN_MARGIN} for a learned "
                                        "model, 0 for the oracle)."),
    masks: str = typer.Option("model", "--masks", help="A learned planner's objects of the current state: model "
                              "(its mask head) | observed (from the TSDF's geometry)."),
) -> None:
    """Plan 3 pushes per task with MPC (sample candidates, score by the paper's cost, execute the best in pybullet),
    write a plan file per task and results.json (final-vs-target voxel IoU per task and mean).

    Every task file is checked against this toolkit's pin first (a task that differs: a warning, results not
    pinned); a rerun keeps the plan files of the same run, rescored from their final states, and plans the others
    again."""
    from rich.progress import Progress

    from dsr_bench.generators.planning import plan_tasks

    with Progress(transient=True) as bar:
        job = bar.add_task(f"plan {model}", total=num_tasks or _size(tasks))
        r = plan_tasks(model, tasks, out, candidates, workers, seed, checkpoint, device, num_tasks,
                       progress=lambda: bar.advance(job), warn=lambda line: typer.echo(f"warning: {line}", err=True),
                       margin=margin, masks=masks)
    m = r["metrics"]
    typer.echo(f"{r['method']} on {r['task_set']} ({r['coverage']['scored']}/{r['coverage']['expected']} tasks"
               f"{', pinned' if r['pinned'] else ''}): IoU {m['iou']:.4f} (start {m['start_iou']:.4f}), occupancy IoU "
               f"{m['iou_occupancy']:.4f}; {m['tasks_per_minute'] or 0:.2f} tasks/min per worker; "
               f"results in {out / 'results.json'}")


def _size(tasks: str) -> int | None:
    """The number of tasks in a task directory (None if it cannot be read: `plan_tasks` says why)."""
    from dsr_bench.planning.tasks import resolve_tasks

    try:
        return len(resolve_tasks(tasks)[1]["tasks"])
    except UserError:
        return None


def register(app: typer.Typer) -> None:
    """Add the generator's commands to the `dsr-bench` CLI (the `dsr_bench.commands` entry point)."""
    app.command("generate")(generate)
    app.command("generate-captures")(generate_captures)
    app.command("generate-plan-tasks")(generate_plan_tasks)
    app.command("plan")(plan)
    from dsr_bench.generators.challenge import register as register_challenge

    register_challenge(app)  # `dsr-bench challenge create` (the rest of the group: dsr_bench.challenge.cli)
