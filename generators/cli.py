"""The generator's `dsr-bench` commands: `generate` (pushing sequences) and `generate-captures` (simulated
two-camera RGB-D captures, the annotator's input), registered through the `dsr_bench.commands` entry point."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dsr_bench.cli.engine_options import (RayAddress, Slurm, SlurmLocal, SlurmLogs, SlurmPartition, SlurmTasks,
                                         SlurmTime)

OBJECT_SETS_HELP = "cube | shapenet | ycb | procedural | procedural-novel"


def generate(
    objects: Optional[str] = typer.Option(None, "--objects", help=f"Object set: {OBJECT_SETS_HELP}."),
    num_sequences: Optional[int] = typer.Option(None, "--num-sequences", "-n", help="Sequences to generate."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Dataset directory (default data/<split> with "
                                       "--split; required otherwise)."),
    split: Optional[str] = typer.Option(None, "--split", help="A named benchmark split (sets objects, size, seed)."),
    seed: Optional[int] = typer.Option(None, "--seed", help="Base seed; sequence i uses a seed derived from it and i."),
    steps: Optional[int] = typer.Option(None, "--steps", help="Pushes per sequence (default 10)."),
    objects_per_scene: Optional[int] = typer.Option(None, "--objects-per-scene", help="Objects per scene, 1-5 (default 4)."),
    policy: Optional[str] = typer.Option(None, "--policy", help="heuristic (the paper's) or random."),
    cameras: str = typer.Option("front", "--cameras", help="front, or front,back for the rig's second view."),
    workers: Optional[int] = typer.Option(None, "--workers", "-w", help="Parallel worker processes (default 1; "
                                          "with --ray local the CPUs of its Ray, with --slurm those of each task)."),
    shard: Optional[str] = typer.Option(None, "--shard", help="Generate only shard i of n (i/n), e.g. in a SLURM "
                                        "array written by hand (--ray and --slurm shard the run themselves)."),
    object_root: Optional[Path] = typer.Option(None, "--object-root", help="Mesh root for shapenet / ycb."),
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
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
    from rich.table import Table

    from dsr_bench.engines import engine_from_options, slurm_options_given
    from dsr_bench.errors import UserError
    from generators.run import finalize_dataset, generate_dataset, plan_from_arguments, prepare_run, summarize

    console = Console(stderr=True)
    plan = plan_from_arguments(objects=objects, num_sequences=num_sequences, out=out, split=split, seed=seed,
                               steps=steps, objects_per_scene=objects_per_scene, policy=policy, cameras=cameras,
                               workers=1 if workers is None else workers, shard=shard or "0/1",
                               object_root=object_root)
    if shard is not None and (ray is not None or slurm):
        raise UserError(f"--shard {shard} with {'--ray' if ray is not None else '--slurm'}: the engine splits the run "
                        "itself; drop --shard")
    engine = engine_from_options(ray, slurm, workers, slurm_options_given(slurm_partition, slurm_time, slurm_tasks,
                                                                          slurm_logs, slurm_local), "dsr-bench-generate")
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
        table.add_row("manifest", "not written yet: other shards missing; run `dsr-bench manifest DIR` when all are done")
    console.print(table)



def generate_captures(
    out: Path = typer.Option(..., "--out", "-o", help="Directory to write captures/seq_0000/, seq_0001/, ... into."),
    num: int = typer.Option(1, "--num-sequences", "-n", help="Captures to generate."),
    objects: str = typer.Option("procedural", "--objects", help="Object set: cube | shapenet | ycb | procedural | "
                                                                "procedural-novel."),
    steps: int = typer.Option(10, "--steps", help="Pushes per capture (T; T + 1 steps of images)."),
    objects_per_scene: int = typer.Option(4, "--objects-per-scene", help="Objects per scene, 1-5."),
    seed: int = typer.Option(0, "--seed", help="Base seed; capture i uses a seed derived from it and i."),
    noise: str = typer.Option("realistic", "--noise", help="Sensor model: realistic (RealSense-like depth noise, "
                                                           "missing pixels, calibration error) or none."),
    object_root: Optional[Path] = typer.Option(None, "--object-root", help="Mesh root for shapenet / ycb."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace captures that already exist."),
) -> None:
    """Simulate pushing sequences and write them as captures: colour + 16-bit depth PNGs of the front and back
    cameras, a calibration with small errors, actions, object meshes, and the true poses kept aside in truth.json."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from generators.capture import CapturePlan, generate_captures as run, prepare_captures

    plan = CapturePlan(out=out, num=num, objects=objects, steps=steps, objects_per_scene=objects_per_scene, seed=seed,
                       noise=noise, object_root=str(object_root) if object_root else None, overwrite=overwrite)
    jobs = prepare_captures(plan)
    console = Console(stderr=True)
    with Progress(TextColumn("[bold]generate-captures"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.description}"), TimeElapsedColumn(), console=console) as bar:
        task = bar.add_task("", total=num, completed=len(jobs.skipped))
        run(plan, jobs, started=lambda name: bar.update(task, description=name),
            finished=lambda name: bar.update(task, advance=1))
    console.print(f"{out}: {len(jobs.todo)} captures written, {len(jobs.skipped)} already present "
                  f"({objects}, {steps} pushes, {objects_per_scene} objects, noise {noise})")


def register(app: typer.Typer) -> None:
    """Add the generator's commands to the `dsr-bench` CLI (the `dsr_bench.commands` entry point)."""
    app.command("generate")(generate)
    app.command("generate-captures")(generate_captures)
