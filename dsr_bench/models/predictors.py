"""Predictors that write the predictions contract: the registry behind `dsr-bench predict`.

Reference predictors need no training: `oracle` (ground truth as predictions: IoU 1 and motion
error 0 by construction), `static` (predicting no motion; masks = connected components of the
current observation's TSDF surface band, largest first; zero 2D flow) and `push` (the yardstick of
a naive action-conditioned guess: the same masks, and every voxel of them moved along the push by
PUSH_YARDSTICK_DISTANCE; in 2D every pixel that sees something above the table). `load_predictor` is the one
loader of predictors: it calls the loader of the model's kind (`registry.KINDS`: `load_reference` here, the 3D
track's `inference.load_voxel`, the 2D track's `image_inference.load_image`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

import numpy as np

from dsr_bench.constants import FREE_HEIGHT, GRID_SHAPE, MAX_OBJECTS_PER_SCENE, NUM_MASK_SLOTS, VOXEL_SIZE
from dsr_bench.atomic import write_text
from dsr_bench.errors import UserError
from dsr_bench.dataset.sequence import SequenceReader
from dsr_bench.models import registry

#: The names of each kind of model, from the one table of models (`dsr_bench.models.registry`): the 3D track's
#: learned models, the 2D track's (`models.image_nets`: their predictions hold motion_2d only), the references.
LEARNED_MODELS = registry.names(registry.VOXEL)
IMAGE_MODELS = registry.names(registry.IMAGE)
REFERENCE_MODELS = registry.names(registry.REFERENCE)
#: How far the `push` yardstick moves every object voxel along the push (m): about how far the pushed
#: object moves (10.2-10.7 cm in the authors' and our cube scenes, bench/bench_fidelity.py).
PUSH_YARDSTICK_DISTANCE = 0.10
MODEL_NAMES = registry.names()


class Predictor(Protocol):
    name: str

    @property
    def num_slots(self) -> int | None:  # None: a model without masks (2DFlow)
        ...

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
        out = {"mask": mask, "motion": motion}
        if "cameras/front/points" in seq:
            height, width = seq.read("cameras/front/points", 0).shape[:2]
            out["motion_2d"] = np.zeros((steps, height, width, 3), dtype=np.float16)
        return out


class PushPredictor(StaticPredictor):
    """Every object voxel moved along the push: the static masks, each of their voxels moved by
    PUSH_YARDSTICK_DISTANCE along the push direction (in 2D: every pixel whose world point is more
    than FREE_HEIGHT above the table)."""

    name = "push"

    def predict_sequence(self, seq: SequenceReader) -> dict[str, np.ndarray]:
        from dsr_bench.geometry import direction_vector

        out = super().predict_sequence(seq)
        actions = seq.read("action")
        for t in range(seq.num_steps):
            dx, dy = direction_vector(int(actions[t, 0])) * PUSH_YARDSTICK_DISTANCE
            occupied = out["mask"][t] > 0
            for c, value in enumerate((dy, dx, 0.0)):  # components (dy, dx, dz), voxels
                out["motion"][t, c][occupied] = value / VOXEL_SIZE
            if "motion_2d" in out:
                points = seq.read("cameras/front/points", t)
                above = np.nan_to_num(points[..., 2], nan=0.0) > FREE_HEIGHT
                out["motion_2d"][t][above] = (dy, dx, 0.0)  # metres
        return out


#: The CPU track's trained weights that ship with the toolkit (`dsr-bench train --track cpu`, docs/models.md):
#: what `dsr-bench predict --model M` uses when no --checkpoint or --weights is given.
SHIPPED_WEIGHTS = Path(__file__).resolve().parent / "weights" / "cpu-track"
#: The "source" a predictions' meta.json (and a plan's results) records for the shipped weights (`weights_file`).
SHIPPED_SOURCE = "dsr-bench, shipped CPU-track weights"


def shipped_weights(model: str) -> Path | None:
    """The shipped CPU-track weights file of a learned model, or None if there is none."""
    path = SHIPPED_WEIGHTS / f"{model}.pt"
    return path if path.is_file() else None


def load_predictor(model: str, checkpoint: Path | None = None, device: str = "cpu", weights: Path | None = None,
                   official_bn: bool | None = None, warp: str | None = None, bn_batch: int | None = None,
                   fast: bool | None = None) -> Predictor:
    """The predictor `model` (an entry of `dsr_bench.models.registry`, whose kind's loader makes it: the one loader
    of predictors, `dsr-bench predict`'s): a learned model needs a dsr-bench `checkpoint` or the authors' released
    `weights` (dsr.pth ... 3dflow.pth), or the shipped CPU-track weights are read. official_bn: BatchNorm with batch
    statistics (the official code's way) or running statistics (eval); None: batch statistics for the authors'
    weights, eval mode for a dsr-bench checkpoint. warp: the history warp's kernel (`warp.WARP_KERNELS`); None: the
    authors' ("official") for their weights, ours ("floor") for a dsr-bench checkpoint. bn_batch: sequences
    normalised together with the authors' weights; None: their test protocol's 12 (`inference.OFFICIAL_BN_BATCH`).
    fast: a 3D-track model's steps through `models.fast.FastDSRNet` (equal up to rounding); None: where
    `inference.fast_by_default` says (on a CPU, fp32, BatchNorm's running statistics, the full 128 x 128 x 48 grid),
    which `dsr-bench predict` relies on."""
    entry = registry.model_entry(model)
    if weights is not None and not entry.released:
        raise UserError(f"--weights is for the authors' released models ({', '.join(registry.released())}), "
                        f"not --model {model}")
    if entry.kind != registry.VOXEL and (warp is not None or bn_batch is not None):
        raise UserError(f"--warp and --bn-batch are for the 3D track's learned models "
                        f"({', '.join(registry.names(registry.VOXEL))}), not --model {model}")
    if warp is not None:
        from dsr_bench.models.warp import WARP_KERNELS  # (torch: a voxel model's loader needs it anyway)

        if warp not in WARP_KERNELS:
            raise UserError(f"--warp {warp!r}: choose one of {', '.join(WARP_KERNELS)}")
    if bn_batch is not None and weights is None:
        raise UserError("--bn-batch is for the authors' weights (--weights), which normalise BatchNorm over a batch; "
                        "a dsr-bench checkpoint runs BatchNorm with its running statistics")
    if bn_batch is not None and bn_batch < 1:
        raise UserError(f"--bn-batch {bn_batch}: sequences per batch must be at least 1 (12: the authors' protocol)")
    if fast and entry.kind != registry.VOXEL:
        raise UserError(f"fast inference is for the 3D track's learned models, not --model {model}")
    load = registry.resolve(entry.model_kind.loader)
    predictor = load(entry, checkpoint=checkpoint, device=device, weights=weights, official_bn=official_bn, warp=warp,
                     bn_batch=bn_batch)
    if fast is not None and entry.kind == registry.VOXEL:
        predictor.set_fast(fast)  # (a ModelPredictor)
    return predictor


def load_reference(entry: registry.ModelEntry, **options) -> Predictor:
    """A reference kind's loader: its predictor (no weights; a --checkpoint is not read)."""
    return entry.make_predictor()


def weights_file(entry: registry.ModelEntry, checkpoint: Path | None) -> tuple[Path, dict[str, str]]:
    """The weights file a learned model's loader reads (`checkpoint`, else the shipped CPU-track file) and where it
    came from (source, file, sha256: the predictions' meta.json); a UserError naming the fix where there is none."""
    from dsr_bench.dataset.manifest import file_sha256

    shipped = checkpoint is None
    path = shipped_weights(entry.name) if checkpoint is None else Path(checkpoint)
    if path is None:
        released = f" or --weights FILE (the authors' {entry.name}.pth)" if entry.released else ""
        raise UserError(f"--model {entry.name} needs --checkpoint CKPT (train one with `dsr-bench train"
                        f"{'' if entry.released else ' --model ' + entry.name}`){released}")
    if not path.is_file():
        raise UserError(f"checkpoint not found: {path}")
    return path, {"source": SHIPPED_SOURCE if shipped else "dsr-bench", "file": path.name,
                  "sha256": file_sha256(path)}


def predict_split(predictor: Predictor, data_dir: str | Path, names: list[str], out: str | Path,
                  progress=None) -> list[Path]:
    """Run a predictor over sequences and write one predictions file each, plus meta.json. A predictor with
    `bn_batch` > 1 (the authors' weights under their test protocol) runs `names` in consecutive groups of that
    many (`predict_sequences`: BatchNorm over the group; the last group holds the rest)."""
    import contextlib
    import json
    import os
    import time

    from dsr_bench.scoring.predictions import write_predictions

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written, seconds, steps = [], 0.0, 0
    group = max(1, int(getattr(predictor, "bn_batch", 1)))
    for first in range(0, len(names), group):
        chunk = names[first: first + group]
        with contextlib.ExitStack() as stack:
            seqs = [stack.enter_context(SequenceReader(Path(data_dir) / f"{name}.h5")) for name in chunk]
            start = time.perf_counter()
            preds = (predictor.predict_sequences(seqs) if group > 1  # type: ignore[attr-defined]
                     else [predictor.predict_sequence(seqs[0])])
            seconds += time.perf_counter() - start
            steps += sum(seq.num_steps for seq in seqs)
        for name, pred in zip(chunk, preds):
            three_d = "mask" in pred  # a 2D-track model's predictions hold motion_2d only
            written.append(write_predictions(out / f"{name}.h5", pred.get("mask"), pred.get("motion"),
                                             predictor.num_slots if three_d else None, pred.get("motion_2d")))
            if progress:
                progress()
    meta: dict[str, Any] = {"name": predictor.name,
            "description": (getattr(predictor, "description", None)
                            or (type(predictor).__doc__ or "").strip().splitlines()[0]),
            "parameters": {**({} if predictor.num_slots is None else {"num_slots": predictor.num_slots}),
                           **({"image": list(predictor.image)} if hasattr(predictor, "image")
                              else {"grid": list(getattr(predictor, "grid", GRID_SHAPE))})},
            "seconds_per_step": seconds / max(steps, 1),
            "hardware": f"{os.cpu_count()} CPU cores"}
    if getattr(predictor, "fast", False):  # how the steps were run, where it is not the eager network
        meta["parameters"]["inference"] = predictor.inference  # type: ignore[attr-defined]
    weights = getattr(predictor, "weights", None)
    if weights:  # where a learned model's weights came from; also under parameters, which results carry
        meta["weights"] = weights
        meta["parameters"]["weights"] = weights
    write_text(out / "meta.json", json.dumps(meta, indent=1) + "\n")
    return written
