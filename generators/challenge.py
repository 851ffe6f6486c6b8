"""`dsr-bench challenge create`: generate a challenge's hidden sequences from a secret seed (the simulator runs
here, so the command lives above the library) and hand them to `dsr_bench.challenge.host` to pin and split."""

from __future__ import annotations

import os
import secrets
from dataclasses import replace
from pathlib import Path
from typing import Optional

import typer

from dsr_bench.challenge.layout import HIDDEN_SPLIT, Layout, write_secret_seed
from dsr_bench.errors import UserError


def create(
    root: Path = typer.Argument(..., help="New challenge directory (made 0700; the secret seed never leaves it)."),
    split: str = typer.Option(..., "--split", help="The split whose generation parameters the hidden set takes "
                              "(objects, steps, objects per scene, policy, size), e.g. procedural-novel-test."),
    num_sequences: Optional[int] = typer.Option(None, "--num-sequences", "-n", help="Hidden sequences (default: "
                                                "the split's size)."),
    steps: Optional[int] = typer.Option(None, "--steps", help="Pushes per sequence (default: the split's; fewer "
                                        "for a trial challenge)."),
    public_fraction: float = typer.Option(0.5, "--public-fraction", help="Share of the hidden sequences whose "
                                          "scores the leaderboard shows during the challenge (the public part)."),
    workers: int = typer.Option(1, "--workers", "-w", help="Parallel generator processes."),
    export: bool = typer.Option(True, "--export-inputs/--no-export-inputs", help="Also write DIR/inputs, which "
                                "the server offers for download."),
) -> None:
    """Make a challenge: a secret seed (from `secrets`, written only to DIR/secret_seed, 0600), the hidden sequences
    generated with the split's parameters but that seed, their public/private parts, and their pins in DIR."""
    from rich.progress import Progress

    from dsr_bench.challenge.host import export_inputs, finish_hidden_set
    from dsr_bench.dataset.splits import get_split
    from dsr_bench.generators.run import finalize_dataset, generate_dataset, plan_from_arguments, prepare_run

    spec = get_split(split)
    if root.exists() and any(root.iterdir()):
        raise UserError(f"{root} exists and is not empty; give a new directory for the challenge")
    n = spec.num_sequences if num_sequences is None else num_sequences
    if n < 2:
        raise UserError(f"--num-sequences {n}: a challenge needs at least 2 (a public and a private part)")
    root.mkdir(parents=True, exist_ok=True)
    os.chmod(root, 0o700)
    layout = Layout(root)
    seed = secrets.randbits(63)
    write_secret_seed(layout, seed)
    plan = plan_from_arguments(objects=spec.objects, num_sequences=n, out=layout.hidden, seed=seed,
                               steps=spec.steps if steps is None else steps, objects_per_scene=spec.objects_per_scene,
                               policy=spec.policy, workers=workers)
    plan = replace(plan, split=HIDDEN_SPLIT)
    todo, _ = prepare_run(plan)
    with Progress(transient=True) as bar:
        task = bar.add_task("generate hidden sequences", total=len(todo))
        generate_dataset(plan, todo, progress=lambda _result: bar.advance(task))
    finalize_dataset(plan)
    parameters = {"split": split, "objects": spec.objects, "steps": plan.config.steps,
                  "objects_per_scene": spec.objects_per_scene, "policy": spec.policy}
    config = finish_hidden_set(layout, parameters, public_fraction)
    if export:
        export_inputs(layout, layout.inputs)
    typer.echo(f"challenge made in {root}: {n} hidden sequences ({len(config['public'])} public, "
               f"{len(config['private'])} private); next: dsr-bench challenge add-team {root} NAME")


def register(app: typer.Typer) -> None:
    """Add `create` to the `challenge` group (dsr_bench.challenge.cli registers the group itself)."""
    from dsr_bench.challenge.cli import challenge_app

    challenge_app.command("create")(create)
