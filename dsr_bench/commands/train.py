"""`dsr-bench train`: one curriculum stage of a reference model."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def train(
    model: str = typer.Option("dsr", "--model", help="dsr | single | nowarp | gtwarp | 3dflow"),
    stage: str = typer.Option(..., "--stage", help="cube-single | cube-multi | shapenet-multi (any data set)"),
    data: Path = typer.Option(..., "--data", help="Dataset directory (e.g. generated with --split cube-train)."),
    out: Path = typer.Option(..., "--out", "-o", help="Run directory: checkpoints, config.json, metrics.jsonl."),
    split: Optional[str] = typer.Option(None, "--split", help="Training split (default: the only one)."),
    val_split: Optional[str] = typer.Option(None, "--val-split", help="Validation split (IoU after each epoch)."),
    init: Optional[Path] = typer.Option(None, "--init", help="Start from this checkpoint's weights (next stage)."),
    resume: Optional[Path] = typer.Option(None, "--resume", help="Resume a run exactly (optimizer, schedule, RNG, data)."),
    epochs: Optional[int] = typer.Option(None, "--epochs", help="Override the stage's epochs."),
    batch_size: Optional[int] = typer.Option(None, "--batch-size", help="Per process (default 12)."),
    lr: Optional[float] = typer.Option(None, "--lr", help="Override the stage's initial learning rate."),
    max_steps: Optional[int] = typer.Option(None, "--max-steps", help="Stop after this many optimisation windows."),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda (torchrun sets one GPU per process)."),
    bf16: bool = typer.Option(False, "--bf16", help="bf16 autocast (pivots, softmax, warp stay fp32)."),
    compile_model: bool = typer.Option(False, "--compile", help="torch.compile the model."),
    channels_last: bool = typer.Option(False, "--channels-last", help="channels_last_3d memory format."),
    workers: int = typer.Option(2, "--workers", help="DataLoader worker processes."),
    seed: int = typer.Option(0, "--seed"),
) -> None:
    """Train a reference model for one stage of the paper's curriculum (torchrun for multi-GPU)."""
    from dsr_bench.errors import UserError
    from dsr_bench.models.config import MODEL_NAMES
    from dsr_bench.train import train as run

    if model not in MODEL_NAMES:
        raise UserError(f"--model {model!r}: choose one of {', '.join(MODEL_NAMES)}")
    path = run(model, stage, data, out, split=split, val_split=val_split, epochs=epochs, batch_size=batch_size, lr=lr,
               max_steps=max_steps, init=init, resume=resume, device=device, bf16=bf16, compile_model=compile_model,
               channels_last=channels_last, workers=workers, seed=seed)
    typer.echo(f"checkpoint: {path}")


def register(app: typer.Typer) -> None:
    app.command("train")(train)
