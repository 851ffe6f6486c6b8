"""Configuration of the 2D track's models: 2DFlow, SE3-Net and SE3Pose-Net (`models.image_nets`).

They see the front camera's point-cloud image (world points, metres) and the push, mapped to the
image plane (`models.image_data.action_pixels`), and predict the 3D displacement of the surface
point seen at every pixel: the `motion_2d` of the predictions contract, in metres (dy, dx, dz).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from dsr_bench.constants import IMAGE_SHAPE, NUM_MASK_SLOTS
from dsr_bench.models import registry
from dsr_bench.models.config import check_known_keys

#: The 2D track's models: the image entries of `dsr_bench.models.registry`.
IMAGE_MODEL_NAMES = registry.names(registry.IMAGE)
#: What each model is, in one line (predictions' meta.json, the leaderboard).
IMAGE_MODEL_DESCRIPTIONS = {name: registry.MODELS[name].description for name in IMAGE_MODEL_NAMES}


@dataclass(frozen=True)
class ImageModelConfig:
    """Everything that defines a 2D-track model; saved in its weights file.

    name: 2dflow | se3net | se3posenet. image_factor: the network sees every `image_factor`-th pixel
    of the 240 x 320 images along each axis (1: the whole image; the CPU track's 2: 120 x 160); its
    flow (2dflow) or masks (SE3 models) are brought back to 240 x 320 bilinearly, and the SE3 models'
    rigid motions are applied to the full-resolution points. num_slots: K masks, background last (does
    not move). width: channels of the first level (each of the 3 downsamplings doubles them).
    pose_consistency: SE3Pose-Net's weight of the pose-consistency loss (the encoder's poses of the next
    image against the transition's predicted poses)."""

    name: str = "se3net"
    image_factor: int = 2
    num_slots: int = NUM_MASK_SLOTS
    width: int = 16
    hidden: int = 256
    pose_consistency: float = 0.1

    def __post_init__(self):
        if self.name not in registry.names(registry.IMAGE):
            raise ValueError(f"image model {self.name!r}: choose one of {', '.join(registry.names(registry.IMAGE))}")
        if self.image_factor not in (1, 2):
            raise ValueError(f"image_factor {self.image_factor}: 1 (240 x 320) or 2 (120 x 160)")
        if self.num_slots < 2 or self.width < 2 or self.hidden < 8 or self.pose_consistency < 0:
            raise ValueError("num_slots must be >= 2, width >= 2, hidden >= 8, pose_consistency >= 0")

    @property
    def image_shape(self) -> tuple[int, int]:
        """(height, width) of the network's input."""
        return IMAGE_SHAPE[0] // self.image_factor, IMAGE_SHAPE[1] // self.image_factor

    @classmethod
    def for_model(cls, name: str, **overrides) -> ImageModelConfig:
        """The configuration of a named 2D-track model (its registry entry; overrides: any other field)."""
        return cls(name=name, **overrides)

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> ImageModelConfig:
        """Inverse of as_dict; unknown keys are an error."""
        check_known_keys(cls, data, "image model config")
        return cls(**data)
