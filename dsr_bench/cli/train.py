"""`dsr-bench train`: a reference model by one recipe of its kind (`models.training.tracks`; torchrun-compatible), or
its weights fine-tuned on a real split (`--finetune`, `models.training.finetune`).

The options are grouped by the tracks that read them (`--help` shows the groups, and after each option the tracks
that take it, from the recipes' tables); each recipe refuses in one line an option it does not read
(`tracks.Track.check`), and checks the values of those it does."""

from __future__ import annotations

import os
from pathlib import Path
from typing import List, Optional, Tuple

import typer

from dsr_bench.models import registry
from dsr_bench.models.training.tracks import COMMON, tracks_taking

EVERY = "Every track"
HELDOUT = "Held-out evaluation (every track)"
FULL = "The full track (--track full, the default): the paper's stages on the 128 x 128 x 48 grid"
BUDGET = "Budget and checkpoints (the full track; a lent GPU's short runs are the same command with a budget)"
DEVICE = "Device (the full track; --device also the 2D track)"
CPU = "The CPU track (--track cpu): both of its stages on 32 x 32 x 16"
FINETUNE = "Fine-tuning on a real split (--finetune; the CPU track's and the 2D track's models)"


def _name_the_tracks(command) -> None:
    """End the help of each option of `command` that not every track reads with the tracks that do (from the
    recipes' tables, `tracks.tracks_taking`)."""
    import inspect

    for name, parameter in inspect.signature(command).parameters.items():
        info = parameter.default
        if isinstance(info, typer.models.OptionInfo) and name not in COMMON:
            info.help = f"{info.help} Tracks: {', '.join(tracks_taking(name))}."


