"""The training data of a run: the windows of its split (checked against the model), the sampler
that gives each process its share in an order a resumed run repeats, and the DataLoaders (compact
batches, `dsr_bench.models.data.collate_compact`)."""

from __future__ import annotations

import torch

from dsr_bench.errors import UserError
from dsr_bench.models.config import ModelConfig
from dsr_bench.models.data import SequenceWindowDataset
from dsr_bench.models.training.config import TrainConfig
from dsr_bench.models.training.schedules import StageConfig

__all__ = ["WindowSampler", "check_objects", "make_loaders", "open_windows"]


class WindowSampler(torch.utils.data.Sampler):
    """Shuffled window indices, identical for a (seed, epoch) on every run, split across ranks, that
    can start mid-epoch: the data position of a resumed run (`start` = samples already consumed by
    this rank). Drops the tail so every rank gets the same number of whole batches. `length`: windows
    per epoch (all ranks) when it is not one pass over the `size` windows: shuffled passes drawn one
    after the other from the epoch's generator (the first the same as without `length`), cut at `length`."""

    def __init__(self, size: int, batch_size: int, seed: int = 0, rank: int = 0, world: int = 1, shuffle: bool = True,
                 length: int | None = None):
        self.size, self.batch_size, self.seed, self.shuffle = size, batch_size, seed, shuffle
        self.rank, self.world = rank, world
        self.length = size if length is None else length
        per_rank = self.length // world
        self.batches = per_rank // batch_size if per_rank >= batch_size else (1 if per_rank else 0)
        self.per_rank = min(per_rank, self.batches * batch_size)
        self.epoch, self.start = 0, 0

    def set_epoch(self, epoch: int, start_batch: int = 0) -> None:
        self.epoch, self.start = epoch, start_batch * self.batch_size

    def __iter__(self):
        passes = -(-self.length // self.size)
        if self.shuffle:
            generator = torch.Generator().manual_seed(self.seed * 100_003 + self.epoch)
            order = torch.cat([torch.randperm(self.size, generator=generator) for _ in range(passes)])
        else:
            order = torch.arange(self.size).repeat(passes)
        order = order[: self.length]
        mine = order[self.rank::self.world][: self.per_rank]
        return iter(mine[self.start:].tolist())

    def __len__(self) -> int:
        return max(self.per_rank - self.start, 0)


def _data_grid(dataset: SequenceWindowDataset) -> tuple[int, int, int]:
    """The grid (Y, X, Z) of the dataset's first sequence file."""
    import h5py

    path = dataset.items[0][0]
    with h5py.File(path, "r") as f:
        if "tsdf" not in f or len(f["tsdf"].shape) != 4:
            raise UserError(f"{path}: no (T, Y, X, Z) tsdf; check it with `dsr-bench validate {path.parent}`")
        y, x, z = (int(s) for s in f["tsdf"].shape[1:])
        return y, x, z


def open_windows(config: TrainConfig, stage: StageConfig) -> tuple[SequenceWindowDataset, tuple[int, int, int]]:
    """The training split's non-overlapping windows of the stage and the data's grid (checked
    against `config.grid` when given)."""
    dataset = SequenceWindowDataset(config.data, config.split, window=stage.window, stride=stage.window)
    if len(dataset) == 0:
        raise UserError(f"split {dataset.split!r} of {config.data} has no windows of {stage.window} pushes")
    grid = _data_grid(dataset)
    if config.grid is not None and tuple(config.grid) != grid:
        raise UserError(f"--grid-size {' '.join(map(str, config.grid))} differs from the data's grid {grid}")
    return dataset, grid


def check_objects(dataset: SequenceWindowDataset, model_config: ModelConfig, data) -> None:
    """Refuse scenes with more objects than the model's K - 1 object slots (from the manifest)."""
    slots = model_config.num_slots
    crowded = sorted(name for name, n in dataset.num_objects.items() if n > slots - 1)
    if crowded:
        raise UserError(f"{data}: {len(crowded)} sequences (e.g. {crowded[0]}) have more than {slots - 1} "
                        f"objects, the reference models' object slots (K = {slots}); train on scenes of "
                        f"at most {slots - 1} objects (dsr-bench generate --objects-per-scene)")


def make_loaders(config: TrainConfig, stage: StageConfig, dataset: SequenceWindowDataset, rank: int, world: int,
                 device: torch.device) -> tuple[WindowSampler, torch.utils.data.DataLoader,
                                                torch.utils.data.DataLoader | None]:
    """(sampler, training loader, validation loader on rank 0 with `config.val_split`, else None)."""
    from torch.utils.data import DataLoader

    from dsr_bench.models.data import collate_compact

    sampler = WindowSampler(len(dataset), stage.batch_size, config.seed, rank, world,
                            length=stage.epoch_windows(len(dataset)))
    if sampler.batches == 0:
        raise UserError(f"{len(dataset)} windows cannot be split across {world} processes")
    workers, pin = config.workers, device.type == "cuda"
    loader = DataLoader(dataset, batch_size=min(stage.batch_size, sampler.per_rank), sampler=sampler,
                        num_workers=workers, persistent_workers=False, pin_memory=pin,
                        prefetch_factor=4 if workers > 0 else None, collate_fn=collate_compact)
    val_loader = None
    if config.val_split and rank == 0:
        val_set = SequenceWindowDataset(config.data, config.val_split, window=stage.window, stride=stage.window)
        val_loader = DataLoader(val_set, batch_size=stage.batch_size, num_workers=workers, collate_fn=collate_compact,
                                pin_memory=pin)
    return sampler, loader, val_loader
