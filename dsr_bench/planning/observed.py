"""The current state as the front camera's TSDF shows it: the objects' amodal voxels estimated from geometry.

A planner compares its prediction of the next state with the target, so it needs the objects of the current state,
whole (amodal) and apart. A network's masks can be coarse or merge objects (the CPU track's 16 mm DSR-Net: matched
IoU about 0.41 with the true amodal state on the validation tasks `plan-val`); the TSDF itself says where surfaces are:

- occupancy: each column (y, x) that holds a voxel of the surface band (-1 < tsdf < 0, just behind a surface the
  camera saw) at or above FOOTPRINT_MIN_Z is filled from the table (z = 0) up to the highest such voxel. Objects
  rest on the table and are seen from above and in front, so what lies under a seen surface is taken as solid;
- objects: the 26-connected components of that occupancy, the largest `max_objects` of at least
  MIN_OBSERVED_VOXELS voxels, labelled 1, 2, ... by decreasing size.

Objects that touch are one component, and an object split by an occlusion is two (the smaller may be dropped).
Nothing here is learned; `dsr_bench.planning.learned.BatchedModel` (masks="observed") gives these objects to a
network's motion head in place of its own masks, so the predicted motion (learned) moves whole observed objects.
"""

from __future__ import annotations

import numpy as np

from dsr_bench.constants import FOOTPRINT_MIN_Z

#: Components smaller than this (voxels of 4 mm: 0.5 cm^3) are noise of the surface band, not objects.
MIN_OBSERVED_VOXELS: int = 30


def observed_occupancy(tsdf: np.ndarray) -> np.ndarray:
    """TSDF (Y, X, Z) -> (Y, X, Z) bool: every column filled from z = 0 up to its highest surface-band voxel at or
    above FOOTPRINT_MIN_Z (see the module doc)."""
    t = np.asarray(tsdf, np.float32)
    band: np.ndarray = np.logical_and(t > -1, t < 0)
    band[:, :, :FOOTPRINT_MIN_Z] = False
    seen = np.any(band, axis=2)
    top = t.shape[2] - 1 - np.argmax(band[:, :, ::-1], axis=2)  # the highest band voxel of each column
    z = np.arange(t.shape[2])
    return seen[:, :, None] & (z[None, None, :] <= top[:, :, None])


def observed_objects(tsdf: np.ndarray, max_objects: int) -> np.ndarray:
    """TSDF (Y, X, Z) -> object labels (Y, X, Z) uint8: 0 empty, 1..max_objects the largest components of
    `observed_occupancy` (26-connected, at least MIN_OBSERVED_VOXELS voxels), by decreasing size."""
    from scipy import ndimage

    components, count = ndimage.label(observed_occupancy(tsdf), structure=np.ones((3, 3, 3), bool))
    sizes = np.bincount(components.reshape(-1), minlength=count + 1)[1:]
    order = np.argsort(-sizes, kind="stable")[:max_objects]
    order = order[sizes[order] >= MIN_OBSERVED_VOXELS]
    relabel = np.zeros(count + 1, np.uint8)
    relabel[order + 1] = np.arange(1, len(order) + 1)
    return relabel[components]


def slots_for(objects: np.ndarray, slot_labels: np.ndarray, num_slots: int) -> np.ndarray:
    """Observed objects (Y, X, Z) (ids 1..) relabelled as a network's slots (ids 1..num_slots): each object takes
    the slot it shares most voxels with in `slot_labels` (Y, X, Z) (the network's own labels), one object per slot
    (Hungarian); an object left over (more objects than slots) is dropped."""
    from dsr_bench.matching import assignment

    count = int(objects.max(initial=0))
    if count == 0:
        return np.zeros_like(objects)
    both = np.flatnonzero(objects)
    pairs = objects.reshape(-1)[both].astype(np.int64) * (num_slots + 1) + slot_labels.reshape(-1)[both]
    shared = np.bincount(pairs, minlength=(count + 1) * (num_slots + 1)).reshape(count + 1, num_slots + 1)[1:, 1:]
    rows, cols = assignment(shared.astype(np.float64))
    relabel = np.zeros(count + 1, np.uint8)
    relabel[rows + 1] = cols + 1
    return relabel[objects]