def train(
    ctx: typer.Context,
    model: str = typer.Option("dsr", "--model", rich_help_panel=EVERY, help=(
        f"{registry.help_text(registry.VOXEL)} (the 3D track) or "
        f"{registry.help_text(registry.IMAGE)} (the 2D track: front-camera images)")),
    track: str = typer.Option("full", "--track", rich_help_panel=EVERY, help=(
        "full (the benchmark's 128 x 128 x 48 grid: one curriculum stage, or all of them) or cpu (the "
        "CPU track: 32 x 32 x 16, both stages, docs/models.md).")),
    data: Path = typer.Option(..., "--data", rich_help_panel=EVERY, help=(
        "Dataset directory (e.g. generated with --split cube-train).")),
    out: Path = typer.Option(..., "--out", "-o", rich_help_panel=EVERY, help=(
        "Run directory: last.pt, config.json, metrics.jsonl (--stage curriculum: one per stage in "
        "it; --track cpu and the 2D track: the weights file to write, e.g. dsr.pt).")),
    split: Optional[str] = typer.Option(None, "--split", rich_help_panel=EVERY, help=(
        "Training split (default: the only one).")),
    batch_size: Optional[int] = typer.Option(None, "--batch-size", rich_help_panel=EVERY, help=(
        "Windows per batch (per process; default: the recipe's, 12 on the full track, 8 on "
        "the others).")),
    lr: Optional[float] = typer.Option(None, "--lr", rich_help_panel=EVERY, help=(
        "Learning rate: on the full track a constant one instead of the official schedule; the CPU "
        "track's stage 1 and the 2D track's (default 1e-3).")),
    seed: int = typer.Option(0, "--seed", rich_help_panel=EVERY, help=(
        "Seed of initialisation and data order.")),
    workers: int = typer.Option(4, "--workers", rich_help_panel=EVERY, help=(
        "DataLoader worker processes per GPU (the CPU-sized tracks: processes reducing the "
        "split once).")),
    quiet: bool = typer.Option(False, "--quiet", rich_help_panel=EVERY, help=(
        "No progress bar or progress lines.")),
    eval_data: Optional[Path] = typer.Option(None, "--eval-data", rich_help_panel=HELDOUT, help=(
        "After training, predict this held-out dataset with the weights written and score it: "
        "OUT/evaluation.json and OUT/predictions (OUT a weights file: beside it, with .evaluation.json, "
        ".predictions for .pt).")),
    eval_split: Optional[str] = typer.Option(None, "--eval-split", rich_help_panel=HELDOUT, help=(
        "The held-out split (default: --eval-data's only one).")),
    finetune: bool = typer.Option(False, "--finetune", rich_help_panel=FINETUNE, help=(
        "Fine-tune --init (weights trained in simulation) on --data, a real split (`dsr-bench real-split`; default "
        "split: its fine-tune part): --epochs passes (default 20) at --lr (default 1e-4) halved after every 3, "
        "then precise BatchNorm (voxel models); writes --out, the weights of NAME-ft. Resumable: the same command "
        "goes on from OUT's .partial.pt.")),
    stage: Optional[str] = typer.Option(None, "--stage", rich_help_panel=FULL, help=(
        "cube-single | cube-multi | shapenet-multi (any data set), or curriculum: the three in turn, "
        "each in OUT/STAGE, resumable by running the command again.")),
    stage_data: Optional[List[str]] = typer.Option(None, "--stage-data", rich_help_panel=FULL, help=(
        "STAGE=DIR: the curriculum's data of that stage instead of --data (e.g. "
        "shapenet-multi=data/shapenet-train); repeat per stage.")),
    init: Optional[Path] = typer.Option(None, "--init", rich_help_panel=FULL, help=(
        "Start from this checkpoint's weights (the next stage; --track cpu: another run's "
        ".stage1.pt, stage 1 skipped, or a finished run's weights file of this model: --multi-batches "
        "more of stage 2, continuing it; --finetune: the weights to fine-tune).")),
    resume: Optional[Path] = typer.Option(None, "--resume", rich_help_panel=FULL, help=(
        "Resume a run exactly (optimizer, schedule, RNG, data); --stage curriculum: go on from this "
        "checkpoint's stage where OUT holds none later.")),
    epochs: Optional[int] = typer.Option(None, "--epochs", rich_help_panel=FULL, help=(
        "Override the stage's epochs (the curriculum: every stage's; --finetune: passes over the fine-tune part, "
        "default 20).")),
    epoch_samples: Optional[int] = typer.Option(None, "--epoch-samples", rich_help_panel=FULL, help=(
        "Sample-steps per epoch, drawn from the data in repeated shuffled passes (default: one "
        "pass; the paper's: 40000).")),
    schedule: str = typer.Option("official", "--schedule", rich_help_panel=FULL, help=(
        "official (the release's per-epoch tables) or paper (1e-3 halved every 5 epochs; fine-tuning "
        "1e-4 halved every 3).")),
    window: Optional[int] = typer.Option(None, "--window", rich_help_panel=FULL, help=(
        "Override the stage's window (pushes per sample; the curriculum: its multi-step stages').")),
    val_split: Optional[str] = typer.Option(None, "--val-split", rich_help_panel=FULL, help=(
        "Validation split (IoU after each epoch).")),
    grid_size: Optional[Tuple[int, int, int]] = typer.Option(None, "--grid-size", rich_help_panel=FULL, help=(
        "Expected grid Y X Z (default: the data's).")),
    bn_recalibration: int = typer.Option(16, "--bn-recalibration", rich_help_panel=FULL, help=(
        "At the stage's end, re-estimate BatchNorm's running statistics on N batches of whole "
        "sequences, the state carried (0: keep the moving averages; docs/models.md, BatchNorm).")),
    official_bn: bool = typer.Option(False, "--official-bn", rich_help_panel=FULL, help=(
        "Validate with BatchNorm in train mode (official).")),
    deterministic: bool = typer.Option(False, "--deterministic", rich_help_panel=FULL, help=(
        "Deterministic algorithms and warp.")),
    max_steps: Optional[int] = typer.Option(None, "--max-steps", rich_help_panel=BUDGET, help=(
        "Stop after this many windows (batches) of the stage (the curriculum: of this command, over "
        "its stages; --finetune: of this command), with a resumable checkpoint.")),
    max_minutes: Optional[float] = typer.Option(None, "--max-minutes", rich_help_panel=BUDGET, help=(
        "Stop after this much training time (the curriculum: this command's, over its stages), with "
        "a resumable checkpoint.")),
    checkpoint_every: int = typer.Option(0, "--checkpoint-every", rich_help_panel=BUDGET, help=(
        "Also save last.pt every N steps (0: per epoch).")),
    device: str = typer.Option("cpu", "--device", rich_help_panel=DEVICE, help=(
        "cpu or cuda (torchrun sets one GPU per process).")),
    bf16: bool = typer.Option(False, "--bf16", rich_help_panel=DEVICE, help=(
        "bf16 autocast (softmax, pivots, motion, warp stay fp32).")),
    compile_model: bool = typer.Option(False, "--compile", rich_help_panel=DEVICE, help=(
        "torch.compile the model (GPU only).")),
    channels_last: bool = typer.Option(False, "--channels-last", rich_help_panel=DEVICE, help=(
        "channels_last_3d memory format.")),
    single_batches: Optional[int] = typer.Option(None, "--single-batches", rich_help_panel=CPU, help=(
        "Stage 1 single-step batches (default 3000; the 2D track: all its batches, default "
        "2000).")),
    multi_batches: int = typer.Option(300, "--multi-batches", rich_help_panel=CPU, help=(
        "Stage 2 batches of --window steps (models without history: x window single-step batches).")),
    multi_lr: Optional[float] = typer.Option(None, "--multi-lr", rich_help_panel=CPU, help=(
        "Stage 2's learning rate (default 5e-4, halved at 50% and 75% of its batches), also a "
        "continued chunk's (--init a finished run).")),
    same_windows: bool = typer.Option(False, "--same-windows", rich_help_panel=CPU, help=(
        "single and 3dflow: stage 2 on the history models' --window-step windows (zero state) "
        "instead of single steps.")),
) -> None:
    """Train a reference model: one stage of the paper's curriculum or all of them (the full track; torchrun for
    multi-GPU), the CPU track's recipe, or the 2D track's. Options a track does not read are refused."""
    options = dict(ctx.params)
    defaults = {param.name: param.default for param in ctx.command.params}
    typed = {name for name in options if getattr(ctx.get_parameter_source(name), "name", "") == "COMMANDLINE"}
    given = {name: value for name, value in options.items() if name in typed and value != defaults.get(name)}
    entry = registry.model_entry(model, *registry.trainable())
    recipe = entry.model_kind.track(track)
    if finetune:
        recipe = recipe.finetuning()
    recipe.check(given)
    rank0 = os.environ.get("RANK", "0") == "0"
    if eval_data is not None:
        eval_split = eval_split or _real_test_part(eval_data)
        _check_heldout(eval_data, eval_split, out, recipe.result)
    report = (lambda line: None) if quiet or not rank0 else (lambda line: typer.echo(line, err=True))
    path = recipe.train(model, options, report)
    if rank0:
        if path.name.endswith(".partial.pt"):  # --finetune stopped by --max-steps: nothing finished to evaluate
            typer.echo(f"resumable checkpoint: {path} (run the same command again to go on)")
            return
        typer.echo(f"{recipe.result}: {path}")
        if eval_data is not None:
            _evaluate(model, path, eval_data, eval_split, out, recipe.result, device)


