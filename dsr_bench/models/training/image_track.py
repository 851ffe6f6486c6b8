"""Training the 2D track's models (2DFlow, SE3-Net, SE3Pose-Net) on the front camera's images.

The split's sequences are reduced once to the network's resolution (`image_split`, cached like the CPU
track's pooled volumes) and single steps are drawn at random (any sequence, any push, with replacement,
from the recipe's seed): `batches` batches of `batch_size` through the one loop (`loop.fit` over `image_step`:
Adam (betas 0.9, 0.95) at `lr`, halved at 50% and again at 75% of the batches, the CPU track's step decay).
The models are single-step, as in their papers.

The loss (`flow_loss`, cm^2): the squared error of the predicted flow summed over its components,
averaged over the pixels that see an object (what the benchmark scores), plus the same average over
the pixels that see the table (whose flow is 0), so that the background stays still; no mask
supervision (the SE3 models learn their masks from the flow alone, as in Byravan and Fox 2017).
SE3Pose-Net adds its pose-consistency term (Byravan et al. 2018): the poses its encoder finds in the next
image against the poses its transition predicted (translations in cm^2, rotations as the squared
Frobenius norm of their difference), weighted by `ImageModelConfig.pose_consistency`.

The result is a weights file (`checkpoints`: role "weights", fp16, the recipe, the first and last tenth's
losses and the data it saw), read by `dsr-bench predict --checkpoint`.
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
from dsr_bench.models.image_config import IMAGE_MODEL_NAMES, ImageModelConfig
from dsr_bench.models.training.checkpoints import data_provenance, save_weights, torch_device
from dsr_bench.models.training.split_cache import cached_split

M2_TO_CM2 = 1e4


@dataclass(frozen=True)
class ImageRecipe:
    """Everything that defines a 2D-track training run (saved in its weights file)."""

    model_name: str
    batches: int = 2000
    batch_size: int = 8
    lr: float = 1e-3
    image_factor: int = 2
    width: int = 16
    seed: int = 0

    def __post_init__(self):
        if self.model_name not in IMAGE_MODEL_NAMES:
            raise UserError(f"--model {self.model_name!r}: the 2D track's models are {', '.join(IMAGE_MODEL_NAMES)}")
        if self.batches < 1 or self.batch_size < 2:
            raise UserError(f"--single-batches {self.batches} must be >= 1 and --batch-size {self.batch_size} >= 2 "
                            "(BatchNorm needs two samples)")
        if self.lr <= 0:
            raise UserError(f"--lr {self.lr}: must be positive")

    def model_config(self) -> ImageModelConfig:
        return ImageModelConfig(name=self.model_name, image_factor=self.image_factor, width=self.width)


def image_split(data_dir: Path, split: str | None, factor: int, workers: int = 1,
                progress: Callable[[int, int], None] | None = None) -> dict[str, np.ndarray]:
    """A split's sequences at the network's resolution, stacked (`image_data.reduce_sequence`): points
    (N, T+1, h, w, 3), flow (N, T, h, w, 3), mask (N, T, h, w), action (N, T, 3), names (N,)."""
    from dsr_bench.models.image_data import reduce_sequence

    return cached_split(data_dir, split, f"image-f{factor}", [factor, "points-flow-mask-action"],
                        partial(reduce_sequence, factor=factor), workers, progress)


def draw_steps(data: dict[str, np.ndarray], batches: int, batch_size: int, seed: int) -> Iterator[dict]:
    """`batches` batches of single steps, each a random sequence and push: points, valid, next_points,
    next_valid (B, 3|1, h, w), flow (B, 3, h, w) metres (x, y, z), mask (B, h, w) int64, action (B, 3) int64."""
    rng = np.random.default_rng(seed)
    count, steps = data["action"].shape[:2]
    for _ in range(batches):
        seqs, ts = rng.integers(count, size=batch_size), rng.integers(steps, size=batch_size)
        yield step_batch(data, seqs, ts)


def step_batch(data: dict[str, np.ndarray], seqs: np.ndarray, ts: np.ndarray) -> dict:
    """One batch of single steps (`draw_steps`' layout): step b is push `ts[b]` of sequence `seqs[b]` of a reduced
    split (`image_split`)."""
    from dsr_bench.models.image_data import point_tensors

    points, valid = point_tensors(data["points"][seqs, ts])
    next_points, next_valid = point_tensors(data["points"][seqs, ts + 1])
    return {"points": points, "valid": valid, "next_points": next_points, "next_valid": next_valid,
            "flow": torch.from_numpy(data["flow"][seqs, ts].astype(np.float32)).movedim(-1, 1),
            "mask": torch.from_numpy(data["mask"][seqs, ts].astype(np.int64)),
            "action": torch.from_numpy(data["action"][seqs, ts].astype(np.int64))}


def flow_loss(flow: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """cm^2: the mean over object pixels (mask > 0) of the squared error summed over components, plus the
    mean over the other pixels with a point. flow, target (B, 3, h, w) metres; mask (B, h, w); valid (B, 1, h, w)."""
    error = ((flow - target) ** 2).sum(1) * M2_TO_CM2
    objects = (mask > 0).float()
    table = valid[:, 0] * (1 - objects)
    return (error * objects).sum() / objects.sum().clamp(min=1) + (error * table).sum() / table.sum().clamp(min=1)


def pose_consistency(net, batch: dict, out: dict) -> torch.Tensor:
    """SE3Pose-Net: the encoder's poses of the next image against the transition's predicted poses (cm^2 of
    translation + squared Frobenius norm of the rotations' difference), averaged over objects."""
    _, _, found = net.poses(batch["next_points"], batch["next_valid"])
    predicted = out["next_poses"]
    translation = ((found[..., :3, 3] - predicted[..., :3, 3]) ** 2).sum(-1) * M2_TO_CM2
    rotation = ((found[..., :3, :3] - predicted[..., :3, :3]) ** 2).sum((-1, -2))
    return (translation + rotation).mean()


def training_loss(net, batch: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The loss of one batch and its terms (detached 0-dim tensors: nothing is read to the host here)."""
    from dsr_bench.models.image_nets import flow_at

    out = net(batch["points"], batch["valid"], batch["action"])
    flow = flow_at(out, batch["points"], batch["valid"])
    loss = flow_loss(flow, batch["flow"], batch["mask"], batch["valid"])
    terms = {"flow": loss.detach()}
    if "next_poses" in out and net.config.pose_consistency:
        consistency = pose_consistency(net, batch, out)
        terms["consistency"] = consistency.detach()
        loss = loss + net.config.pose_consistency * consistency
    terms["total"] = loss.detach()
    return loss, terms


def image_step(net, batch: dict, optimizer, device) -> list[dict]:
    """The 2D track's training step (a single time step): forward, loss, backward, optimiser step, then the
    terms read once (floats); a non-finite loss is a FloatingPointError."""
    loss, terms = training_loss(net, {k: v.to(device, non_blocking=True) for k, v in batch.items()})
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    row = dict(zip(terms, torch.stack(list(terms.values())).tolist()))  # the one read
    if not math.isfinite(row["total"]):
        raise FloatingPointError(f"loss is {row['total']}; lower the learning rate (--lr)")
    return [row]


def train_image_model(recipe: ImageRecipe, data_dir: Path, split: str | None, out: Path, device: str = "cpu",
                      workers: int = 1, report: Callable[[str], None] = print) -> Path:
    """Train one 2D-track model by `recipe` on DATA_DIR's split and write its weights file to `out`."""
    from dsr_bench.models.image_nets import ImageNet
    from dsr_bench.models.training.loop import fit

    dev = torch_device(device)
    config = recipe.model_config()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    data = image_split(data_dir, split, recipe.image_factor, workers,
                       lambda i, n: report(f"reducing {i}/{n}") if i % 50 == 0 or i == n else None)
    torch.manual_seed(recipe.seed)
    net = ImageNet(config).to(dev)
    steps = draw_steps(data, recipe.batches, recipe.batch_size, recipe.seed)
    summary = fit(partial(image_step, device=dev), net, steps, recipe.batches, recipe.lr, config.name, report)
    net.eval()
    return save_weights(out, config, net.cpu().state_dict(), "weights", fp16=True,
                        data=data_provenance(data_dir, split, data["action"].shape[0]),
                        recipe=dataclasses.asdict(recipe), training=summary)
