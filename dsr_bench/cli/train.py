"""`dsr-bench train`: one curriculum stage of a reference model (torchrun-compatible)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Optional, Tuple

import typer

from dsr_bench.models import registry


def train(
    model: str = typer.Option("dsr", "--model", help=f"{registry.help_text(registry.VOXEL)} (the 3D track) or "
                              f"{registry.help_text(registry.IMAGE)} (the 2D track: front-camera images)"),
    stage: Optional[str] = typer.Option(None, "--stage", help="cube-single | cube-multi | shapenet-multi (any data "
                                        "set); not with --track cpu, whose recipe has its own two stages"),
    data: Path = typer.Option(..., "--data", help="Dataset directory (e.g. generated with --split cube-train)."),
    out: Path = typer.Option(..., "--out", "-o", help="Run directory: last.pt, config.json, metrics.jsonl "
                             "(--track cpu: the weights file to write, e.g. dsr.pt)."),
    track: str = typer.Option("full", "--track", help="full (the benchmark's 128 x 128 x 48 grid, one curriculum "
                              "stage) or cpu (the CPU track: 32 x 32 x 16, both stages, docs/models.md)."),
    split: Optional[str] = typer.Option(None, "--split", help="Training split (default: the only one)."),
    val_split: Optional[str] = typer.Option(None, "--val-split", help="Validation split (IoU after each epoch)."),
    init: Optional[Path] = typer.Option(None, "--init", help="Start from this checkpoint's weights (next stage; "
                                         "--track cpu: another run's .stage1.pt, stage 1 skipped; or a finished "
                                         "run's weights file of this model: --multi-batches more of stage 2, "
                                         "continuing it)."),
    resume: Optional[Path] = typer.Option(None, "--resume", help="Resume a run exactly (optimizer, schedule, RNG, "
                                          "data)."),
    epochs: Optional[int] = typer.Option(None, "--epochs", help="Override the stage's epochs."),
    epoch_samples: Optional[int] = typer.Option(None, "--epoch-samples", help="Sample-steps per epoch, drawn from "
                                                "the data in repeated shuffled passes (default: one pass; the "
                                                "paper's: 40000)."),
    batch_size: Optional[int] = typer.Option(None, "--batch-size", help="Per process (default 12)."),
    lr: Optional[float] = typer.Option(None, "--lr", help="Constant learning rate instead of the official schedule."),
    schedule: str = typer.Option("official", "--schedule", help="official (the release's per-epoch tables) or paper "
                                 "(1e-3 halved every 5 epochs; fine-tuning 1e-4 halved every 3)."),
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
    checkpoint_every: int = typer.Option(0, "--checkpoint-every", help="Also save last.pt every N steps (0: per "
                                         "epoch)."),
    seed: int = typer.Option(0, "--seed", help="Seed of initialisation and data order."),
    bn_recalibration: int = typer.Option(16, "--bn-recalibration", help="At the stage's end, re-estimate BatchNorm's "
                                         "running statistics on N batches of whole sequences, the state carried "
                                         "(0: keep the moving averages; docs/models.md, BatchNorm)."),
    single_batches: Optional[int] = typer.Option(None, "--single-batches", help="--track cpu: stage 1 single-step "
                                                 "batches (default 3000; the 2D track: all its batches, default "
                                                 "2000)."),
    multi_batches: int = typer.Option(300, "--multi-batches", help="--track cpu: stage 2 batches of --window "
                                      "steps (models without history: x window single-step batches)."),
    multi_lr: Optional[float] = typer.Option(None, "--multi-lr", help="--track cpu: stage 2's learning rate "
                                             "(default 5e-4, halved at 50% and 75% of its batches), also a "
                                             "continued chunk's (--init a finished run)."),
    same_windows: bool = typer.Option(False, "--same-windows", help="--track cpu, single and 3dflow: stage 2 on the "
                                      "history models' --window-step windows (zero state) instead of single steps."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
) -> None:
    """Train a reference model for one stage of the paper's curriculum (torchrun for multi-GPU)."""
    from dsr_bench.errors import UserError

    kind = registry.model_entry(model, registry.VOXEL, registry.IMAGE).kind  # the trainable kinds
    if kind == registry.IMAGE:
        given = [flag for flag, value in (("--stage", stage), ("--init", init), ("--resume", resume),
                                          ("--window", window), ("--val-split", val_split), ("--epochs", epochs),
                                          ("--epoch-samples", epoch_samples), ("--multi-lr", multi_lr))
                 if value is not None]
        if given:
            raise UserError(f"{given[0]} is not an option of the 2D track's models (single-step, one stage); drop it")
        _train_image(model, data, out, track, split, batch_size, lr, seed, device, workers, single_batches, quiet)
        return
    from dsr_bench.models.training.config import TrainConfig
    from dsr_bench.models.training.trainer import train as run

    if track == "cpu":
        if epoch_samples is not None:
            raise UserError("--epoch-samples is an option of the full track (its recipe counts batches); drop it")
        _train_cpu(model, stage, data, out, split, batch_size, lr, window, seed, workers, bn_recalibration,
                   3000 if single_batches is None else single_batches, multi_batches, multi_lr, init, same_windows,
                   quiet)
        return
    if track != "full":
        raise UserError(f"--track {track!r}: choose full or cpu")
    if multi_lr is not None:
        raise UserError("--multi-lr is the CPU track's stage-2 rate (--track cpu); the full track's is --lr")
    # TrainConfig checks its own values (--stage, --max-steps, --max-minutes, --workers, --resume with --init)
    config = TrainConfig(model_name=model, stage_name=stage or "", data=data, out=out, split=split, val_split=val_split,
                         epochs=epochs, epoch_samples=epoch_samples, batch_size=batch_size, lr=lr, window=window,
                         max_steps=max_steps,
                         max_seconds=None if max_minutes is None else max_minutes * 60, init=init, resume=resume,
                         device=device, bf16=bf16, compile_model=compile_model, channels_last=channels_last,
                         workers=workers, seed=seed, official_bn=official_bn, deterministic=deterministic,
                         grid=grid_size or None, checkpoint_every=checkpoint_every,
                         progress=not quiet, bn_recalibration=bn_recalibration, schedule=schedule)
    path = run(config)
    if os.environ.get("RANK", "0") == "0":
        typer.echo(f"checkpoint: {path}")


