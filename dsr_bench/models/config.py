"""Model configuration: the variant switches and the choices where paper and official code differ."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from dsr_bench.constants import GRID_SHAPE, NUM_MASK_SLOTS
from dsr_bench.models import registry

#: The 3D track's learned models: the voxel entries of `dsr_bench.models.registry`, each a set of the switches below.
MODEL_NAMES = registry.names(registry.VOXEL)


def check_known_keys(cls, data: dict, what: str) -> None:
    """ValueError naming the keys of `data` that are not fields of the dataclass `cls` (a file from another toolkit)."""
    unknown = sorted(set(data) - {f.name for f in fields(cls)})
    if unknown:
        raise ValueError(f"unknown {what} keys {unknown}")


@dataclass(frozen=True)
class ModelConfig:
    """Everything that defines a model; saved in every checkpoint (defaults: the official code).

    grid: volume size (D0, D1, D2) = (world y, world x, z) voxels, every side a multiple of 16.
    history: "warp" (DSR-Net), "none" (SingleStep, 3DFlow), "nowarp", "gtwarp" (oracle).
    motion: "se3" (mask-blended rigid motions) or "flow" (3DFlow's per-voxel conv decoder).
    leaky_slope: official 0.01 (the paper says 0.2). mlp_layers / mlp_hidden: linear layers of the
    SE(3) MLP (official: 4 hidden layers of 512 + the output layer = 5). euler: "official" builds
    R = Rz Ry Rx from passive elementary rotations (R_x(a) is the usual R_x(-a)); "standard" uses
    active ones. gtwarp_weight: splat weights of GTWarp, "predicted" foreground probability
    (official) or the ground-truth "gt" foreground. init: "official" (Kaiming-normal convs, Xavier
    MLP) or "zero-motion" (the same, with the last MLP layer zeroed: identity motions at the start).
    width: the official channel counts divided by this (1: official; the CPU track's models use 2).
    voxel_factor: benchmark voxels per model voxel along each axis: 1 (the model works on the
    benchmark's 128 x 128 x 48 grid) or the CPU track's 4 (16 mm voxels, `models.coarse`: the model
    sees the volumes pooled to `coarse.coarse_grid(4)` = 32 x 32 x 16, its motions are in its own
    voxels, and its predictions are brought back to the benchmark's grid; the motion loss is taken
    in benchmark voxels, so it weighs against the mask term as at full size).
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
    gtwarp_weight: str = "predicted"
    init: str = "official"
    width: int = 1
    voxel_factor: int = 1

    def __post_init__(self):
        choices = {"history": ("warp", "none", "nowarp", "gtwarp"), "motion": ("se3", "flow"),
                   "euler": ("official", "standard"), "gtwarp_weight": ("predicted", "gt"),
                   "init": ("official", "zero-motion")}
        for key, allowed in choices.items():
            if getattr(self, key) not in allowed:
                raise ValueError(f"{key} {getattr(self, key)!r}: choose one of {', '.join(allowed)}")
        if len(self.grid) != 3 or any(int(g) <= 0 or int(g) % 16 for g in self.grid):
            raise ValueError(f"grid {tuple(self.grid)}: every side must be a positive multiple of 16 "
                             "(four 2x downsamplings)")
        if self.width not in (1, 2, 4):
            raise ValueError(f"width {self.width}: 1 (official), 2 or 4")
        if self.voxel_factor != 1:
            from dsr_bench.models.coarse import coarse_grid

            if tuple(self.grid) != coarse_grid(self.voxel_factor):
                raise ValueError(f"voxel_factor {self.voxel_factor} needs the grid {coarse_grid(self.voxel_factor)}, "
                                 f"not {tuple(self.grid)}")
        if self.num_slots < 2 or self.mlp_layers < 1 or self.state_channels < 1:
            raise ValueError("num_slots must be >= 2, mlp_layers and state_channels >= 1")

    @classmethod
    def for_model(cls, name: str, **overrides) -> ModelConfig:
        """The configuration of a named reference model (its registry entry's switches; overrides: any other field)."""
        entry = registry.MODELS.get(name)
        if entry is None or entry.kind != registry.VOXEL:
            raise ValueError(f"unknown model {name!r}; choose from {', '.join(MODEL_NAMES)}")
        if "grid" in overrides:
            overrides["grid"] = tuple(int(g) for g in overrides["grid"])
        return cls(name=name, **{**entry.variant, **overrides})

    def as_dict(self) -> dict:
        """Plain types only (JSON and torch.load(weights_only=True) safe)."""
        out = asdict(self)
        out["grid"] = list(self.grid)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> ModelConfig:
        """Inverse of as_dict; unknown keys are an error (a checkpoint from another toolkit)."""
        check_known_keys(cls, data, "model config")
        data = dict(data)
        data["grid"] = tuple(int(g) for g in data["grid"])
        return cls(**data)
