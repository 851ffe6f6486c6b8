"""The recipes of `dsr-bench train`: one `Track` per kind of model and `--track` (`registry.KINDS` names them),
each saying which of the command's options it reads and how it trains. Every check of which options go with which
track is here, one `Track` each; the values themselves are checked by what the recipe builds (`TrainConfig`,
`CpuRecipe`, `ImageRecipe`). Torch-free: `dsr-bench train --help` shows each option's tracks from these tables.

- `VOXEL_FULL` (`--track full`, the default): the paper's curriculum on the benchmark's 128 x 128 x 48 grid, one
  stage (`trainer.train`) or all of them in turn (`--stage curriculum`, `training.curriculum`); a run directory.
- `VOXEL_CPU` (`--track cpu`): the CPU track's two-stage recipe on 32 x 32 x 16 (`cpu_track`); one weights file.
- `IMAGE_FULL`, `IMAGE_CPU`: the 2D track's single-stage recipe on 240 x 320 or 120 x 160 images (`image_track`).

`--finetune` swaps a track for its fine-tuning recipe (`Track.finetuning`: `VOXEL_CPU_FT`, `IMAGE_FT`,
`training.finetune`): the paper's fine-tuning of weights trained in simulation on a real split's fine-tune part, with
options of its own; the full track has none (its `--stage cube-multi --schedule paper` is the paper's rate).

`evaluate_heldout` predicts a held-out split with a trained model and scores it (`--eval-data`, any track).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from dsr_bench.errors import UserError
from dsr_bench.models import registry

__all__ = ["COMMON", "IMAGE_CPU", "IMAGE_FT", "IMAGE_FULL", "Track", "VOXEL_CPU", "VOXEL_CPU_FT", "VOXEL_FULL",
           "evaluate_heldout", "flag", "tracks_taking"]

#: the options every recipe reads (parameter names of `dsr-bench train`)
COMMON = ("model", "track", "data", "out", "split", "batch_size", "lr", "seed", "workers", "quiet", "eval_data",
          "eval_split")
#: option names whose flag is not the name with dashes
_FLAGS = {"compile_model": "--compile"}

Report = Callable[[str], None]


def flag(name: str) -> str:
    """The command-line flag of an option's parameter name (batch_size -> --batch-size)."""
    return _FLAGS.get(name, "--" + name.replace("_", "-"))


@dataclass(frozen=True)
class Track:
    """One recipe of `dsr-bench train`: the `--track` it answers, how messages name it (`words`), the options it
    reads beside `COMMON`, what it writes (`result`: "checkpoint", a run's last.pt; "weights", one file), its
    runner ("module:function" (model, options, report) -> the file written) and, for some options it does not read,
    the message that refuses them ("{flag}", "{value}" and "{words}" filled in)."""

    name: str
    words: str
    options: tuple[str, ...]
    runner: str
    result: str = "weights"
    refusals: Mapping[str, str] = field(default_factory=dict)
    #: the recipe `--finetune` runs instead ("module:attribute" of a Track; "": none, `refusals["finetune"]` says why)
    finetune: str = ""

    def __post_init__(self):
        object.__setattr__(self, "refusals", MappingProxyType(dict(self.refusals)))

    def takes(self, option: str) -> bool:
        """Whether it reads `option` (a parameter name of `dsr-bench train`)."""
        return option in COMMON or option in self.options

    def check(self, given: Mapping[str, Any]) -> None:
        """A one-line UserError for the first option of `given` (name -> value: the options the command line sets to
        other than their defaults) that this recipe does not read: the option is named and dropping it is the fix,
        or the recipe's own message for it."""
        for name, value in given.items():
            if not self.takes(name):
                message = self.refusals.get(name, "{flag} is not an option of {words}; drop it")
                raise UserError(message.format(flag=flag(name), value=value, words=self.words))

    def finetuning(self) -> Track:
        """The recipe of `--finetune` on this track (a Track), or a one-line UserError saying why there is none."""
        if not self.finetune:
            message = self.refusals.get("finetune", "--finetune is not offered on {words}; drop it")
            raise UserError(message.format(flag="--finetune", value=True, words=self.words))
        return registry.resolve(self.finetune)

    def train(self, model: str, options: Mapping[str, Any], report: Report) -> Path:
        """Train `model` by this recipe with the command's `options` (every option by name); returns the file written
        (a run's last.pt, or the weights file)."""
        return registry.resolve(self.runner)(model, options, report)


