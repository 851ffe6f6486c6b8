"""PyTorch datasets of model-ready windows of L consecutive pushes (torch is the only heavy import).

Each item is a dict for pushes s .. s+L-1 of one sequence:
  tsdf          (L, Y, X, Z) float32  observation t
  action        (L, 8, Y, X) float32  one-hot action map at [d, row, col]
  mask_3d       (L, Y, X, Z) int64    amodal ids at t (0 empty, 1..N objects)
  scene_flow_3d (L, 3, Y, X, Z) float32 voxels, (dy, dx, dz), t -> t+1
  sequence (str), start (int)
Files are opened lazily in each worker process (h5py handles never cross a fork) and only the
requested steps are read.
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np
import torch
from torch.utils.data import Dataset

from dsr_bench.constants import GRID_SHAPE, NUM_DIRECTIONS
from dsr_bench.errors import UserError

DEFAULT_FIELDS = ("tsdf", "action", "mask_3d", "scene_flow_3d")


def action_map(action: np.ndarray, shape: tuple[int, int] = GRID_SHAPE[:2]) -> torch.Tensor:
    """One-hot action maps (L, 8, Y, X) float32 from actions (L, 3) = [d, row, col]."""
    action = np.asarray(action, dtype=np.int64).reshape(-1, 3)
    out = torch.zeros((len(action), NUM_DIRECTIONS) + tuple(shape), dtype=torch.float32)
    out[torch.arange(len(action)), action[:, 0], action[:, 1], action[:, 2]] = 1.0
    return out


class _LazyFiles:
    """Per-process cache of open h5py files."""

    def __init__(self):
        self._pid, self._files = None, {}

    def get(self, path: Path) -> h5py.File:
        if self._pid != os.getpid():
            self._pid, self._files = os.getpid(), {}
        if path not in self._files:
            self._files[path] = h5py.File(path, "r")
        return self._files[path]

    def __getstate__(self):
        return {}

    def __setstate__(self, state):
        self._pid, self._files = None, {}


class SequenceWindowDataset(Dataset):
    """Windows of `window` consecutive pushes over a split of a dsr-bench dataset directory."""

    def __init__(self, data_dir: str | Path, split: str | None = None, window: int = 1,
                 fields: tuple[str, ...] = DEFAULT_FIELDS, stride: int = 1):
        from dsr_bench.manifest import read_split

        if window < 1 or stride < 1:
            raise UserError(f"window {window} and stride {stride} must be at least 1")
        unknown = set(fields) - set(DEFAULT_FIELDS)
        if unknown:
            raise UserError(f"unknown fields {sorted(unknown)}; choose from {DEFAULT_FIELDS}")
        self.data_dir, self.window, self.fields = Path(data_dir), window, tuple(fields)
        self.split, names = read_split(data_dir, split)
        self.items: list[tuple[Path, str, int]] = []
        for name in names:
            path = self.data_dir / f"{name}.h5"
            if not path.is_file():
                raise UserError(f"split {self.split!r} names {name}, but {path} is missing")
            with h5py.File(path, "r") as f:
                steps = int(f.attrs["num_steps"])
            if steps < window:
                raise UserError(f"{path.name} has {steps} pushes, fewer than the window {window}")
            self.items += [(path, name, s) for s in range(0, steps - window + 1, stride)]
        self._files = _LazyFiles()

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, index: int) -> dict:
        path, name, s = self.items[index]
        f = self._files.get(path)
        sl = slice(s, s + self.window)
        out: dict = {"sequence": name, "start": s}
        if "tsdf" in self.fields:
            out["tsdf"] = torch.from_numpy(f["tsdf"][sl])
        if "action" in self.fields:
            out["action"] = action_map(f["action"][sl])
        if "mask_3d" in self.fields:
            out["mask_3d"] = torch.from_numpy(f["mask_3d"][sl].astype(np.int64))
        if "scene_flow_3d" in self.fields:
            out["scene_flow_3d"] = torch.from_numpy(f["scene_flow_3d"][sl])
        return out


class OfficialWindowDataset(Dataset):
    """The same windows read directly from the official release layout (`<seq>_<step>.hdf5`)."""

    def __init__(self, src: str | Path, split: str = "train", window: int = 1,
                 fields: tuple[str, ...] = DEFAULT_FIELDS, stride: int = 1):
        from dsr_bench.official import find_official_sequences, read_official_split

        sequences = find_official_sequences(src)
        self.window, self.fields = window, tuple(fields)
        self.items: list[tuple[tuple[Path, ...], str, int]] = []
        for seq_id in read_official_split(src, split):
            if seq_id not in sequences:
                raise UserError(f"{src}/{split}.txt lists {seq_id}, which has no step files")
            files = sequences[seq_id].files
            self.items += [(files, seq_id, s) for s in range(0, len(files) - window + 1, stride)]
        self._files = _LazyFiles()

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, index: int) -> dict:
        files, seq_id, s = self.items[index]
        steps = [self._files.get(files[t]) for t in range(s, s + self.window)]
        out: dict = {"sequence": seq_id, "start": s}
        if "tsdf" in self.fields:
            out["tsdf"] = torch.from_numpy(np.stack([f["tsdf"][()] for f in steps]).astype(np.float32))
        if "action" in self.fields:
            out["action"] = action_map(np.stack([f["action"][()] for f in steps]))
        if "mask_3d" in self.fields:
            out["mask_3d"] = torch.from_numpy(np.stack([f["mask_3d"][()] for f in steps]).astype(np.int64))
        if "scene_flow_3d" in self.fields:
            flow = np.stack([np.moveaxis(f["scene_flow_3d"][()], -1, 0) for f in steps])
            out["scene_flow_3d"] = torch.from_numpy(flow.astype(np.float32))
        return out
