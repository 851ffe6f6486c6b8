"""Running a trained model over sequences: the predictor behind `dsr-bench predict --model dsr|...`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dsr_bench.errors import UserError
from dsr_bench.models.config import ModelConfig
from dsr_bench.models.dsr_net import DSRNet
from dsr_bench.sequence import SequenceReader


class ModelPredictor:
    """A trained network carried across a sequence's steps (state warped as in training)."""

    def __init__(self, model: DSRNet, device: torch.device, official_bn: bool = False):
        self.model, self.device = model, device
        self.name = model.config.name
        self.num_slots = model.config.num_slots - 1
        model.train(official_bn)  # BatchNorm in eval mode unless reproducing the official code

    @torch.no_grad()
    def predict_sequence(self, seq: SequenceReader) -> dict[str, np.ndarray]:
        from dsr_bench.torch_data import action_map

        steps = seq.num_steps
        grid = tuple(self.model.config.grid)
        masks = np.zeros((steps,) + grid, dtype=np.uint8)
        motions = np.zeros((steps, 3) + grid, dtype=np.float16)
        state = self.model.initial_state(1, self.device)
        actions = action_map(seq.read("action"), grid[:2])
        for t in range(steps):
            tsdf = torch.from_numpy(seq.read("tsdf", t)).unsqueeze(0).to(self.device)
            out = self.model(tsdf, actions[t: t + 1].to(self.device), state)
            labels = out["mask"].argmax(1)[0]
            k = out["mask"].shape[1]
            masks[t] = torch.where(labels == k - 1, 0, labels + 1).to(torch.uint8).cpu().numpy()
            motions[t] = out["motion"][0].cpu().numpy().astype(np.float16)
            gt_flow = gt_mask = None
            if self.model.config.history == "gtwarp":
                gt_flow = torch.from_numpy(seq.read("scene_flow_3d", t)).unsqueeze(0).to(self.device)
                gt_mask = torch.from_numpy(seq.read("mask_3d", t)).unsqueeze(0).to(self.device)
            state = self.model.next_state(out, gt_flow, gt_mask)
        return {"mask": masks, "motion": motions}


def load_predictor(model: str, checkpoint: Path, device: str = "cpu", official_bn: bool = False) -> ModelPredictor:
    """A predictor from a training checkpoint (loaded with weights_only=True)."""
    from dsr_bench.train import load_checkpoint

    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError("--device cuda but no CUDA device is available; use --device cpu")
    state = load_checkpoint(checkpoint, map_location=dev)
    config = ModelConfig.from_dict(state["model_config"])
    if config.name != model:
        raise UserError(f"{checkpoint} holds a {config.name!r} model, not {model!r}; pass --model {config.name}")
    net = DSRNet(config).to(dev)
    net.load_state_dict(state["model"])
    return ModelPredictor(net, dev, official_bn)
