"""A small per-process cache of read-only arrays computed from constant inputs (a camera, a grid), shared by
the TSDF's voxel projections and the renderer's table views: building them costs more than using them."""

from __future__ import annotations

from collections.abc import Callable, Hashable

import numpy as np


class FrozenCache:
    """At most `size` entries, the oldest dropped first; each value (an array or a tuple of arrays) is made
    read-only when stored, so callers can share it safely."""

    def __init__(self, size: int):
        self.size = size
        self._store: dict[Hashable, object] = {}

    def get(self, key: Hashable, build: Callable[[], object]):
        """The value for `key`, built (and frozen) on first use."""
        hit = self._store.get(key)
        if hit is None:
            hit = build()
            for array in hit if isinstance(hit, tuple) else (hit,):
                array.setflags(write=False)
            if len(self._store) >= self.size:
                self._store.pop(next(iter(self._store)))
            self._store[key] = hit
        return hit


def camera_key(camera) -> tuple:
    """A hashable key of a camera's size, intrinsics and extrinsics."""
    return (camera.height, camera.width, np.asarray(camera.intrinsics, np.float64).tobytes(),
            np.asarray(camera.extrinsics, np.float64).tobytes())