def _train_cpu(model: str, stage: str | None, data: Path, out: Path, split: str | None, batch_size: int | None,
               lr: float | None, window: int | None, seed: int, workers: int, bn_recalibration: int,
               single_batches: int, multi_batches: int, multi_lr: float | None, init: Path | None, same_windows: bool,
               quiet: bool) -> None:
    """`--track cpu`: the CPU track's recipe (`models.training.cpu_track`), one weights file (and its
    stage-1 weights beside it); --init: stage 2 from another run's stage-1 weights."""
    from dsr_bench.errors import UserError
    from dsr_bench.models.training.cpu_track import CpuRecipe, train_cpu

    if stage is not None:
        raise UserError(f"--stage {stage}: the CPU track's recipe runs both its stages; drop --stage")
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; --track cpu writes one weights file "
                        f"(e.g. {out / (model + '.pt')})")
    overrides: dict[str, Any] = {k: v for k, v in {"batch_size": batch_size, "lr": lr, "multi_lr": multi_lr,
                                                   "window": window}.items() if v is not None}
    recipe = CpuRecipe(model, single_batches=single_batches, multi_batches=multi_batches, seed=seed,
                       bn_recalibration=bn_recalibration, init=None if init is None else str(init),
                       same_windows=same_windows, **overrides)
    path = train_cpu(recipe, data, split, out, workers=max(1, workers),
                     report=(lambda line: None) if quiet else (lambda line: typer.echo(line, err=True)))
    typer.echo(f"weights: {path}")


def _train_image(model: str, data: Path, out: Path, track: str, split: str | None, batch_size: int | None,
                 lr: float | None, seed: int, device: str, workers: int, batches: int | None, quiet: bool) -> None:
    """The 2D track (`models.training.image_track`): one weights file; --track cpu: 120 x 160 input images,
    full: 240 x 320."""
    from dsr_bench.errors import UserError
    from dsr_bench.models.training.image_track import ImageRecipe, train_image_model

    if track not in ("cpu", "full"):
        raise UserError(f"--track {track!r}: choose full or cpu")
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; the 2D track writes one weights file "
                        f"(e.g. {out / (model + '.pt')})")
    overrides: dict[str, Any] = {k: v for k, v in {"batch_size": batch_size, "lr": lr, "batches": batches}.items()
                                 if v is not None}
    recipe = ImageRecipe(model, seed=seed, image_factor=2 if track == "cpu" else 1, **overrides)
    path = train_image_model(recipe, data, split, out, device, workers=max(1, workers),
                             report=(lambda line: None) if quiet else (lambda line: typer.echo(line, err=True)))
    typer.echo(f"weights: {path}")


def register(app: typer.Typer) -> None:
    app.command("train")(train)
