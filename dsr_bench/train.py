"""Training DSR-Net and the baselines: the paper's curriculum, checkpoints that resume exactly,
DDP through torchrun, bf16 autocast, a JSONL metrics log.

Stages (paper appendix; official schedule): `cube-single` (single-step windows on cubes, 30 epochs,
lr 1e-3 halved every 5 epochs), `cube-multi` (10-step windows, 20 epochs, lr 1e-4 halved every 3),
`shapenet-multi` (10-step, 20 epochs, 1e-4 halved every 3). SingleStep and 3DFlow train single-step
in every stage. Adam betas (0.9, 0.95), batch 12 per GPU. Within a window the state is detached
between steps and the optimiser steps at every time step (official).
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from dsr_bench.errors import UserError
from dsr_bench.models.config import ModelConfig
from dsr_bench.models.dsr_net import DSRNet
from dsr_bench.models.loss import dsr_loss


@dataclass(frozen=True)
class StageConfig:
    """One stage of the curriculum."""

    name: str
    window: int
    epochs: int
    lr: float
    decay_every: int
    decay: float = 0.5
    batch_size: int = 12
    betas: tuple[float, float] = (0.9, 0.95)


STAGES = {
    "cube-single": StageConfig("cube-single", 1, 30, 1e-3, 5),
    "cube-multi": StageConfig("cube-multi", 10, 20, 1e-4, 3),
    "shapenet-multi": StageConfig("shapenet-multi", 10, 20, 1e-4, 3),
}
SINGLE_STEP_MODELS = ("single", "3dflow")


def stage_for(model: str, stage: str, **overrides) -> StageConfig:
    """The stage's configuration for a model (single-step models always use windows of 1)."""
    if stage not in STAGES:
        raise UserError(f"--stage {stage!r}: choose one of {', '.join(STAGES)}")
    base = asdict(STAGES[stage])
    if model in SINGLE_STEP_MODELS:
        base["window"] = 1
    base.update({k: v for k, v in overrides.items() if v is not None})
    base["betas"] = tuple(base["betas"])
    return StageConfig(**base)