def tracks_taking(option: str) -> list[str]:
    """How `--help` names the recipes that read `option`: "full", "cpu", "2D" (the 2D track's, either track)."""
    labels = []
    for kind in registry.KINDS.values():
        for name in kind.tracks:
            track = kind.track(name)
            label = "2D" if kind.name == registry.IMAGE else name
            if track.takes(option) and label not in labels:
                labels.append(label)
    tuning = [registry.resolve(kind.track(name).finetune) for kind in registry.KINDS.values() for name in kind.tracks
              if kind.track(name).finetune]
    if any(track.takes(option) for track in tuning) and option not in COMMON:
        labels.append("fine-tuning")
    return labels


# --- the full track -----------------------------------------------------------------------------------------------
def train_full(model: str, options: Mapping[str, Any], report: Report) -> Path:
    """`--track full`: one stage of the curriculum (`trainer.train`), or all of them (`--stage curriculum`); returns
    the last checkpoint written."""
    from dsr_bench.models.training.config import CURRICULUM, TrainConfig
    from dsr_bench.models.training.schedules import STAGES

    o = options
    if o["stage"] is not None and o["stage"] not in (*STAGES, CURRICULUM):
        raise UserError(f"--stage {o['stage']!r}: choose one of {', '.join(STAGES)} or {CURRICULUM} (all of them "
                        "in turn)")
    # TrainConfig checks its own values (--stage, --max-steps, --max-minutes, --workers, --resume with --init)
    config = TrainConfig(model_name=model, stage_name=o["stage"] or "", data=o["data"], out=o["out"], split=o["split"],
                         val_split=o["val_split"], epochs=o["epochs"], epoch_samples=o["epoch_samples"],
                         batch_size=o["batch_size"], lr=o["lr"], window=o["window"], max_steps=o["max_steps"],
                         max_seconds=None if o["max_minutes"] is None else o["max_minutes"] * 60, init=o["init"],
                         resume=o["resume"], device=o["device"], bf16=o["bf16"], compile_model=o["compile_model"],
                         channels_last=o["channels_last"], workers=o["workers"], seed=o["seed"],
                         official_bn=o["official_bn"], deterministic=o["deterministic"], grid=o["grid_size"] or None,
                         checkpoint_every=o["checkpoint_every"], progress=not o["quiet"],
                         bn_recalibration=o["bn_recalibration"], schedule=o["schedule"],
                         stage_data=tuple(_stage_data(item) for item in o["stage_data"] or ()))
    if config.stage_name == CURRICULUM:
        from dsr_bench.models.training.curriculum import train_curriculum

        done = train_curriculum(config, report)
        if done.last is None:
            raise UserError(f"{config.out}: no stage was trained; give a larger --max-minutes or --max-steps")
        return done.last
    from dsr_bench.models.training.trainer import train

    return train(config)


def _stage_data(item: str) -> tuple[str, Path]:
    """`--stage-data STAGE=DIR` as (stage, directory)."""
    from dsr_bench.models.training.schedules import STAGES

    stage, sep, directory = item.partition("=")
    if not sep or stage not in STAGES or not directory:
        raise UserError(f"--stage-data {item!r}: give STAGE=DIR, STAGE one of {', '.join(STAGES)}")
    return stage, Path(directory)


