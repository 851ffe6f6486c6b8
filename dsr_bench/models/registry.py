"""The model registry: every model that `dsr-bench predict` and `dsr-bench train` know, one entry each, and the kinds
of model, one object each.

A kind (`KINDS`, a `ModelKind`) owns everything its models share: the configuration class, the network, the loader
behind `dsr-bench predict` and the recipes of `dsr-bench train` (one per track, `models.training.tracks`), each
named "module:attribute" and imported on use. There are three:
- "reference": a predictor that needs no training (the entry's `predictor`: "module:Class", made with no arguments);
- "voxel": the 3D track's DSR-Net family, one network (`models.dsr_net`) whose `ModelConfig` switches are the
  entry's `variant`; loaded from a dsr-bench weights file, the shipped CPU-track weights or the authors' released
  .pth (`--weights`), trained on the full track (the paper's curriculum) or the CPU track;
- "image": the 2D track's models (`models.image_nets`, `ImageModelConfig`), 2D-only predictions, one stage.

The name is what a weights file records (`model_type`, the configuration's `name`): reading weights back, the name
resolves the entry, the entry its kind, and the kind the configuration class, the network and the loader (as
LeRobot's config registry resolves a policy from the type saved with it). The order of the table is the order every
list of names shows (`--help`, error messages). Adding a model or a kind: docs/models.md, "Adding a model". Pure
Python: the CLI builds its help from these tables without importing numpy or torch.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from dsr_bench.errors import UserError

REFERENCE, VOXEL, IMAGE = "reference", "voxel", "image"


def resolve(spec: str) -> Any:
    """The object "module:attribute" names (imported on use)."""
    from importlib import import_module

    module, _, attr = spec.partition(":")
    return getattr(import_module(module), attr)


@dataclass(frozen=True)
class ModelKind:
    """One kind of model and everything its models share, each part named "module:attribute" (`resolve`):

    - `config`: its configuration class: `for_model(name, **fields)` (the entry's defaults), `from_dict`, `as_dict`,
      and a `name` field, the model's (what a weights file records as its model type);
    - `network`: the torch module built from that configuration;
    - `loader`: the predictor of `dsr-bench predict` (`predictors.load_predictor` calls it with the entry and the
      command's options);
    - `tracks`: the recipes of `dsr-bench train`, one per `--track` (`models.training.tracks.Track`), in the order
      `--track`'s choices show them; none: a kind that is not trained (reference predictors);
    - `files`: what messages call its weights files ("3D-track weights file").
    """

    name: str
    loader: str
    config: str = ""
    network: str = ""
    tracks: Mapping[str, str] = field(default_factory=dict)
    files: str = ""

    def __post_init__(self):
        if bool(self.config) != bool(self.network) or (self.tracks and not self.config):
            raise ValueError(f"kind {self.name!r}: a trained kind names its config and network, both or neither")
        object.__setattr__(self, "tracks", MappingProxyType(dict(self.tracks)))

    @property
    def trainable(self) -> bool:
        """Whether `dsr-bench train` trains its models (it has tracks)."""
        return bool(self.tracks)

    def config_class(self) -> Any:
        """Its configuration class (imported on use)."""
        return resolve(self.config)

    def network_class(self) -> Any:
        """Its network class (imported on use)."""
        return resolve(self.network)

    def track(self, name: str) -> Any:
        """Its recipe of `dsr-bench train --track name` (a `tracks.Track`); a UserError naming its tracks otherwise."""
        if name not in self.tracks:
            raise UserError(f"--track {name!r}: choose {' or '.join(self.tracks)}")
        return resolve(self.tracks[name])

    def train_command(self) -> str:
        """How a user makes a weights file of this kind, for messages."""
        return f"`dsr-bench train --model {'|'.join(names(self.name))}`"


_TRACKS = "dsr_bench.models.training.tracks"

#: The kinds of model: everything a model of each kind needs beside its entry in MODELS (docs/models.md, "Adding a
#: model"). A new kind is one object here; its models are entries of MODELS of that kind.
KINDS: Mapping[str, ModelKind] = MappingProxyType({kind.name: kind for kind in (
    ModelKind(REFERENCE, loader="dsr_bench.models.predictors:load_reference"),
    ModelKind(VOXEL, loader="dsr_bench.models.inference:load_voxel", config="dsr_bench.models.config:ModelConfig",
              network="dsr_bench.models.dsr_net:DSRNet", files="3D-track",
              tracks={"full": f"{_TRACKS}:VOXEL_FULL", "cpu": f"{_TRACKS}:VOXEL_CPU"}),
    ModelKind(IMAGE, loader="dsr_bench.models.image_inference:load_image",
              config="dsr_bench.models.image_config:ImageModelConfig", network="dsr_bench.models.image_nets:ImageNet",
              files="2D-track", tracks={"full": f"{_TRACKS}:IMAGE_FULL", "cpu": f"{_TRACKS}:IMAGE_CPU"}),
)})


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

    @property
    def model_kind(self) -> ModelKind:
        """Its kind's object (`KINDS`): config class, network, loader and training recipes."""
        return KINDS[self.kind]

    def make_predictor(self):
        """A reference model's predictor (its class imported on use)."""
        return resolve(self.predictor)()


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


def trainable() -> tuple[str, ...]:
    """The kinds `dsr-bench train` trains (those with tracks), in the table's order."""
    return tuple(name for name, kind in KINDS.items() if kind.trainable)


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
