"""Candidate actions through a DSR-Net-like model (`dsr_bench.models.dsr_net.DSRNet`) against one state.

The representation and the masks depend on the observation and the history only, so the volume encoder, the
decoder and the mask head run once per step (`DSRNet.represent`); only the motion head (`DSRNet.motion_of`:
SE(3) or 3DFlow) runs per candidate, in batches. With BatchNorm in eval mode (the shipped CPU-track weights)
this gives, per candidate, exactly what `DSRNet.forward` gives; with the official batch statistics each
candidate runs alone (batch 1), as forward would at inference.

The predicted next state of a candidate: each voxel labelled in the predicted masks at t (on the benchmark's
grid) moved by the predicted 3D flow at it (benchmark voxels) and rounded to the nearest voxel (forward
warping of labels; a voxel moved out of the grid is dropped, two voxels landing on one keep the later one
in C order). A CPU-track model (`voxel_factor` 4) sees the TSDF pooled, and its masks and motions are brought
back to the benchmark's grid (`dsr_bench.models.coarse`) before the warp.

With masks="observed" the labels warped are the objects the TSDF shows (`dsr_bench.planning.observed`), each
given the network slot it overlaps most, and each of their voxels moves by the network's motion at it (computed with
the network's own masks, which also keep weighting DSR-Net's history). On the validation tasks this was the better of
two ways: giving the observed objects to the SE(3) head as its mask (pivots and blending) planned worse (IoU 0.433 vs
0.444 over 30 plan-val tasks, start 0.442), and its predicted gains did not rank the true ones (docs/planning.md).
"""

from __future__ import annotations

import numpy as np
import torch

from dsr_bench.constants import GRID_SHAPE
from dsr_bench.planning.cost import SparseLabels
from dsr_bench.planning.observed import observed_objects, slots_for
from dsr_bench.planning.protocol import PLANNER_MASKS


def moved_labels(mask: np.ndarray, motion_at: np.ndarray, voxels: np.ndarray) -> list[SparseLabels]:
    """Forward-warp labels: mask (Y, X, Z) uint8, voxels (M, 3) int64 the labelled voxels' indices (C order),
    motion_at (B, 3, M) their flow in voxels (dy, dx, dz) -> B label volumes (labels at round(index + flow)) as
    `SparseLabels`; a voxel moved out of the grid is dropped, and of two landing on one the later in C order
    stays."""
    labels = mask[voxels[:, 0], voxels[:, 1], voxels[:, 2]]
    target = np.rint(voxels.T[None].astype(np.float32) + motion_at).astype(np.int64)  # (B, 3, M)
    shape = np.array(GRID_SHAPE).reshape(1, 3, 1)
    inside = np.all((target >= 0) & (target < shape), axis=1)  # (B, M)
    flat = (target[:, 0] * GRID_SHAPE[1] + target[:, 1]) * GRID_SHAPE[2] + target[:, 2]
    out = []
    for f, keep in zip(flat, inside):
        reversed_flat, reversed_labels = f[keep][::-1], labels[keep][::-1]
        unique, last = np.unique(reversed_flat, return_index=True)  # the first of the reversed: the last written
        out.append(SparseLabels(unique, reversed_labels[last], GRID_SHAPE))
    return out


def move_labels(mask: np.ndarray, motion_at: np.ndarray, voxels: np.ndarray) -> np.ndarray:
    """`moved_labels` as dense volumes (B, Y, X, Z) uint8."""
    return np.stack([s.dense() for s in moved_labels(mask, motion_at, voxels)])


