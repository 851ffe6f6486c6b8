"""`dsr-bench generate-captures`: simulated two-camera RGB-D captures (the annotator's input format)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dsr_bench.errors import UserError


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

    from dsr_bench.constants import MAX_OBJECTS_PER_SCENE
    from dsr_bench.splits import sequence_name, sequence_seed
    from generators.capture import capture_arguments, existing_capture, generate_capture, get_sensor_model
    from generators.episode import SceneRejected
    from generators.objects import get_object_set

    if num < 1:
        raise UserError(f"--num-sequences {num}: must be at least 1")
    if steps < 1:
        raise UserError(f"--steps {steps}: must be at least 1")
    if not 1 <= objects_per_scene <= MAX_OBJECTS_PER_SCENE:
        raise UserError(f"--objects-per-scene {objects_per_scene}: must be 1..{MAX_OBJECTS_PER_SCENE}")
    get_sensor_model(noise)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory; give a directory for the captures")
    object_set = get_object_set(objects, str(object_root) if object_root else None)

    todo, skipped = [], []
    for i in range(num):
        name, s = sequence_name(i), sequence_seed(seed, i)
        state = existing_capture(out / name, capture_arguments(seed=s, objects=objects, steps=steps,
                                                               objects_per_scene=objects_per_scene, noise=noise))
        if state == "absent" or overwrite:
            todo.append((name, s))
        elif state == "same":
            skipped.append(name)
        else:
            raise UserError(f"{out / name} exists with other arguments; pass --overwrite to replace it or choose "
                            "another --out")
    console = Console(stderr=True)
    with Progress(TextColumn("[bold]generate-captures"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.description}"), TimeElapsedColumn(), console=console) as bar:
        task = bar.add_task("", total=num, completed=len(skipped))
        for name, s in todo:
            bar.update(task, description=name)
            try:
                generate_capture(out / name, name=name, seed=s, objects=objects, steps=steps,
                                 objects_per_scene=objects_per_scene, noise=noise,
                                 object_root=str(object_root) if object_root else None, object_set=object_set,
                                 overwrite=True)
            except SceneRejected as exc:
                raise UserError(f"{exc}; try another --seed or fewer --objects-per-scene") from None
            bar.update(task, advance=1)
    console.print(f"{out}: {len(todo)} captures written, {len(skipped)} already present "
                  f"({objects}, {steps} pushes, {objects_per_scene} objects, noise {noise})")


def register(app: typer.Typer) -> None:
    app.command("generate-captures")(generate_captures)
