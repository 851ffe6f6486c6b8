"""What one training run is told: `TrainConfig`, built by `dsr-bench train` from its options (or by
a script) and passed to `dsr_bench.models.training.trainer.train`; it checks its own values (one-line
UserErrors naming the option). Torch-free."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dsr_bench.errors import UserError

#: the `--stage` that runs a model's whole curriculum (`training.curriculum`), each stage a run of its own
CURRICULUM = "curriculum"


@dataclass(frozen=True)
class TrainConfig:
    """Every argument of one training run (one curriculum stage of one model).

    None for an override keeps the stage's value (`dsr_bench.models.training.schedules`). The
    defaults are the library's; the CLI passes every field (its own default for `workers` is 4).
    """

    #: the reference model: dsr | single | nowarp | gtwarp | 3dflow
    model_name: str
    #: the curriculum stage: cube-single | cube-multi | shapenet-multi (any data set), or "curriculum": all of the
    #: model's stages in turn (`training.curriculum`)
    stage_name: str
    #: dataset directory (sequence files, manifest, split lists); the curriculum's: every stage's but those of
    #: `stage_data`
    data: Path
    #: run directory: last.pt, config.json, metrics.jsonl, tensorboard/
    out: Path
    #: training split (None: the dataset's only split)
    split: str | None = None
    #: validation split, scored after each epoch on rank 0 (None: no validation)
    val_split: str | None = None
    #: epochs of the stage (None: the stage's; with `resume`, replaces the checkpoint's)
    epochs: int | None = None
    #: sample-steps per epoch, drawn from the data in repeated shuffled passes (None: one pass; with `resume`,
    #: the checkpoint's stage keeps its own)
    epoch_samples: int | None = None
    #: windows per batch per process (None: the stage's, 12)
    batch_size: int | None = None
    #: constant learning rate instead of the stage's per-epoch table (None: the table)
    lr: float | None = None
    #: pushes per window (None: the stage's; models without history always 1)
    window: int | None = None
    #: end the stage after this many batches (optimiser windows), with a resumable checkpoint
    max_steps: int | None = None
    #: end the stage after this many seconds of the training loop (wall time), checked after each batch
    max_seconds: float | None = None
    #: start from this checkpoint's weights (the next stage of the curriculum)
    init: Path | None = None
    #: continue this checkpoint's run exactly (weights, optimiser, schedule, RNG, data position)
    resume: Path | None = None
    #: torch device: cpu, cuda or cuda:N (under torchrun each process takes cuda:LOCAL_RANK)
    device: str = "cpu"
    #: bf16 autocast (softmax, pivots, motion and the warp stay fp32)
    bf16: bool = False
    #: torch.compile the model and the warp (GPU only)
    compile_model: bool = False
    #: channels_last_3d memory format for the 3D convolutions
    channels_last: bool = False
    #: DataLoader worker processes per process
    workers: int = 2
    #: seed of the initialisation and of the data order (rank r seeds seed + r)
    seed: int = 0
    #: validate with BatchNorm in train mode, as the official code
    official_bn: bool = False
    #: when the stage ends, re-estimate BatchNorm's running statistics on this many batches of whole
    #: sequences of the training split, the state carried (precise BN; 0: keep the training's moving
    #: averages, which after single-step windows never saw a state: docs/models.md, BatchNorm)
    bn_recalibration: int = 0
    #: learning rates: the official per-epoch tables ("official") or the paper's halving ("paper")
    schedule: str = "official"
    #: deterministic algorithms and warp
    deterministic: bool = False
    #: expected grid (Y, X, Z) in voxels (None: the data's)
    grid: tuple[int, int, int] | None = None
    #: also save last.pt every this many batches (0: at the end of each epoch only)
    checkpoint_every: int = 0
    #: TensorBoard scalars every this many batches (metrics.jsonl gets every batch)
    log_every: int = 10
    #: show a progress bar (rank 0)
    progress: bool = True
    #: the curriculum's data of some of its stages, ((stage, directory), ...), instead of `data`
    stage_data: tuple[tuple[str, Path], ...] = ()

    def __post_init__(self):
        for name in ("data", "out", "init", "resume"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, Path):
                object.__setattr__(self, name, Path(value))
        if self.grid is not None:
            object.__setattr__(self, "grid", tuple(int(g) for g in self.grid))
        if not self.stage_name:
            raise UserError("--stage is needed on the full track: cube-single, cube-multi or shapenet-multi")
        if self.bn_recalibration < 0:
            raise UserError(f"--bn-recalibration {self.bn_recalibration}: must be >= 0")
        if self.max_steps is not None and self.max_steps < 1:
            raise UserError(f"--max-steps {self.max_steps}: must be at least 1")
        if self.max_seconds is not None and not self.max_seconds > 0:
            raise UserError(f"--max-minutes {self.max_seconds / 60}: must be positive")
        if self.workers < 0 or self.checkpoint_every < 0:
            raise UserError("--workers and --checkpoint-every must be >= 0")
        if self.log_every < 1:
            raise UserError(f"log_every {self.log_every}: must be at least 1")
        if self.resume is not None and self.init is not None:
            raise UserError("--resume continues a run with its own weights; drop --init")
        if self.stage_data:
            from dsr_bench.models.training.schedules import STAGES

            if self.stage_name != CURRICULUM:
                raise UserError(f"--stage-data gives the data of the curriculum's stages (--stage {CURRICULUM}); "
                                "a single stage trains on --data")
            stages = [stage for stage, _ in self.stage_data]
            for stage in stages:
                if stage not in STAGES or stages.count(stage) > 1:
                    raise UserError(f"--stage-data {stage}=...: give each of {', '.join(STAGES)} at most once")
            object.__setattr__(self, "stage_data", tuple((stage, Path(d)) for stage, d in self.stage_data))