def _real_test_part(data: Path) -> str | None:
    """A real split's held-out test part (what --eval-data scores by default), None for another dataset."""
    from dsr_bench.dataset.real import read_real_split

    real = read_real_split(data) if data.is_dir() else None
    return None if real is None else real["parts"]["test"]


def _heldout_paths(out: Path, result: str) -> tuple[Path, Path]:
    """(results JSON, predictions directory) of the held-out evaluation of a run writing OUT."""
    if result == "checkpoint":  # a run directory
        return out / "evaluation.json", out / "predictions"
    return out.with_suffix(".evaluation.json"), out.with_suffix(".predictions")


def _check_heldout(data: Path, split: str | None, out: Path, result: str) -> None:
    """The held-out split and the files the evaluation writes, checked before any training."""
    from dsr_bench.atomic import check_writable
    from dsr_bench.dataset.manifest import read_split

    read_split(data, split)
    results, predictions = _heldout_paths(out, result)
    check_writable(results, "--out", directory=False)
    check_writable(predictions, "--out")


def _evaluate(model: str, weights: Path, data: Path, split: str | None, out: Path, result: str, device: str) -> None:
    """Predict and score the held-out split with the weights written; the results beside them."""
    import json

    from dsr_bench.atomic import write_text
    from dsr_bench.models.training.tracks import evaluate_heldout

    results_path, predictions = _heldout_paths(out, result)
    results = evaluate_heldout(model, weights, data, split, predictions, device)
    write_text(results_path, json.dumps(results, indent=1, sort_keys=True) + "\n")
    shown = ", ".join(f"{key} {value:.4f}" for key, value in results["metrics"].items() if isinstance(value, float))
    typer.echo(f"held-out {results['split']} ({results['coverage']['scored']} sequences): {shown}; {results_path}")


_name_the_tracks(train)


def register(app: typer.Typer) -> None:
    app.command("train")(train)