class BatchedModel:
    """One state of a `ModelPredictor`'s network, and candidate actions scored against it.

    observe(tsdf) runs the network's state-dependent part; predict(actions) the motion head per batch;
    executed(action) carries the history as `ModelPredictor` does (`DSRNet.next_state` of the executed action)."""

    # what observe() saw (None before it): the representation and mask logits, the labels and their voxels
    _rep: torch.Tensor | None
    _mask: torch.Tensor | None
    _labels: np.ndarray | None
    _voxels: np.ndarray | None

    def __init__(self, predictor, masks: str = "model"):
        if masks not in PLANNER_MASKS:
            raise ValueError(f"masks {masks!r}: one of {PLANNER_MASKS}")
        self.masks = masks
        self.predictor = predictor
        self.model = predictor.model
        self.config = self.model.config
        self.device = predictor.device
        self.factor = int(self.config.voxel_factor)
        self.reset()

    def reset(self) -> None:
        self.state = self.model.initial_state(1, self.device)
        self._rep = self._mask = self._labels = self._voxels = None

    def _bn(self):
        from dsr_bench.models.dsr_net import batchnorm_statistics

        return batchnorm_statistics(self.model, batch=bool(self.predictor.official_bn))

    @torch.no_grad()
    def observe(self, tsdf: np.ndarray) -> np.ndarray:
        """TSDF (Y, X, Z) -> the predicted masks at t on the benchmark grid (Y, X, Z) uint8 (slot k -> k + 1)."""
        from dsr_bench.models import coarse
        from dsr_bench.models.labels import slot_labels

        volume = np.asarray(tsdf, np.float32)
        volume = volume if self.factor == 1 else coarse.pool_tsdf(volume, self.factor)
        x = torch.from_numpy(volume).unsqueeze(0).to(self.device)
        with self._bn():
            out = self.model.represent(x, self.state)
        self._rep, self._mask = out["representation"], out["mask"]
        labels = slot_labels(out["mask"])[0].cpu().numpy()
        labels = labels if self.factor == 1 else coarse.unpool_mask(labels, self.factor)
        if self.masks == "observed":
            num_slots = int(out["mask"].shape[1]) - 1
            labels = slots_for(observed_objects(np.asarray(tsdf), num_slots), labels, num_slots)
        self._labels = labels
        self._voxels = np.argwhere(labels > 0)
        return labels

    @torch.no_grad()
    def motion(self, actions: np.ndarray) -> torch.Tensor:
        """Candidate actions (B, 3) on the benchmark grid -> the model's motion (B, 3, *model grid) in model voxels."""
        from dsr_bench.models import coarse
        from dsr_bench.models.data import action_map

        acts = np.asarray(actions, np.int64).reshape(-1, 3)
        grid = tuple(self.config.grid)
        pushes = acts if self.factor == 1 else coarse.coarse_action(acts, self.factor)
        maps = action_map(pushes, grid[:2]).to(self.device)
        b = len(acts)
        chunks = [slice(i, i + 1) for i in range(b)] if self.predictor.official_bn else [slice(0, b)]
        assert self._rep is not None and self._mask is not None, "observe(tsdf) first"
        out = []
        with self._bn():
            for part in chunks:
                n = part.stop - part.start
                rep = self._rep.expand(n, *self._rep.shape[1:])
                mask = self._mask.expand(n, *self._mask.shape[1:])
                out.append(self.model.motion_of(rep, mask, maps[part]))
        return torch.cat(out)

    def motion_at(self, actions: np.ndarray, voxels: np.ndarray) -> np.ndarray:
        """Candidate actions (B, 3) -> the model's flow (B, 3, M) float32 in benchmark voxels (dy, dx, dz) at
        `voxels` (M, 3), indices on the benchmark grid (a coarse model's flow is read at the coarse voxel holding
        each and scaled by its factor)."""
        motion = self.motion(actions).cpu().numpy()  # (B, 3, *grid) model voxels
        v = voxels
        if self.factor == 1:
            at = motion[:, :, v[:, 0], v[:, 1], v[:, 2]]
        else:
            c = v // self.factor
            at = motion[:, :, c[:, 0], c[:, 1], c[:, 2]] * np.float32(self.factor)
        return at.astype(np.float32)

    def predict_labels(self, actions: np.ndarray) -> list[SparseLabels]:
        """Candidate actions (B, 3) -> predicted next masks as `SparseLabels` (see the module doc)."""
        v = self._voxels
        assert v is not None and self._labels is not None, "observe(tsdf) first"
        return moved_labels(self._labels, self.motion_at(actions, v), v)

    def predict(self, actions: np.ndarray) -> np.ndarray:
        """Candidate actions (B, 3) -> predicted next masks (B, Y, X, Z) uint8 (see the module doc)."""
        return np.stack([s.dense() for s in self.predict_labels(actions)])

    @torch.no_grad()
    def executed(self, action: np.ndarray) -> None:
        """Carry the history: `DSRNet.next_state` of this step's outputs for the executed action."""
        outputs = {"representation": self._rep, "mask": self._mask, "motion": self.motion(np.asarray(action)[None])}
        self.state = self.model.next_state(outputs)


class MotionEnsemble:
    """Several models against one state, planning with the mean of their motions (an ensemble of learned
    dynamics: the members' independent errors partly cancel).

    The labels are the first member's (its masks, or the observed objects given its slots: `BatchedModel`), each
    voxel moved by the mean over the members of their flow at it (`BatchedModel.motion_at`, benchmark voxels);
    every member runs its own network on the observation and carries its own history."""

    def __init__(self, models: list[BatchedModel]):
        if len(models) < 2:
            raise ValueError("an ensemble needs at least two models")
        self.models = models

    def reset(self) -> None:
        for model in self.models:
            model.reset()

    def observe(self, tsdf: np.ndarray) -> np.ndarray:
        """TSDF (Y, X, Z) -> the first member's labels (Y, X, Z) uint8; every member observes."""
        labels = self.models[0].observe(tsdf)
        for model in self.models[1:]:
            model.observe(tsdf)
        return labels

    def predict_labels(self, actions: np.ndarray) -> list[SparseLabels]:
        """Candidate actions (B, 3) -> the first member's labels moved by the members' mean flow, as `SparseLabels`."""
        first = self.models[0]
        v, labels = first._voxels, first._labels
        assert v is not None and labels is not None, "observe(tsdf) first"
        flow = np.mean([model.motion_at(actions, v) for model in self.models], axis=0, dtype=np.float32)
        return moved_labels(labels, np.asarray(flow), v)

    def predict(self, actions: np.ndarray) -> np.ndarray:
        """Candidate actions (B, 3) -> predicted next masks (B, Y, X, Z) uint8."""
        return np.stack([s.dense() for s in self.predict_labels(actions)])

    def executed(self, action: np.ndarray) -> None:
        """Carry each member's history (`BatchedModel.executed`)."""
        for model in self.models:
            model.executed(action)
