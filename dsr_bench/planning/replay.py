"""Plans replayed: nothing a plan file says it did is believed. The simulator is deterministic bit for bit on any
x86-64 CPU (the generator's guarantee, `tests/test_reproducibility.py`), so the task's start and a plan's executed
pushes determine every state that followed; the seeds (`--seed`, the task's seed) and what the planner observed
determine every candidate; the costs determine the push that was chosen.

  replay_problem   the first way a plan file's contents differ from its replay, or None: every stored state (object
                   poses, amodal masks, TSDF, colour image) against the simulator's replay of its executed pushes; the
                   candidates against the ones the seeds draw around the stored planner masks in the replayed TSDFs;
                   each executed push against the candidate chosen, the choice against the costs and the margin, the
                   chosen candidate's cost and terms against its stored predicted masks; the stored scores against
                   the ones recomputed from the replayed final state
  load_simulator   the simulator's replay function, registered by the generator under the `dsr_bench.simulators`
                   entry point (this library never imports the generator)

Not replayed (a planner's network is not run again): the costs of the candidates that were not chosen and the
planner's masks, recorded as the planner gave them; the seconds, self-reported.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np

from dsr_bench.errors import UserError

#: The entry-point group through which the generator lends the library its simulator (`pyproject.toml`).
SIMULATORS_GROUP = "dsr_bench.simulators"
#: The entry point of the plan replay: `(task, actions (S, 3)) -> [WorldState] * (S + 1)`.
PLAN_REPLAY = "plan-replay"

Replay = Callable[..., list]


def load_simulator() -> Replay:
    """The simulator's plan replay (`generators.planning.replay_plan`, found through its entry point), or a
    UserError naming what to install."""
    from importlib.metadata import entry_points

    found = list(entry_points(group=SIMULATORS_GROUP, name=PLAN_REPLAY))
    if not found:
        raise UserError("replaying plans needs the toolkit's simulator, which is not registered in this installation; "
                        "reinstall dsr-bench (`pip install -e '.[sim]'` in its checkout, or `bash scripts/setup.sh`)")
    try:
        replay = found[0].load()
        import pybullet  # noqa: F401 - the simulator's engine, imported when a world is built
    except ImportError as exc:
        raise UserError(f"replaying plans needs the simulator ({exc.name or 'pybullet'} is not installed); "
                        "pip install 'dsr-bench[sim]'") from None
    return replay


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and bool(np.array_equal(a, b))


def _state_problem(plan: Mapping[str, np.ndarray], states: Sequence) -> str | None:
    fields = (("states/object_poses", "object_poses"), ("states/mask_3d", "mask_3d"), ("states/tsdf", "tsdf"),
              ("states/color", "color"))
    for s, state in enumerate(states):
        for name, field in fields:
            ours = getattr(state, field)
            if ours is None and name not in plan:
                continue
            if name not in plan or len(plan[name]) != len(states) or ours is None or \
                    not _same(np.asarray(plan[name][s]), np.asarray(ours)):
                return (f"{name}[{s}] is not what the task's start and the plan's executed pushes give when replayed "
                        "(an edited state or action)")
    return None


def _step_problem(plan: Mapping[str, np.ndarray], attrs: Mapping, task, states: Sequence) -> str | None:
    """The first step whose candidates, choice or chosen cost differ from what the seeds and costs give."""
    from dsr_bench.planning.cost import TargetStats, plan_cost
    from dsr_bench.planning.runner import choose, step_candidates

    steps = len(states) - 1
    predicts = attrs.get("model") != "random"
    rng = np.random.default_rng([int(attrs["seed"]), int(task.seed)])
    candidates, costs, clear = plan["candidates"], plan["costs"], plan["clear"]
    chosen, actions, masks, predicted = plan["chosen"], plan["actions"], plan["planner_masks"], plan["predicted"]
    terms_pos, terms_iou = plan["cost_position_mse"], plan["cost_iou"]
    n = task.num_objects
    width = max(1, int(attrs["candidates"])) if predicts else 1
    if candidates.shape[:2] != costs.shape or candidates.shape[0] != steps or candidates.shape[1] < width or \
            clear.shape != costs.shape or chosen.shape != (steps,) or masks.shape[0] != steps or \
            predicted.shape[0] != steps or terms_pos.shape != costs.shape + (n,) or terms_iou.shape != terms_pos.shape:
        return "its candidates, costs, choices or masks are not one record per step and candidate"
    stats = TargetStats.of(task.target_mask, n)
    for s in range(steps):
        acts, is_clear = step_candidates(states[s].tsdf, masks[s] if predicts else None, rng, predicts,
                                         int(attrs["candidates"]), int(attrs["clear"]))
        k = len(acts)
        if not (_same(candidates[s, :k], acts) and _same(clear[s, :k], is_clear) and not candidates[s, k:].any()
                and not clear[s, k:].any() and np.isnan(costs[s, k:]).all()):
            return (f"step {s}: its candidates are not the ones its seeds draw around its planner masks in the "
                    "replayed state (an edited candidate, mask or seed)")
        c = int(chosen[s])
        if not 0 <= c < k or not _same(actions[s], acts[c]):
            return f"step {s}: the executed push is not the candidate it says it chose"
        if not predicts:
            if c != 0 or not np.isnan(costs[s]).all() or masks[s].any() or predicted[s].any():
                return f"step {s}: a random plan with costs, masks or a prediction"
            continue
        if not np.isfinite(costs[s, :k]).all() or c != choose(costs[s, :k], is_clear, float(attrs["margin"])):
            return f"step {s}: the executed push is not the one its costs and margin choose"
        slots = max(int(predicted[s].max(initial=0)), 1)
        terms = plan_cost(predicted[s], task.target_mask, slots, n, float(attrs["lambda"]), stats)
        if terms.total != costs[s, c] or not (_same(terms.position_mse, terms_pos[s, c])
                                              and _same(terms.iou, terms_iou[s, c])):
            return f"step {s}: the chosen push's cost is not the cost of its stored predicted masks"
    return None


def replay_problem(plan: Mapping[str, np.ndarray], attrs: Mapping, task, states: Sequence,
                   scores: Mapping) -> str | None:
    """The first way a plan file (`plan`: its arrays, `attrs`: its attributes) of `task` differs from the replay
    (`states`: the simulator's states from the task's start through the plan's executed pushes; `scores`: the
    scores recomputed from the replayed final state), as a phrase for `PlanMismatch`, or None (module doc)."""
    from dsr_bench.planning.verify import SCORE_KEYS

    problem = _state_problem(plan, states) or _step_problem(plan, attrs, task, states)
    if problem:
        return problem
    for key in SCORE_KEYS + ("iou_per_object",):
        if attrs.get(key) != scores[key]:
            return f"its stored {key} is not the score of its replayed final state (an edited record)"
    return None
