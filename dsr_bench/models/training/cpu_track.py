"""The CPU track's training recipe: a reference model on 16 mm voxels, trained on 2 CPU cores.

The model (`ModelConfig.voxel_factor` = 4: a 32 x 32 x 16 grid, channel counts halved: `width` 2) sees
the split's sequences pooled once (`models.coarse`; kept in memory and cached on disk, see
`pooled_split`). Training is the one loop (`loop.fit` over `trainer.train_step`: the matched loss, the
matching carried from step to step, the state warped between steps) on windows drawn at random (any
sequence, any start, with replacement, from the recipe's seed):

1. stage 1, single-step windows (`single_batches`), learning rate `lr`;
2. stage 2, whole windows of `window` steps with the state carried (`multi_batches`) at `multi_lr`;
   a model without history (single, 3dflow) gets `window` x as many single-step windows instead: the
   same sample-steps (`same_windows`: the same windows of `window` steps instead, a control);

each stage's rate halved at 50% and again at 75% of its batches (the paper's step decay, in batches).
Stage 1 is the same computation for dsr, nowarp, gtwarp and single (a single-step window has no
history, the initial weights and the windows come from the same seed), so its weights are saved beside
the result (`<out>.stage1.pt`) and `init` starts another of these models from them, skipping stage 1.
`init` may also be a finished run's weights file of the same model: the run continues it (a longer run in chunks,
each resumable from the last file written): `multi_batches` more of stage 2's batches from those weights, Adam
restarted and stage 2's rate and decay run again, on windows drawn from a seed of their own (the recipe's + 10 +
the continuations before), recorded in `stages["continued"]` after the file's own stages (with the loss every
10 batches: the curve).
Then precise BatchNorm (`trainer.recalibrate_batchnorm`): the running statistics are re-estimated on
`bn_recalibration` batches of whole windows with the state carried, as prediction runs, so that eval
mode does not diverge along a sequence (docs/models.md, BatchNorm). The result is a weights file
(`checkpoints`: role "weights", fp16, the recipe, each stage's record and the data it saw; the stage-1
file: role "stage1"), read by `dsr-bench predict --checkpoint` like any checkpoint.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch

from dsr_bench.errors import UserError
from dsr_bench.models import coarse, registry
from dsr_bench.models.config import ModelConfig
from dsr_bench.models.training.checkpoints import data_provenance, half, read_weights, save_weights
from dsr_bench.models.training.split_cache import cached_split


@dataclass(frozen=True)
class CpuRecipe:
    """Everything that defines a CPU-track training run (saved in its weights file)."""

    model_name: str
    single_batches: int = 3000
    multi_batches: int = 300
    window: int = 10
    batch_size: int = 8
    lr: float = 1e-3
    multi_lr: float = 5e-4
    width: int = 2
    bn_recalibration: int = 16
    seed: int = 0
    #: a stage-1 weights file (`<out>.stage1.pt` of an earlier run) to start stage 2 from, or a finished run's
    #: weights file of this model to continue (`multi_batches` more of stage 2's batches); None: run stage 1
    init: str | None = None
    #: a model without history trains stage 2 on the history models' windows of `window` steps (a zero state,
    #: step t's loss under step t-1's matching, an optimiser step per step): the history models' protocol
    #: without the history, a control for what the state itself adds
    same_windows: bool = False

    def __post_init__(self):
        if min(self.single_batches, self.batch_size, self.window) < 1 or self.multi_batches < 0:
            raise UserError("--single-batches, --batch-size and --window must be at least 1, --multi-batches >= 0")
        for flag, rate in (("--lr", self.lr), ("--multi-lr", self.multi_lr)):
            if not (math.isfinite(rate) and rate > 0):
                raise UserError(f"{flag} {rate}: a learning rate must be a finite number above 0")
        if self.batch_size < 2:
            raise UserError(f"--batch-size {self.batch_size}: the CPU track needs at least 2 (on its grid BatchNorm "
                            "in the SE(3) head sees one voxel per sample, so training statistics need two samples)")
        if self.bn_recalibration < 0:
            raise UserError(f"--bn-recalibration {self.bn_recalibration}: must be >= 0")
        if self.init is not None and not self.multi_batches:
            raise UserError("--init starts stage 2 from stage-1 weights; give --multi-batches >= 1")

    def model_config(self) -> ModelConfig:
        factor = coarse.CPU_TRACK_FACTOR
        return ModelConfig.for_model(self.model_name, grid=coarse.coarse_grid(factor), voxel_factor=factor,
                                     width=self.width, init="zero-motion")


# --- data -------------------------------------------------------------------------------------------
def _pool_sequence(path: Path, factor: int) -> dict[str, np.ndarray]:
    """One sequence pooled: tsdf and mask at the T observations before each push, flow, actions."""
    from dsr_bench.dataset.sequence import SequenceReader

    with SequenceReader(path) as seq:
        steps = seq.num_steps
        tsdf, mask = seq.read("tsdf")[:steps], seq.read("mask_3d")[:steps]
        flow, action = seq.read("scene_flow_3d")[:steps], np.asarray(seq.read("action"))[:steps]
    return {"tsdf": coarse.pool_tsdf(tsdf, factor).astype(np.float16), "mask": coarse.pool_labels(mask, factor),
            "flow": coarse.pool_flow(flow, mask, factor).astype(np.float16),
            "action": coarse.coarse_action(action, factor).astype(np.int16)}


def pooled_split(data_dir: Path, split: str | None, factor: int = coarse.CPU_TRACK_FACTOR, workers: int = 1,
                 progress: Callable[[int, int], None] | None = None) -> dict[str, np.ndarray]:
    """A split's sequences pooled to the CPU track's grid, stacked: tsdf (N, T, y, x, z) float16, mask
    (N, T, ...) uint8, flow (N, T, 3, ...) float16 in model voxels, action (N, T, 3) int16, names (N,).
    Cached (`split_cache.cached_split`): a changed or regenerated file is pooled again."""
    return cached_split(data_dir, split, f"pooled-f{factor}", [factor, coarse.MIN_BLOCK_FRACTION],
                        partial(_pool_sequence, factor=factor), workers, progress)


def draw_windows(data: dict[str, np.ndarray], batches: int, window: int, batch_size: int, seed: int,
                 grid: tuple[int, int, int]) -> Iterator[dict]:
    """`batches` window batches (B, L, ...) in the loaders' layout, each window a random sequence and start."""
    rng = np.random.default_rng(seed)
    count, steps = data["action"].shape[:2]
    for _ in range(batches):
        seqs = rng.integers(count, size=batch_size)
        starts = rng.integers(steps - window + 1, size=batch_size)
        yield window_batch(data, seqs, starts, window, grid)


