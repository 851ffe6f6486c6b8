"""The track's planners, all behind `dsr_bench.planning.protocol.Planner`:

- `random`: one uniformly drawn valid action per step, never scored (the lower bound);
- `oracle`: the true next state of every candidate, from a simulator callback (the upper bound of the cost);
  the library never imports the simulator: `generators.planning` passes the callbacks in;
- learned models (`dsr`, `single`, `nowarp`, `3dflow`, ...): `dsr_bench.models.predictors.load_predictor`
  and `dsr_bench.planning.learned.BatchedModel`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from dsr_bench.constants import MAX_OBJECTS_PER_SCENE, PLAN_MARGIN
from dsr_bench.errors import UserError
from dsr_bench.planning.protocol import PLANNER_MASKS

PLANNER_NAMES = ("random", "oracle", "dsr", "single", "nowarp", "3dflow")


class RandomPlanner:
    """A uniformly random valid action per step (start on a free cell of what the TSDF sees)."""

    name, predicts, num_slots, margin = "random", False, 0, 0.0
    description = "random: a uniformly drawn valid push per step (lower bound)"

    def reset(self) -> None:
        pass

    def observe(self, tsdf: np.ndarray) -> None:
        return None

    def predict(self, actions: np.ndarray) -> np.ndarray:
        raise RuntimeError("the random planner predicts nothing")

    def executed(self, action: np.ndarray) -> None:
        pass


class OraclePlanner:
    """The true next state of each candidate: `current()` gives the world's amodal masks (Y, X, Z) uint8 (object
    ids), `simulate(actions (B, 3))` the masks (B, Y, X, Z) uint8 after each action from the current state,
    leaving the world as it was (the simulator restores its saved state after each)."""

    name, predicts, num_slots = "oracle", True, MAX_OBJECTS_PER_SCENE
    margin = 0.0  # its predictions are the outcomes: any predicted gain is a true one
    description = "oracle: candidates scored on the simulator's true next states (upper bound)"

    def __init__(self, current: Callable[[], np.ndarray], simulate: Callable[[np.ndarray], np.ndarray]):
        self._current, self._simulate = current, simulate

    def reset(self) -> None:
        pass

    def observe(self, tsdf: np.ndarray) -> np.ndarray:
        return self._current()

    def predict(self, actions: np.ndarray) -> np.ndarray:
        return self._simulate(np.asarray(actions, np.int64).reshape(-1, 3))

    def executed(self, action: np.ndarray) -> None:
        pass


class LearnedPlanner:
    """A learned model's predictions (`dsr_bench.planning.learned.BatchedModel`)."""

    predicts = True
    margin = PLAN_MARGIN

    def __init__(self, predictor, masks: str = "model"):
        from dsr_bench.planning.learned import BatchedModel

        self.predictor = predictor
        self.masks = masks
        self.name = predictor.name if masks == "model" else f"{predictor.name}+{masks}"
        self.description = predictor.description + ("" if masks == "model" else
                                                    "; the current state's objects from the TSDF's geometry")
        self.num_slots = predictor.num_slots
        self.weights = getattr(predictor, "weights", None)
        #: the grid the network works on (y, x, z), recorded in the results and shown on the leaderboard
        self.grid = tuple(getattr(predictor, "grid", ()))
        self._model = BatchedModel(predictor, masks)

    def reset(self) -> None:
        self._model.reset()

    def observe(self, tsdf: np.ndarray) -> np.ndarray:
        return self._model.observe(tsdf)

    def predict(self, actions: np.ndarray) -> np.ndarray:
        return self._model.predict(actions)

    def predict_labels(self, actions: np.ndarray) -> list:
        """`predict` as `dsr_bench.planning.cost.SparseLabels` (the runner's path: no dense volumes)."""
        return self._model.predict_labels(actions)

    def executed(self, action: np.ndarray) -> None:
        self._model.executed(action)


def make_planner(name: str, oracle_callbacks: tuple[Callable, Callable] | None = None,
                 checkpoint: Path | None = None, device: str = "cpu", masks: str = "model"):
    """A planner by name. `oracle` needs `oracle_callbacks` = (current, simulate) from a simulator; a learned
    model loads `checkpoint` or, without one, the shipped CPU-track weights, and takes its masks of the current
    state from `masks` (`dsr_bench.planning.protocol.PLANNER_MASKS`)."""
    if masks not in PLANNER_MASKS:
        raise UserError(f"--masks {masks!r}: choose one of {', '.join(PLANNER_MASKS)}")
    if masks != "model" and name in ("random", "oracle"):
        raise UserError(f"--masks {masks}: only a learned model's masks can be replaced ({name} has none to replace)")
    if name == "random":
        return RandomPlanner()
    if name == "oracle":
        if oracle_callbacks is None:
            raise UserError("--model oracle needs the simulator: run it through `dsr-bench plan`")
        return OraclePlanner(*oracle_callbacks)
    from dsr_bench.models.predictors import IMAGE_MODELS, LEARNED_MODELS, load_predictor

    if name in IMAGE_MODELS:
        raise UserError(f"--model {name}: the 2D track's models predict image flow, not the 3D masks a plan is scored "
                        f"on; choose one of {', '.join(PLANNER_NAMES)}")
    if name not in LEARNED_MODELS or name == "gtwarp":
        raise UserError(f"--model {name!r}: choose one of {', '.join(PLANNER_NAMES)} (gtwarp needs ground-truth "
                        "flow, which a plan has not)")
    return LearnedPlanner(load_predictor(name, checkpoint, device), masks)
