"""The paper's training curriculum as data: stages, windows, epochs and the official learning rates.

Stages (paper appendix, official scripts): `cube-single` (windows of 1 push, 30 epochs, from
scratch), `cube-multi` (windows of 10, 20 epochs, fine-tuning) and `shapenet-multi` (windows of 10,
20 epochs, fine-tuning). SingleStep and 3DFlow train with windows of 1 in every stage. Adam betas
(0.9, 0.95), batch 12 per GPU. Learning rates per epoch are the official piecewise-constant
tables (`scratch`: 1e-5 for 2 warm-up epochs, 1e-3, 5e-4, 2e-4, 5e-5, 1e-5; `finetune`: 5e-4,
2e-4, 5e-5, 1e-5); `--schedule paper` takes the paper's instead (appendix: 1e-3 halved every 5
epochs from scratch, 1e-4 halved every 3 when fine-tuning). Windows do not overlap (stride = window), as in
the official data loader. Any stage may run on any dataset directory (e.g. the procedural sets instead of ShapeNet).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from dsr_bench.errors import UserError

#: epoch from which each learning rate applies
SCHEDULES: dict[str, tuple[tuple[int, float], ...]] = {
    "scratch": ((0, 1e-5), (2, 1e-3), (5, 5e-4), (10, 2e-4), (20, 5e-5), (25, 1e-5)),
    "finetune": ((0, 5e-4), (5, 2e-4), (10, 5e-5), (15, 1e-5)),
    "paper-scratch": tuple((e, 1e-3 / 2 ** (e // 5)) for e in range(0, 30, 5)),
    "paper-finetune": tuple((e, 1e-4 / 2 ** (e // 3)) for e in range(0, 30, 3)),
}
#: `--schedule`: which table a stage's schedule name refers to
SCHEDULE_FAMILIES = ("official", "paper")
SINGLE_STEP_MODELS = ("single", "3dflow")
#: sample-steps of one epoch of the paper's stages: the official scripts' 4000 training sequences of 10 pushes
PAPER_EPOCH_SAMPLES = 40_000


@dataclass(frozen=True)
class StageConfig:
    """One stage of the curriculum. `lr` set: a constant learning rate instead of the schedule."""

    name: str
    window: int
    epochs: int
    schedule: str
    lr: float | None = None
    batch_size: int = 12
    betas: tuple[float, float] = (0.9, 0.95)
    mask_reduction: str = "sum"  # official: per-sample mean cross-entropy summed over the batch
    #: sample-steps (windows x pushes) that make one epoch, drawn from the data in shuffled passes repeated as
    #: needed (the last one cut short); None: one pass over the data's windows. The paper's epoch (4000
    #: sequences of 10 pushes, `PAPER_EPOCH_SAMPLES`) keeps its schedule on a smaller copy of the data.
    epoch_samples: int | None = None

    def lr_at(self, epoch: int) -> float:
        """Learning rate of an epoch (0-based)."""
        if self.lr is not None:
            return self.lr
        rate = SCHEDULES[self.schedule][0][1]
        for start, value in SCHEDULES[self.schedule]:
            if epoch >= start:
                rate = value
        return rate

    def epoch_windows(self, available: int) -> int:
        """Windows in one epoch of this stage when the data holds `available` windows: `epoch_samples` // window
        where set (at least 1), else all of them."""
        return available if self.epoch_samples is None else max(self.epoch_samples // self.window, 1)

    def as_dict(self) -> dict:
        out = asdict(self)
        out["betas"] = list(self.betas)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> StageConfig:
        known = {f.name for f in fields(cls)}
        data = {k: v for k, v in data.items() if k in known}
        data["betas"] = tuple(data["betas"])
        return cls(**data)


STAGES = {
    "cube-single": StageConfig("cube-single", window=1, epochs=30, schedule="scratch"),
    "cube-multi": StageConfig("cube-multi", window=10, epochs=20, schedule="finetune"),
    "shapenet-multi": StageConfig("shapenet-multi", window=10, epochs=20, schedule="finetune"),
}

#: the curriculum of each model: stages in order (single-step models keep windows of 1)
CURRICULUM = {model: ("cube-single", "cube-multi", "shapenet-multi") for model in ("dsr", "nowarp", "gtwarp", "single",
                                                                                 "3dflow")}


def stage_for(model: str, stage: str, *, epochs: int | None = None, batch_size: int | None = None,
              lr: float | None = None, window: int | None = None, schedule: str = "official",
              epoch_samples: int | None = None) -> StageConfig:
    """The stage's configuration for a model, with overrides (None keeps the stage's value); `schedule`:
    the official per-epoch tables or the paper's halving schedule."""
    if stage not in STAGES:
        raise UserError(f"--stage {stage!r}: choose one of {', '.join(STAGES)}")
    if schedule not in SCHEDULE_FAMILIES:
        raise UserError(f"--schedule {schedule!r}: choose official or paper")
    base = STAGES[stage].as_dict()
    if schedule == "paper":
        base["schedule"] = f"paper-{base['schedule']}"
    if model in SINGLE_STEP_MODELS:
        base["window"] = 1
    for key, value, low in (("epochs", epochs, 1), ("batch_size", batch_size, 1), ("window", window, 1),
                            ("epoch_samples", epoch_samples, 1)):
        if value is not None:
            if value < low:
                raise UserError(f"--{key.replace('_', '-')} {value}: must be at least {low}")
            base[key] = value
    if lr is not None:
        if not lr > 0:
            raise UserError(f"--lr {lr}: must be positive")
        base["lr"] = lr
    if model in SINGLE_STEP_MODELS and base["window"] != 1:
        raise UserError(f"--model {model} has no history: it trains on windows of 1 (drop --window)")
    return StageConfig.from_dict(base)
