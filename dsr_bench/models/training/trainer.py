"""Training DSR-Net and the baselines: one curriculum stage per run (`dsr_bench.models.training.schedules`),
checkpoints that resume exactly (`checkpoints`), DDP through torchrun, bf16 autocast, a JSONL metrics log.

`train(config)` runs the loop over what `setup.prepare` builds (data from `loaders`): epochs of
windows, a checkpoint when max_steps or the time budget ends the stage (and every
`checkpoint_every` batches, and after each epoch), validation after each epoch. Within a window
the state starts at zero, is detached between steps, and the optimiser steps at every time step
(official); step t's mask loss uses the best slot matching of step t-1 (`train_step`).

`recalibrate_batchnorm` re-estimates BatchNorm's running statistics on whole windows with the state
carried (precise BN); `train` runs it when the stage ends if `bn_recalibration` asks.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterable, Iterator
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from dsr_bench.atomic import write_text
from dsr_bench.errors import UserError
from dsr_bench.models.dsr_net import DSRNet, batchnorm_layers, batchnorm_statistics
from dsr_bench.models.labels import slot_labels
from dsr_bench.models.loss import MaskIdError, check_ids, dsr_loss
from dsr_bench.models.training.checkpoints import data_provenance, git_hash, save_checkpoint, unwrap
from dsr_bench.models.training.config import TrainConfig
from dsr_bench.models.training.loop import WindowError, run_steps
from dsr_bench.models.training.setup import Run, prepare

if TYPE_CHECKING:
    from torch.utils.tensorboard import SummaryWriter

__all__ = ["TrainConfig", "WindowError", "recalibrate_batchnorm", "train", "train_step", "train_windows", "validate",
           "window_record"]


def _to(batch: dict, device, num_slots: int | None = None) -> tuple[torch.Tensor, ...]:
    """The window's tensors on `device` (tsdf, action, mask int64, flow); masks travel as uint8 (8x less
    to copy) and are widened there, flow and actions in the compact form of `collate_compact`.
    With `num_slots`, the mask ids are checked against the model's slots first, on the CPU copy (a
    check on the GPU copy would make the host wait for the device)."""
    from dsr_bench.models.data import batch_to_device

    if num_slots is not None:
        check_ids(batch["mask_3d"], num_slots)
    dense = batch_to_device(batch, device)  # compact batches (collate_compact) are expanded there
    return dense["tsdf"], dense["action"], dense["mask_3d"].long(), dense["scene_flow_3d"]


def train_step(model, batch: dict, optimizer, device, bf16: bool = False, deterministic: bool = False,
               mask_reduction: str = "sum") -> list[dict]:
    """One window (B, L, ...): per step, forward, loss under the previous step's matching, backward,
    optimiser step; the state is detached between steps (and not computed after the last step: with
    windows of 1 there is no warp at all). Returns the loss terms of every step
    (floats). The steps are queued without waiting for the device; the terms are read once, at the
    end of the window (a non-finite loss is reported then, naming its step)."""
    device = torch.device(device)
    net: DSRNet = unwrap(model)
    tsdf, action, gt_mask, gt_flow = _to(batch, device, net.config.num_slots)
    state = net.initial_state(tsdf.shape[0], device)
    matching, terms = None, []
    for t in range(tsdf.shape[1]):
        optimizer.zero_grad(set_to_none=True)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            outputs = model(tsdf[:, t], action[:, t], state)
        loss, step_terms, matching = dsr_loss(outputs, gt_mask[:, t], gt_flow[:, t], matching,
                                              reduction=mask_reduction, check=False,
                                              voxel_factor=net.config.voxel_factor)
        loss.backward()
        optimizer.step()
        terms.append(torch.stack([step_terms["total"], step_terms["motion"], step_terms["mask"]]))
        if t + 1 < tsdf.shape[1]:  # the state after a window's last step is never used: no warp for it
            state = net.next_state(outputs, gt_flow[:, t], gt_mask[:, t], deterministic)
    logs = [dict(zip(("total", "motion", "mask"), row)) for row in torch.stack(terms).tolist()]  # the one sync
    for t, row in enumerate(logs):
        if not math.isfinite(row["total"]):
            raise FloatingPointError(f"loss is {row['total']} at window step {t}; lower the learning rate (--lr)")
    return logs


def train_windows(model, batches: Iterable[dict], optimizer, device, *, bf16: bool = False,
                  deterministic: bool = False, mask_reduction: str = "sum",
                  start: int = 0) -> Iterator[tuple[dict, list[dict], float]]:
    """The loop (`loop.run_steps`) with `train_step` as its step: yields (batch, its loss terms per step,
    seconds the step took); a window that cannot be trained raises `WindowError` (numbered from `start` + 1)."""
    step = partial(train_step, device=device, bf16=bf16, deterministic=deterministic, mask_reduction=mask_reduction)
    return run_steps(step, model, batches, optimizer, start=start)


def window_record(terms: list[dict]) -> dict:
    """A window's losses for the log: means over its steps and the total of each step."""
    return {"loss": float(np.mean([t["total"] for t in terms])),
            "motion_loss": float(np.mean([t["motion"] for t in terms])),
            "mask_loss": float(np.mean([t["mask"] for t in terms])),
            "loss_per_step": [round(t["total"], 6) for t in terms]}


