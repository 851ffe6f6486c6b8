"""PyTorch datasets of model-ready windows of L consecutive pushes (torch is the only heavy import).

Each item is a dict for pushes s .. s+L-1 of one sequence:
  tsdf          (L, Y, X, Z) float32  observation t
  action        (L, 8, Y, X) float32  one-hot action map at [d, row, col]
  mask_3d       (L, Y, X, Z) uint8    amodal ids at t (0 empty, 1..N objects); 8x less to copy and
                                      move than int64: widen on the device (`.long()`)
  scene_flow_3d (L, 3, Y, X, Z) float32 voxels, (dy, dx, dz), t -> t+1
  sequence (str), start (int)
Files are opened lazily in each worker process (h5py handles never cross a fork) and only the
requested steps are read.

`collate_compact` (a DataLoader collate_fn) batches windows in a compact form for the trip to the
GPU: the flow as its non-zero voxels (objects only, 1-3% of the grid) and the action maps as one
index per step, about 3x fewer bytes through shared memory, pinning and the host-to-device copy;
`batch_to_device` rebuilds the dense tensors on the device, bit for bit.
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np
import torch
from torch.utils.data import Dataset, default_collate

from dsr_bench.constants import GRID_SHAPE, NUM_DIRECTIONS
from dsr_bench.errors import UserError
from dsr_bench.dataset.storage import read_steps

#: The arrays of a sequence file that training reads (and the window datasets read by default):
#: `scripts/slim_dataset.py` keeps these.
TRAINING_FIELDS = ("tsdf", "action", "mask_3d", "scene_flow_3d")


def check_actions(actions: np.ndarray, shape: tuple[int, ...], source) -> np.ndarray:
    """Actions (L, 3) [direction 0..7, row, col] with the pixel inside the (Y, X) map, as int64;
    UserError naming `source` (a file) otherwise (the checks of `dsr-bench validate`)."""
    from dsr_bench.dataset.checks import action_problems

    problems = action_problems(actions, shape)
    if problems:
        raise UserError(f"{source}: {'; '.join(problems)}; check it with `dsr-bench validate`")
    return np.asarray(actions).astype(np.int64, copy=False)


def action_map(action: np.ndarray, shape: tuple[int, ...] = GRID_SHAPE[:2]) -> torch.Tensor:
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


def _check_options(window: int, stride: int, fields: tuple[str, ...]) -> None:
    if window < 1 or stride < 1:
        raise UserError(f"window {window} and stride {stride} must be at least 1")
    unknown = sorted(set(fields) - set(TRAINING_FIELDS))
    if unknown or not fields:
        raise UserError(f"unknown fields {unknown}; choose one or more of {', '.join(TRAINING_FIELDS)}")


#: our dataset name -> shape of one step
_STEP_SHAPE = {"tsdf": GRID_SHAPE, "action": (3,), "mask_3d": GRID_SHAPE, "scene_flow_3d": (3,) + GRID_SHAPE}


class SequenceWindowDataset(Dataset):
    """Windows of `window` consecutive pushes over a split of a dsr-bench dataset directory.

    Item i is a dict for pushes s .. s+L-1 of one sequence (windows start every `stride` pushes):
    tsdf (L, Y, X, Z) float32, action (L, 8, Y, X) float32 one-hot, mask_3d (L, Y, X, Z) uint8,
    scene_flow_3d (L, 3, Y, X, Z) float32 voxels (dy, dx, dz), sequence (str), start (int); only
    the requested `fields` are read. `split=None` takes the dataset's only split.
    """

    def __init__(self, data_dir: str | Path, split: str | None = None, window: int = 1,
                 fields: tuple[str, ...] = TRAINING_FIELDS, stride: int = 1):
        from dsr_bench.dataset.manifest import MANIFEST_NAME, load_manifest, read_split

        _check_options(window, stride, tuple(fields))
        self.data_dir, self.window, self.stride, self.fields = Path(data_dir), window, stride, tuple(fields)
        self.split, names = read_split(data_dir, split)
        known: dict[str, tuple[int, int]] = {}
        if (self.data_dir / MANIFEST_NAME).is_file():  # counts without opening thousands of files
            known = {s["name"]: (s["num_steps"], s["num_objects"]) for s in load_manifest(data_dir)["sequences"]}
        self.items: list[tuple[Path, str, int]] = []
        #: Objects per sequence (from the manifest or the files' attributes).
        self.num_objects: dict[str, int] = {}
        for name in names:
            path = self.data_dir / f"{name}.h5"
            if not path.is_file():
                raise UserError(f"split {self.split!r} names {name}, but {path} is missing")
            steps, self.num_objects[name] = known[name] if name in known else self._counts(path)
            if steps < window:
                raise UserError(f"{path.name} has {steps} pushes, fewer than the window {window}")
            self.items += [(path, name, s) for s in range(0, steps - window + 1, stride)]
        self._files = _LazyFiles()

    @staticmethod
    def _counts(path: Path) -> tuple[int, int]:
        """(pushes, objects) of one sequence file."""
        from dsr_bench.dataset.sequence import SequenceReader

        with SequenceReader(path) as seq:  # checks the format marker and schema version
            return seq.num_steps, seq.num_objects

    def __len__(self) -> int:
        return len(self.items)

    def _dataset(self, f: h5py.File, path: Path, name: str, end: int) -> h5py.Dataset:
        step_shape = _STEP_SHAPE[name]
        ds = f.get(name)
        if ds is None or tuple(ds.shape[1:]) != step_shape or ds.shape[0] < end:
            got = None if ds is None else tuple(ds.shape)
            raise UserError(f"{path}: {name} has shape {got}, expected (>= {end}, {', '.join(map(str, step_shape))}); "
                            f"check the file with `dsr-bench validate {path.parent}`")
        return ds

    def __getitem__(self, index: int) -> dict:
        path, name, s = self.items[index]
        f = self._files.get(path)
        sl = slice(s, s + self.window)
        out: dict = {"sequence": name, "start": s}
        for field in self.fields:
            value = read_steps(self._dataset(f, path, field, s + self.window), sl.start, sl.stop)
            if field == "action":
                out[field] = action_map(check_actions(value, GRID_SHAPE[:2], path))
            elif field == "mask_3d":
                out[field] = torch.from_numpy(np.ascontiguousarray(value, dtype=np.uint8))
            else:
                out[field] = torch.from_numpy(np.ascontiguousarray(value, dtype=np.float32))
        return out


class OfficialWindowDataset(Dataset):
    """The same windows and tensors read directly from the official release layout
    (`<seq>_<step>.hdf5` files, `train.txt` / `test.txt`); flow is moved to (3, Y, X, Z) and cast to float32."""

    def __init__(self, src: str | Path, split: str = "train", window: int = 1,
                 fields: tuple[str, ...] = TRAINING_FIELDS, stride: int = 1):
        from dsr_bench.dataset.official import find_official_sequences, read_official_split

        _check_options(window, stride, tuple(fields))
        sequences = find_official_sequences(src)
        self.window, self.stride, self.fields = window, stride, tuple(fields)
        self.items: list[tuple[tuple[Path, ...], str, int]] = []
        for seq_id in read_official_split(src, split):
            if seq_id not in sequences:
                raise UserError(f"{src}/{split}.txt lists {seq_id}, which has no step files")
            files = sequences[seq_id].files
            if len(files) < window:
                raise UserError(f"official sequence {seq_id} has {len(files)} steps, fewer than the window {window}")
            self.items += [(files, seq_id, s) for s in range(0, len(files) - window + 1, stride)]
        self._files = _LazyFiles()

    def __len__(self) -> int:
        return len(self.items)

    def _read(self, path: Path, name: str) -> np.ndarray:
        from dsr_bench.dataset.official import check_dataset

        f = self._files.get(path)
        if name not in f:
            raise UserError(f"{path}: missing dataset {name!r}; is this an official DSR step file?")
        check_dataset(path, name, f[name])
        return f[name][()]

    def __getitem__(self, index: int) -> dict:
        files, seq_id, s = self.items[index]
        paths = files[s:s + self.window]
        out: dict = {"sequence": seq_id, "start": s}
        for field in self.fields:
            value = np.stack([self._read(p, field) for p in paths])
            if field == "action":
                out[field] = action_map(check_actions(value, GRID_SHAPE[:2], paths[0]))
            elif field == "mask_3d":
                out[field] = torch.from_numpy(np.ascontiguousarray(value, dtype=np.uint8))
            elif field == "scene_flow_3d":
                out[field] = torch.from_numpy(np.ascontiguousarray(np.moveaxis(value, -1, 1), dtype=np.float32))
            else:
                out[field] = torch.from_numpy(value.astype(np.float32))
        return out


_COMPACT = ("action", "scene_flow_3d")


def collate_compact(items: list[dict]) -> dict:
    """Batch window items like `default_collate`, except two fields in compact form:

    action_index (B, L) int64: flat index of each step's one-hot entry in its (8, Y, X) map;
    flow_index (N,) int64: flat indices into (B, L, Y * X * Z) of the voxels with non-zero flow, and
    flow_value (N, 3) float32: their flow (dy, dx, dz) in voxels. Other fields as default_collate."""
    batch = default_collate([{k: v for k, v in item.items() if k not in _COMPACT} for item in items])
    if "action" in items[0]:
        indices = []
        for item in items:
            flat = item["action"].numpy().reshape(len(item["action"]), -1)  # (L, 8 * Y * X)
            index = flat.argmax(1)
            if not (np.all(flat.sum(1) == 1) and np.all(flat[np.arange(len(flat)), index] == 1)):
                raise ValueError("action maps must be one-hot (one entry per step) to be sent as indices")
            indices.append(index)
        batch["action_index"] = torch.from_numpy(np.stack(indices))
        batch["action_shape"] = tuple(items[0]["action"].shape[1:])
    if "scene_flow_3d" in items[0]:
        shape = (len(items),) + tuple(items[0]["scene_flow_3d"].shape)  # (B, L, 3, Y, X, Z)
        per_sample = shape[1] * int(np.prod(shape[3:]))
        index, value = [], []
        for b, item in enumerate(items):  # numpy: about 5x faster than torch.nonzero here
            flow = item["scene_flow_3d"].numpy().reshape(shape[1], 3, -1)
            moving = np.flatnonzero((flow[:, 0] != 0) | (flow[:, 1] != 0) | (flow[:, 2] != 0))
            step, voxel = np.divmod(moving, flow.shape[-1])
            index.append(moving + b * per_sample)
            value.append(flow[step, :, voxel])
        batch["flow_index"] = torch.from_numpy(np.concatenate(index).astype(np.int64))
        batch["flow_value"] = torch.from_numpy(np.concatenate(value).astype(np.float32, copy=False))
        batch["flow_shape"] = shape
    return batch


def batch_to_device(batch: dict, device) -> dict:
    """The model fields of a batch (dense, or from `collate_compact`) as dense tensors on `device`:
    tsdf, action (B, L, 8, Y, X) one-hot, mask_3d (uint8), scene_flow_3d (B, L, 3, Y, X, Z); copies
    from pinned memory do not block the host."""
    device = torch.device(device)
    nb = device.type == "cuda"
    out = {k: batch[k].to(device, non_blocking=nb) for k in TRAINING_FIELDS if k in batch}
    if "action_index" in batch:
        index = batch["action_index"].to(device, non_blocking=nb)
        plane = tuple(batch["action_shape"])  # (the DataLoader's pinning turns tuples into lists)
        action = torch.zeros(*index.shape, int(np.prod(plane)), device=device)
        action.scatter_(-1, index.unsqueeze(-1), 1.0)
        out["action"] = action.reshape(*index.shape, *plane)
    if "flow_index" in batch:
        shape = tuple(batch["flow_shape"])
        voxels = int(np.prod(shape[3:]))
        index = batch["flow_index"].to(device, non_blocking=nb)
        flow = torch.zeros(shape[0] * shape[1], 3, voxels, device=device)
        flow[index // voxels, :, index % voxels] = batch["flow_value"].to(device, non_blocking=nb)
        out["scene_flow_3d"] = flow.reshape(shape)
    return out