#: The options a budget or a run directory of the full track reads; the curriculum's too.
VOXEL_FULL = Track(
    "full", "the full track",
    ("stage", "stage_data", "val_split", "init", "resume", "epochs", "epoch_samples", "schedule", "window",
     "max_steps", "max_minutes", "checkpoint_every", "grid_size", "bn_recalibration", "official_bn", "deterministic",
     "device", "bf16", "compile_model", "channels_last"),
    f"{__name__}:train_full", result="checkpoint",
    refusals={"multi_lr": "--multi-lr is the CPU track's stage-2 rate (--track cpu); the full track's is --lr",
              "finetune": "--finetune fine-tunes the CPU track's and the 2D track's weights (--track cpu); on the full "
                          "track fine-tune a run's last.pt with --stage cube-multi --schedule paper --init RUN/last.pt "
                          "--data REAL --split NAME-finetune (the paper's fine-tuning rate)"})


# --- the CPU track ------------------------------------------------------------------------------------------------
def train_cpu_track(model: str, options: Mapping[str, Any], report: Report) -> Path:
    """`--track cpu`: the CPU track's recipe (`models.training.cpu_track`), one weights file (and its stage-1 weights
    beside it); --init: stage 2 from another run's stage-1 weights, or more of stage 2 from a finished run's."""
    from dsr_bench.models.training.cpu_track import CpuRecipe, train_cpu

    o, out = options, Path(options["out"])
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; --track cpu writes one weights file "
                        f"(e.g. {out / (model + '.pt')})")
    overrides = {k: o[k] for k in ("batch_size", "lr", "multi_lr", "window") if o[k] is not None}
    recipe = CpuRecipe(model, single_batches=3000 if o["single_batches"] is None else o["single_batches"],
                       multi_batches=o["multi_batches"], seed=o["seed"], bn_recalibration=o["bn_recalibration"],
                       init=None if o["init"] is None else str(o["init"]), same_windows=o["same_windows"], **overrides)
    return train_cpu(recipe, o["data"], o["split"], out, workers=max(1, o["workers"]), report=report)


VOXEL_CPU = Track(
    "cpu", "the CPU track",
    ("init", "window", "bn_recalibration", "single_batches", "multi_batches", "multi_lr", "same_windows"),
    f"{__name__}:train_cpu_track",
    refusals={"stage": "--stage {value}: the CPU track's recipe runs both its stages; drop --stage",
              "epoch_samples": "--epoch-samples is an option of the full track (its recipe counts batches); drop it",
              "device": "--device {value}: the CPU track trains on the CPU; drop --device"},
    finetune=f"{__name__}:VOXEL_CPU_FT")


# --- the 2D track -------------------------------------------------------------------------------------------------
def train_image_track(model: str, options: Mapping[str, Any], report: Report) -> Path:
    """The 2D track (`models.training.image_track`): one weights file; --track cpu: 120 x 160 input images, full:
    240 x 320."""
    from dsr_bench.models.training.image_track import ImageRecipe, train_image_model

    o, out = options, Path(options["out"])
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; the 2D track writes one weights file "
                        f"(e.g. {out / (model + '.pt')})")
    overrides = {k: v for k, v in {"batch_size": o["batch_size"], "lr": o["lr"], "batches": o["single_batches"]}.items()
                 if v is not None}
    recipe = ImageRecipe(model, seed=o["seed"], image_factor=2 if o["track"] == "cpu" else 1, **overrides)
    return train_image_model(recipe, o["data"], o["split"], out, o["device"], workers=max(1, o["workers"]),
                             report=report)


_IMAGE_WORDS = "the 2D track's models (single-step, one stage)"
IMAGE_FULL = Track("full", _IMAGE_WORDS, ("single_batches", "device"), f"{__name__}:train_image_track",
                   finetune=f"{__name__}:IMAGE_FT")
IMAGE_CPU = Track("cpu", _IMAGE_WORDS, ("single_batches", "device"), f"{__name__}:train_image_track",
                  finetune=f"{__name__}:IMAGE_FT")


