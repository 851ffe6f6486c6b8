"""Predictors that write the predictions contract: the registry behind `dsr-bench predict`.

`oracle` (ground truth as predictions: IoU 1 and motion error 0 by construction) and `static`
(zero motion; masks = connected components of the current observation's TSDF surface band,
largest first) need no training; the learned models come from `dsr_bench.models.inference`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from dsr_bench.constants import MAX_OBJECTS_PER_SCENE, NUM_MASK_SLOTS
from dsr_bench.atomic import write_text
from dsr_bench.errors import UserError
from dsr_bench.dataset.sequence import SequenceReader

LEARNED_MODELS = ("dsr", "single", "nowarp", "gtwarp", "3dflow")
REFERENCE_MODELS = ("oracle", "static")
MODEL_NAMES = REFERENCE_MODELS + LEARNED_MODELS


class Predictor(Protocol):
    name: str
    num_slots: int

    def predict_sequence(self, seq: SequenceReader) -> dict[str, np.ndarray]:
        """{"mask": (T, Y, X, Z) uint8, "motion": (T, 3, Y, X, Z) float16/32[, "motion_2d"]}."""


class OraclePredictor:
    """Ground truth as predictions: amodal mask at t and flow t -> t+1 (and the 2D flow)."""

    name = "oracle"
    num_slots = MAX_OBJECTS_PER_SCENE

    def predict_sequence(self, seq: SequenceReader) -> dict[str, np.ndarray]:
        out = {"mask": seq.read("mask_3d", slice(0, seq.num_steps)).astype(np.uint8),
               "motion": seq.read("scene_flow_3d")}
        if "cameras/front/scene_flow_2d" in seq:
            out["motion_2d"] = seq.read("cameras/front/scene_flow_2d")
        return out


class StaticPredictor:
    """Zero motion; masks: 6-connected components of the TSDF surface band (tsdf < 0), largest first."""

    name = "static"

    def __init__(self, num_slots: int = NUM_MASK_SLOTS - 1, min_voxels: int = 10):
        self.num_slots, self.min_voxels = num_slots, min_voxels

    def components(self, tsdf: np.ndarray) -> np.ndarray:
        """Slot volume (Y, X, Z) uint8 of one TSDF."""
        from scipy import ndimage

        labels, count = ndimage.label(tsdf < 0)
        sizes = np.bincount(labels.reshape(-1), minlength=count + 1)[1:]
        order = [i + 1 for i in np.argsort(-sizes, kind="stable")[: self.num_slots] if sizes[i] >= self.min_voxels]
        lut = np.zeros(count + 1, dtype=np.uint8)
        lut[order] = np.arange(1, len(order) + 1)
        return lut[labels]

    def predict_sequence(self, seq: SequenceReader) -> dict[str, np.ndarray]:
        steps = seq.num_steps
        mask = np.stack([self.components(seq.read("tsdf", t)) for t in range(steps)])
        motion = np.zeros((steps, 3) + mask.shape[1:], dtype=np.float16)
        return {"mask": mask, "motion": motion}


def load_predictor(model: str, checkpoint: Path | None = None, device: str = "cpu") -> Predictor:
    """The predictor `model` (a learned model needs its checkpoint)."""
    if model == "oracle":
        return OraclePredictor()
    if model == "static":
        return StaticPredictor()
    if model in LEARNED_MODELS:
        if checkpoint is None:
            raise UserError(f"--model {model} needs --checkpoint CKPT (train one with `dsr-bench train`)")
        if not Path(checkpoint).is_file():
            raise UserError(f"checkpoint not found: {checkpoint}")
        from dsr_bench.models.inference import load_predictor as load_learned

        return load_learned(model, Path(checkpoint), device)
    raise UserError(f"--model {model!r}: choose one of {', '.join(MODEL_NAMES)}")


def predict_split(predictor: Predictor, data_dir: str | Path, names: list[str], out: str | Path,
                  progress=None) -> list[Path]:
    """Run a predictor over sequences and write one predictions file each, plus meta.json."""
    import json
    import os
    import time

    from dsr_bench.scoring.predictions import write_predictions

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written, seconds, steps = [], 0.0, 0
    for name in names:
        with SequenceReader(Path(data_dir) / f"{name}.h5") as seq:
            start = time.perf_counter()
            pred = predictor.predict_sequence(seq)
            seconds += time.perf_counter() - start
            steps += seq.num_steps
        written.append(write_predictions(out / f"{name}.h5", pred["mask"], pred["motion"], predictor.num_slots,
                                         pred.get("motion_2d")))
        if progress:
            progress()
    meta = {"name": predictor.name, "description": (type(predictor).__doc__ or "").strip().splitlines()[0],
            "parameters": {"num_slots": predictor.num_slots}, "seconds_per_step": seconds / max(steps, 1),
            "hardware": f"{os.cpu_count()} CPU cores"}
    write_text(out / "meta.json", json.dumps(meta, indent=1) + "\n")
    return written
