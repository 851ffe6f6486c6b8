"""The ground truth as the metrics read it: digests that `evaluate` recomputes while it scores.

A named split's pin (`split_pins.json`) holds, per sequence, `scored`: one digest (SHA-256, first 32 hex digits)
of each input of the metrics, defined on the values the metrics use and on nothing else, so that `evaluate` can
recompute them from the arrays it reads anyway, at a small fraction of a full hash's cost (most of the 3D flow is
zero, and the TSDF enters the score only as the surface band at object voxels). A sequence whose recomputed
digests differ from its pin is a different benchmark, whatever digest attributes its file carries.

Over the steps t = 0..T-1 that are scored (T pushes), each field hashes a header (its name, dtype, shape and the
rule) and then, per step, `t:` and:

- `objects`: the number of objects and the canonical JSON of the object list (once);
- `mask_3d`: the flat C-order indices (int32) of the non-zero voxels of `mask_3d[t]`, then their values (uint8);
- `tsdf`: the surface band `TSDF_SURFACE_LOW < tsdf[t] < 0` at those voxels, in that order (`np.packbits`);
- `scene_flow_3d`: the flat indices (int32) of the Z columns of `scene_flow_3d[t]` (shape (3, Y, X), a column
  being the Z run of one component at one (y, x)) holding any non-zero byte, then those columns' bytes;
- `visible_fraction`: the whole array's bytes (once);
- `mask_2d`: the bytes of the front camera's `mask[t]`;
- `scene_flow_2d`: the bytes of the front camera's `scene_flow_2d[t]` at the pixels where `mask[t]` > 0.

Array bytes are little-endian. `file_scored_digests` computes them from a file in the plain way (what pins are
made with); `evaluate` feeds a `ScoredDigests` step by step, and a test holds the two equal.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from dsr_bench.constants import TSDF_SURFACE_LOW
from dsr_bench.dataset.arraybytes import le_contiguous, nonzero_rows
from dsr_bench.dataset.sequence import SequenceReader

#: what a pin's `scored` entry holds, in this order
SCORED_FIELDS = ("objects", "mask_3d", "tsdf", "scene_flow_3d", "visible_fraction", "mask_2d", "scene_flow_2d")
#: hex digits of SHA-256 kept per digest (128 bits)
DIGEST_HEX = 32
FRONT_MASK, FRONT_FLOW_2D = "cameras/front/mask", "cameras/front/scene_flow_2d"


def _bytes(a: np.ndarray):
    return le_contiguous(a).reshape(-1).view(np.uint8)


def _dtype(a: np.ndarray) -> str:
    """The little-endian dtype string of an array's values, as hashed (`'<f4'`, `'|u1'`)."""
    return np.asarray(a).dtype.newbyteorder("<").str


def surface_band(tsdf_values: np.ndarray) -> np.ndarray:
    """Whether TSDF values lie in the metrics' visible surface band (TSDF_SURFACE_LOW, 0)."""
    return (tsdf_values > TSDF_SURFACE_LOW) & (tsdf_values < 0)


