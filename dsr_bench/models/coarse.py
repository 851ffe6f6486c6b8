"""The CPU track's volumes: the benchmark's 128 x 128 x 48 grid pooled to coarse voxels and back.

The CPU track's models (`ModelConfig.voxel_factor` = 4) work on 16 mm voxels, `factor` benchmark
voxels along every axis, so a rigid motion in model voxels is a rigid motion in metres. The pooled
grid is (128/4, 128/4, 48/4) = (32, 32, 12), padded on top to (32, 32, 16) (four 2x downsamplings
need sides that are multiples of 16) with empty space: TSDF 1, background, zero flow. All functions
take the benchmark's axis order (y, x, z) with any leading axes, numpy in, numpy out:

- `pool_tsdf`: each block's mean TSDF.
- `pool_labels`: each block's most frequent object id when that object fills at least
  `MIN_BLOCK_FRACTION` of the block, else background (0).
- `pool_flow`: each coarse object voxel's mean flow over the fine voxels of its label, in model
  voxels (benchmark voxels / factor); zero on background.
- `coarse_action`: [d, row, col] with row and col divided (floor) by the factor.
- `unpool_mask`, `unpool_motion`: a coarse prediction back on the benchmark's grid, each fine voxel
  taking its block's value (nearest), motions in benchmark voxels (x factor), the padding dropped.

Predictions of these models are written and scored on the benchmark's grid like any other entry.
"""

from __future__ import annotations

import numpy as np

from dsr_bench.constants import GRID_SHAPE

#: The CPU track's factor: 4 benchmark voxels (4 mm) per model voxel along each axis (16 mm).
CPU_TRACK_FACTOR: int = 4
#: A coarse voxel belongs to an object that fills at least this fraction of its block (24 of 64 voxels: of
#: 1/4, 3/8 and 1/2, the best IoU of the ground truth pooled and brought back, 0.65, on novel-object scenes).
MIN_BLOCK_FRACTION: float = 3 / 8


def coarse_grid(factor: int) -> tuple[int, int, int]:
    """The model grid (y, x, z) for `factor`: the benchmark grid divided by it, each side rounded up to a
    multiple of 16 ((32, 32, 16) for 4)."""
    if factor < 1 or any(g % factor for g in GRID_SHAPE):
        raise ValueError(f"voxel factor {factor}: must divide the grid {GRID_SHAPE}")
    y, x, z = (-(-(g // factor) // 16) * 16 for g in GRID_SHAPE)
    return y, x, z


def _blocks(volume: np.ndarray, factor: int) -> np.ndarray:
    """(..., Y, X, Z) -> (..., Y/f, X/f, Z/f, f**3): each block's voxels on the last axis."""
    *lead, y, x, z = volume.shape
    if (y, x, z) != GRID_SHAPE:
        raise ValueError(f"volume {tuple(volume.shape)}: expected (..., {', '.join(map(str, GRID_SHAPE))})")
    f = factor
    b = volume.reshape(*lead, y // f, f, x // f, f, z // f, f)
    n = len(lead)
    b = np.moveaxis(b, [n + 1, n + 3, n + 5], [-3, -2, -1])
    return b.reshape(*lead, y // f, x // f, z // f, f ** 3)


def _pad_top(volume: np.ndarray, factor: int, fill) -> np.ndarray:
    """Pad the last axis up to the coarse grid's height with `fill`."""
    extra = coarse_grid(factor)[2] - volume.shape[-1]
    return np.pad(volume, [(0, 0)] * (volume.ndim - 1) + [(0, extra)], constant_values=fill)


def pool_tsdf(tsdf: np.ndarray, factor: int = CPU_TRACK_FACTOR) -> np.ndarray:
    """(..., 128, 128, 48) TSDF -> (..., 32, 32, 16) float32: block means, empty (1) above the volume."""
    return _pad_top(_blocks(np.asarray(tsdf, np.float32), factor).mean(-1, dtype=np.float32), factor, 1.0)


def _label_counts(mask: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Per block, the most frequent non-zero id and its voxel count (0, 0 for a block of background)."""
    blocks = _blocks(np.asarray(mask), factor)
    top = int(blocks.max(initial=0))
    counts = np.stack([(blocks == k).sum(-1) for k in range(1, top + 1)], -1) if top else \
        np.zeros(blocks.shape[:-1] + (1,), np.int64)
    best = counts.argmax(-1)
    return (best + 1) * (counts.max(-1) > 0), np.take_along_axis(counts, best[..., None], -1)[..., 0]


def pool_labels(mask: np.ndarray, factor: int = CPU_TRACK_FACTOR) -> np.ndarray:
    """(..., 128, 128, 48) object ids -> (..., 32, 32, 16) uint8 (see the module's docstring)."""
    label, count = _label_counts(mask, factor)
    keep = count >= MIN_BLOCK_FRACTION * factor ** 3
    return _pad_top(np.where(keep, label, 0).astype(np.uint8), factor, 0)


def pool_flow(flow: np.ndarray, mask: np.ndarray, factor: int = CPU_TRACK_FACTOR) -> np.ndarray:
    """Flow (..., 3, 128, 128, 48) in benchmark voxels and its mask (..., 128, 128, 48) -> (..., 3, 32, 32, 16)
    float32 in model voxels: the mean over the fine voxels of each coarse voxel's `pool_labels` id."""
    coarse = pool_labels(mask, factor)[..., :GRID_SHAPE[2] // factor]
    blocks_mask = _blocks(np.asarray(mask), factor)
    chosen = (blocks_mask == coarse[..., None]) & (coarse[..., None] > 0)  # (..., y, x, z, f^3)
    count = np.maximum(chosen.sum(-1), 1)
    flow = np.asarray(flow, np.float32)
    out = np.stack([(_blocks(flow[..., c, :, :, :], factor) * chosen).sum(-1) / count for c in range(3)], -4)
    return _pad_top((out / factor).astype(np.float32), factor, 0.0)


def coarse_action(action: np.ndarray, factor: int = CPU_TRACK_FACTOR) -> np.ndarray:
    """[d, row, col] (..., 3) on the benchmark's 128 x 128 action map -> the coarse map's [d, row // f, col // f]."""
    action = np.asarray(action).astype(np.int64)
    return np.concatenate([action[..., :1], action[..., 1:] // factor], -1)


def unpool_mask(mask: np.ndarray, factor: int = CPU_TRACK_FACTOR) -> np.ndarray:
    """(..., 32, 32, 16) -> (..., 128, 128, 48): every fine voxel takes its block's value."""
    z = GRID_SHAPE[2] // factor
    out = mask[..., :z]
    for axis in (-3, -2, -1):
        out = np.repeat(out, factor, axis)
    return out


def unpool_motion(motion: np.ndarray, factor: int = CPU_TRACK_FACTOR) -> np.ndarray:
    """(..., 3, 32, 32, 16) in model voxels -> (..., 3, 128, 128, 48) float32 in benchmark voxels."""
    return (unpool_mask(np.asarray(motion, np.float32), factor) * np.float32(factor)).astype(np.float32)