@torch.no_grad()
def recalibrate_batchnorm(model, batches: Iterable[dict], device, bf16: bool = False,
                          deterministic: bool = False) -> int:
    """Precise BatchNorm: replace every BatchNorm layer's running statistics with their average over
    the forward passes of `batches` (windows (B, L, ...) as the loaders give them), each window run as
    prediction runs a sequence: the state starts at zero and is carried (warped) from step to step.

    Why: the running statistics are a moving average (momentum 0.1) over the last training forward
    passes, made with the weights of the time. After single-step windows they describe inputs whose
    state is always zero, while prediction feeds the state back at every step: in eval mode the
    first convolution (whose state weights a single-step stage never trains) is then normalised
    with a variance that leaves the state out, and the mismatch grows through the warped state from
    step to step (docs/models.md, BatchNorm). Here the forward passes normalise with each batch's
    own statistics (as in training, the state hence as training produces it) and every pass counts
    equally (momentum None: a cumulative average), with the final weights; no gradients, the
    weights and the momentum are left as they were. Returns the number of forward passes."""
    device = torch.device(device)
    net: DSRNet = unwrap(model)
    layers = batchnorm_layers(net)
    momenta = [m.momentum for m in layers]
    for m in layers:
        m.reset_running_stats()
        m.momentum = None
    was_training = net.training
    net.train()
    passes = 0
    try:
        for batch in batches:
            tsdf, action, gt_mask, gt_flow = _to(batch, device)
            state = net.initial_state(tsdf.shape[0], device)
            for t in range(tsdf.shape[1]):
                with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                    out = net(tsdf[:, t], action[:, t], state)
                passes += 1
                if t + 1 < tsdf.shape[1]:
                    state = net.next_state(out, gt_flow[:, t], gt_mask[:, t], deterministic)
    finally:
        for m, momentum in zip(layers, momenta):
            m.momentum = momentum
        net.train(was_training)
    return passes


@torch.no_grad()
def validate(model, loader, device, official_bn: bool = False, bf16: bool = False,
             max_batches: int | None = None) -> dict:
    """Mean per-step unordered mask IoU (the benchmark's matching) and loss on a loader, state carried
    across each window's steps. BatchNorm in eval mode unless `official_bn` (the official code
    never switches it: batch statistics, the running statistics left untouched)."""
    from dsr_bench.matching import assignment, matched_iou, overlap

    device = torch.device(device)
    net: DSRNet = unwrap(model)
    ious, losses = [], []
    with batchnorm_statistics(net, batch=official_bn):
        for i, batch in enumerate(loader):
            if max_batches is not None and i >= max_batches:
                break
            tsdf, action, gt_mask, gt_flow = _to(batch, device, net.config.num_slots)
            state = net.initial_state(tsdf.shape[0], device)
            matching = None
            for t in range(tsdf.shape[1]):
                with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                    out = net(tsdf[:, t], action[:, t], state)
                _, terms, matching = dsr_loss(out, gt_mask[:, t], gt_flow[:, t], matching, reduction="mean",
                                              check=False, voxel_factor=net.config.voxel_factor)
                losses.append(float(terms["total"]))
                slots = out["mask"].shape[1] - 1
                for pred, gt in zip(slot_labels(out["mask"]).cpu().numpy(), gt_mask[:, t].cpu().numpy()):
                    ov = overlap(pred, gt, slots, max(int(gt.max()), 1))
                    ious.append(matched_iou(ov, *assignment(ov.iou))[0])
                if t + 1 < tsdf.shape[1]:
                    state = net.next_state(out, gt_flow[:, t], gt_mask[:, t])
    return {"val_iou": float(np.mean(ious)) if ious else float("nan"),
            "val_loss": float(np.mean(losses)) if losses else float("nan")}


