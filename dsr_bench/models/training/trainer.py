"""Training DSR-Net and the baselines: one curriculum stage per run (`dsr_bench.models.training.schedules`),
checkpoints that resume exactly, DDP through torchrun, bf16 autocast, a JSONL metrics log.

Within a window the state starts at zero, is detached between steps, and the optimiser steps at
every time step (official); step t's mask loss uses the best slot matching of step t-1.
Checkpoints are plain dicts (state_dicts, configs as dicts, RNG states as tensors, data position,
git hash) loadable with torch.load(weights_only=True).
"""

from __future__ import annotations

import json
import math
import os
import random
import subprocess
import time
from pathlib import Path

import numpy as np
import torch

from dsr_bench.errors import UserError
from dsr_bench.models.config import ModelConfig
from dsr_bench.models.dsr_net import DSRNet
from dsr_bench.models.loss import MaskIdError, check_ids, dsr_loss
from dsr_bench.models.training.schedules import STAGES, StageConfig, stage_for

__all__ = ["STAGES", "StageConfig", "load_checkpoint", "save_checkpoint", "train", "train_step", "validate",
           "WindowSampler"]


def git_hash() -> str:
    """The toolkit's git commit (or "unknown" outside a checkout)."""
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                              cwd=Path(__file__).resolve().parent).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _rng_state() -> dict:
    np_state = np.random.get_state()
    return {"torch": torch.get_rng_state(), "numpy": torch.from_numpy(np_state[1].astype(np.int64)),
            "numpy_pos": int(np_state[2]), "python": json.dumps(random.getstate()[1]),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []}


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(("MT19937", state["numpy"].numpy().astype(np.uint32), state["numpy_pos"], 0, 0.0))
    random.setstate((3, tuple(json.loads(state["python"])), None))
    if torch.cuda.is_available() and state["cuda"]:
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: Path, model, optimizer, scheduler, model_config: ModelConfig, stage: StageConfig,
                    epoch: int, batch_index: int, step: int, extra: dict | None = None) -> Path:
    """Write a checkpoint atomically: model/optimizer/scheduler state, configs, RNG states, data
    position (epoch, batch_index = batches of that epoch already consumed), step, git hash."""
    net = model.module if hasattr(model, "module") else model
    net = getattr(net, "_orig_mod", net)
    payload = {"format": "dsr-bench-checkpoint", "model": net.state_dict(), "optimizer": optimizer.state_dict(),
               "scheduler": scheduler.state_dict(), "model_config": model_config.as_dict(),
               "stage": stage.as_dict(), "epoch": int(epoch), "batch_index": int(batch_index), "step": int(step),
               "rng": _rng_state(), "git": git_hash(), "torch_version": str(torch.__version__), **(extra or {})}
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        torch.save(payload, tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def load_checkpoint(path: Path, map_location="cpu") -> dict:
    """Load a dsr-bench checkpoint safely (weights_only=True); UserError if it is not one."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"checkpoint not found: {path}")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise UserError(f"{path}: not a loadable dsr-bench checkpoint ({type(exc).__name__}: {first[:200]})") from None
    if not isinstance(state, dict) or not {"model", "model_config"} <= set(state):
        raise UserError(f"{path}: not a dsr-bench checkpoint (no model / model_config); "
                        "train one with `dsr-bench train`")
    try:
        ModelConfig.from_dict(state["model_config"])
    except (TypeError, ValueError, KeyError) as exc:
        raise UserError(f"{path}: unusable model_config ({exc})") from None
    return state


class WindowSampler(torch.utils.data.Sampler):
    """Shuffled window indices, identical for a (seed, epoch) on every run, split across ranks, that
    can start mid-epoch: the data position of a resumed run (`start` = samples already consumed by
    this rank). Drops the tail so every rank gets the same number of whole batches."""

    def __init__(self, size: int, batch_size: int, seed: int = 0, rank: int = 0, world: int = 1, shuffle: bool = True):
        self.size, self.batch_size, self.seed, self.shuffle = size, batch_size, seed, shuffle
        self.rank, self.world = rank, world
        per_rank = size // world
        self.batches = per_rank // batch_size if per_rank >= batch_size else (1 if per_rank else 0)
        self.per_rank = min(per_rank, self.batches * batch_size)
        self.epoch, self.start = 0, 0

    def set_epoch(self, epoch: int, start_batch: int = 0) -> None:
        self.epoch, self.start = epoch, start_batch * self.batch_size

    def __iter__(self):
        if self.shuffle:
            order = torch.randperm(self.size, generator=torch.Generator().manual_seed(self.seed * 100_003 + self.epoch))
        else:
            order = torch.arange(self.size)
        mine = order[self.rank::self.world][: self.per_rank]
        return iter(mine[self.start:].tolist())

    def __len__(self) -> int:
        return max(self.per_rank - self.start, 0)


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
    net = model.module if hasattr(model, "module") else model
    net = getattr(net, "_orig_mod", net)
    tsdf, action, gt_mask, gt_flow = _to(batch, device, net.config.num_slots)
    state = net.initial_state(tsdf.shape[0], device)
    matching, terms = None, []
    for t in range(tsdf.shape[1]):
        optimizer.zero_grad(set_to_none=True)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            outputs = model(tsdf[:, t], action[:, t], state)
        loss, step_terms, matching = dsr_loss(outputs, gt_mask[:, t], gt_flow[:, t], matching,
                                              reduction=mask_reduction, check=False)
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


@torch.no_grad()
def validate(model, loader, device, official_bn: bool = False, bf16: bool = False,
             max_batches: int | None = None) -> dict:
    """Mean per-step unordered mask IoU (the benchmark's matching) and loss on a loader, state carried
    across each window's steps. BatchNorm in eval mode unless `official_bn` (the official code
    never switches it)."""
    from dsr_bench.scoring.metrics import assignment, matched_iou, overlap

    device = torch.device(device)
    net = model.module if hasattr(model, "module") else model
    net = getattr(net, "_orig_mod", net)
    was_training = net.training
    net.train(official_bn)
    ious, losses = [], []
    try:
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
                                              check=False)
                losses.append(float(terms["total"]))
                k = out["mask"].shape[1]
                labels = out["mask"].argmax(1)
                labels = torch.where(labels == k - 1, 0, labels + 1).cpu().numpy()
                gts = gt_mask[:, t].cpu().numpy()
                for pred, gt in zip(labels, gts):
                    ov = overlap(pred, gt, k - 1, max(int(gt.max()), 1))
                    ious.append(matched_iou(ov, *assignment(ov.iou))[0])
                if t + 1 < tsdf.shape[1]:
                    state = net.next_state(out, gt_flow[:, t], gt_mask[:, t])
    finally:
        net.train(was_training)
    return {"val_iou": float(np.mean(ious)) if ious else float("nan"),
            "val_loss": float(np.mean(losses)) if losses else float("nan")}


def _data_grid(dataset) -> tuple[int, int, int]:
    import h5py

    path = dataset.items[0][0]
    with h5py.File(path, "r") as f:
        if "tsdf" not in f or len(f["tsdf"].shape) != 4:
            raise UserError(f"{path}: no (T, Y, X, Z) tsdf; check it with `dsr-bench validate {path.parent}`")
        return tuple(int(s) for s in f["tsdf"].shape[1:])


def _load_weights(net: DSRNet, state: dict, source: Path) -> None:
    try:
        net.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise UserError(f"{source}: weights do not fit this model ({str(exc).splitlines()[0][:160]}); "
                        "check --model and --grid-size") from None


def train(model_name: str, stage_name: str, data: Path, out: Path, split: str | None = None,
          val_split: str | None = None, epochs: int | None = None, batch_size: int | None = None,
          lr: float | None = None, window: int | None = None, max_steps: int | None = None,
          max_seconds: float | None = None, init: Path | None = None,
          resume: Path | None = None, device: str = "cpu", bf16: bool = False, compile_model: bool = False,
          channels_last: bool = False, workers: int = 2, seed: int = 0, official_bn: bool = False,
          deterministic: bool = False, grid: tuple[int, int, int] | None = None, checkpoint_every: int = 0,
          log_every: int = 10, progress: bool = True) -> Path:
    """Train `model_name` for one stage on DATA's split; returns the last checkpoint (OUT/last.pt).

    Single process by default; under torchrun (WORLD_SIZE > 1) one process per GPU with DDP.
    `max_steps` (batches) and `max_seconds` (wall time of the loop) end the stage early, with a
    checkpoint that resumes exactly."""
    from torch.utils.data import DataLoader
    from tqdm import tqdm

    from dsr_bench.models.data import SequenceWindowDataset, collate_compact

    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    distributed = world > 1
    if distributed:
        if torch.cuda.is_available():
            local = int(os.environ.get("LOCAL_RANK", "0"))
            torch.cuda.set_device(local)
            device = f"cuda:{local}"
        torch.distributed.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    try:
        dev = torch.device(device)
    except RuntimeError:
        raise UserError(f"--device {device!r}: use cpu, cuda or cuda:N") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError("--device cuda but no CUDA device is available; use --device cpu")
    if compile_model and dev.type != "cuda":
        raise UserError(f"--compile needs --device cuda: torch.compile's CPU backend fails on DSR-Net's backward "
                        f"pass (torch {torch.__version__}); drop --compile")
    checkpoint = load_checkpoint(resume) if resume is not None else None
    if checkpoint is not None:
        saved = ModelConfig.from_dict(checkpoint["model_config"])
        if saved.name != model_name or checkpoint.get("stage", {}).get("name") != stage_name:
            raise UserError(f"{resume} is a {saved.name!r} run of stage {checkpoint.get('stage', {}).get('name')!r}; "
                            f"resume it with --model {saved.name} --stage {checkpoint.get('stage', {}).get('name')}")
        stage = StageConfig.from_dict(checkpoint["stage"])
        if epochs is not None:
            stage = StageConfig.from_dict({**stage.as_dict(), "epochs": epochs})
    else:
        stage = stage_for(model_name, stage_name, epochs=epochs, batch_size=batch_size, lr=lr, window=window)
    torch.manual_seed(seed + rank)
    np.random.seed(seed + rank)
    random.seed(seed + rank)
    if deterministic:
        torch.use_deterministic_algorithms(True, warn_only=True)
        torch.backends.cudnn.benchmark = False
    elif dev.type == "cuda":
        torch.backends.cudnn.benchmark = True
    dataset = SequenceWindowDataset(data, split, window=stage.window, stride=stage.window)
    if len(dataset) == 0:
        raise UserError(f"split {dataset.split!r} of {data} has no windows of {stage.window} pushes")
    data_grid = _data_grid(dataset)
    if grid is not None and tuple(grid) != data_grid:
        raise UserError(f"--grid-size {' '.join(map(str, grid))} differs from the data's grid {data_grid}")
    if checkpoint is not None:
        model_config = ModelConfig.from_dict(checkpoint["model_config"])
    else:
        try:
            model_config = ModelConfig.for_model(model_name, grid=data_grid)
        except ValueError as exc:
            raise UserError(f"{data}: {exc}") from None
    if tuple(model_config.grid) != data_grid:
        raise UserError(f"data grid {data_grid} differs from the checkpoint's model grid {tuple(model_config.grid)}")
    slots = model_config.num_slots
    crowded = sorted(name for name, n in dataset.num_objects.items() if n > slots - 1)
    if crowded:
        raise UserError(f"{data}: {len(crowded)} sequences (e.g. {crowded[0]}) have more than {slots - 1} "
                        f"objects, the reference models' object slots (K = {slots}); train on scenes of "
                        f"at most {slots - 1} objects (dsr-bench generate --objects-per-scene)")
    sampler = WindowSampler(len(dataset), stage.batch_size, seed, rank, world)
    if sampler.batches == 0:
        raise UserError(f"{len(dataset)} windows cannot be split across {world} processes")
    loader = DataLoader(dataset, batch_size=min(stage.batch_size, sampler.per_rank), sampler=sampler,
                        num_workers=workers, persistent_workers=False, pin_memory=dev.type == "cuda",
                        prefetch_factor=4 if workers > 0 else None, collate_fn=collate_compact)
    val_loader = None
    if val_split and rank == 0:
        val_set = SequenceWindowDataset(data, val_split, window=stage.window, stride=stage.window)
        val_loader = DataLoader(val_set, batch_size=stage.batch_size, num_workers=workers, collate_fn=collate_compact,
                                pin_memory=dev.type == "cuda")
    net = DSRNet(model_config).to(dev)
    if channels_last:
        net.to_channels_last()
    if init is not None and checkpoint is None:
        source = load_checkpoint(init, map_location=dev)
        _load_weights(net, source, init)
    # fused Adam on a GPU: one kernel for every parameter's update instead of a few per tensor group
    optimizer = torch.optim.Adam(net.parameters(), lr=stage.lr_at(0), betas=stage.betas,
                                 fused=True if dev.type == "cuda" else None)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda e: stage.lr_at(e) / stage.lr_at(0))
    start_epoch, start_batch, step = 0, 0, 0
    if checkpoint is not None:
        _load_weights(net, checkpoint, resume)
        optimizer.load_state_dict(checkpoint["optimizer"])
        scheduler.load_state_dict(checkpoint["scheduler"])
        start_epoch, start_batch, step = checkpoint["epoch"], checkpoint["batch_index"], checkpoint["step"]
        _set_rng_state(checkpoint["rng"])
    model = net
    if distributed:
        model = torch.nn.parallel.DistributedDataParallel(net, device_ids=[dev.index] if dev.type == "cuda" else None)
    train_model = torch.compile(model) if compile_model else model
    if compile_model:
        net.compile_warp()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    latest = out / "last.pt"
    log = writer = None
    if rank == 0:
        run_config = {"model": model_config.as_dict(), "stage": stage.as_dict(), "data": str(data),
                      "split": dataset.split, "val_split": val_split, "windows": len(dataset), "git": git_hash(),
                      "seed": seed, "bf16": bf16, "compile": compile_model, "channels_last": channels_last,
                      "world_size": world, "init": str(init) if init else None,
                      "resume": str(resume) if resume else None,
                      "official_bn": official_bn, "deterministic": deterministic}
        tmp = out / f".config.json.tmp-{os.getpid()}"
        tmp.write_text(json.dumps(run_config, indent=1) + "\n")
        os.replace(tmp, out / "config.json")
        try:
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(str(out / "tensorboard"))
        except Exception:  # TensorBoard is optional
            writer = None
        log = open(out / "metrics.jsonl", "a")

    def save(epoch: int, batch_index: int) -> None:
        if rank == 0:
            save_checkpoint(latest, model, optimizer, scheduler, model_config, stage, epoch, batch_index, step,
                            {"data": str(data), "split": dataset.split, "seed": seed, "world_size": world})

    started = time.monotonic()

    def out_of_time() -> bool:
        """Whether the loop has run max_seconds (rank 0 decides for every process)."""
        if max_seconds is None:
            return False
        over = time.monotonic() - started >= max_seconds
        if not distributed:
            return over
        flag = torch.tensor(float(over), device=dev)
        torch.distributed.broadcast(flag, 0)
        return bool(flag.item())

    try:
        for epoch in range(start_epoch, stage.epochs):
            first = start_batch if epoch == start_epoch else 0
            sampler.set_epoch(epoch, first)
            bar = tqdm(loader, desc=f"{model_name} {stage.name} epoch {epoch + 1}/{stage.epochs}",
                       disable=rank != 0 or not progress, leave=False, initial=first, total=sampler.batches)
            batch_index = first
            for batch in bar:
                t0 = time.perf_counter()
                try:
                    terms = train_step(train_model, batch, optimizer, dev, bf16, deterministic, stage.mask_reduction)
                except (MaskIdError, FloatingPointError) as exc:
                    raise UserError(f"batch {batch_index + 1} of epoch {epoch + 1} "
                                    f"({', '.join(sorted(set(batch['sequence'])))}): {exc}") from None
                seconds = time.perf_counter() - t0
                step += 1
                batch_index += 1
                if log is not None:
                    samples = batch["tsdf"].shape[0] * batch["tsdf"].shape[1] * world
                    record = {"step": step, "epoch": epoch, "batch": batch_index, "lr": optimizer.param_groups[0]["lr"],
                              "loss": float(np.mean([t["total"] for t in terms])),
                              "motion_loss": float(np.mean([t["motion"] for t in terms])),
                              "mask_loss": float(np.mean([t["mask"] for t in terms])),
                              "loss_per_step": [round(t["total"], 6) for t in terms],
                              "samples_per_s": samples / seconds}
                    log.write(json.dumps(record) + "\n")
                    log.flush()
                    bar.set_postfix(loss=f"{record['loss']:.4f}")
                    if writer is not None and step % log_every == 0:
                        for key in ("loss", "motion_loss", "mask_loss", "lr", "samples_per_s"):
                            writer.add_scalar(f"train/{key}", record[key], step)
                if (max_steps is not None and step >= max_steps) or out_of_time():
                    save(epoch, batch_index)
                    return latest
                if checkpoint_every and step % checkpoint_every == 0:
                    save(epoch, batch_index)
            scheduler.step()
            if rank == 0:
                record = {"epoch": epoch + 1, "step": step, "lr_next": optimizer.param_groups[0]["lr"]}
                if val_loader is not None:
                    try:
                        record.update(validate(model, val_loader, dev, official_bn, bf16))
                    except MaskIdError as exc:
                        raise UserError(f"--val-split {val_split}: {exc}") from None
                    if writer is not None:
                        writer.add_scalar("val/iou", record["val_iou"], step)
                        writer.add_scalar("val/loss", record["val_loss"], step)
                log.write(json.dumps(record) + "\n")
                log.flush()
            save(epoch + 1, 0)
        return latest
    finally:
        if log is not None:
            log.close()
        if writer is not None:
            writer.close()
        if distributed:
            torch.distributed.destroy_process_group()
