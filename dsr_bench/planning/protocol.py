"""The planning track's constants, the state a planner observes, and the one `Planner` protocol.

Volumes are (world y, world x, z) = (128, 128, 48) voxels of 4 mm (`dsr_bench.constants.GRID_SHAPE`);
actions are (direction 0..7, row, col) on the 128 x 128 workspace grid (`dsr_bench.geometry.grid`).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

# The track's constants live with the benchmark's others (`dsr_bench.constants`, "Planning track").
from dsr_bench.constants import (CLEAR_CANDIDATES, CLEAR_SWEEP_CELLS, COST_LAMBDA, DEFAULT_BATCH,  # noqa: E402,F401
                                 DEFAULT_CANDIDATES, FOOTPRINT_MIN_Z, MATCH_TIE_BREAK, MAX_BACKOFF_CELLS, PLAN_MARGIN,
                                 PLAN_STEPS, UNMATCHED_POSITION_MSE)

#: Where a learned planner's masks of the current state come from (`dsr-bench plan --masks`): the network's mask
#: head ("model"), or the objects the TSDF shows (`dsr_bench.planning.observed`), each voxel moved by the network's
#: motion at it ("observed").
PLANNER_MASKS: tuple[str, ...] = ("model", "observed")


class Planner(Protocol):
    """A planner of the track: it observes the front camera's TSDF and predicts the next amodal masks of
    candidate actions. `predicts=False` (random): candidates are drawn uniformly and never scored.

    Order of calls per task: reset(); then per step observe(tsdf) -> masks to sample around (or None for
    uniform sampling), predict(actions) (any number of batches), executed(action)."""

    name: str
    description: str
    predicts: bool
    num_slots: int
    #: the cost an object push must beat the best clear push by (`dsr_bench.planning.runner.choose`)
    margin: float

    def reset(self) -> None:
        """Forget the history: a new task starts."""

    def observe(self, tsdf: np.ndarray) -> np.ndarray | None:
        """The front camera's TSDF (Y, X, Z) float32 of the current state -> the planner's amodal masks of it,
        (Y, X, Z) uint8 slot ids (0 background), or None (sample uniformly)."""

    def predict(self, actions: np.ndarray) -> np.ndarray:
        """Candidate actions (B, 3) int64 (d, row, col) -> predicted next amodal masks (B, Y, X, Z) uint8,
        slot ids 1..num_slots (0 background), from the state last observed."""

    def executed(self, action: np.ndarray) -> None:
        """The action (3,) was executed in the world: carry the history to the next observation."""
