"""Running a trained model over sequences: the predictor behind `dsr-bench predict --model dsr|...`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dsr_bench.errors import UserError
from dsr_bench.models.config import ModelConfig
from dsr_bench.models.dsr_net import DSRNet
from dsr_bench.dataset.sequence import SequenceReader

_DESCRIPTIONS = {
    "dsr": "DSR-Net: history forward-warped by the predicted motion",
    "single": "SingleStep: DSR-Net without history",
    "nowarp": "NoWarp: DSR-Net with the history not warped",
    "gtwarp": "GTWarp (oracle): history warped with the ground-truth flow",
    "3dflow": "3DFlow: per-voxel flow from a 3D conv decoder, no history",
}


class ModelPredictor:
    """A trained network run over a sequence's steps with its state carried as in training.

    Prediction t sees observations 0..t and action t. mask: argmax of the K softmax channels,
    background (last) -> 0, object slot k -> k + 1; motion: fp32 voxels (dy, dx, dz)."""

    def __init__(self, model: DSRNet, device: torch.device, official_bn: bool = False, bf16: bool = False):
        self.model, self.device, self.bf16 = model, device, bf16
        self.name = model.config.name
        self.num_slots = model.config.num_slots - 1
        self.description = _DESCRIPTIONS.get(self.name, self.name)
        model.train(official_bn)  # BatchNorm in eval mode unless reproducing the official code

    @torch.no_grad()
    def predict_sequence(self, seq: SequenceReader) -> dict[str, np.ndarray]:
        """{"mask": (T, Y, X, Z) uint8, "motion": (T, 3, Y, X, Z) float32} for one sequence."""
        from dsr_bench.models.data import action_map, check_actions

        config = self.model.config
        grid = tuple(config.grid)
        steps = seq.num_steps
        tsdf_shape = tuple(seq.dataset("tsdf").shape)
        if tsdf_shape[1:] != grid or tsdf_shape[0] < steps:
            raise UserError(f"{seq.path}: tsdf {tsdf_shape} does not fit the model's grid {grid}")
        actions = np.asarray(seq.read("action"))[:steps]
        if len(actions) != steps:
            raise UserError(f"{seq.path}: {len(actions)} actions for {steps} pushes; "
                            "check it with `dsr-bench validate`")
        maps = action_map(check_actions(actions, grid[:2], seq.path), grid[:2])
        masks = np.zeros((steps,) + grid, dtype=np.uint8)
        motions = np.zeros((steps, 3) + grid, dtype=np.float32)
        state = self.model.initial_state(1, self.device)
        k = config.num_slots
        for t in range(steps):
            tsdf = torch.from_numpy(np.asarray(seq.read("tsdf", t), dtype=np.float32)).unsqueeze(0).to(self.device)
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.bf16):
                out = self.model(tsdf, maps[t: t + 1].to(self.device), state)
            labels = out["mask"].argmax(1)[0]
            masks[t] = torch.where(labels == k - 1, 0, labels + 1).to(torch.uint8).cpu().numpy()
            motions[t] = out["motion"][0].float().cpu().numpy()
            gt_flow = gt_mask = None
            if config.history == "gtwarp" and t + 1 < steps:
                gt_flow = torch.from_numpy(np.asarray(seq.read("scene_flow_3d", t), np.float32)).unsqueeze(0)
                gt_mask = torch.from_numpy(np.asarray(seq.read("mask_3d", t), np.int64)).unsqueeze(0)
                gt_flow, gt_mask = gt_flow.to(self.device), gt_mask.to(self.device)
            if t + 1 < steps:
                state = self.model.next_state(out, gt_flow, gt_mask)
        return {"mask": masks, "motion": motions}


def load_predictor(model: str, checkpoint: Path, device: str = "cpu", official_bn: bool = False,
                   bf16: bool = False) -> ModelPredictor:
    """A predictor from a `dsr-bench train` checkpoint (loaded with weights_only=True)."""
    from dsr_bench.models.training.trainer import load_checkpoint

    try:
        dev = torch.device(device)
    except RuntimeError:
        raise UserError(f"--device {device!r}: use cpu, cuda or cuda:N") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError("--device cuda but no CUDA device is available; use --device cpu")
    state = load_checkpoint(Path(checkpoint), map_location=dev)
    config = ModelConfig.from_dict(state["model_config"])
    if config.name != model:
        raise UserError(f"{checkpoint} holds a {config.name!r} model, not {model!r}; pass --model {config.name}")
    net = DSRNet(config).to(dev)
    try:
        net.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise UserError(f"{checkpoint}: weights do not fit the {model!r} model ({str(exc).splitlines()[0][:160]})"
                        ) from None
    return ModelPredictor(net, dev, official_bn, bf16)
