"""Push policies: the heuristic softmax policy of the paper's appendix (official details) and a
uniform random policy. A policy sees only what the real robot could: the top-down heightmap and the
objects' xy positions.

Object choice: each object has a counter (start 0); choice probabilities are softmax(counters, +0.5
for the optional large object); after a push the chosen counter += 1, and a counter above 2, or above
1 with probability 0.5 (official code), becomes -2. Locally this pushes an object about twice in a
row; globally it balances the objects.

Direction choice (official scoring, softmax(score / 2)), for unit direction v and the chosen object
at p (initial position p0, centre c = workspace centre):
- out of centre: -w * max(0, v . (p - c) / |p - c|) * min(1, |p - c| / 0.2), w = 5 on the object's
  first push and 1 afterwards;
- neighbours closer than 0.15 m: -3 * max(0, cos(v, towards neighbour)), and +1.5 for the two
  directions perpendicular to it (within 22.5 deg);
- +1.5 * cos(v, p - p0) while the object is within 0.25 m of where it started;
- +2 * cos(v, last direction this object was pushed);
- and, as in the appendix, -10 for directions with an outward component when |p - c| >= 0.2 m.
`scoring="paper"` uses the appendix's Q(v) = 1.5 v.(p0->p) + 2 v.(p_prev->p) (unit vectors) with
-10 for outward directions when |p - c| >= 0.2 and softmax(Q).

Start point (official): p - 0.04 m along v, stepped back 0.01 m up to 5 times, until a 5-cell-radius
disc of the heightmap is free (<= 5 mm) and something taller than 5 mm lies within 0.04 m ahead;
otherwise object and direction are sampled again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dsr_bench.constants import (
    AHEAD_DISTANCE, FREE_HEIGHT, GRID_SHAPE, NUM_DIRECTIONS, POLICY_DIRECTION_TEMPERATURE, POLICY_FAR_FROM_CENTER,
    START_BACKOFF, START_FREE_RADIUS_PX, START_MAX_STEPS, START_STEP, VOXEL_SIZE, WORKSPACE_CENTER,
)
from dsr_bench.geometry import direction_vector, pixel_to_world, world_to_pixel

MAX_SAMPLES = 64
NEIGHBOUR_DISTANCE = 0.15
NEAR_START_DISTANCE = 0.25
LARGE_OBJECT_BONUS = 0.5
PERPENDICULAR_COS = np.sin(np.pi / 8)  # the two directions within 22.5 deg of perpendicular
DIRECTIONS = direction_vector(np.arange(NUM_DIRECTIONS))  # (8, 2)
_DISC = np.argwhere(np.hypot(*np.mgrid[-START_FREE_RADIUS_PX:START_FREE_RADIUS_PX + 1,
                                       -START_FREE_RADIUS_PX:START_FREE_RADIUS_PX + 1]) <= START_FREE_RADIUS_PX
                    ) - START_FREE_RADIUS_PX
_AHEAD_STEPS = np.arange(1, int(round(AHEAD_DISTANCE / (VOXEL_SIZE / 2))) + 1) * (VOXEL_SIZE / 2)


@dataclass(frozen=True)
class PushDecision:
    """A push chosen by a policy, with the distributions it was drawn from."""

    object_index: int
    direction: int
    start_rc: tuple[int, int]
    start_xy: np.ndarray
    object_probs: np.ndarray
    direction_scores: np.ndarray
    direction_probs: np.ndarray
    attempts: int


def softmax(x: np.ndarray) -> np.ndarray:
    z = np.exp(x - np.max(x))
    return z / z.sum()


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    return v / n if n > 1e-9 else np.zeros_like(v)


def find_start(heightmap: np.ndarray, object_xy: np.ndarray, direction: int) -> tuple[tuple[int, int], np.ndarray] | None:
    """The official start-point search: ((row, col), cell-centre xy) or None.

    heightmap: (Y, X) metres above the table, rows along world y; object_xy: (2,) world metres.
    """
    v = DIRECTIONS[direction]
    for k in range(START_MAX_STEPS + 1):
        start = object_xy - v * (START_BACKOFF + k * START_STEP)
        rc = world_to_pixel(start)
        if np.any(rc < 0) or np.any(rc >= GRID_SHAPE[:2]):
            continue
        disc = _DISC + rc
        disc = disc[np.all((disc >= 0) & (disc < GRID_SHAPE[:2]), axis=1)]
        if np.any(heightmap[disc[:, 0], disc[:, 1]] > FREE_HEIGHT):
            continue
        centre = pixel_to_world(rc)
        ahead = world_to_pixel(centre + _AHEAD_STEPS[:, None] * v)
        ahead = ahead[np.all((ahead >= 0) & (ahead < GRID_SHAPE[:2]), axis=1)]
        if ahead.size and np.any(heightmap[ahead[:, 0], ahead[:, 1]] > FREE_HEIGHT):
            return (int(rc[0]), int(rc[1])), centre
    return None


class PushPolicy:
    """Base class: object choice, direction choice and the start-point search."""

    name = "base"

    def __init__(self, rng: np.random.Generator, num_objects: int, large_index: int | None = None):
        self.rng, self.num_objects, self.large_index = rng, num_objects, large_index
        self.initial = np.zeros((num_objects, 2))
        self.previous = np.zeros((num_objects, 2))
        self.last_direction: list[int | None] = [None] * num_objects
        self.pushes = np.zeros(num_objects, dtype=np.int64)

    def reset(self, initial_positions: np.ndarray) -> None:
        """Start an episode from object xy positions (N, 2) in metres."""
        self.initial = np.array(initial_positions, dtype=np.float64)
        self.previous = self.initial.copy()
        self.last_direction = [None] * self.num_objects
        self.pushes[:] = 0

    def object_probs(self) -> np.ndarray:
        raise NotImplementedError

    def direction_scores(self, k: int, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def propose(self, heightmap: np.ndarray, positions: np.ndarray) -> PushDecision | None:
        """Sample a valid push (object, direction, start); None if none is found in MAX_SAMPLES draws."""
        probs = self.object_probs()
        for attempt in range(1, MAX_SAMPLES + 1):
            k = int(self.rng.choice(self.num_objects, p=probs))
            scores, dprobs = self.direction_scores(k, positions)
            d = int(self.rng.choice(NUM_DIRECTIONS, p=dprobs))
            start = find_start(heightmap, positions[k], d)
            if start is not None:
                return PushDecision(k, d, start[0], start[1], probs, scores, dprobs, attempt)
        return None

    def accept(self, decision: PushDecision, positions_after: np.ndarray) -> None:
        """Record an executed push (positions_after: (N, 2) xy after it)."""
        k = decision.object_index
        self.last_direction[k] = decision.direction
        self.pushes[k] += 1
        self.previous = np.array(positions_after, dtype=np.float64)


class HeuristicPolicy(PushPolicy):
    """The paper's heuristic softmax policy (official scoring by default)."""

    name = "heuristic"

    def __init__(self, rng, num_objects, large_index=None, scoring: str = "official"):
        super().__init__(rng, num_objects, large_index)
        if scoring not in ("official", "paper"):
            raise ValueError(f"scoring {scoring!r}: official or paper")
        self.scoring = scoring
        self.counters = np.zeros(num_objects)
        self._before_push = np.zeros((num_objects, 2))

    def reset(self, initial_positions):
        super().reset(initial_positions)
        self.counters[:] = 0
        self._before_push = self.initial.copy()

    def object_probs(self) -> np.ndarray:
        scores = self.counters.copy()
        if self.large_index is not None:
            scores[self.large_index] += LARGE_OBJECT_BONUS
        return softmax(scores)

    def direction_scores(self, k, positions):
        p = np.asarray(positions[k], dtype=np.float64)
        centre = np.array(WORKSPACE_CENTER)
        out = p - centre
        if self.scoring == "paper":
            from_start = _unit(p - self.initial[k])
            from_prev = _unit(p - self._before_push[k])
            scores = 1.5 * DIRECTIONS @ from_start + 2.0 * DIRECTIONS @ from_prev
            if np.linalg.norm(out) >= POLICY_FAR_FROM_CENTER:
                scores = scores - 10.0 * (DIRECTIONS @ _unit(out) > 0)
            return scores, softmax(scores)
        weight = 5.0 if self.pushes[k] == 0 else 1.0
        outward = DIRECTIONS @ _unit(out)
        scores = -weight * np.maximum(0.0, outward) * min(1.0, np.linalg.norm(out) / POLICY_FAR_FROM_CENTER)
        if np.linalg.norm(out) >= POLICY_FAR_FROM_CENTER:  # the appendix's guard, kept in both scorings
            scores = scores - 10.0 * (outward > 0)
        for j in range(self.num_objects):
            towards = positions[j] - p
            if j == k or np.linalg.norm(towards) >= NEIGHBOUR_DISTANCE:
                continue
            cos = DIRECTIONS @ _unit(towards)
            scores += -3.0 * np.maximum(0.0, cos) + 1.5 * (np.abs(cos) < PERPENDICULAR_COS)
        if np.linalg.norm(p - self.initial[k]) < NEAR_START_DISTANCE:
            scores += 1.5 * DIRECTIONS @ _unit(p - self.initial[k])
        if self.last_direction[k] is not None:
            scores += 2.0 * DIRECTIONS @ DIRECTIONS[self.last_direction[k]]
        temperature = POLICY_DIRECTION_TEMPERATURE
        return scores, softmax(scores / temperature)

    def accept(self, decision, positions_after):
        k = decision.object_index
        self._before_push[k] = np.asarray(self.previous[k])
        super().accept(decision, positions_after)
        self.counters[k] += 1
        if self.counters[k] > 2 or (self.counters[k] > 1 and self.rng.random() < 0.5):
            self.counters[k] = -2


class RandomPolicy(PushPolicy):
    """Uniform object and direction, with the same start-point validity search."""

    name = "random"

    def object_probs(self):
        return np.full(self.num_objects, 1.0 / self.num_objects)

    def direction_scores(self, k, positions):
        return np.full(NUM_DIRECTIONS, np.nan), np.full(NUM_DIRECTIONS, 1.0 / NUM_DIRECTIONS)


def make_policy(name: str, rng: np.random.Generator, num_objects: int, large_index: int | None = None) -> PushPolicy:
    """'heuristic' (the paper's, official scoring) or 'random'."""
    if name == "heuristic":
        return HeuristicPolicy(rng, num_objects, large_index)
    if name == "random":
        return RandomPolicy(rng, num_objects, large_index)
    raise ValueError(f"unknown policy {name!r}: heuristic or random")
