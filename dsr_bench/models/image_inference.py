"""Running a 2D-track model over sequences: the predictor behind `dsr-bench predict --model 2dflow|se3net|
se3posenet`. Its predictions are 2D-only: `motion_2d` (T, 240, 320, 3) metres (dy, dx, dz), no volumes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dsr_bench.dataset.sequence import SequenceReader
from dsr_bench.errors import UserError
from dsr_bench.models import registry
from dsr_bench.models.training.checkpoints import mark_finetuned, read_weights, torch_device


class ImagePredictor:
    """A trained 2D-track network run on each push of a sequence (single-step: prediction t sees
    observation t and action t). BatchNorm in eval mode (running statistics)."""

    #: where the weights came from (source, file, sha256), set by the loader
    weights: dict[str, str]

    def __init__(self, net, device: torch.device):
        self.net, self.device = net.to(device).eval(), device
        config = net.config
        self.name = config.name if config.image_factor == 1 else f"{config.name}-cpu"
        self.num_slots = None if config.name == "2dflow" else config.num_slots - 1  # 2DFlow has no masks
        height, width = config.image_shape
        factor = "" if config.image_factor == 1 else f" (CPU track: {height} x {width} input)"
        self.description = registry.MODELS[config.name].description + factor
        #: the image the network sees (height, width), recorded in the predictions' meta.json
        self.image = config.image_shape

    @torch.no_grad()
    def predict_points(self, points: np.ndarray, actions: np.ndarray, camera) -> np.ndarray:
        """motion_2d (T, H, W, 3) float32 metres (dy, dx, dz) from the front camera's points (T, H, W, 3) world
        metres (NaN: no return), actions (T, 3) [d, row, col] and that camera (`geometry.Camera`)."""
        from dsr_bench.models.image_data import action_pixels, point_tensors
        from dsr_bench.models.image_nets import flow_at

        factor = self.net.config.image_factor
        full, full_valid = point_tensors(points)
        small, small_valid = point_tensors(np.asarray(points)[:, ::factor, ::factor])
        if tuple(small.shape[-2:]) != self.image:
            raise UserError(f"images of {points.shape[1]} x {points.shape[2]} do not fit a model of "
                            f"{self.image[0] * factor} x {self.image[1] * factor} images")
        action = torch.from_numpy(action_pixels(actions, camera, self.image))
        out = self.net(small.to(self.device), small_valid.to(self.device), action.to(self.device))
        flow = flow_at(out, full.to(self.device), full_valid.to(self.device))  # (T, 3, H, W) world (x, y, z)
        return flow.movedim(1, -1)[..., [1, 0, 2]].float().cpu().numpy()

    def predict_sequence(self, seq: SequenceReader) -> dict[str, np.ndarray]:
        """{"motion_2d": (T, 240, 320, 3) float32} for one sequence."""
        from dsr_bench.models.data import check_actions
        from dsr_bench.constants import GRID_SHAPE

        if "cameras/front/points" not in seq:
            raise UserError(f"{seq.path}: no cameras/front/points; the 2D track's models need the front camera's "
                            "images (generate the sequences without --no-images)")
        steps = seq.num_steps
        actions = check_actions(np.asarray(seq.read("action"))[:steps], GRID_SHAPE[:2], seq.path)
        points = seq.read("cameras/front/points", slice(0, steps))
        camera = seq.camera("front")
        chunks = [self.predict_points(points[s: s + 5], actions[s: s + 5], camera) for s in range(0, steps, 5)]
        return {"motion_2d": np.concatenate(chunks)}


def load_image(entry: registry.ModelEntry, *, checkpoint: Path | None = None, device: str = "cpu",
               **options) -> ImagePredictor:
    """The image kind's loader (`registry.KINDS`, called by `predictors.load_predictor`): a 2D-track model from a
    `dsr-bench train --model 2dflow|se3net|se3posenet` weights file (any version of the one weights format,
    `training.checkpoints`), by default the shipped CPU-track weights."""
    from dsr_bench.models.predictors import weights_file

    path, source = weights_file(entry, checkpoint)
    dev = torch_device(device)
    read = read_weights(path, dev, kind=registry.IMAGE, model=entry.name)
    predictor = ImagePredictor(read.network(dev), dev)
    predictor.weights = source
    mark_finetuned(predictor, read)  # NAME-ft: fine-tuned on a real split (`training.finetune`)
    return predictor