class ScoredDigests:
    """The `scored` digests of one sequence, fed step by step in step order (see the module's text); each step's
    part starts with its index, so a sequence fed other steps, or fewer, has other digests."""

    def __init__(self) -> None:
        self._hashers: dict[str, hashlib._Hash] = {}
        self._steps: dict[str, int] = {}

    def _start(self, field: str, header: str):
        if field not in self._hashers:
            self._hashers[field] = hashlib.sha256(f"{field}|{header}|".encode())
            self._steps[field] = 0
        return self._hashers[field]

    def _step(self, field: str, header: str, t: int):
        h = self._start(field, header)
        self._steps[field] += 1
        h.update(f"{t}:".encode())
        return h

    def objects(self, num_objects: int, objects: list) -> None:
        self._start("objects", "count+json").update(
            f"{int(num_objects)}|".encode() + json.dumps(objects, sort_keys=True).encode())

    def mask_step(self, t: int, mask: np.ndarray, index: np.ndarray) -> None:
        """mask: mask_3d[t] (Y, X, Z); index: the flat indices of its non-zero voxels."""
        h = self._step("mask_3d", f"{_dtype(mask)}|{mask.shape}|nonzero", t)
        h.update(_bytes(index.astype(np.int32)))
        h.update(_bytes(mask.reshape(-1)[index]))

    def tsdf_step(self, t: int, tsdf: np.ndarray, index: np.ndarray) -> None:
        """tsdf: tsdf[t] (Y, X, Z); index: the flat indices of mask_3d[t]'s non-zero voxels."""
        h = self._step("tsdf", f"{_dtype(tsdf)}|{tsdf.shape}|band-at-objects|{TSDF_SURFACE_LOW}", t)
        h.update(np.packbits(surface_band(tsdf.reshape(-1)[index])).tobytes())

    def flow_step(self, t: int, flow: np.ndarray, columns: np.ndarray | None = None) -> None:
        """flow: scene_flow_3d[t] (3, Y, X, Z); columns: which of its Z columns are non-zero, (3, Y, X) bool, when
        the reader knows it already (computed here otherwise)."""
        h = self._step("scene_flow_3d", f"{_dtype(flow)}|{flow.shape}|nonzero-z-columns", t)
        rows = flow.reshape(-1, flow.shape[-1])
        keep = np.flatnonzero(nonzero_rows(rows) if columns is None else columns.reshape(-1))
        h.update(_bytes(keep.astype(np.int32)))
        h.update(_bytes(rows[keep]))

    def visible_fraction(self, values: np.ndarray) -> None:
        self._start("visible_fraction", f"{_dtype(values)}|{values.shape}|all").update(_bytes(values))

    def mask_2d_step(self, t: int, mask: np.ndarray) -> None:
        self._step("mask_2d", f"{_dtype(mask)}|{mask.shape}|all", t).update(_bytes(mask))

    def flow_2d_step(self, t: int, flow: np.ndarray, mask: np.ndarray) -> None:
        """flow: scene_flow_2d[t] (H, W, 3); mask: the front camera's mask[t] (H, W)."""
        h = self._step("scene_flow_2d", f"{_dtype(flow)}|{flow.shape}|at-mask", t)
        h.update(_bytes(flow[mask > 0]))

    def hexdigests(self) -> dict[str, str]:
        """{field: digest} of the fields fed, each with the number of steps it was fed (`field@T`) folded in."""
        return {f: hashlib.sha256(f"{h.hexdigest()}@{self._steps[f]}".encode()).hexdigest()[:DIGEST_HEX]
                for f, h in self._hashers.items()}


def file_scored_digests(path: str | Path) -> dict[str, str]:
    """The `scored` digests of a sequence file, read plainly (every field the file can feed: the 2D ones only
    where it has the front camera's mask and 2D flow, `visible_fraction` where present)."""
    d = ScoredDigests()
    with SequenceReader(path) as seq:
        steps = seq.num_steps
        d.objects(seq.num_objects, seq.objects)
        for t in range(steps):
            mask = seq.read("mask_3d", t)
            index = np.flatnonzero(mask)
            d.mask_step(t, mask, index)
            d.tsdf_step(t, seq.read("tsdf", t), index)
            d.flow_step(t, seq.read("scene_flow_3d", t))
        if "visible_fraction" in seq:
            d.visible_fraction(seq.read("visible_fraction"))
        if FRONT_MASK in seq and FRONT_FLOW_2D in seq:
            for t in range(steps):
                mask_2d = seq.read(FRONT_MASK, t)
                d.mask_2d_step(t, mask_2d)
                d.flow_2d_step(t, seq.read(FRONT_FLOW_2D, t), mask_2d)
    return d.hexdigests()


def differing_fields(recomputed: Mapping[str, str], pinned: Mapping[str, str]) -> list[str]:
    """The fields of `recomputed` whose digest differs from (or is missing in) the pinned ones, in order."""
    return [f for f in SCORED_FIELDS if f in recomputed and recomputed[f] != pinned.get(f)]