def window_batch(data: dict[str, np.ndarray], seqs: np.ndarray, starts: np.ndarray, window: int,
                 grid: tuple[int, int, int]) -> dict:
    """One batch (B, L, ...) in the loaders' layout: window b is sequence `seqs[b]`'s pushes `starts[b]` ..
    `starts[b]` + `window` - 1 of a pooled split (`pooled_split`)."""
    from dsr_bench.models.data import action_map

    idx = (np.asarray(seqs)[:, None], np.asarray(starts)[:, None] + np.arange(window))
    return {"tsdf": torch.from_numpy(data["tsdf"][idx].astype(np.float32)),
            "action": torch.stack([action_map(a, grid[:2]) for a in data["action"][idx].astype(np.int64)]),
            "mask_3d": torch.from_numpy(data["mask"][idx]),
            "scene_flow_3d": torch.from_numpy(data["flow"][idx].astype(np.float32)),
            "sequence": [str(data["names"][s]) for s in seqs]}


# --- training -----------------------------------------------------------------------------------------
def _stage(net, data, batches: int, window: int, recipe: CpuRecipe, lr: float, seed: int, label: str,
           report: Callable[[str], None]) -> dict:
    """Train `batches` windows of `window` steps (`loop.fit`); returns the stage's record."""
    from dsr_bench.models.training.loop import fit
    from dsr_bench.models.training.trainer import train_step

    windows = draw_windows(data, batches, window, recipe.batch_size, seed, tuple(net.config.grid))
    record = fit(partial(train_step, device="cpu"), net, windows, batches, lr, label, report)
    return {**record, "window": window, "sample_steps": batches * window * recipe.batch_size}


def sample_steps(stages: dict, batch_size: int = 8) -> int:
    """The sample-steps (windows x pushes) a CPU-track weights file's stages record (`stages`: stage 1, stage 2 and
    every continued chunk) trained on; records written before they counted them are counted from their batches,
    window and `batch_size` (the recipe's)."""
    records = [stages.get("single"), stages.get("multi"), *stages.get("continued", [])]
    return sum(int(r.get("sample_steps", r["batches"] * r.get("window", 1) * batch_size))
               for r in records if isinstance(r, dict))


def _recorded(recipe: CpuRecipe) -> dict:
    """The recipe as a weights file records it: --init by its file name, never a path of this machine."""
    record = dataclasses.asdict(recipe)
    if record["init"] is not None:
        record["init"] = Path(record["init"]).name
    return record


def stage1_path(out: Path) -> Path:
    """Where a run writing `out` keeps its stage-1 weights."""
    return Path(out).with_suffix(".stage1.pt")


