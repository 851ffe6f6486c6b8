"""The MPC loop of the track: for each of PLAN_STEPS steps, observe (the front camera's TSDF), sample
candidate actions (around the planner's masks and CLEAR_CANDIDATES clear pushes that touch nothing seen, or one
uniformly), score each by the cost of its predicted next state against the target, execute the cheapest, repeat.
A push of an object is executed only when its predicted cost beats the best clear push's by the planner's
`margin` (cost units: an IoU of 1 is 1): the plan keeps the scene when no push is predicted to bring it
closer to the target by more than what the model's error can explain (pushes are never skipped: a clear
push is the plan's way of leaving the scene as it is). The world is an `Environment` (the
simulator implements it in `generators.planning`); this module imports no simulator.

Randomness: candidates are drawn from numpy's Generator seeded with (--seed, the task's seed), the same for
every planner, so a plan is a pure function of (task, planner, candidates, seed) up to the model's floating
point.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from dsr_bench.planning.cost import SparseLabels, TargetStats, plan_cost
from dsr_bench.planning.protocol import CLEAR_CANDIDATES, COST_LAMBDA, DEFAULT_BATCH, PLAN_STEPS
from dsr_bench.planning.sampling import free_cells, sample_around_masks, sample_clear, sample_uniform, tsdf_footprint
from dsr_bench.planning.tasks import Task


@dataclass
class WorldState:
    """What the world shows after a reset or a push: the front camera's TSDF (Y, X, Z) float32, the true amodal
    masks (Y, X, Z) uint8 (object ids; recorded and scored, never shown to a learned planner), the object poses
    (N, 7) and the front camera's colour image (H, W, 3) uint8 (for the viewer)."""

    tsdf: np.ndarray
    mask_3d: np.ndarray
    object_poses: np.ndarray
    color: np.ndarray | None = None


class Environment(Protocol):
    """A world a plan runs in (the simulator's: `generators.planning.SimEnvironment`)."""

    def reset(self, task: Task) -> WorldState:
        """Restore the task's start state."""

    def step(self, action: np.ndarray) -> WorldState:
        """Execute the push (d, row, col) and observe."""


@dataclass
class PlanRecord:
    """Everything a plan did, as the plan file stores it (`dsr_bench.planning.plans`)."""

    states: list[WorldState] = field(default_factory=list)  # PLAN_STEPS + 1: the start, then after each push
    actions: list[np.ndarray] = field(default_factory=list)  # (3,) chosen per step
    candidates: list[np.ndarray] = field(default_factory=list)  # (C, 3) per step
    costs: list[np.ndarray] = field(default_factory=list)  # (C,) per step (NaN: not scored)
    position_mse: list[np.ndarray] = field(default_factory=list)  # (C, N) cm^2
    object_iou: list[np.ndarray] = field(default_factory=list)  # (C, N)
    chosen: list[int] = field(default_factory=list)
    clear: list[np.ndarray] = field(default_factory=list)  # (C,) bool per step: the candidate is a clear push
    planner_masks: list[np.ndarray] = field(default_factory=list)  # (Y, X, Z) the masks sampled around per step
    predicted: list[np.ndarray] = field(default_factory=list)  # (Y, X, Z) the chosen candidate's predicted next masks
    seconds: list[float] = field(default_factory=list)  # planning (not simulation) seconds per step


def predicted_labels(planner, actions: np.ndarray) -> list[SparseLabels]:
    """A planner's predicted next masks of actions (B, 3) as `SparseLabels`: its `predict_labels` where it has one
    (learned models: no dense volumes), else its dense `predict`."""
    if hasattr(planner, "predict_labels"):
        return planner.predict_labels(actions)
    return [SparseLabels.of(p) for p in planner.predict(actions)]


def choose(costs: np.ndarray, clear: np.ndarray, margin: float) -> int:
    """The executed candidate: the cheapest push of an object if its cost (C,) is below the cheapest clear push's
    (`clear` (C,) bool) minus `margin`, else the cheapest clear push (the cheapest of all when there is none of
    one kind)."""
    pushes, keeps = np.flatnonzero(~clear), np.flatnonzero(clear)
    if len(keeps) == 0 or len(pushes) == 0:
        return int(np.argmin(costs))
    push, keep = pushes[np.argmin(costs[pushes])], keeps[np.argmin(costs[keeps])]
    return int(push if costs[push] < costs[keep] - margin else keep)


