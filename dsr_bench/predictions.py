"""The predictions contract: one HDF5 file per test sequence, named like the sequence.

PRED_DIR/seq_0042.h5 holds, for each push t = 0..T-1 (made after observations 0..t and action t):
  mask       (T, 128, 128, 48) uint8    amodal instance slots: 0 empty, 1..num_slots
  motion     (T, 3, 128, 128, 48) float16 or float32  scene flow t -> t+1 in voxels, (dy, dx, dz)
  motion_2d  (T, 240, 320, 3) float16/32, optional    front-camera flow in metres, (dy, dx, dz)
and the root attribute `num_slots` (K - 1, the number of object slots the model has; slot numbers
are the model's own, matching is the metric's job). PRED_DIR/meta.json optionally describes the
method: {"name", "description", "code_url", "parameters", "hardware", "seconds_per_step"}.
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from dsr_bench.constants import GRID_SHAPE, IMAGE_SHAPE
from dsr_bench.errors import UserError

PREDICTION_FORMAT = "dsr-bench-predictions"
MOTION_DTYPES = (np.dtype("float16"), np.dtype("float32"))
MAX_SLOTS = 254


def write_predictions(path: str | Path, mask: np.ndarray, motion: np.ndarray, num_slots: int,
                      motion_2d: np.ndarray | None = None) -> Path:
    """Validate arrays against the contract and write them atomically to `path` (.h5)."""
    path = Path(path)
    mask, motion = np.asarray(mask), np.asarray(motion)
    problems = []
    if mask.ndim != 4 or mask.shape[1:] != GRID_SHAPE or mask.dtype != np.uint8:
        problems.append(f"mask must be (T, {', '.join(map(str, GRID_SHAPE))}) uint8, got {mask.shape} {mask.dtype}")
    if motion.shape != (mask.shape[0], 3) + GRID_SHAPE or motion.dtype not in MOTION_DTYPES:
        problems.append(f"motion must be (T, 3, {', '.join(map(str, GRID_SHAPE))}) float16/float32, got {motion.shape} {motion.dtype}")
    elif not np.all(np.isfinite(motion)):
        problems.append("motion has NaN or inf")
    if not 1 <= num_slots <= MAX_SLOTS:
        problems.append(f"num_slots {num_slots} must be 1..{MAX_SLOTS}")
    elif mask.size and int(mask.max()) > num_slots:
        problems.append(f"mask has slot {int(mask.max())} > num_slots {num_slots}")
    if motion_2d is not None:
        motion_2d = np.asarray(motion_2d)
        if motion_2d.shape != (mask.shape[0],) + IMAGE_SHAPE + (3,) or motion_2d.dtype not in MOTION_DTYPES:
            problems.append(f"motion_2d must be (T, 240, 320, 3) float16/float32, got {motion_2d.shape} {motion_2d.dtype}")
    if problems:
        raise UserError(f"refusing to write {path.name}: " + "; ".join(problems))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = PREDICTION_FORMAT
            f.attrs["num_slots"] = int(num_slots)
            opts = {"compression": "gzip", "compression_opts": 1}
            f.create_dataset("mask", data=mask, chunks=(1,) + GRID_SHAPE, track_times=False, **opts)
            f.create_dataset("motion", data=motion, chunks=(1, 3) + GRID_SHAPE, track_times=False, **opts)
            if motion_2d is not None:
                f.create_dataset("motion_2d", data=motion_2d, chunks=(1,) + IMAGE_SHAPE + (3,), track_times=False, **opts)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def check_prediction_header(f: h5py.File, num_steps: int) -> list[str]:
    """Structural problems of an open prediction file for a sequence of `num_steps` pushes."""
    problems = []
    slots = f.attrs.get("num_slots")
    if slots is None or not 1 <= int(slots) <= MAX_SLOTS:
        problems.append(f"attribute num_slots missing or not in 1..{MAX_SLOTS}")
    for name, shape, dtypes in (("mask", (num_steps,) + GRID_SHAPE, (np.dtype("uint8"),)),
                                ("motion", (num_steps, 3) + GRID_SHAPE, MOTION_DTYPES)):
        if name not in f or not isinstance(f[name], h5py.Dataset):
            problems.append(f"missing dataset {name!r}")
            continue
        if f[name].shape != shape:
            problems.append(f"{name}: shape {f[name].shape}, expected {shape}")
        if f[name].dtype not in dtypes:
            problems.append(f"{name}: dtype {f[name].dtype}, expected {' or '.join(map(str, dtypes))}")
    if "motion_2d" in f:
        shape = (num_steps,) + IMAGE_SHAPE + (3,)
        if f["motion_2d"].shape != shape or f["motion_2d"].dtype not in MOTION_DTYPES:
            problems.append(f"motion_2d: {f['motion_2d'].shape} {f['motion_2d'].dtype}, expected {shape} float16/float32")
    return problems
