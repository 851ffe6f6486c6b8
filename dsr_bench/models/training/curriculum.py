"""The paper's curriculum in one command: `dsr-bench train --stage curriculum`.

A model's stages (`schedules.CURRICULUM`: cube-single, cube-multi, shapenet-multi) run one after the other, each
a run of the one training path (`trainer.train`) in OUT/<stage>/ (last.pt, config.json, metrics.jsonl), each
started from the weights the stage before it finished with (as `--init`), each on its own data: `--stage-data
STAGE=DIR`, else `--data` (cube data for the cube stages, then ShapeNet's or a built-in set's for shapenet-multi).

Resumable by running the same command again: the files in OUT say where the curriculum stands. A stage whose
epochs are done is skipped, an unfinished one is resumed exactly (`--resume` of its last.pt: weights, optimiser,
schedule, RNG states, data position), the next one started. `config.resume` (a checkpoint of some stage, e.g. the
lent-GPU weights in weights/gpu-track/) places the curriculum at that file's position where OUT holds nothing yet.

A budget makes the short runs of a lent GPU the same command: `max_seconds` bounds one invocation's training and
`max_steps` its batches, over the stages (a stage the budget ends is saved resumable, with precise BatchNorm when
`bn_recalibration` asks). Each data directory and split is checked before any training.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from dsr_bench.errors import UserError
from dsr_bench.models.training.config import CURRICULUM, TrainConfig
from dsr_bench.models.training.schedules import CURRICULUM as STAGES_OF, SINGLE_STEP_MODELS, STAGES

__all__ = ["CURRICULUM", "CurriculumRun", "StageRun", "next_stage", "train_curriculum"]


@dataclass
class StageRun:
    """What one invocation did in one stage: whether it resumed the stage, its step counter before and after, the
    epoch reached of its epochs, the batches' records (metrics.jsonl lines of this invocation), the wall time and
    the checkpoint written."""

    stage: str
    data: Path
    resumed: bool
    steps: tuple[int, int]
    epoch: int
    epochs: int
    batches: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    last: Path | None = None

    @property
    def sample_steps(self) -> int:
        """Sample-steps (windows x pushes x processes) trained in this invocation."""
        return sum(int(record["samples"]) for record in self.batches)

    def summary(self) -> dict:
        """The stage's record in a summary: stage, resumed, steps [before, after], epoch, epochs, sample_steps."""
        return {"stage": self.stage, "resumed": self.resumed, "steps": list(self.steps), "epoch": self.epoch,
                "epochs": self.epochs, "sample_steps": self.sample_steps}


@dataclass
class CurriculumRun:
    """What `train_curriculum` did: each stage it trained, in order, the latest checkpoint (None: none yet), and
    the stage that comes next (None: the curriculum is done)."""

    stages: list[StageRun]
    last: Path | None
    next_stage: str | None


def next_stage(model: str, stage: dict | None, epoch: int, epochs: int | None = None) -> tuple[str | None, bool]:
    """(stage to train, whether to resume the position in it) for a model whose latest checkpoint is at `epoch` of
    `stage` (its saved stage dict; None: no checkpoint). A stage whose epochs (`epochs` where given, as --epochs
    replaces a resumed stage's, else its own) are done hands on to the next stage of the curriculum (started from
    its weights, not resumed); (None, False) once the curriculum's last stage is done."""
    curriculum = STAGES_OF[model]
    if stage is None:
        return curriculum[0], False
    if epoch < (int(stage["epochs"]) if epochs is None else epochs):
        return str(stage["name"]), True
    following = curriculum.index(stage["name"]) + 1 if stage["name"] in curriculum else len(curriculum)
    return (curriculum[following], False) if following < len(curriculum) else (None, False)


def stage_data(config: TrainConfig) -> dict[str, Path]:
    """Each stage of the model's curriculum -> its data directory (`config.stage_data`, else `config.data`)."""
    return {**{stage: config.data for stage in STAGES_OF[config.model_name]}, **dict(config.stage_data)}


def _check_data(config: TrainConfig, data: dict[str, Path]) -> None:
    """Every stage's data directory holds the split (and the validation split): one line naming it otherwise."""
    from dsr_bench.dataset.manifest import read_split

    for directory in dict.fromkeys(data.values()):
        read_split(directory, config.split)
        if config.val_split:
            read_split(directory, config.val_split)