class TimeBudget:
    """Whether the loop has run `seconds` of wall time (None: never); under DDP rank 0 decides for
    every process."""

    def __init__(self, seconds: float | None, run: Run):
        self.seconds, self.run, self.started = seconds, run, time.monotonic()

    def spent(self) -> bool:
        if self.seconds is None:
            return False
        over = time.monotonic() - self.started >= self.seconds
        if not self.run.distributed:
            return over
        flag = torch.tensor(float(over), device=self.run.device)
        torch.distributed.broadcast(flag, 0)
        return bool(flag.item())


class RunLog:
    """Rank 0's record of a run: OUT/config.json (written at the start), OUT/metrics.jsonl (a line
    per batch and per epoch, appended), TensorBoard scalars when TensorBoard is installed."""

    def __init__(self, run: Run):
        config, out = run.config, run.config.out
        run_config = {"model": run.model_config.as_dict(), "stage": run.stage.as_dict(), "data": str(config.data),
                      "split": run.dataset.split, "val_split": config.val_split, "windows": len(run.dataset),
                      "git": git_hash(), "seed": config.seed, "bf16": config.bf16, "compile": config.compile_model,
                      "channels_last": config.channels_last, "world_size": run.world,
                      "init": str(config.init) if config.init else None,
                      "resume": str(config.resume) if config.resume else None,
                      "official_bn": config.official_bn, "deterministic": config.deterministic}
        write_text(out / "config.json", json.dumps(run_config, indent=1) + "\n")
        self.log_every = config.log_every
        try:
            from torch.utils.tensorboard import SummaryWriter

            self.writer: SummaryWriter | None = SummaryWriter(str(out / "tensorboard"))
        except Exception:  # TensorBoard is optional
            self.writer = None
        self.file = open(out / "metrics.jsonl", "a")

    def _write(self, record: dict) -> None:
        self.file.write(json.dumps(record) + "\n")
        self.file.flush()

    def note(self, record: dict) -> None:
        """A record of the run that is neither a batch nor an epoch (the BatchNorm recalibration)."""
        self._write(record)

    def window(self, record: dict) -> None:
        """A batch's record (TensorBoard every `log_every` steps)."""
        self._write(record)
        if self.writer is not None and record["step"] % self.log_every == 0:
            for key in ("loss", "motion_loss", "mask_loss", "lr", "samples_per_s"):
                self.writer.add_scalar(f"train/{key}", record[key], record["step"])

    def epoch(self, record: dict) -> None:
        """An epoch's record (with validation: val_iou, val_loss)."""
        if self.writer is not None and "val_iou" in record:
            self.writer.add_scalar("val/iou", record["val_iou"], record["step"])
            self.writer.add_scalar("val/loss", record["val_loss"], record["step"])
        self._write(record)

    def close(self) -> None:
        self.file.close()
        if self.writer is not None:
            self.writer.close()


def _save(run: Run, epoch: int, batch_index: int) -> None:
    """Rank 0 writes OUT/last.pt at this data position."""
    if run.rank == 0:
        config = run.config
        save_checkpoint(run.latest, run.model, run.optimizer, run.scheduler, run.model_config, run.stage, epoch,
                        batch_index, run.step, {"data": run.provenance, "seed": config.seed, "world_size": run.world})


def _train_epoch(run: Run, log: RunLog | None, budget: TimeBudget, epoch: int, first: int) -> bool:
    """One epoch from its batch `first`; True when max_steps or the time budget ended the stage
    (its checkpoint saved)."""
    from contextlib import nullcontext

    from dsr_bench.progress import no_progress, progress_bar

    config, stage = run.config, run.stage
    run.sampler.set_epoch(epoch, first)
    windows = train_windows(run.train_model, run.loader, run.optimizer, run.device, bf16=config.bf16,
                            deterministic=config.deterministic, mask_reduction=stage.mask_reduction, start=first)
    batch_index = first
    shown = run.rank == 0 and config.progress
    bar = progress_bar(f"{config.model_name} {stage.name} epoch {epoch + 1}/{stage.epochs}") if shown \
        else nullcontext(no_progress)
    try:
        with bar as progress:
            return _train_batches(run, log, budget, epoch, windows, batch_index, progress)
    except WindowError as exc:
        raise UserError(f"batch {exc.index} of epoch {epoch + 1} "
                        f"({', '.join(sorted(set(exc.sequences or ())))}): {exc.cause}") from None


