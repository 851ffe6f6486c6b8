"""The model registry: every model that `dsr-bench predict` and `dsr-bench train` know, one entry each.

An entry's kind says how the model is made, loaded and trained; everything else follows from the table:
- "reference": a predictor that needs no training (`predictor`: "module:Class", made with no arguments);
- "voxel": the 3D track's DSR-Net family, one network (`models.dsr_net`) whose `ModelConfig` switches are the
  entry's `variant`; loaded from a dsr-bench checkpoint, the shipped CPU-track weights or the authors' released
  .pth (`--weights`), trained with `dsr-bench train` (full or CPU track);
- "image": the 2D track's models (`models.image_nets`, `ImageModelConfig`), 2D-only predictions, trained with
  `dsr-bench train` (one stage).

The name is what a checkpoint's saved config records (`ModelConfig.name`, `ImageModelConfig.name`): reading
weights back, the name resolves the entry, and with it the config class and the network. The order of the table
is the order every list of names shows (`--help`, error messages). Adding a model: docs/models.md, "Adding a
model". Pure Python: the CLI builds its help from this table without importing numpy or torch.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from dsr_bench.errors import UserError

REFERENCE, VOXEL, IMAGE = "reference", "voxel", "image"
KINDS = (REFERENCE, VOXEL, IMAGE)


@dataclass(frozen=True)
class ModelEntry:
    """One model: its name (`--model NAME`, the name saved with its weights), kind, one-line description
    (the predictions' meta.json and the leaderboard; a reference predictor's is its class's docstring),
    the ModelConfig switches of a voxel model, the predictor class of a reference one, and whether the authors
    released weights for it (a voxel model: `predict --weights`, `models.official_weights`)."""

    name: str
    kind: str
    description: str = ""
    variant: Mapping[str, str] = field(default_factory=dict)
    predictor: str = ""
    released: bool = False

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"model {self.name!r}: kind {self.kind!r}, choose one of {', '.join(KINDS)}")
        if (self.kind == REFERENCE) != bool(self.predictor):
            raise ValueError(f"model {self.name!r}: a reference model names its predictor class, no other does")
        if self.variant and self.kind != VOXEL:
            raise ValueError(f"model {self.name!r}: only a voxel model has ModelConfig switches (variant)")
        if self.released and self.kind != VOXEL:
            raise ValueError(f"model {self.name!r}: the authors released weights of voxel models only")
        object.__setattr__(self, "variant", MappingProxyType(dict(self.variant)))

    def make_predictor(self):
        """A reference model's predictor (its class imported on use)."""
        from importlib import import_module

        module, _, attr = self.predictor.partition(":")
        return getattr(import_module(module), attr)()


_PREDICTORS = "dsr_bench.models.predictors"

MODELS: Mapping[str, ModelEntry] = MappingProxyType({entry.name: entry for entry in (
    ModelEntry("oracle", REFERENCE, predictor=f"{_PREDICTORS}:OraclePredictor"),
    ModelEntry("static", REFERENCE, predictor=f"{_PREDICTORS}:StaticPredictor"),
    ModelEntry("push", REFERENCE, predictor=f"{_PREDICTORS}:PushPredictor"),
    ModelEntry("dsr", VOXEL, "DSR-Net: history forward-warped by the predicted motion", {"history": "warp"},
               released=True),
    ModelEntry("single", VOXEL, "SingleStep: DSR-Net without history", {"history": "none"}, released=True),
    ModelEntry("nowarp", VOXEL, "NoWarp: DSR-Net with the history not warped", {"history": "nowarp"}, released=True),
    ModelEntry("gtwarp", VOXEL, "GTWarp (oracle): history warped with the ground-truth flow", {"history": "gtwarp"},
               released=True),
    ModelEntry("3dflow", VOXEL, "3DFlow: per-voxel flow from a 3D conv decoder, no history",
               {"history": "none", "motion": "flow"}, released=True),
    ModelEntry("2dflow", IMAGE, "2DFlow: per-pixel 3D flow from a 2D encoder-decoder (Byravan and Fox 2017's flow "
                                "baseline)"),
    ModelEntry("se3net", IMAGE, "SE3-Net: K masks and K rigid motions from image and action, flow blended (Byravan "
                                "and Fox 2017)"),
    ModelEntry("se3posenet", IMAGE, "SE3Pose-Net: masks and poses from the image, a pose-space transition under the "
                                    "action, flow from the poses (Byravan et al. 2018)"),
)})


def released() -> tuple[str, ...]:
    """The models whose weights the authors released (`predict --weights`), in the table's order."""
    return tuple(name for name, entry in MODELS.items() if entry.released)


def names(*kinds: str) -> tuple[str, ...]:
    """The models of these kinds (all without any), in the table's order."""
    return tuple(name for name, entry in MODELS.items() if not kinds or entry.kind in kinds)


def model_entry(name: str, *kinds: str, choices: tuple[str, ...] | None = None) -> ModelEntry:
    """The entry of `--model name` among the models of `kinds` (all without any); a UserError naming the choices
    (`choices`, default those models) otherwise."""
    entry = MODELS.get(name)
    if entry is None or (kinds and entry.kind not in kinds):
        raise UserError(f"--model {name!r}: choose one of {', '.join(choices or names(*kinds))}")
    return entry


def help_text(*kinds: str) -> str:
    """'a | b | c': the models of these kinds (all without any), for a --model option's help."""
    return " | ".join(names(*kinds))
