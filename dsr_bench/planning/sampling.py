"""Candidate actions (d, row, col) on the 128 x 128 workspace grid (rows along world y, columns along world x).

Around masks (the appendix: "we only sample around the masks"): a candidate picks an object slot uniformly
among the non-empty ones of the planner's current masks, a cell of that object's top-down footprint uniformly,
and a direction d uniformly in 0..7; its start is the first cell behind that cell (stepping back along -v one
cell at a time, up to MAX_BACKOFF_CELLS) that is free, so the push runs through the chosen cell of the object.
Uniform (the random planner): d uniform, the start uniform over the free cells.

A cell is free when no footprint cell lies within START_FREE_RADIUS_PX cells of it (the tool's approach from
above needs free space, as the heuristic policy's start search); a footprint cell is a column with an object
voxel at or above FOOTPRINT_MIN_Z. Every candidate lies inside the grid and on a free cell.
"""

from __future__ import annotations

import numpy as np

from dsr_bench.constants import GRID_SHAPE, NUM_DIRECTIONS, START_FREE_RADIUS_PX
from dsr_bench.geometry import direction_vector
from dsr_bench.planning.protocol import CLEAR_SWEEP_CELLS, FOOTPRINT_MIN_Z, MAX_BACKOFF_CELLS

_MAX_ROUNDS = 20


def footprints(mask: np.ndarray) -> np.ndarray:
    """Top-down footprint (Y, X) of a label volume (Y, X, Z): the largest id in each column above the table
    (0 where none)."""
    return np.asarray(mask)[:, :, FOOTPRINT_MIN_Z:].max(axis=2)


def tsdf_footprint(tsdf: np.ndarray) -> np.ndarray:
    """Top-down footprint (Y, X) bool of what a TSDF sees above the table: columns with a voxel of its surface
    band (-1 < tsdf < 0) at or above FOOTPRINT_MIN_Z."""
    t = np.asarray(tsdf)[:, :, FOOTPRINT_MIN_Z:]
    return np.any((t > -1) & (t < 0), axis=2)


def free_cells(occupied: np.ndarray) -> np.ndarray:
    """(Y, X) bool: cells with no occupied cell within START_FREE_RADIUS_PX cells (a disc)."""
    from scipy import ndimage

    r = START_FREE_RADIUS_PX
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    disc = yy * yy + xx * xx <= r * r
    return ~ndimage.binary_dilation(np.asarray(occupied, bool), structure=disc)


def sample_uniform(free: np.ndarray, rng: np.random.Generator, count: int) -> np.ndarray:
    """`count` actions (count, 3) int64: d uniform in 0..7, (row, col) uniform over the free cells (any cell if
    none is free)."""
    cells = np.argwhere(free)
    if len(cells) == 0:
        cells = np.argwhere(np.ones(GRID_SHAPE[:2], bool))
    pick = cells[rng.integers(0, len(cells), count)]
    return np.column_stack([rng.integers(0, NUM_DIRECTIONS, count), pick]).astype(np.int64)


def clear_pushes(occupied: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """(B,) bool: whether each action (B, 3) (d, row, col) sweeps only free cells (`free_cells` of `occupied`
    (Y, X)): every cell at 0, 1, ..., CLEAR_SWEEP_CELLS steps from its start along its direction, rounded, is
    free or off the grid (the workspace grid is all a TSDF sees). A clear push touches nothing that was seen."""
    acts = np.asarray(actions, np.int64).reshape(-1, 3)
    free = free_cells(occupied)
    v = direction_vector(acts[:, 0])[:, ::-1]  # (B, 2) as (d row, d col)
    steps = np.arange(CLEAR_SWEEP_CELLS + 1, dtype=np.float64)
    cells = np.rint(acts[:, None, 1:] + steps[None, :, None] * v[:, None, :]).astype(np.int64)  # (B, S, 2)
    inside = np.all((cells >= 0) & (cells < np.array(GRID_SHAPE[:2])), axis=-1)
    clipped = np.clip(cells, 0, np.array(GRID_SHAPE[:2]) - 1)
    return np.all(~inside | free[clipped[..., 0], clipped[..., 1]], axis=1)


def sample_clear(occupied: np.ndarray, rng: np.random.Generator, count: int) -> np.ndarray:
    """Up to `count` clear pushes (count', 3) int64 (`clear_pushes`): the candidates that move nothing, so that a
    plan can keep the scene as it is when no push is predicted to bring it closer to the target (a push is never
    skipped). Drawn as `sample_uniform` and kept when clear; fewer (possibly none) when the scene leaves no room."""
    if count <= 0:
        return np.zeros((0, 3), np.int64)
    free = free_cells(occupied)
    found: list[np.ndarray] = []
    have = 0
    for _ in range(_MAX_ROUNDS):
        acts = sample_uniform(free, rng, 4 * count)
        acts = acts[clear_pushes(occupied, acts)]
        found.append(acts)
        have += len(acts)
        if have >= count:
            break
    return np.concatenate(found)[:count].astype(np.int64)


def sample_around_masks(mask: np.ndarray, rng: np.random.Generator, count: int) -> np.ndarray:
    """`count` actions (count, 3) int64 (d, row, col) around the objects of a label volume (Y, X, Z) (see the
    module doc). Falls back to `sample_uniform` when the volume has no object above the table, and fills up
    uniformly when fewer than `count` pushes around the objects start on free cells."""
    top = footprints(mask)
    free = free_cells(top > 0)
    slots = [int(s) for s in np.unique(top) if s > 0]
    if not slots:
        return sample_uniform(free, rng, count)
    cells = [np.argwhere(top == s) for s in slots]
    steps = np.arange(1, MAX_BACKOFF_CELLS + 1, dtype=np.float64)
    found: list[np.ndarray] = []
    have = 0
    for _ in range(_MAX_ROUNDS):
        m = 2 * count
        which = rng.integers(0, len(slots), m)
        pick = np.array([cells[w][rng.integers(0, len(cells[w]))] for w in which.tolist()])  # (m, 2) row, col
        d = rng.integers(0, NUM_DIRECTIONS, m)
        v = direction_vector(d)[:, ::-1]  # (m, 2) as (d row, d col) = (dy, dx)
        back = np.rint(pick[:, None, :] - steps[None, :, None] * v[:, None, :]).astype(np.int64)  # (m, S, 2)
        inside = np.all((back >= 0) & (back < np.array(GRID_SHAPE[:2])), axis=-1)
        clipped = np.clip(back, 0, np.array(GRID_SHAPE[:2]) - 1)
        ok = inside & free[clipped[..., 0], clipped[..., 1]]
        valid = ok.any(axis=1)
        first = ok.argmax(axis=1)
        start = back[np.arange(m), first]
        actions = np.column_stack([d, start])[valid]
        found.append(actions)
        have += len(actions)
        if have >= count:
            break
    out = np.concatenate(found)[:count] if found else np.zeros((0, 3), np.int64)
    if len(out) < count:
        out = np.concatenate([out, sample_uniform(free, rng, count - len(out))])
    return out.astype(np.int64)