# --- fine-tuning on a real split ----------------------------------------------------------------------------------
def finetune_cpu_track(model: str, options: Mapping[str, Any], report: Report) -> Path:
    """`--finetune --track cpu`: a CPU-track voxel model's weights (`--init`) fine-tuned on a real split
    (`training.finetune`); the weights file written (with `--max-steps`, the partial checkpoint when stopped)."""
    from dsr_bench.models.training.finetune import finetune_voxel, partial_path

    o = _finetune_options(options)
    written = finetune_voxel(model, o["init"], o["data"], o["split"], Path(o["out"]), epochs=o["epochs"], lr=o["lr"],
                             batch_size=o["batch_size"], window=o["window"], bn_recalibration=o["bn_recalibration"],
                             seed=o["seed"], max_steps=o["max_steps"], workers=max(1, o["workers"]), report=report)
    return partial_path(Path(o["out"])) if written is None else written


def finetune_image_track(model: str, options: Mapping[str, Any], report: Report) -> Path:
    """`--finetune` of a 2D-track model's weights (`--init`) on a real split (`training.finetune`)."""
    from dsr_bench.models.training.finetune import finetune_image, partial_path

    o = _finetune_options(options)
    written = finetune_image(model, o["init"], o["data"], o["split"], Path(o["out"]), epochs=o["epochs"], lr=o["lr"],
                             batch_size=o["batch_size"], seed=o["seed"], device=o["device"], max_steps=o["max_steps"],
                             workers=max(1, o["workers"]), report=report)
    return partial_path(Path(o["out"])) if written is None else written


def _finetune_options(options: Mapping[str, Any]) -> dict:
    """The options of a fine-tuning run: --init required, --epochs the paper's 20 where not given."""
    from dsr_bench.models.training.finetune import PAPER_EPOCHS

    if options["init"] is None:
        raise UserError("--finetune needs --init WEIGHTS: the weights trained in simulation to fine-tune (e.g. "
                        "dsr_bench/models/weights/cpu-track/dsr.pt)")
    return {**options, "epochs": PAPER_EPOCHS if options["epochs"] is None else options["epochs"]}


_FT_REFUSALS = {"multi_batches": "--multi-batches is the CPU track's recipe; fine-tuning runs --epochs passes over the "
                                 "fine-tune part; drop it",
                "single_batches": "--single-batches is a recipe's from scratch; fine-tuning runs --epochs passes over "
                                  "the fine-tune part; drop it"}
#: `--finetune --track cpu`: the CPU track's voxel models
VOXEL_CPU_FT = Track("cpu", "fine-tuning on the CPU track",
                     ("finetune", "init", "epochs", "window", "bn_recalibration", "max_steps"),
                     f"{__name__}:finetune_cpu_track", refusals=_FT_REFUSALS)
#: `--finetune` of the 2D track's models (either track: the network's image is the weights')
IMAGE_FT = Track("2D", "fine-tuning the 2D track's models", ("finetune", "init", "epochs", "max_steps", "device"),
                 f"{__name__}:finetune_image_track", refusals=_FT_REFUSALS)


# --- the held-out evaluation --------------------------------------------------------------------------------------
def evaluate_heldout(model: str, weights: Path | None, data: Path, split: str | None, predictions: Path,
                     device: str = "cpu", sequences: int = 0, workers: int = 0) -> dict:
    """Predict DATA's split (its first `sequences`; 0: all) with `model` (`weights`: its weights file; None: a
    reference model, or the shipped weights) into `predictions`, as `dsr-bench predict` does, and score them as
    `dsr-bench evaluate` does (a subset as a partial split); returns the results."""
    from dsr_bench.dataset.manifest import read_split
    from dsr_bench.models.predictors import load_predictor, predict_split
    from dsr_bench.scoring.evaluate import evaluate
    from dsr_bench.scoring.predictions import record_source

    split, names = read_split(data, split)
    subset = names[:sequences] if sequences else names
    predictor = load_predictor(model, weights, device if weights is not None else "cpu")
    predict_split(predictor, data, subset, predictions)
    record_source(predictions, data, split)
    evaluation = evaluate(predictions, data, split, allow_partial=len(subset) < len(names), workers=workers)
    if evaluation.results is None:
        raise UserError(f"evaluating {model} on {data}: " + "; ".join(f"{f}: {p}" for f, p in evaluation.problems[:3]))
    return evaluation.results