def _load_stage1(net, path: Path, recipe: CpuRecipe) -> dict:
    """Load stage-1 weights into `net` (a model of the same architecture, by the same stage-1 recipe);
    returns that run's stage-1 record, marked with where it came from."""
    if not path.is_file():
        raise UserError(f"--init {path}: not found; it is the .stage1.pt file a CPU-track run writes beside its "
                        "weights")
    try:
        state = read_weights(path, kind=registry.VOXEL, role="stage1")
    except UserError as exc:
        raise UserError(f"--init {exc}") from None
    if not isinstance(state.get("recipe"), dict) or not isinstance(state.get("stages"), dict) \
            or "single" not in state["stages"]:
        raise UserError(f"--init {path}: a stage-1 file without its recipe and stage record")
    theirs = {k: v for k, v in state["recipe"].items() if k not in ("model_name", "multi_batches", "multi_lr", "init",
                                                                     "bn_recalibration", "window", "same_windows")}
    ours = {k: v for k, v in dataclasses.asdict(recipe).items() if k in theirs}
    if theirs != ours:
        differ = sorted(k for k in theirs if theirs[k] != ours.get(k))
        raise UserError(f"--init {path}: stage 1 ran with other settings ({', '.join(differ)}); use the same ones")
    saved = state.config
    if (saved.grid, saved.width, saved.motion, saved.voxel_factor) != (net.config.grid, net.config.width,
                                                                       net.config.motion, net.config.voxel_factor):
        raise UserError(f"--init {path}: a {saved.name!r} network of another architecture than {net.config.name!r}")
    state.load_into(net)
    return {**state["stages"]["single"], "from": path.name, "model": saved.name}


def _init_role(path: Path) -> str:
    """The role of an --init file ("stage1" or "weights"), checked as a voxel model's weights file."""
    if not path.is_file():
        raise UserError(f"--init {path}: not found; give a .stage1.pt file or a CPU-track run's weights file")
    try:
        return read_weights(path, kind=registry.VOXEL).role
    except UserError as exc:
        raise UserError(f"--init {exc}") from None


def _load_trained(net, path: Path, recipe: CpuRecipe) -> dict:
    """Load a finished CPU-track run's weights (`path`: role "weights", the same model and architecture) into
    `net` to continue it; returns that run's stages record."""
    try:
        state = read_weights(path, kind=registry.VOXEL, model=recipe.model_name, role="weights")
    except UserError as exc:
        raise UserError(f"--init {exc}") from None
    saved = state.config
    if (saved.grid, saved.width, saved.voxel_factor) != (net.config.grid, net.config.width, net.config.voxel_factor) \
            or not isinstance(state.get("stages"), dict):
        raise UserError(f"--init {path}: not a CPU-track run of {recipe.model_name!r} with this recipe's grid and "
                        "width; continue a file `dsr-bench train --track cpu` wrote")
    state.load_into(net)
    return dict(state["stages"])


def train_cpu(recipe: CpuRecipe, data_dir: Path, split: str | None, out: Path, workers: int = 1,
              report: Callable[[str], None] = print) -> Path:
    """Train one CPU-track model by `recipe` on DATA_DIR's split and write its weights file to `out`."""
    from dsr_bench.models.dsr_net import DSRNet
    from dsr_bench.models.training.trainer import recalibrate_batchnorm

    config = recipe.model_config()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    data = pooled_split(data_dir, split, config.voxel_factor, workers,
                        lambda i, n: report(f"pooling {i}/{n}") if i % 50 == 0 or i == n else None)
    count, steps = data["action"].shape[:2]
    if recipe.window > steps:
        raise UserError(f"--window {recipe.window}: the sequences have {steps} pushes")
    provenance = data_provenance(data_dir, split, count)
    torch.manual_seed(recipe.seed)
    net = DSRNet(config)
    history = config.history != "none"
    batches, window = ((recipe.multi_batches, recipe.window) if history or recipe.same_windows
                       else (recipe.multi_batches * recipe.window, 1))
    if recipe.init is not None and _init_role(Path(recipe.init)) == "weights":
        stages = _load_trained(net, Path(recipe.init), recipe)
        continued = list(stages.get("continued", []))
        record = _stage(net, data, batches, window, recipe, recipe.multi_lr, recipe.seed + 10 + len(continued),
                        f"{config.name} continued {len(continued) + 1}", report)
        stages["continued"] = [*continued, {**record, "from": Path(recipe.init).name, "data": provenance}]
    else:
        if recipe.init is None:
            stages = {"single": _stage(net, data, recipe.single_batches, 1, recipe, recipe.lr, recipe.seed,
                                       f"{config.name} stage 1", report)}
            save_weights(stage1_path(out), config, net.state_dict(), "stage1", data=provenance,
                         recipe=_recorded(recipe), stages=dict(stages))
        else:
            stages = {"single": _load_stage1(net, Path(recipe.init), recipe)}
        if recipe.multi_batches:
            stages["multi"] = _stage(net, data, batches, window, recipe, recipe.multi_lr, recipe.seed + 1,
                                     f"{config.name} stage 2", report)
    passes = 0
    moving = {k: v.clone() for k, v in net.state_dict().items() if "running_" in k or "num_batches" in k}
    if recipe.bn_recalibration:
        windows = draw_windows(data, recipe.bn_recalibration, steps, recipe.batch_size, recipe.seed + 2,
                               config.grid)
        passes = recalibrate_batchnorm(net, windows, "cpu")
    net.eval()
    # the training's moving averages, which recalibration replaced, are kept (scripts/batchnorm_modes.py)
    return save_weights(out, config, net.state_dict(), "weights", fp16=True, data=provenance,
                        recipe=_recorded(recipe), stages=stages, bn_recalibration_passes=passes,
                        bn_moving_averages=half(moving))
