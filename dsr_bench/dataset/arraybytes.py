"""The bytes of arrays as the digests and the storage layer see them: an array in little-endian C order
(`le_contiguous`) and which rows of one hold a non-zero byte (`nonzero_rows`).

numpy alone, and no other module of the dataset package: the digests (`digests`, `scored`) and the raw-chunk reader
(`storage`) both stand on it, so that storage need not know what is scored.
"""

from __future__ import annotations

from typing import cast

import numpy as np


def le_contiguous(a: np.ndarray) -> np.ndarray:
    """`a` as a C-contiguous little-endian array (no copy where it is one already)."""
    a = np.asarray(a)
    return np.ascontiguousarray(a.astype(a.dtype.newbyteorder("<"), copy=False))


def nonzero_rows(rows: np.ndarray) -> np.ndarray:
    """Which rows of a C-contiguous 2-D array hold any non-zero byte (-0.0 counts), as bool."""
    raw = np.ascontiguousarray(rows).view(np.uint8).reshape(rows.shape[0], -1)
    width = raw.shape[1]
    word = 8 if width % 8 == 0 else 4 if width % 4 == 0 else 1
    return cast(np.ndarray, raw.view({8: np.uint64, 4: np.uint32, 1: np.uint8}[word]).any(axis=1))  # 2-D: an array
