"""The track's planners, all behind `dsr_bench.planning.protocol.Planner`:

- `random`: one uniformly drawn valid action per step, never scored (the lower bound);
- `oracle`: the true next state of every candidate, from a simulator callback (the upper bound of the cost);
  the library never imports the simulator: `generators.planning` passes the callbacks in;
- learned models (`dsr`, `single`, `nowarp`, `3dflow`, ...): `dsr_bench.models.predictors.load_predictor`
  and `dsr_bench.planning.learned.BatchedModel`; several at once (`3dflow,single,dsr`), an ensemble planning with
  the mean of their motions (`dsr_bench.planning.learned.MotionEnsemble`).
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
    """A learned model's predictions (`dsr_bench.planning.learned.BatchedModel`), or with `others` an ensemble:
    the first model's objects moved by the mean of every model's motion (`dsr_bench.planning.learned.MotionEnsemble`;
    named `mean(first, ...)`, its `weights` a list, one record per model)."""

    predicts = True
    margin = PLAN_MARGIN

    def __init__(self, predictor, masks: str = "model", others: tuple = ()):
        from dsr_bench.planning.learned import BatchedModel, MotionEnsemble

        self.predictor = predictor
        self.masks = masks
        members = (predictor, *others)
        name = f"mean({', '.join(p.name for p in members)})" if others else predictor.name
        self.name = name if masks == "model" else f"{name}+{masks}"
        description = (f"the mean motion of {len(members)} models ({'; '.join(p.description for p in members)}) "
                       f"moving the objects of {predictor.name}") if others else predictor.description
        self.description = description + ("" if masks == "model" else
                                          "; the current state's objects from the TSDF's geometry")
        self.num_slots = predictor.num_slots
        weights = [getattr(p, "weights", None) for p in members]
        self.weights = weights if others else weights[0]
        #: the grid the (first) network works on (y, x, z), recorded in the results and shown on the leaderboard
        self.grid = tuple(getattr(predictor, "grid", ()))
        first = BatchedModel(predictor, masks)
        # the other members' labels are never used: only their motion at the first's voxels
        self._model = MotionEnsemble([first, *(BatchedModel(p) for p in others)]) if others else first

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


def planner_members(name: str, checkpoint: Path | None = None) -> list[str]:
    """The models a `--model` value names: one planner (random, oracle, a learned model) or a comma-separated
    ensemble of different learned models (e.g. `3dflow,single,dsr`, each with its shipped weights: no
    `checkpoint`); a one-line UserError otherwise."""
    from dsr_bench.models.predictors import IMAGE_MODELS, LEARNED_MODELS

    members = name.split(",")
    choose = f"choose one of {', '.join(PLANNER_NAMES)}, or several learned ones separated by commas (an ensemble)"
    for member in members:
        if member in IMAGE_MODELS:
            raise UserError(f"--model {member}: the 2D track's models predict image flow, not the 3D masks a plan is "
                            f"scored on; {choose}")
        if member == "gtwarp":
            raise UserError(f"--model {member}: gtwarp needs ground-truth flow, which a plan has not; {choose}")
        if member not in PLANNER_NAMES or (len(members) > 1 and member not in LEARNED_MODELS):
            raise UserError(f"--model {name!r}: {member!r} is not a planner; {choose}")
    if len(set(members)) != len(members):
        raise UserError(f"--model {name!r}: a model is named twice; an ensemble names different models "
                        "(e.g. 3dflow,single,dsr)")
    if len(members) > 1 and checkpoint is not None:
        raise UserError(f"--checkpoint {checkpoint}: an ensemble (--model {name}) plans with each model's shipped "
                        "weights; give one model to plan with a checkpoint")
    return members


def make_planner(name: str, oracle_callbacks: tuple[Callable, Callable] | None = None,
                 checkpoint: Path | None = None, device: str = "cpu", masks: str = "model"):
    """A planner by name (`planner_members`). `oracle` needs `oracle_callbacks` = (current, simulate) from a
    simulator; a learned model loads `checkpoint` or, without one, the shipped CPU-track weights, and takes its
    masks of the current state from `masks` (`dsr_bench.planning.protocol.PLANNER_MASKS`); an ensemble
    (`3dflow,single,dsr`) loads each model's shipped weights."""
    if masks not in PLANNER_MASKS:
        raise UserError(f"--masks {masks!r}: choose one of {', '.join(PLANNER_MASKS)}")
    members = planner_members(name, checkpoint)
    if masks != "model" and name in ("random", "oracle"):
        raise UserError(f"--masks {masks}: only a learned model's masks can be replaced ({name} has none to replace)")
    if name == "random":
        return RandomPlanner()
    if name == "oracle":
        if oracle_callbacks is None:
            raise UserError("--model oracle needs the simulator: run it through `dsr-bench plan`")
        return OraclePlanner(*oracle_callbacks)
    from dsr_bench.models.predictors import load_predictor

    first, *others = (load_predictor(member, checkpoint, device) for member in members)
    return LearnedPlanner(first, masks, tuple(others))