def _train_batches(run: Run, log: RunLog | None, budget: TimeBudget, epoch: int, windows, batch_index: int,
                   progress) -> bool:
    """The loop of `_train_epoch` over its windows; `progress(done, total, note)` moves the bar."""
    config = run.config
    for batch, terms, seconds in windows:
        run.step += 1
        batch_index += 1
        note = ""
        if log is not None:
            samples = batch["tsdf"].shape[0] * batch["tsdf"].shape[1] * run.world
            record = {"step": run.step, "epoch": epoch, "batch": batch_index,
                      "lr": run.optimizer.param_groups[0]["lr"], **window_record(terms),
                      "samples": samples, "samples_per_s": samples / seconds}
            log.window(record)
            note = f"loss {record['loss']:.4f}"
        progress(batch_index, run.sampler.batches, note)
        if (config.max_steps is not None and run.step >= config.max_steps) or budget.spent():
            _recalibrate(run, log)
            _save(run, epoch, batch_index)
            return True
        if config.checkpoint_every and run.step % config.checkpoint_every == 0:
            _save(run, epoch, batch_index)
    return False


def _recalibrate(run: Run, log: RunLog | None) -> None:
    """The stage is over: with `bn_recalibration` = N, rank 0 re-estimates BatchNorm's running
    statistics (`recalibrate_batchnorm`) on N batches of the training split's whole sequences (windows
    of its shortest sequence's pushes, drawn in the order of the seed's first epoch, workers seeded
    from their own generator: the global RNG states the checkpoint saves are not drawn from)."""
    config = run.config
    if not config.bn_recalibration or run.rank != 0:
        return
    from itertools import islice

    from torch.utils.data import DataLoader

    from dsr_bench.models.data import SequenceWindowDataset, collate_compact
    from dsr_bench.models.training.loaders import WindowSampler

    pushes = SequenceWindowDataset(config.data, config.split, window=1, fields=("tsdf",))
    window = min(np.unique([name for _, name, _ in pushes.items], return_counts=True)[1])
    windows = SequenceWindowDataset(config.data, config.split, window=int(window), stride=int(window))
    batch = min(run.stage.batch_size, len(windows))
    loader = DataLoader(windows, batch_size=batch, sampler=WindowSampler(len(windows), batch, config.seed),
                        num_workers=config.workers, collate_fn=collate_compact,
                        generator=torch.Generator().manual_seed(config.seed), pin_memory=run.device.type == "cuda")
    passes = recalibrate_batchnorm(run.model, islice(loader, config.bn_recalibration), run.device, config.bf16,
                                   config.deterministic)
    if log is not None:
        log.note({"step": run.step, "bn_recalibration": {"window": int(window), "batch_size": batch,
                                                           "forward_passes": passes}})


def _end_epoch(run: Run, log: RunLog | None, epoch: int) -> None:
    """Step the schedule; on rank 0 validate and log the epoch (after the stage's last epoch, with the
    recalibrated BatchNorm statistics if asked); save the checkpoint of the next epoch."""
    run.scheduler.step()
    if epoch + 1 == run.stage.epochs:
        _recalibrate(run, log)
    if log is not None:  # rank 0
        record = {"epoch": epoch + 1, "step": run.step, "lr_next": run.optimizer.param_groups[0]["lr"]}
        if run.val_loader is not None:
            try:
                record.update(validate(run.model, run.val_loader, run.device, run.config.official_bn,
                                       run.config.bf16))
            except MaskIdError as exc:
                raise UserError(f"--val-split {run.config.val_split}: {exc}") from None
        log.epoch(record)
    _save(run, epoch + 1, 0)


def train(config: TrainConfig) -> Path:
    """Train `config.model_name` for one stage on the data's split; returns the last checkpoint (OUT/last.pt).

    Single process by default; under torchrun (WORLD_SIZE > 1) one process per GPU with DDP.
    `max_steps` (batches) and `max_seconds` (wall time of the loop) end the stage early, with a
    checkpoint that resumes exactly."""
    run = prepare(config)
    config.out.mkdir(parents=True, exist_ok=True)
    log = RunLog(run) if run.rank == 0 else None
    if run.rank == 0:  # what the checkpoints record of the data (its directory's name, never a local path)
        run.provenance = data_provenance(config.data, run.dataset.split, len(run.dataset.num_objects))
    budget = TimeBudget(config.max_seconds, run)
    try:
        for epoch in range(run.start_epoch, run.stage.epochs):
            first = run.start_batch if epoch == run.start_epoch else 0
            if _train_epoch(run, log, budget, epoch, first):
                break
            _end_epoch(run, log, epoch)
        if run.distributed:  # every process returns once rank 0 has saved (a curriculum's next stage reads it)
            torch.distributed.barrier()
        return run.latest
    finally:
        if log is not None:
            log.close()
        if run.distributed:
            torch.distributed.destroy_process_group()
