"""Running a trained model over sequences: the predictor behind `dsr-bench predict --model dsr|...`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import cast

import numpy as np
import torch

from dsr_bench.dataset.sequence import SequenceReader
from dsr_bench.constants import GRID_SHAPE
from dsr_bench.errors import UserError
from dsr_bench.models import registry
from dsr_bench.models.config import ModelConfig
from dsr_bench.models.dsr_net import DSRNet, batchnorm_statistics
from dsr_bench.models.labels import slot_labels
from dsr_bench.models.training.checkpoints import read_weights, torch_device

#: What each model is, in one line (predictions' meta.json, the leaderboard): `dsr_bench.models.registry`.
_DESCRIPTIONS = {name: entry.description for name, entry in registry.MODELS.items()}


class ModelPredictor:
    """A trained network run over a sequence's steps with its state carried as in training.

    Prediction t sees observations 0..t and action t. mask: `slot_labels` of the K softmax
    channels (background, the last, -> 0; object slot k -> k + 1); motion: fp32 voxels (dy, dx, dz).

    BatchNorm normalises with its running statistics (eval mode), or with `official_bn` with each
    step's own statistics (batch 1: the sample's), as the official code evaluates; either way the
    model's running statistics are left as they are (`dsr_net.batchnorm_statistics`)."""

    #: where the weights came from (source, file, sha256, BatchNorm mode), set by the loaders
    weights: dict[str, str]

    def __init__(self, model: DSRNet, device: torch.device, official_bn: bool = False, bf16: bool = False):
        self.model, self.device, self.bf16, self.official_bn = model, device, bf16, official_bn
        config = model.config
        self.name = config.name if config.voxel_factor == 1 else f"{config.name}-cpu"
        self.num_slots = config.num_slots - 1
        self.description = _DESCRIPTIONS.get(config.name, config.name) + (
            "" if config.voxel_factor == 1 else f" (CPU track: a {'x'.join(map(str, config.grid))} grid)")
        #: the grid the network works on (y, x, z), recorded in the predictions' meta.json
        self.grid = tuple(config.grid)
        model.eval()  # the statistics BatchNorm uses are chosen for each sequence (_predict)

    def predict_sequence(self, seq: SequenceReader) -> dict[str, np.ndarray]:
        """{"mask": (T, Y, X, Z) uint8, "motion": (T, 3, Y, X, Z) float32} for one sequence (read step by step),
        and "motion_2d" (T, H, W, 3) float32 metres (dy, dx, dz) when it has `cameras/front/points` and the
        predictions are on the benchmark's grid: the predicted flow read at each pixel's world point over the
        predicted object voxels (`geometry.projection.flow_at_points`), as the paper scores DSR-Net in 2D."""
        from dsr_bench.geometry.projection import flow_at_points

        steps = seq.num_steps
        tsdf_shape = tuple(seq.dataset("tsdf").shape)

        def ground_truth(t: int) -> tuple[np.ndarray, np.ndarray]:
            return seq.read("scene_flow_3d", t), seq.read("mask_3d", t)

        out = self._predict(steps, tsdf_shape, lambda t: seq.read("tsdf", t),
                            lambda: np.asarray(seq.read("action"))[:steps], ground_truth, seq.path)
        if "cameras/front/points" in seq and out["mask"].shape[1:] == GRID_SHAPE:
            out["motion_2d"] = np.stack([flow_at_points(out["motion"][t], out["mask"][t],
                                                        seq.read("cameras/front/points", t)) for t in range(steps)])
        return out

    def predict_arrays(self, tsdf: np.ndarray, actions: np.ndarray, flow: np.ndarray | None = None,
                       mask: np.ndarray | None = None, source: str = "arrays") -> dict[str, np.ndarray]:
        """The same for a sequence held in memory: tsdf (T, Y, X, Z), actions (T, 3); the ground-truth
        flow (T, 3, Y, X, Z) and mask (T, Y, X, Z) are read only by the gtwarp oracle."""
        steps = len(actions)
        tsdf_shape = tuple(np.shape(tsdf))

        def ground_truth(t: int) -> tuple[np.ndarray, np.ndarray]:
            if flow is None or mask is None:
                raise ValueError("gtwarp needs the ground-truth flow and mask (flow=, mask=)")
            return flow[t], mask[t]

        return self._predict(steps, tsdf_shape, lambda t: tsdf[t], lambda: np.asarray(actions), ground_truth, source)

    @torch.no_grad()
    def _predict(self, steps: int, tsdf_shape: tuple, tsdf_at: Callable[[int], np.ndarray],
                 read_actions: Callable[[], np.ndarray], ground_truth: Callable[[int], tuple[np.ndarray, np.ndarray]],
                 source) -> dict[str, np.ndarray]:
        """The steps in order: tsdf_at(t) and ground_truth(t) (flow, mask) read one step at a time.
        A CPU-track model (`voxel_factor` > 1) sees them pooled (`models.coarse`) and its predictions are
        brought back to the benchmark's grid."""
        from dsr_bench.models import coarse
        from dsr_bench.models.data import action_map, check_actions

        config = self.model.config
        grid, factor = tuple(config.grid), config.voxel_factor
        data_grid = grid if factor == 1 else GRID_SHAPE
        if tsdf_shape[1:] != data_grid or tsdf_shape[0] < steps:
            raise UserError(f"{source}: tsdf {tsdf_shape} does not fit the model's grid {data_grid}")
        actions = read_actions()
        if len(actions) != steps:
            raise UserError(f"{source}: {len(actions)} actions for {steps} pushes; "
                            "check it with `dsr-bench validate`")
        actions = check_actions(actions, data_grid[:2], source)
        maps = action_map(actions if factor == 1 else coarse.coarse_action(actions, factor), grid[:2])
        masks = np.zeros((steps,) + data_grid, dtype=np.uint8)
        motions = np.zeros((steps, 3) + data_grid, dtype=np.float32)
        state = self.model.initial_state(1, self.device)
        for t in range(steps):
            volume = np.asarray(tsdf_at(t), dtype=np.float32)
            volume = volume if factor == 1 else coarse.pool_tsdf(volume, factor)
            tsdf = torch.from_numpy(volume).unsqueeze(0).to(self.device)
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.bf16), \
                    batchnorm_statistics(self.model, batch=self.official_bn):
                try:
                    out = self.model(tsdf, maps[t: t + 1].to(self.device), state)
                except ValueError as exc:  # batch statistics of a single value (a small grid at batch 1)
                    if self.official_bn and "more than 1 value per channel" in str(exc):
                        raise UserError(f"official BatchNorm (batch statistics) at batch 1 needs more than one "
                                        f"value per channel, and the grid {grid} leaves one voxel in the SE(3) "
                                        "head; predict with BatchNorm in eval mode") from None
                    raise
            mask, motion = slot_labels(out["mask"])[0].cpu().numpy(), out["motion"][0].float().cpu().numpy()
            masks[t] = mask if factor == 1 else coarse.unpool_mask(mask, factor)
            motions[t] = motion if factor == 1 else coarse.unpool_motion(motion, factor)
            gt_flow = gt_mask = None
            if config.history == "gtwarp" and t + 1 < steps:
                flow, mask = ground_truth(t)
                if factor != 1:
                    flow, mask = coarse.pool_flow(flow, mask, factor), coarse.pool_labels(mask, factor)
                gt_flow = torch.from_numpy(np.asarray(flow, np.float32)).unsqueeze(0).to(self.device)
                gt_mask = torch.from_numpy(np.asarray(mask, np.int64)).unsqueeze(0).to(self.device)
            if t + 1 < steps:
                state = self.model.next_state(out, gt_flow, gt_mask)
        return {"mask": masks, "motion": motions}


def load_predictor(model: str, checkpoint: Path, device: str = "cpu", official_bn: bool = False,
                   bf16: bool = False) -> ModelPredictor:
    """A predictor from a dsr-bench weights file of a 3D-track model (any role and version of the one weights
    format, `training.checkpoints`: a run's last.pt, a CPU-track weights file, the shipped weights)."""
    dev = torch_device(device)
    net = cast(DSRNet, read_weights(Path(checkpoint), dev, kind=registry.VOXEL, model=model).network(dev))  # VOXEL
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
