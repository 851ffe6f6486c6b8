"""Fine-tuning on a real split: `dsr-bench train --finetune --init WEIGHTS --data REAL_SPLIT` (the paper's "ft" rows).

The paper fine-tunes models trained in simulation on 50 annotated real sequences and tests on 100 others (Sec. 4,
"Train/Test split"); its appendix ("Training Details") says how it fine-tunes a trained model: an initial learning
rate of 1e-4 halved after every 3 epochs (the rate of its fine-tuning stages, which run 20 epochs; Adam, betas 0.9
and 0.95). The recipe here is that: `epochs` passes (default 20) over the fine-tune part of a real split
(`dsr_bench.dataset.real`: `<name>-finetune`, the default split of a real split), each pass every window once in
an order drawn from (seed, epoch), the rate `lr` (1e-4) halved after every `decay_every` (3) epochs, through the one
loop (`loop.run_steps`) and the recipes' own steps:

- the CPU track's voxel models (`cpu_track`): the split pooled to 32 x 32 x 16, the model's stage-2 windows (the
  history models: whole windows of `window` pushes, the init's recipe's, at most the sequences' length, not
  overlapping, the state carried; SingleStep and 3DFlow: single steps), `trainer.train_step`; then precise BatchNorm
  on `bn_recalibration` batches of whole sequences of the fine-tune part, as the recipe ends (the real depth's
  statistics are not the simulator's);
- the 2D track's image models (`image_track`): single steps, `image_track.image_step`.

The full track (128 x 128 x 48) fine-tunes with its own stages: `--stage cube-multi --schedule paper` is the same
rate (`schedules.SCHEDULES["paper-finetune"]`) from `--init` a run's last.pt on `--data REAL --split NAME-finetune`.

Resumable: a checkpoint `<out>.partial.pt` (role "checkpoint": weights in fp32, optimiser, epoch and batch position,
RNG states, the recipe) is written after every epoch and when `max_steps` ends this invocation; the same command
resumes it exactly (the windows of an epoch are drawn again from (seed, epoch)) and removes it when the weights are
written. The weights file is the one format (`checkpoints`: role "weights", fp16), the init's own records kept
(`recipe`, `stages` or `training`, its `data`: what it was trained on in simulation) and the stage's record added
under `finetune`: the file and SHA-256 it started from, the data (the real split's name, part and checksum), epochs,
rate, windows, batches and sample-steps, the loss per epoch, and BatchNorm's recalibration. A predictor of such
weights is named `NAME-ft` (`mark_finetuned`), as the paper labels its fine-tuned rows.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch

from dsr_bench.dataset.manifest import file_sha256, read_split
from dsr_bench.dataset.real import read_real_split
from dsr_bench.errors import UserError
from dsr_bench.models import registry
from dsr_bench.models.training.checkpoints import (Weights, data_provenance, read_weights, rng_state, save_weights,
                                                   set_rng_state, torch_device)
from dsr_bench.models.training.loop import run_steps

#: the paper's fine-tuning rate (appendix, "Training Details"): 1e-4, halved after every 3 epochs, for 20 epochs
PAPER_LR, PAPER_DECAY_EVERY, PAPER_EPOCHS = 1e-4, 3, 20


@dataclass(frozen=True)
class FinetuneRecipe:
    """Everything that defines a fine-tuning run (saved in its weights file under `finetune`, and in its partial
    checkpoint, which a resumed run must match)."""

    model_name: str
    #: the zero-shot weights' file name (never a path of this machine) and SHA-256
    init: str
    init_sha256: str
    epochs: int = PAPER_EPOCHS
    lr: float = PAPER_LR
    decay_every: int = PAPER_DECAY_EVERY
    batch_size: int = 8
    #: pushes per window of a history model (1: models without history and the 2D track)
    window: int = 1
    bn_recalibration: int = 16
    seed: int = 0

    def __post_init__(self):
        if self.epochs < 1 or self.decay_every < 1:
            raise UserError(f"--epochs {self.epochs}: must be at least 1")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise UserError(f"--lr {self.lr}: a learning rate must be a finite number above 0")
        if self.batch_size < 2:
            raise UserError(f"--batch-size {self.batch_size}: fine-tuning needs at least 2 (BatchNorm's training "
                            "statistics need two samples)")
        if self.window < 1 or self.bn_recalibration < 0:
            raise UserError("--window must be at least 1 and --bn-recalibration >= 0")

    def lr_at(self, epoch: int) -> float:
        """The learning rate of epoch `epoch` (0-based): `lr` halved after every `decay_every` epochs."""
        return self.lr / 2 ** (epoch // self.decay_every)


def partial_path(out: Path) -> Path:
    """Where a fine-tuning run writing `out` keeps its resumable checkpoint."""
    return Path(out).with_suffix(".partial.pt")


def finetune_split(data: Path, split: str | None) -> tuple[str, dict | None]:
    """(the split to fine-tune on, the real split's record or None): --split, else a real split's fine-tune part,
    else the dataset's only split. A real split's test part is refused: it is what the fine-tuned model is scored
    on."""
    real = read_real_split(data)
    if real is not None:
        if split is None:
            split = real["parts"]["finetune"]
        elif split == real["parts"]["test"]:
            raise UserError(f"--split {split} is the held-out test part of the real split {real['name']!r}; "
                            f"fine-tune on {real['parts']['finetune']}")
    return read_split(data, split)[0], real


# --- the epochs ---------------------------------------------------------------------------------------------------
def _units(count: int, steps: int, window: int) -> np.ndarray:
    """Every (sequence, first push) of an epoch: windows of `window` pushes that do not overlap (stride = window, as
    the official loader), or every push for single steps."""
    starts = np.arange(0, steps - window + 1, window)
    return np.stack(np.meshgrid(np.arange(count), starts, indexing="ij"), -1).reshape(-1, 2)


def epoch_batches(units: np.ndarray, batch_size: int, seed: int, epoch: int) -> list[np.ndarray]:
    """The batches of one epoch: `units` in an order drawn from (seed, epoch), `batch_size` at a time; a last batch
    of a single window joins the one before (BatchNorm needs two samples)."""
    order = units[np.random.default_rng([int(seed), int(epoch)]).permutation(len(units))]
    batches = [order[i:i + batch_size] for i in range(0, len(order), batch_size)]
    if len(batches) > 1 and len(batches[-1]) == 1:
        batches[-2:] = [np.concatenate(batches[-2:])]
    return batches


def _run(net, recipe: FinetuneRecipe, units: np.ndarray, batch_of: Callable[[np.ndarray], dict], step, out: Path,
         config, sections: dict, max_steps: int | None, report: Callable[[str], None]) -> dict | None:
    """Train the epochs (resuming `out`'s partial checkpoint); returns the run's record, or None when `max_steps` ended
    this invocation first (the partial checkpoint then holds where it stands)."""
    if len(units) < 2:
        raise UserError(f"the fine-tune split holds {len(units)} window(s) of {recipe.window} pushes; fine-tuning "
                        "needs at least 2 (BatchNorm)")
    optimizer = torch.optim.Adam(net.parameters(), lr=recipe.lr, betas=(0.9, 0.95))
    epoch, index, done, losses, seconds = 0, 0, 0, [], 0.0
    saved = partial_path(out)
    if saved.is_file():
        state = read_weights(saved, model=recipe.model_name, role="checkpoint")
        if state.get("finetune_recipe") != dataclasses.asdict(recipe):
            raise UserError(f"{saved}: a fine-tuning run with other settings or weights than these; give the same "
                            "options to resume it, or delete it to start again")
        state.load_into(net)
        optimizer.load_state_dict(state["optimizer"])
        set_rng_state(state["rng"])
        epoch, index, done = int(state["epoch"]), int(state["batch_index"]), int(state["step"])
        losses, seconds = list(state["losses"]), float(state["seconds"])
        report(f"{recipe.model_name}: resuming fine-tuning at epoch {epoch + 1}/{recipe.epochs}, batch {index}")
    net.train()
    ran = 0
    while epoch < recipe.epochs:
        for group in optimizer.param_groups:
            group["lr"] = recipe.lr_at(epoch)
        batches = epoch_batches(units, recipe.batch_size, recipe.seed, epoch)
        started = time.perf_counter()
        for _, terms, _ in run_steps(step, net, (batch_of(b) for b in batches[index:]), optimizer, start=done):
            losses.append([epoch, float(np.mean([t["total"] for t in terms]))])
            index, done, ran = index + 1, done + 1, ran + 1
            if max_steps is not None and ran >= max_steps and index < len(batches):
                break
        seconds += time.perf_counter() - started
        if index >= len(batches):
            epoch, index = epoch + 1, 0
            mean = np.mean([loss for e, loss in losses if e == epoch - 1])
            report(f"{recipe.model_name}: fine-tuning epoch {epoch}/{recipe.epochs}, loss {mean:.4f}, "
                   f"lr {recipe.lr_at(epoch - 1):.2g}, {seconds:.0f} s")
        _save_partial(saved, net, config, optimizer, recipe, epoch, index, done, losses, seconds, sections)
        if max_steps is not None and ran >= max_steps and epoch < recipe.epochs:
            report(f"{recipe.model_name}: stopped after {ran} batches (--max-steps) at epoch {epoch + 1}, batch "
                   f"{index}; run the same command again to go on ({saved})")
            return None
    per_epoch = [round(float(np.mean([loss for e, loss in losses if e == k])), 5) for k in range(recipe.epochs)]
    return {"epochs": recipe.epochs, "batches": done, "seconds": round(seconds, 1), "loss_per_epoch": per_epoch,
            "lr": recipe.lr, "decay_every": recipe.decay_every, "window": recipe.window,
            "batch_size": recipe.batch_size}


def _save_partial(path: Path, net, config, optimizer, recipe: FinetuneRecipe, epoch: int, index: int, step: int,
                  losses: list, seconds: float, sections: dict) -> None:
    save_weights(path, config, net.state_dict(), "checkpoint", optimizer=optimizer.state_dict(),
                 scheduler={"lr": recipe.lr_at(min(epoch, recipe.epochs - 1))},
                 stage={"name": "finetune", "epochs": recipe.epochs}, epoch=epoch, batch_index=index, step=step,
                 rng=rng_state(), finetune_recipe=dataclasses.asdict(recipe), losses=losses, seconds=seconds,
                 data=sections["data"])


def _record(recipe: FinetuneRecipe, run: dict, provenance: dict, real: dict | None, split: str, units: int) -> dict:
    """The `finetune` record of the weights file."""
    real_about = None if real is None else {"name": real["name"], "part": "finetune",
                                            "checksum": real["pins"][split]["checksum"]}
    return {"from": recipe.init, "from_sha256": recipe.init_sha256, "data": provenance, "real_split": real_about,
            "windows_per_epoch": units, "sample_steps": int(run["epochs"] * units * recipe.window),
            "recipe": "the paper's fine-tuning (appendix, Training Details): Adam (0.9, 0.95), 1e-4 halved after "
                      "every 3 epochs", "seed": recipe.seed, **run}


def _check_out(out: Path, init: Path) -> None:
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; fine-tuning writes one weights file (e.g. {out / 'dsr-ft.pt'})")
    if out.resolve() == init.resolve():
        raise UserError(f"--out {out} is the --init file; the zero-shot weights are scored beside the fine-tuned "
                        "ones: write the fine-tuned weights to a file of their own (e.g. dsr-ft.pt)")
    out.parent.mkdir(parents=True, exist_ok=True)


# --- the CPU track's voxel models ---------------------------------------------------------------------------------
def finetune_voxel(model: str, init: Path, data: Path, split: str | None, out: Path, *, epochs: int = PAPER_EPOCHS,
                   lr: float | None = None, batch_size: int | None = None, window: int | None = None,
                   bn_recalibration: int = 16, seed: int = 0, max_steps: int | None = None, workers: int = 1,
                   report: Callable[[str], None] = print) -> Path | None:
    """Fine-tune a CPU-track voxel model's weights `init` on DATA's split (module doc); returns the weights file
    written, or None when `max_steps` stopped it first (resumable)."""
    from dsr_bench.models.training.cpu_track import pooled_split, window_batch
    from dsr_bench.models.training.trainer import recalibrate_batchnorm, train_step

    out, init = Path(out), Path(init)
    _check_out(out, init)
    zero_shot = _read_init(init, registry.VOXEL, model)
    if zero_shot.config.voxel_factor == 1:
        raise UserError(f"--init {init}: a full-track model (128 x 128 x 48); fine-tune it on the full track with "
                        "--stage cube-multi --schedule paper (the paper's fine-tuning rate), not --finetune")
    split, real = finetune_split(data, split)
    pooled = pooled_split(data, split, zero_shot.config.voxel_factor, workers,
                          lambda i, n: report(f"pooling {i}/{n}") if i % 50 == 0 or i == n else None)
    count, steps = pooled["action"].shape[:2]
    history = zero_shot.config.history != "none"
    recorded = (zero_shot.get("recipe") or {}).get("window", 10) if history else 1
    recipe = FinetuneRecipe(model, init.name, file_sha256(init), epochs=epochs, lr=PAPER_LR if lr is None else lr,
                            batch_size=batch_size or 8, window=min(window or recorded, steps) if history else 1,
                            bn_recalibration=bn_recalibration, seed=seed)
    net = zero_shot.network("cpu")
    grid = tuple(zero_shot.config.grid)
    units = _units(count, steps, recipe.window)
    provenance = data_provenance(data, split, count)
    torch.manual_seed(seed)
    run = _run(net, recipe, units, lambda b: window_batch(pooled, b[:, 0], b[:, 1], recipe.window, grid),
               partial(train_step, device="cpu"), out, net.config, {"data": provenance}, max_steps, report)
    if run is None:
        return None
    passes = 0
    if recipe.bn_recalibration and count < 2:
        # a batch of one sequence drawn twice has no spread: the SE(3) head's BatchNorm (one voxel per sample) would
        # divide by a variance of 0
        report(f"{model}: precise BatchNorm skipped: the fine-tune split holds one sequence (it needs two)")
    elif recipe.bn_recalibration:
        passes = recalibrate_batchnorm(net, _whole_sequences(pooled, recipe, steps, grid), "cpu")
    net.eval()
    record = {**_record(recipe, run, provenance, real, split, len(units)), "bn_recalibration_passes": passes}
    kept = {k: zero_shot[k] for k in ("recipe", "stages", "bn_recalibration_passes") if k in zero_shot.payload}
    written = save_weights(out, net.config, net.state_dict(), "weights", fp16=True, data=zero_shot.get("data"),
                           finetune=record, **kept)
    partial_path(out).unlink(missing_ok=True)
    return written


def _whole_sequences(pooled: dict, recipe: FinetuneRecipe, steps: int, grid) -> Iterator[dict]:
    """Precise BatchNorm's batches: whole sequences of the fine-tune part, drawn from the recipe's seed."""
    from dsr_bench.models.training.cpu_track import draw_windows

    return draw_windows(pooled, recipe.bn_recalibration, steps, recipe.batch_size, recipe.seed + 2, grid)


def _read_init(init: Path, kind: str, model: str) -> Weights:
    """The zero-shot weights: a finished weights file of `model` (its kind's), one line naming the fix otherwise."""
    if not init.is_file():
        raise UserError(f"--init {init}: not found; give the weights trained in simulation (e.g. "
                        f"dsr_bench/models/weights/cpu-track/{model}.pt)")
    try:
        weights = read_weights(init, kind=kind, model=model)
    except UserError as exc:
        raise UserError(f"--init {exc}") from None
    if weights.role != "weights":
        raise UserError(f"--init {init}: a training {weights.role}, not finished weights; fine-tune the weights a "
                        "run wrote")
    return weights


# --- the 2D track -------------------------------------------------------------------------------------------------
def finetune_image(model: str, init: Path, data: Path, split: str | None, out: Path, *, epochs: int = PAPER_EPOCHS,
                   lr: float | None = None, batch_size: int | None = None, seed: int = 0, device: str = "cpu",
                   max_steps: int | None = None, workers: int = 1,
                   report: Callable[[str], None] = print) -> Path | None:
    """Fine-tune a 2D-track model's weights `init` on DATA's split (single steps; module doc); returns the weights
    file written, or None when `max_steps` stopped it first (resumable)."""
    from dsr_bench.models.training.image_track import image_split, image_step, step_batch

    out, init = Path(out), Path(init)
    _check_out(out, init)
    zero_shot = _read_init(init, registry.IMAGE, model)
    split, real = finetune_split(data, split)
    reduced = image_split(data, split, zero_shot.config.image_factor, workers,
                          lambda i, n: report(f"reducing {i}/{n}") if i % 50 == 0 or i == n else None)
    count, steps = reduced["action"].shape[:2]
    recipe = FinetuneRecipe(model, init.name, file_sha256(init), epochs=epochs, lr=PAPER_LR if lr is None else lr,
                            batch_size=batch_size or 8, window=1, bn_recalibration=0, seed=seed)
    dev = torch_device(device)
    net = zero_shot.network(dev)
    units = _units(count, steps, 1)
    provenance = data_provenance(data, split, count)
    torch.manual_seed(seed)
    run = _run(net, recipe, units, lambda b: step_batch(reduced, b[:, 0], b[:, 1]), partial(image_step, device=dev),
               out, net.config, {"data": provenance}, max_steps, report)
    if run is None:
        return None
    net.eval()
    kept = {k: zero_shot[k] for k in ("recipe", "training") if k in zero_shot.payload}
    written = save_weights(out, net.config, net.cpu().state_dict(), "weights", fp16=True, data=zero_shot.get("data"),
                           finetune=_record(recipe, run, provenance, real, split, len(units)), **kept)
    partial_path(out).unlink(missing_ok=True)
    return written
