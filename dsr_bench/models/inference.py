"""Running a trained model over sequences: the predictor behind `dsr-bench predict --model dsr|...`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from dsr_bench.dataset.sequence import SequenceReader
from dsr_bench.errors import UserError
from dsr_bench.models.config import ModelConfig
from dsr_bench.models.dsr_net import DSRNet
from dsr_bench.models.labels import slot_labels
from dsr_bench.models.training.checkpoints import load_checkpoint, load_weights, torch_device

_DESCRIPTIONS = {
    "dsr": "DSR-Net: history forward-warped by the predicted motion",
    "single": "SingleStep: DSR-Net without history",
    "nowarp": "NoWarp: DSR-Net with the history not warped",
    "gtwarp": "GTWarp (oracle): history warped with the ground-truth flow",
    "3dflow": "3DFlow: per-voxel flow from a 3D conv decoder, no history",
}


class ModelPredictor:
    """A trained network run over a sequence's steps with its state carried as in training.

    Prediction t sees observations 0..t and action t. mask: `slot_labels` of the K softmax
    channels (background, the last, -> 0; object slot k -> k + 1); motion: fp32 voxels (dy, dx, dz)."""

    def __init__(self, model: DSRNet, device: torch.device, official_bn: bool = False, bf16: bool = False):
        self.model, self.device, self.bf16 = model, device, bf16
        self.name = model.config.name
        self.num_slots = model.config.num_slots - 1
        self.description = _DESCRIPTIONS.get(self.name, self.name)
        model.train(official_bn)  # BatchNorm in eval mode unless reproducing the official code

    def predict_sequence(self, seq: SequenceReader) -> dict[str, np.ndarray]:
        """{"mask": (T, Y, X, Z) uint8, "motion": (T, 3, Y, X, Z) float32} for one sequence (read step by step)."""
        steps = seq.num_steps
        tsdf_shape = tuple(seq.dataset("tsdf").shape)

        def ground_truth(t: int) -> tuple[np.ndarray, np.ndarray]:
            return seq.read("scene_flow_3d", t), seq.read("mask_3d", t)

        return self._predict(steps, tsdf_shape, lambda t: seq.read("tsdf", t),
                             lambda: np.asarray(seq.read("action"))[:steps], ground_truth, seq.path)

    def predict_arrays(self, tsdf: np.ndarray, actions: np.ndarray, flow: np.ndarray | None = None,
                       mask: np.ndarray | None = None, source: str = "arrays") -> dict[str, np.ndarray]:
        """The same for a sequence held in memory: tsdf (T, Y, X, Z), actions (T, 3); the ground-truth
        flow (T, 3, Y, X, Z) and mask (T, Y, X, Z) are read only by the gtwarp oracle."""
        steps = len(actions)
        tsdf_shape = tuple(np.shape(tsdf))

        def ground_truth(t: int) -> tuple[np.ndarray, np.ndarray]:
            return flow[t], mask[t]

        return self._predict(steps, tsdf_shape, lambda t: tsdf[t], lambda: np.asarray(actions), ground_truth, source)

    @torch.no_grad()
    def _predict(self, steps: int, tsdf_shape: tuple, tsdf_at: Callable[[int], np.ndarray],
                 read_actions: Callable[[], np.ndarray], ground_truth: Callable[[int], tuple[np.ndarray, np.ndarray]],
                 source) -> dict[str, np.ndarray]:
        """The steps in order: tsdf_at(t) and ground_truth(t) (flow, mask) read one step at a time."""
        from dsr_bench.models.data import action_map, check_actions

        config = self.model.config
        grid = tuple(config.grid)
        if tsdf_shape[1:] != grid or tsdf_shape[0] < steps:
            raise UserError(f"{source}: tsdf {tsdf_shape} does not fit the model's grid {grid}")
        actions = read_actions()
        if len(actions) != steps:
            raise UserError(f"{source}: {len(actions)} actions for {steps} pushes; "
                            "check it with `dsr-bench validate`")
        maps = action_map(check_actions(actions, grid[:2], source), grid[:2])
        masks = np.zeros((steps,) + grid, dtype=np.uint8)
        motions = np.zeros((steps, 3) + grid, dtype=np.float32)
        state = self.model.initial_state(1, self.device)
        for t in range(steps):
            tsdf = torch.from_numpy(np.asarray(tsdf_at(t), dtype=np.float32)).unsqueeze(0).to(self.device)
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.bf16):
                out = self.model(tsdf, maps[t: t + 1].to(self.device), state)
            masks[t] = slot_labels(out["mask"])[0].cpu().numpy()
            motions[t] = out["motion"][0].float().cpu().numpy()
            gt_flow = gt_mask = None
            if config.history == "gtwarp" and t + 1 < steps:
                flow, mask = ground_truth(t)
                gt_flow = torch.from_numpy(np.asarray(flow, np.float32)).unsqueeze(0).to(self.device)
                gt_mask = torch.from_numpy(np.asarray(mask, np.int64)).unsqueeze(0).to(self.device)
            if t + 1 < steps:
                state = self.model.next_state(out, gt_flow, gt_mask)
        return {"mask": masks, "motion": motions}


def load_predictor(model: str, checkpoint: Path, device: str = "cpu", official_bn: bool = False,
                   bf16: bool = False) -> ModelPredictor:
    """A predictor from a `dsr-bench train` checkpoint (loaded with weights_only=True)."""
    dev = torch_device(device)
    state = load_checkpoint(Path(checkpoint), map_location=dev)
    config = ModelConfig.from_dict(state["model_config"])
    if config.name != model:
        raise UserError(f"{checkpoint} holds a {config.name!r} model, not {model!r}; pass --model {config.name}")
    net = DSRNet(config).to(dev)
    load_weights(net, state, checkpoint, model=f"the {model!r} model")
    return ModelPredictor(net, dev, official_bn, bf16)


def load_official_predictor(model: str, weights: Path, device: str = "cpu", official_bn: bool = True,
                            bf16: bool = False) -> ModelPredictor:
    """A predictor from the authors' released weights (dsr.pth, dsr_ft.pth, single.pth, nowarp.pth,
    gtwarp.pth, 3dflow.pth; `dsr_bench.models.official_weights`) on the official 128 x 128 x 48 grid.
    official_bn=True (the default here): BatchNorm with batch statistics, as the authors trained and ran
    them. The predictor's `weights` records the file (source, name, sha256, BatchNorm mode)."""
    from dsr_bench.dataset.manifest import file_sha256
    from dsr_bench.models.official_weights import check_release_name, convert_official_state, read_official_file

    dev = torch_device(device)
    weights = Path(weights)
    state = convert_official_state(read_official_file(weights), model, source=str(weights))
    check_release_name(weights, model)
    net = DSRNet(ModelConfig.for_model(model))
    net.load_state_dict(state)  # strict: the converter returns exactly our keys, shapes checked
    predictor = ModelPredictor(net.to(dev), dev, official_bn, bf16)
    predictor.weights = {"source": "official", "file": weights.name, "sha256": file_sha256(weights),
                         "batchnorm": "batch statistics (official)" if official_bn else "running statistics (eval)"}
    return predictor
