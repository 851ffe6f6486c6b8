"""`dsr-bench train`: one curriculum stage of a reference model (torchrun-compatible)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Tuple

import typer


def train(
    model: str = typer.Option("dsr", "--model", help="dsr | single | nowarp | gtwarp | 3dflow"),
    stage: str = typer.Option(..., "--stage", help="cube-single | cube-multi | shapenet-multi (any data set)"),
    data: Path = typer.Option(..., "--data", help="Dataset directory (e.g. generated with --split cube-train)."),
    out: Path = typer.Option(..., "--out", "-o", help="Run directory: last.pt, config.json, metrics.jsonl."),
    split: Optional[str] = typer.Option(None, "--split", help="Training split (default: the only one)."),
    val_split: Optional[str] = typer.Option(None, "--val-split", help="Validation split (IoU after each epoch)."),
    init: Optional[Path] = typer.Option(None, "--init", help="Start from this checkpoint's weights (next stage)."),
    resume: Optional[Path] = typer.Option(None, "--resume", help="Resume a run exactly (optimizer, schedule, RNG, data)."),
    epochs: Optional[int] = typer.Option(None, "--epochs", help="Override the stage's epochs."),
    batch_size: Optional[int] = typer.Option(None, "--batch-size", help="Per process (default 12)."),
    lr: Optional[float] = typer.Option(None, "--lr", help="Constant learning rate instead of the official schedule."),
    window: Optional[int] = typer.Option(None, "--window", help="Override the stage's window (pushes per sample)."),
    max_steps: Optional[int] = typer.Option(None, "--max-steps", help="Stop after this many windows (batches)."),
    max_minutes: Optional[float] = typer.Option(None, "--max-minutes", help="Stop after this much training time."),
    grid_size: Optional[Tuple[int, int, int]] = typer.Option(None, "--grid-size", help="Expected grid Y X Z "
                                                             "(default: the data's)."),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda (torchrun sets one GPU per process)."),
    bf16: bool = typer.Option(False, "--bf16", help="bf16 autocast (softmax, pivots, motion, warp stay fp32)."),
    compile_model: bool = typer.Option(False, "--compile", help="torch.compile the model (GPU only)."),
    channels_last: bool = typer.Option(False, "--channels-last", help="channels_last_3d memory format."),
    deterministic: bool = typer.Option(False, "--deterministic", help="Deterministic algorithms and warp."),
    official_bn: bool = typer.Option(False, "--official-bn", help="Validate with BatchNorm in train mode (official)."),
    workers: int = typer.Option(4, "--workers", help="DataLoader worker processes per GPU."),
    checkpoint_every: int = typer.Option(0, "--checkpoint-every", help="Also save last.pt every N steps (0: per epoch)."),
    seed: int = typer.Option(0, "--seed", help="Seed of initialisation and data order."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
) -> None:
    """Train a reference model for one stage of the paper's curriculum (torchrun for multi-GPU)."""
    from dsr_bench.errors import UserError
    from dsr_bench.models.config import MODEL_NAMES
    from dsr_bench.models.training.config import TrainConfig
    from dsr_bench.models.training.trainer import train as run

    if model not in MODEL_NAMES:
        raise UserError(f"--model {model!r}: choose one of {', '.join(MODEL_NAMES)}")
    if max_steps is not None and max_steps < 1:
        raise UserError(f"--max-steps {max_steps}: must be at least 1")
    if max_minutes is not None and max_minutes <= 0:
        raise UserError(f"--max-minutes {max_minutes}: must be positive")
    if workers < 0 or checkpoint_every < 0:
        raise UserError("--workers and --checkpoint-every must be >= 0")
    if resume is not None and init is not None:
        raise UserError("--resume continues a run with its own weights; drop --init")
    config = TrainConfig(model_name=model, stage_name=stage, data=data, out=out, split=split, val_split=val_split,
                         epochs=epochs, batch_size=batch_size, lr=lr, window=window, max_steps=max_steps,
                         max_seconds=None if max_minutes is None else max_minutes * 60, init=init, resume=resume,
                         device=device, bf16=bf16, compile_model=compile_model, channels_last=channels_last,
                         workers=workers, seed=seed, official_bn=official_bn, deterministic=deterministic,
                         grid=tuple(grid_size) if grid_size else None, checkpoint_every=checkpoint_every,
                         progress=not quiet)
    path = run(config)
    if os.environ.get("RANK", "0") == "0":
        typer.echo(f"checkpoint: {path}")


def register(app: typer.Typer) -> None:
    app.command("train")(train)
