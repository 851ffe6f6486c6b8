"""Setting up a training run: processes and device, the stage (or the run to resume), seeds, the
model, optimiser and scheduler, and the resumed position. `prepare` does it all in the order that
makes a resumed run repeat a straight one bit for bit (and checks user input in a fixed order)."""

from __future__ import annotations

import os
import random
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np
import torch

from dsr_bench.errors import UserError
from dsr_bench.models import registry
from dsr_bench.models.config import ModelConfig
from dsr_bench.models.data import SequenceWindowDataset
from dsr_bench.models.dsr_net import DSRNet
from dsr_bench.models.training.checkpoints import Weights, read_weights, set_rng_state, torch_device
from dsr_bench.models.training.config import TrainConfig
from dsr_bench.models.training.loaders import WindowSampler, check_objects, make_loaders, open_windows
from dsr_bench.models.training.schedules import StageConfig, stage_for

__all__ = ["Run", "make_optimizer", "make_scheduler", "prepare"]


@dataclass
class Run:
    """A run ready to train: what `prepare` built, and the loop's position (`step` advances)."""

    config: TrainConfig
    rank: int
    world: int
    device: torch.device
    stage: StageConfig
    model_config: ModelConfig
    dataset: SequenceWindowDataset
    sampler: WindowSampler
    loader: torch.utils.data.DataLoader
    val_loader: torch.utils.data.DataLoader | None  # rank 0 with a validation split only
    net: DSRNet
    model: torch.nn.Module  # net, or net under DistributedDataParallel
    train_model: torch.nn.Module  # model, or model under torch.compile
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler
    start_epoch: int = 0
    start_batch: int = 0  # batches of start_epoch already consumed
    step: int = 0  # batches trained so far (all epochs)
    provenance: dict | None = None  # the data trained on, as the checkpoints record it (`data_provenance`)

    @property
    def distributed(self) -> bool:
        return self.world > 1

    @property
    def latest(self) -> Path:
        """The checkpoint this run writes (OUT/last.pt)."""
        return self.config.out / "last.pt"


def start_processes(config: TrainConfig) -> tuple[int, int, torch.device]:
    """(rank, world size, device): one process per GPU under torchrun (WORLD_SIZE > 1, the process
    group started here), else one process on `config.device`."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    device = config.device
    if world > 1:
        if torch.cuda.is_available():
            local = int(os.environ.get("LOCAL_RANK", "0"))
            torch.cuda.set_device(local)
            device = f"cuda:{local}"
        torch.distributed.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    dev = torch_device(device)
    if config.compile_model and dev.type != "cuda":
        raise UserError(f"--compile needs --device cuda: torch.compile's CPU backend fails on DSR-Net's backward "
                        f"pass (torch {torch.__version__}); drop --compile")
    return rank, world, dev


def resolve_stage(config: TrainConfig) -> tuple[StageConfig, Weights | None]:
    """The stage to train and the checkpoint to resume (None for a new run). A resumed run keeps its
    stage (and model, and epoch length), but for `config.epochs`."""
    if config.resume is None:
        return stage_for(config.model_name, config.stage_name, epochs=config.epochs, batch_size=config.batch_size,
                         lr=config.lr, window=config.window, schedule=config.schedule,
                         epoch_samples=config.epoch_samples), None
    checkpoint = read_weights(config.resume, kind=registry.VOXEL, role="checkpoint")
    saved, stage_name = checkpoint.config, checkpoint["stage"].get("name")
    if saved.name != config.model_name or stage_name != config.stage_name:
        raise UserError(f"{config.resume} is a {saved.name!r} run of stage {stage_name!r}; "
                        f"resume it with --model {saved.name} --stage {stage_name}")
    stage = StageConfig.from_dict(checkpoint["stage"])
    if config.epoch_samples is not None and config.epoch_samples != stage.epoch_samples:
        raise UserError(f"--epoch-samples {config.epoch_samples}: {config.resume} goes on with its own epochs of "
                        f"{stage.epoch_samples or 'one pass over the data'}; drop --epoch-samples to resume it")
    if config.epochs is not None:
        stage = StageConfig.from_dict({**stage.as_dict(), "epochs": config.epochs})
    return stage, checkpoint


def seed_everything(seed: int, deterministic: bool, device: torch.device) -> None:
    """Seed torch, numpy and Python; deterministic algorithms, or cuDNN autotuning on a GPU."""
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
    if deterministic:
        torch.use_deterministic_algorithms(True, warn_only=True)
        torch.backends.cudnn.benchmark = False
    elif device.type == "cuda":
        torch.backends.cudnn.benchmark = True


def model_config_for(config: TrainConfig, checkpoint: Weights | None, data_grid: tuple[int, int, int]) -> ModelConfig:
    """The model's configuration (a resumed run's own), on the data's grid."""
    if checkpoint is not None:
        model_config = checkpoint.config
    else:
        try:
            model_config = ModelConfig.for_model(config.model_name, grid=data_grid)
        except ValueError as exc:
            raise UserError(f"{config.data}: {exc}") from None
    if tuple(model_config.grid) != data_grid:
        raise UserError(f"data grid {data_grid} differs from the checkpoint's model grid {tuple(model_config.grid)}")
    return model_config