def git_hash() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                              cwd=Path(__file__).resolve().parent).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _rng_state() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": json.dumps(np.random.get_state()[1].tolist()),
            "numpy_pos": int(np.random.get_state()[2]), "python": json.dumps(random.getstate()[1]),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []}


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(("MT19937", np.array(json.loads(state["numpy"]), dtype=np.uint32), state["numpy_pos"], 0, 0.0))
    random.setstate((3, tuple(json.loads(state["python"])), None))
    if torch.cuda.is_available() and state["cuda"]:
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: Path, model, optimizer, scheduler, model_config: ModelConfig, stage: StageConfig,
                    epoch: int, batch_index: int, step: int) -> Path:
    """A checkpoint of plain tensors and containers (loadable with weights_only=True), written atomically."""
    net = model.module if hasattr(model, "module") else model
    payload = {"model": net.state_dict(), "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
               "model_config": model_config.as_dict(), "stage": {**asdict(stage), "betas": list(stage.betas)},
               "epoch": epoch, "batch_index": batch_index, "step": step, "rng": _rng_state(), "git": git_hash(),
               "torch_version": str(torch.__version__)}
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    torch.save(payload, tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(path: Path, map_location="cpu") -> dict:
    """Load a checkpoint safely (weights_only=True)."""
    if not Path(path).is_file():
        raise UserError(f"checkpoint not found: {path}")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise UserError(f"{path}: not a loadable dsr-bench checkpoint ({type(exc).__name__}: {first})") from None


def train_step(model: DSRNet, batch: dict, optimizer, device, bf16: bool = False,
               deterministic: bool = False) -> list[dict]:
    """One window: for each step, forward, loss under the carried matching, backward, optimiser
    step; the state is detached between steps. Returns the loss terms per step."""
    tsdf, action = batch["tsdf"].to(device), batch["action"].to(device)
    gt_mask, gt_flow = batch["mask_3d"].to(device), batch["scene_flow_3d"].to(device)
    net = model.module if hasattr(model, "module") else model
    state = net.initial_state(tsdf.shape[0], device)
    matching, logs = None, []
    for t in range(tsdf.shape[1]):
        optimizer.zero_grad(set_to_none=True)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            outputs = model(tsdf[:, t], action[:, t], state)
        loss, terms, matching = dsr_loss(outputs, gt_mask[:, t], gt_flow[:, t], matching)
        loss.backward()
        optimizer.step()
        logs.append(terms)
        state = net.next_state(outputs, gt_flow[:, t], gt_mask[:, t], deterministic)
    return logs


@torch.no_grad()
def validate(model: DSRNet, loader, device, official_bn: bool = False, max_batches: int | None = None) -> dict:
    """Mean unordered IoU and losses on a loader (BatchNorm in eval mode unless official_bn)."""
    from dsr_bench.metrics import assignment, matched_iou, overlap

    net = model.module if hasattr(model, "module") else model
    net.train(official_bn)
    ious, losses = [], []
    for i, batch in enumerate(loader):
        if max_batches is not None and i >= max_batches:
            break
        tsdf, action = batch["tsdf"].to(device), batch["action"].to(device)
        gt_mask, gt_flow = batch["mask_3d"].to(device), batch["scene_flow_3d"].to(device)
        state = net.initial_state(tsdf.shape[0], device)
        for t in range(tsdf.shape[1]):
            out = net(tsdf[:, t], action[:, t], state)
            losses.append(dsr_loss(out, gt_mask[:, t], gt_flow[:, t])[1]["total"])
            labels = out["mask"].argmax(1)
            k = out["mask"].shape[1]
            labels = torch.where(labels == k - 1, 0, labels + 1).cpu().numpy()
            for b in range(labels.shape[0]):
                gt = gt_mask[b, t].cpu().numpy()
                ov = overlap(labels[b], gt, k - 1, int(gt.max()))
                ious.append(matched_iou(ov, *assignment(ov.iou))[0])
            state = net.next_state(out, gt_flow[:, t], gt_mask[:, t])
    net.train(True)
    return {"val_iou": float(np.mean(ious)) if ious else float("nan"), "val_loss": float(np.mean(losses)) if losses else float("nan")}


def train(model_name: str, stage_name: str, data: Path, out: Path, split: str | None = None,
          val_split: str | None = None, epochs: int | None = None, batch_size: int | None = None,
          lr: float | None = None, max_steps: int | None = None, init: Path | None = None, resume: Path | None = None,
          device: str = "cpu", bf16: bool = False, compile_model: bool = False, channels_last: bool = False,
          workers: int = 2, seed: int = 0, official_bn: bool = False, deterministic: bool = False,
          log_every: int = 10) -> Path:
    """Train a model for one stage; returns the final checkpoint's path."""
    from torch.utils.data import DataLoader
    from tqdm import tqdm

    from dsr_bench.torch_data import SequenceWindowDataset

    distributed = int(os.environ.get("WORLD_SIZE", "1")) > 1
    rank = int(os.environ.get("RANK", "0"))
    if distributed:
        torch.distributed.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
        if torch.cuda.is_available():
            local = int(os.environ.get("LOCAL_RANK", "0"))
            torch.cuda.set_device(local)
            device = f"cuda:{local}"
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError("--device cuda but no CUDA device is available; use --device cpu")
    stage = stage_for(model_name, stage_name, epochs=epochs, batch_size=batch_size, lr=lr)
    checkpoint = load_checkpoint(resume) if resume else None
    model_config = ModelConfig.from_dict(checkpoint["model_config"]) if checkpoint else ModelConfig.for_model(model_name)
    torch.manual_seed(seed + rank)
    np.random.seed(seed + rank)
    random.seed(seed + rank)
    dataset = SequenceWindowDataset(data, split, window=stage.window)
    if tuple(dataset[0]["tsdf"].shape[1:]) != tuple(model_config.grid):
        raise UserError(f"data grid {tuple(dataset[0]['tsdf'].shape[1:])} differs from the model's {model_config.grid}")
    sampler = torch.utils.data.distributed.DistributedSampler(dataset, seed=seed) if distributed else None
    generator = torch.Generator().manual_seed(seed)
    loader = DataLoader(dataset, batch_size=stage.batch_size, shuffle=sampler is None, sampler=sampler,
                        num_workers=workers, generator=generator, drop_last=len(dataset) >= stage.batch_size,
                        persistent_workers=workers > 0, pin_memory=dev.type == "cuda")
    val_loader = None
    if val_split:
        val_loader = DataLoader(SequenceWindowDataset(data, val_split, window=stage.window), batch_size=stage.batch_size,
                                num_workers=workers)
    model = DSRNet(model_config).to(dev)
    if channels_last:
        model = model.to(memory_format=torch.channels_last_3d)
    if init is not None and checkpoint is None:
        model.load_state_dict(load_checkpoint(init)["model"])
    optimizer = torch.optim.Adam(model.parameters(), lr=stage.lr, betas=stage.betas)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=stage.decay_every, gamma=stage.decay)
    start_epoch, start_batch, step = 0, 0, 0
    if checkpoint is not None:
        model.load_state_dict(checkpoint["model"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        scheduler.load_state_dict(checkpoint["scheduler"])
        start_epoch, start_batch, step = checkpoint["epoch"], checkpoint["batch_index"], checkpoint["step"]
        _set_rng_state(checkpoint["rng"])
    if distributed:
        model = torch.nn.parallel.DistributedDataParallel(model)
    train_model = torch.compile(model) if compile_model else model
    out.mkdir(parents=True, exist_ok=True)
    if rank == 0:
        (out / "config.json").write_text(json.dumps({"model": model_config.as_dict(), "stage": asdict(stage),
                                                    "data": str(data), "split": dataset.split, "git": git_hash(),
                                                    "seed": seed, "bf16": bf16}, indent=1, default=list))
    writer = None
    if rank == 0:
        try:
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(str(out / "tensorboard"))
        except Exception:  # TensorBoard is optional
            writer = None
    log = open(out / "metrics.jsonl", "a") if rank == 0 else None
    latest = out / "last.pt"
    try:
        for epoch in range(start_epoch, stage.epochs):
            if sampler is not None:
                sampler.set_epoch(epoch)
            generator.manual_seed(seed + epoch)
            bar = tqdm(loader, desc=f"{model_name} {stage.name} epoch {epoch + 1}/{stage.epochs}", disable=rank != 0,
                       leave=False)
            for batch_index, batch in enumerate(bar):
                if epoch == start_epoch and batch_index < start_batch:
                    continue  # resume at the data position
                t0 = time.perf_counter()
                terms = train_step(train_model, batch, optimizer, dev, bf16, deterministic)
                step += 1
                seconds = time.perf_counter() - t0
                record = {"step": step, "epoch": epoch, "lr": optimizer.param_groups[0]["lr"],
                          "loss": float(np.mean([t["total"] for t in terms])),
                          "motion_loss": float(np.mean([t["motion"] for t in terms])),
                          "mask_loss": float(np.mean([t["mask"] for t in terms])),
                          "samples_per_s": batch["tsdf"].shape[0] * batch["tsdf"].shape[1] / seconds}
                if log is not None:
                    log.write(json.dumps(record) + "\n")
                    log.flush()
                    bar.set_postfix(loss=f"{record['loss']:.4f}")
                    if writer is not None and step % log_every == 0:
                        for key in ("loss", "motion_loss", "mask_loss", "lr", "samples_per_s"):
                            writer.add_scalar(key, record[key], step)
                if max_steps is not None and step >= max_steps:
                    if rank == 0:
                        save_checkpoint(latest, model, optimizer, scheduler, model_config, stage, epoch, batch_index + 1,
                                        step)
                    return latest
            scheduler.step()
            if rank == 0:
                record = {"epoch": epoch + 1, "step": step}
                if val_loader is not None:
                    record.update(validate(model, val_loader, dev, official_bn))
                log.write(json.dumps(record) + "\n")
                save_checkpoint(latest, model, optimizer, scheduler, model_config, stage, epoch + 1, 0, step)
        return latest
    finally:
        if log is not None:
            log.close()
        if writer is not None:
            writer.close()
        if distributed:
            torch.distributed.destroy_process_group()
