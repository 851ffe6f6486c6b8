"""Model configuration: the variant switches and the choices where paper and official code differ."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from dsr_bench.constants import GRID_SHAPE, NUM_MASK_SLOTS

MODEL_NAMES = ("dsr", "single", "nowarp", "gtwarp", "3dflow")


@dataclass(frozen=True)
class ModelConfig:
    """Everything that defines a model; saved in every checkpoint.

    history: "warp" (DSR-Net), "none" (SingleStep, 3DFlow), "nowarp", "gtwarp".
    motion: "se3" (mask-blended rigid motions) or "flow" (3DFlow's per-voxel decoder).
    leaky_slope: official code 0.01 (the paper says 0.2). mlp_layers: linear layers of the SE(3)
    MLP (paper: five with 512 hidden units). euler: "official" builds R = Rz Ry Rx from passive
    elementary rotations (R_x(theta) is the usual R_x(-theta)); "standard" uses active ones.
    """

    name: str = "dsr"
    grid: tuple[int, int, int] = GRID_SHAPE
    num_slots: int = NUM_MASK_SLOTS  # K, background last
    state_channels: int = 8
    history: str = "warp"
    motion: str = "se3"
    leaky_slope: float = 0.01
    mlp_layers: int = 5
    mlp_hidden: int = 512
    euler: str = "official"
    warp_eps: float = 1e-3
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.history not in ("warp", "none", "nowarp", "gtwarp"):
            raise ValueError(f"history {self.history!r}")
        if self.motion not in ("se3", "flow"):
            raise ValueError(f"motion {self.motion!r}")
        if self.euler not in ("official", "standard"):
            raise ValueError(f"euler {self.euler!r}")
        if any(g % 16 for g in self.grid):
            raise ValueError(f"grid {self.grid}: every side must be a multiple of 16 (four 2x downsamplings)")

    @classmethod
    def for_model(cls, name: str, **overrides) -> ModelConfig:
        """The configuration of a named reference model."""
        variants = {"dsr": {"history": "warp"}, "single": {"history": "none"}, "nowarp": {"history": "nowarp"},
                    "gtwarp": {"history": "gtwarp"}, "3dflow": {"history": "none", "motion": "flow"}}
        if name not in variants:
            raise ValueError(f"unknown model {name!r}; choose from {', '.join(MODEL_NAMES)}")
        return cls(name=name, **{**variants[name], **overrides})

    def as_dict(self) -> dict:
        out = asdict(self)
        out["grid"] = list(self.grid)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> ModelConfig:
        data = dict(data)
        data["grid"] = tuple(data["grid"])
        return cls(**data)