def step_candidates(tsdf: np.ndarray, masks: np.ndarray | None, rng: np.random.Generator, predicts: bool,
                    candidates: int, clear: int) -> tuple[np.ndarray, np.ndarray]:
    """One step's candidates (C, 3) int64 (d, row, col) and whether each is a clear push (C,) bool, drawn from `rng`
    in the plan's order: for a planner that predicts nothing one uniform push on a free cell of what the TSDF
    (Y, X, Z) sees; else up to `clear` clear pushes (at most `candidates` - 1), then the rest around `masks`
    (Y, X, Z), the clear ones last. A replay draws them again from the same seeds (`dsr_bench.planning.replay`)."""
    footprint = tsdf_footprint(tsdf)
    if not predicts:
        return sample_uniform(free_cells(footprint), rng, 1), np.zeros(1, bool)
    if masks is None:
        raise ValueError("a planner that predicts must give the masks to sample around")
    keep = sample_clear(footprint, rng, min(clear, candidates - 1))
    acts = np.concatenate([sample_around_masks(masks, rng, candidates - len(keep)), keep])
    return acts, np.arange(len(acts)) >= len(acts) - len(keep)


def run_plan(task: Task, planner, env: Environment, candidates: int, seed: int = 0, batch: int = DEFAULT_BATCH,
             lam: float = COST_LAMBDA, steps: int = PLAN_STEPS, margin: float = 0.0,
             clear: int = CLEAR_CANDIDATES) -> PlanRecord:
    """Plan and execute `steps` pushes from the task's start towards its target, with `clear` of the `candidates`
    clear pushes and an object push's `margin` over them (see the module doc)."""
    rng = np.random.default_rng([int(seed), int(task.seed)])
    n = task.num_objects
    target = task.target_mask
    stats = TargetStats.of(target, n)
    record = PlanRecord()
    state = env.reset(task)
    record.states.append(state)
    planner.reset()
    zeros = np.zeros_like(target)
    for _ in range(steps):
        start = time.perf_counter()
        masks = planner.observe(state.tsdf)
        acts, is_clear = step_candidates(state.tsdf, masks, rng, planner.predicts, candidates, clear)
        if not planner.predicts:
            costs, pos, iou = np.full(1, np.nan), np.full((1, n), np.nan), np.full((1, n), np.nan)
            best, best_pred = 0, zeros
        else:
            costs = np.zeros(len(acts))
            pos, iou = np.zeros((len(acts), n)), np.zeros((len(acts), n))
            cheapest: dict[bool, tuple[int, SparseLabels]] = {}  # per kind (clear or not): the cheapest so far
            for lo in range(0, len(acts), batch):
                for j, pred in enumerate(predicted_labels(planner, acts[lo: lo + batch])):
                    terms = plan_cost(pred, target, planner.num_slots, n, lam, stats)
                    costs[lo + j], pos[lo + j], iou[lo + j] = terms.total, terms.position_mse, terms.iou
                    kind = bool(is_clear[lo + j])
                    if kind not in cheapest or terms.total < costs[cheapest[kind][0]]:
                        cheapest[kind] = (lo + j, pred)
            best = choose(costs, is_clear, margin)
            best_pred = cheapest[bool(is_clear[best])][1].dense()
        action = acts[best]
        planner.executed(action)
        record.seconds.append(time.perf_counter() - start)
        state = env.step(action)
        record.states.append(state)
        record.actions.append(action)
        record.candidates.append(acts)
        record.costs.append(costs)
        record.position_mse.append(pos)
        record.object_iou.append(iou)
        record.chosen.append(int(best))
        record.clear.append(is_clear)
        record.planner_masks.append(zeros if masks is None else np.asarray(masks, np.uint8))
        record.predicted.append(best_pred)
    return record