def _latest(config: TrainConfig):
    """The checkpoint the curriculum goes on from: the latest stage's OUT/<stage>/last.pt, else `config.resume`,
    else None."""
    from dsr_bench.models import registry
    from dsr_bench.models.training.checkpoints import read_weights

    for stage in reversed(STAGES_OF[config.model_name]):
        path = config.out / stage / "last.pt"
        if path.exists():
            return read_weights(path, kind=registry.VOXEL, model=config.model_name, role="checkpoint")
    if config.resume is None:
        return None
    weights = read_weights(config.resume, kind=registry.VOXEL, model=config.model_name, role="checkpoint")
    if weights["stage"].get("name") not in STAGES_OF[config.model_name]:
        raise UserError(f"--resume {config.resume}: a run of stage {weights['stage'].get('name')!r}, not one of the "
                        f"curriculum's ({', '.join(STAGES_OF[config.model_name])})")
    return weights


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines() if path.is_file() else []


def train_curriculum(config: TrainConfig, report: Callable[[str], None] = print,
                     min_stage_seconds: float = 0.0) -> CurriculumRun:
    """Train `config.model_name` through its curriculum from where OUT (or `config.resume`) stands, until it is done
    or the budget (`max_seconds`, `max_steps`: this invocation's) is spent; a further stage starts only with more
    than `min_stage_seconds` of the budget left. The config's other fields apply to every stage; `epoch_samples`,
    `batch_size` and `window` (the multi-step stages' window, history models only) to the stages started here
    (a resumed stage keeps its own)."""
    from dsr_bench.models.training.trainer import train

    if config.stage_name != CURRICULUM:
        raise ValueError(f"train_curriculum runs --stage {CURRICULUM}, not {config.stage_name!r}")
    model = config.model_name
    data = stage_data(config)
    _check_data(config, data)
    weights = _latest(config)
    source = config.init if weights is None else weights.path
    stage, resume = next_stage(model, None if weights is None else weights["stage"],
                               0 if weights is None else int(weights["epoch"]), config.epochs)
    deadline = None if config.max_seconds is None else time.monotonic() + config.max_seconds
    steps_left = config.max_steps
    done: list[StageRun] = []
    while stage is not None:
        seconds = None if deadline is None else deadline - time.monotonic()
        if (steps_left is not None and steps_left < 1) or (seconds is not None and done
                                                           and seconds <= min_stage_seconds):
            break
        before = int(weights["step"]) if resume and weights is not None else 0
        multi = STAGES[stage].window > 1 and model not in SINGLE_STEP_MODELS
        stage_config = dataclasses.replace(
            config, stage_name=stage, data=data[stage], out=config.out / stage, stage_data=(),
            resume=source if resume else None, init=None if resume else source,
            epoch_samples=None if resume else config.epoch_samples, batch_size=None if resume else config.batch_size,
            window=config.window if multi and not resume else None,
            max_steps=None if steps_left is None else before + steps_left,
            max_seconds=None if seconds is None else max(seconds, 1e-3))
        report(f"{model}: {'resuming' if resume else 'starting'} stage {stage} at its step {before} "
               f"({'from ' + Path(source).name if source else 'new weights'}; data {data[stage]})"
               + ("" if seconds is None else f", {seconds:.0f} s left"))
        metrics = config.out / stage / "metrics.jsonl"
        logged, started = len(_lines(metrics)), time.monotonic()
        last = train(stage_config)
        batches = [r for r in (json.loads(line) for line in _lines(metrics)[logged:] if line.strip()) if "loss" in r]
        weights = _read(last, model)
        record = StageRun(stage, data[stage], resume, (before, int(weights["step"])), int(weights["epoch"]),
                          int(weights["stage"]["epochs"]), batches, time.monotonic() - started, last)
        done.append(record)
        report(f"{model}: stage {stage} at step {record.steps[1]}, epoch {record.epoch}/{record.epochs}, "
               f"{len(batches)} batches ({record.sample_steps} sample-steps) in {record.seconds:.0f} s")
        if steps_left is not None:
            steps_left -= record.steps[1] - before
        source = last
        stage, resume = next_stage(model, weights["stage"], record.epoch, config.epochs)
        if stage is not None and resume:  # the budget ended the stage: the next invocation goes on with it
            break
    if stage is None:
        report(f"{model}: the curriculum is done ({', '.join(STAGES_OF[model])})")
    return CurriculumRun(done, None if weights is None else weights.path, stage)


def _read(path: Path, model: str):
    from dsr_bench.models import registry
    from dsr_bench.models.training.checkpoints import read_weights

    return read_weights(path, kind=registry.VOXEL, model=model, role="checkpoint")