def build_model(config: TrainConfig, model_config: ModelConfig, device: torch.device, resuming: bool) -> DSRNet:
    """The network on `device` (channels_last if asked), initialised from `config.init` unless resuming."""
    net = DSRNet(model_config).to(device)
    if config.channels_last:
        net.to_channels_last()
    if config.init is not None and not resuming:
        init = read_weights(config.init, map_location=device, kind=registry.VOXEL)
        init.load_into(net, fix="check --model and --grid-size")
    return net


def make_optimizer(net: torch.nn.Module, stage: StageConfig, device: torch.device) -> torch.optim.Adam:
    """Adam at the stage's first learning rate and betas; fused on a GPU (one kernel for every
    parameter's update instead of a few per tensor group)."""
    return torch.optim.Adam(net.parameters(), lr=stage.lr_at(0), betas=stage.betas,
                            fused=True if torch.device(device).type == "cuda" else None)


def make_scheduler(optimizer: torch.optim.Optimizer, stage: StageConfig) -> torch.optim.lr_scheduler.LambdaLR:
    """The stage's per-epoch learning rates (stepped at the end of each epoch)."""
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda e: stage.lr_at(e) / stage.lr_at(0))


def restore(checkpoint: Weights, net: DSRNet, optimizer, scheduler) -> tuple[int, int, int]:
    """Load a resumed run's weights, optimiser, schedule and RNG states; returns its position
    (epoch, batches of that epoch consumed, step)."""
    checkpoint.load_into(net, fix="check --model and --grid-size")
    optimizer.load_state_dict(checkpoint["optimizer"])
    scheduler.load_state_dict(checkpoint["scheduler"])
    set_rng_state(checkpoint["rng"])
    return checkpoint["epoch"], checkpoint["batch_index"], checkpoint["step"]


def wrap(net: DSRNet, distributed: bool, device: torch.device, compile_model: bool) -> tuple[torch.nn.Module,
                                                                                              torch.nn.Module]:
    """(model: the network, under DDP when distributed; the model the steps run: compiled if asked)."""
    model: torch.nn.Module = net
    if distributed:
        model = torch.nn.parallel.DistributedDataParallel(net, device_ids=[device.index] if device.type == "cuda"
                                                          else None)
    train_model = cast(torch.nn.Module, torch.compile(model)) if compile_model else model  # a Module's: a Module
    if compile_model:
        net.compile_warp()
    return model, train_model


def prepare(config: TrainConfig) -> Run:
    """Processes, stage, seeds, data, model, optimiser and scheduler of a run, resumed if asked."""
    rank, world, device = start_processes(config)
    stage, checkpoint = resolve_stage(config)
    seed_everything(config.seed + rank, config.deterministic, device)
    dataset, data_grid = open_windows(config, stage)
    model_config = model_config_for(config, checkpoint, data_grid)
    check_objects(dataset, model_config, config.data)
    sampler, loader, val_loader = make_loaders(config, stage, dataset, rank, world, device)
    net = build_model(config, model_config, device, resuming=checkpoint is not None)
    optimizer = make_optimizer(net, stage, device)
    scheduler = make_scheduler(optimizer, stage)
    position = (0, 0, 0) if checkpoint is None else restore(checkpoint, net, optimizer, scheduler)
    model, train_model = wrap(net, world > 1, device, config.compile_model)
    return Run(config, rank, world, device, stage, model_config, dataset, sampler, loader, val_loader, net, model,
               train_model, optimizer, scheduler, *position)
