"""Push policies of the generator: the paper's heuristic softmax policy (official details by default)
and a uniform random policy. A policy sees only what the real robot could: the top-down heightmap
(128x128, rows along world y, metres above the table) and the objects' world xy positions.

Object choice (heuristic): one counter per object, starting at 0; probabilities softmax(counters),
+0.5 for the optional large object. After an executed push the chosen counter += 1; a counter above
2 becomes -2, and one that reaches 2 becomes -2 with probability 0.5 (official code).

Direction choice, official scoring (default: the authors' generator, term by term), probabilities
softmax(score / 2), for unit direction v, the chosen object at p, its initial position p0, the
workspace centre c and o = c - p, u = o / |o|:
- towards the centre: + w (u . v) exp(|o_x| + |o_y|), w = 5 on the object's first push, 1 afterwards
  (rewards pushing towards the centre, more so the farther out the object is);
- far out: -10 for every direction with u . v < 0 once |o| > 0.2 m;
- each neighbour q with e = q - p, |e| < 0.15 m, cosine k = (e / |e|) . v: -3 k where k > 0.4;
  +1.5 where |k| < 0.3;
- back towards the start: once |p - p0|_1 > 1 mm, with g = (p - p0) / |p - p0|: + 1.5 (g . v) for the
  directions with g . v < 0 while |p - p0| < 0.25 m (a penalty);
- keep going: + 2 (v_last . v), v_last the direction this object was last pushed.
`scoring="paper"`: Q(v) = 1.5 cos(v, p - p0) + 2 cos(v, p - p_prev) with the -10 far-out penalty
and softmax(Q) (no temperature); p_prev is the object's position before its latest push.

Start point (official): p - 0.04 m along v, stepped back by 0.01 m up to 5 times, until the disc of
radius 5 cells around it is free (heightmap <= 5 mm) and something taller than 5 mm lies within
0.04 m ahead of it along v; otherwise object and direction are drawn again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dsr_bench.constants import (
    AHEAD_DISTANCE,
    FREE_HEIGHT,
    GRID_SHAPE,
    NUM_DIRECTIONS,
    POLICY_COUNTER_MAX,
    POLICY_COUNTER_RESET,
    POLICY_DIRECTION_TEMPERATURE,
    POLICY_EARLY_RESET_PROB,
    POLICY_FAR_FROM_CENTER,
    POLICY_LARGE_OBJECT_BONUS,
    POLICY_MAX_SAMPLES,
    POLICY_NEAR_START_DISTANCE,
    POLICY_NEIGHBOUR_DISTANCE,
    POLICY_OUTWARD_PENALTY,
    START_BACKOFF,
    START_FREE_RADIUS_PX,
    START_MAX_STEPS,
    START_STEP,
    VOXEL_SIZE,
    WORKSPACE_CENTER,
)
from dsr_bench.geometry import direction_vector, dot_last, pixel_to_world, vector_norm, world_to_pixel

POLICIES = ("heuristic", "random")
SCORINGS = ("official", "paper")
#: Unit push directions (8, 2) in world xy, angle d * pi / 4.
DIRECTIONS = direction_vector(np.arange(NUM_DIRECTIONS))
# Official direction-score weights and thresholds (the authors' generator).
CENTRE_WEIGHT_FIRST, CENTRE_WEIGHT_LATER = 5.0, 1.0
NEIGHBOUR_WEIGHT, PERPENDICULAR_BONUS = 3.0, 1.5
#: A neighbour is "ahead" above this cosine and "beside" below this absolute cosine.
NEIGHBOUR_AHEAD_COS, NEIGHBOUR_BESIDE_COS = 0.4, 0.3
AWAY_FROM_START_WEIGHT, CONTINUE_WEIGHT = 1.5, 2.0
#: L1 distance (m) an object must have moved from its start before the start term applies.
MOVED_FROM_START = 0.001

_HW = np.array(GRID_SHAPE[:2])
_R = START_FREE_RADIUS_PX
_DISC = np.argwhere(np.hypot(*np.mgrid[-_R:_R + 1, -_R:_R + 1]) <= _R) - _R  # (D, 2) cell offsets
#: Distances (m) sampled along the ray ahead of a start point: every half cell up to AHEAD_DISTANCE.
_AHEAD = np.arange(1, int(round(AHEAD_DISTANCE / (VOXEL_SIZE / 2))) + 1) * (VOXEL_SIZE / 2)
_BACKOFFS = START_BACKOFF + START_STEP * np.arange(START_MAX_STEPS + 1)


@dataclass(frozen=True)
class PushDecision:
    """A push chosen by a policy, with the distributions it was drawn from.

    direction: 0..7, angle d * pi / 4 in world xy; start_rc: (row, col) workspace cell, row along
    world y; start_xy: (2,) world metres, that cell's centre; attempts: draws until this one was valid.
    """

    object_index: int
    direction: int
    start_rc: tuple[int, int]
    start_xy: np.ndarray
    object_probs: np.ndarray
    direction_scores: np.ndarray
    direction_probs: np.ndarray
    attempts: int


def softmax(x: np.ndarray) -> np.ndarray:
    """Numerically stable softmax of a 1-D array, the same bits on every CPU: glibc's exp element by
    element (numpy's exp is vectorised differently per instruction set) and a left-to-right sum."""
    x = np.asarray(x, dtype=np.float64)
    z = np.array([math.exp(v) for v in (x - np.max(x)).tolist()])
    total = 0.0
    for v in z.tolist():
        total += v
    return z / total


def _unit(v: np.ndarray) -> np.ndarray:
    """v / |v| for a (2,) vector; zeros when |v| is (nearly) zero."""
    n = vector_norm(v)
    return v / n if n > 1e-9 else np.zeros_like(v)


def _any_taller(heightmap: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Whether any in-grid cell of cells (..., M, 2) (row, col) is taller than FREE_HEIGHT: (...,)."""
    inside = np.all((cells >= 0) & (cells < _HW), axis=-1)
    clipped = np.clip(cells, 0, _HW - 1)
    return np.any((heightmap[clipped[..., 0], clipped[..., 1]] > FREE_HEIGHT) & inside, axis=-1)


def find_start(heightmap: np.ndarray, object_xy: np.ndarray,
               direction: int) -> tuple[tuple[int, int], np.ndarray] | None:
    """The official start-point search for pushing the object at object_xy along a direction.

    heightmap: (128, 128) metres above the table, rows along world y; object_xy: (2,) world metres.
    Returns ((row, col), (2,) cell-centre xy in metres) of the first of the 6 candidates (0.04 m
    behind the object, then 0.01 m further back each) that lies in the grid, has a free disc of
    radius 5 cells and something taller than 5 mm within 0.04 m ahead; None if none does.
    """
    v = DIRECTIONS[direction]
    rc = world_to_pixel(np.asarray(object_xy, dtype=np.float64) - _BACKOFFS[:, None] * v)  # (S, 2)
    inside = np.all((rc >= 0) & (rc < _HW), axis=-1)
    disc_blocked = _any_taller(heightmap, rc[:, None, :] + _DISC)  # (S,)
    centres = pixel_to_world(rc)  # (S, 2)
    ahead = world_to_pixel(centres[:, None, :] + _AHEAD[:, None] * v)  # (S, A, 2)
    valid = inside & ~disc_blocked & _any_taller(heightmap, ahead)
    if not valid.any():
        return None
    i = int(np.argmax(valid))
    return (int(rc[i, 0]), int(rc[i, 1])), centres[i]


class PushPolicy:
    """Base class: object choice, direction choice, start-point search; state changes only in accept()."""

    name = "base"

    def __init__(self, rng: np.random.Generator, num_objects: int, large_index: int | None = None):
        if num_objects < 1:
            raise ValueError(f"num_objects={num_objects}: a policy needs at least one object")
        if large_index is not None and not 0 <= large_index < num_objects:
            raise ValueError(f"large_index={large_index}: must be None or in 0..{num_objects - 1}")
        self.rng, self.num_objects, self.large_index = rng, int(num_objects), large_index
        self.initial = np.zeros((self.num_objects, 2))
        self.previous = np.zeros((self.num_objects, 2))
        self.before_push = np.zeros((self.num_objects, 2))
        self.last_direction = np.full(self.num_objects, -1, dtype=np.int64)  # -1: not pushed yet
        self.pushes = np.zeros(self.num_objects, dtype=np.int64)

    def _positions(self, positions: np.ndarray, what: str) -> np.ndarray:
        p = np.asarray(positions, dtype=np.float64)
        if p.shape != (self.num_objects, 2) or not np.all(np.isfinite(p)):
            raise ValueError(f"{what}: expected finite ({self.num_objects}, 2) world xy, got shape {p.shape}")
        return p

    def reset(self, initial_positions: np.ndarray) -> None:
        """Start an episode from the objects' xy positions (N, 2) in world metres at t = 0."""
        self.initial = self._positions(initial_positions, "initial_positions").copy()
        self.previous = self.initial.copy()
        self.before_push = self.initial.copy()
        self.last_direction[:] = -1
        self.pushes[:] = 0

    def object_probs(self) -> np.ndarray:
        """(N,) probabilities of choosing each object."""
        raise NotImplementedError

    def direction_scores(self, k: int, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(8,) scores and (8,) probabilities of the directions for object k at positions (N, 2)."""
        raise NotImplementedError

    def propose(self, heightmap: np.ndarray, positions: np.ndarray) -> PushDecision | None:
        """Draw a valid push; None if none is found in POLICY_MAX_SAMPLES draws.

        heightmap: (128, 128) metres above the table, rows along world y, columns along world x;
        positions: (N, 2) current object xy (m). Draws from the rng only; the policy state is unchanged.
        """
        hm = np.asarray(heightmap)
        if hm.shape != GRID_SHAPE[:2] or not np.all(np.isfinite(hm)):
            raise ValueError(f"heightmap: expected finite {GRID_SHAPE[:2]} metres, got shape {hm.shape}")
        positions = self._positions(positions, "positions")
        probs = self.object_probs()
        for attempt in range(1, POLICY_MAX_SAMPLES + 1):
            k = int(self.rng.choice(self.num_objects, p=probs))
            scores, dprobs = self.direction_scores(k, positions)
            d = int(self.rng.choice(NUM_DIRECTIONS, p=dprobs))
            start = find_start(hm, positions[k], d)
            if start is not None:
                return PushDecision(k, d, start[0], start[1], probs, scores, dprobs, attempt)
        return None

    def accept(self, decision: PushDecision, positions_after: np.ndarray) -> None:
        """The simulator executed this push; positions_after: (N, 2) xy (m) after it."""
        k = decision.object_index
        after = self._positions(positions_after, "positions_after")
        self.before_push[k] = self.previous[k]
        self.last_direction[k] = decision.direction
        self.pushes[k] += 1
        self.previous = after.copy()


class HeuristicPolicy(PushPolicy):
    """The paper's heuristic softmax policy; scoring "official" (default) or "paper" (appendix Q(v))."""

    name = "heuristic"

    def __init__(self, rng: np.random.Generator, num_objects: int, large_index: int | None = None,
                 scoring: str = "official"):
        super().__init__(rng, num_objects, large_index)
        if scoring not in SCORINGS:
            raise ValueError(f"scoring {scoring!r}: choose one of {', '.join(SCORINGS)}")
        self.scoring = scoring
        self.counters = np.zeros(self.num_objects, dtype=np.int64)

    def reset(self, initial_positions: np.ndarray) -> None:
        super().reset(initial_positions)
        self.counters[:] = 0

    def object_probs(self) -> np.ndarray:
        scores = self.counters.astype(np.float64)
        if self.large_index is not None:
            scores[self.large_index] += POLICY_LARGE_OBJECT_BONUS
        return softmax(scores)

    def direction_scores(self, k: int, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # The order of the float operations below is part of the bit-exact dataset reproduction
        # (pinned split digests): change it only together with re-pinning.
        positions = np.asarray(positions, dtype=np.float64)
        p = positions[k]
        if self.scoring == "paper":
            out = p - np.asarray(WORKSPACE_CENTER)
            scores = (AWAY_FROM_START_WEIGHT * dot_last(DIRECTIONS, _unit(p - self.initial[k]))
                      + CONTINUE_WEIGHT * dot_last(DIRECTIONS, _unit(p - self.before_push[k])))
            if float(vector_norm(out)) >= POLICY_FAR_FROM_CENTER:
                scores = scores - POLICY_OUTWARD_PENALTY * (dot_last(DIRECTIONS, _unit(out)) > 0)
            return scores, softmax(scores)
        o = np.asarray(WORKSPACE_CENTER) - p
        towards = dot_last(DIRECTIONS, _unit(o))  # (8,) u . v
        weight = CENTRE_WEIGHT_FIRST if self.pushes[k] == 0 else CENTRE_WEIGHT_LATER
        scores = weight * towards * math.exp(abs(float(o[0])) + abs(float(o[1])))
        if float(vector_norm(o)) > POLICY_FAR_FROM_CENTER:
            scores = scores - POLICY_OUTWARD_PENALTY * (towards < 0)
        for j in range(self.num_objects):
            e = positions[j] - p
            if j == k or float(vector_norm(e)) >= POLICY_NEIGHBOUR_DISTANCE:
                continue
            cos = dot_last(DIRECTIONS, _unit(e))
            scores = (scores - NEIGHBOUR_WEIGHT * np.where(cos > NEIGHBOUR_AHEAD_COS, cos, 0.0)
                      + PERPENDICULAR_BONUS * (np.abs(cos) < NEIGHBOUR_BESIDE_COS))
        moved = p - self.initial[k]
        if abs(float(moved[0])) + abs(float(moved[1])) > MOVED_FROM_START and \
                float(vector_norm(moved)) < POLICY_NEAR_START_DISTANCE:
            g = dot_last(DIRECTIONS, _unit(moved))
            scores = scores + AWAY_FROM_START_WEIGHT * np.where(g < 0, g, 0.0)
        if self.last_direction[k] >= 0:
            scores = scores + CONTINUE_WEIGHT * dot_last(DIRECTIONS, DIRECTIONS[self.last_direction[k]])
        return scores, softmax(scores / POLICY_DIRECTION_TEMPERATURE)

    def accept(self, decision: PushDecision, positions_after: np.ndarray) -> None:
        super().accept(decision, positions_after)
        k = decision.object_index
        self.counters[k] += 1
        if self.counters[k] > POLICY_COUNTER_MAX or (
                self.counters[k] == POLICY_COUNTER_MAX and self.rng.random() < POLICY_EARLY_RESET_PROB):
            self.counters[k] = POLICY_COUNTER_RESET


class RandomPolicy(PushPolicy):
    """Uniform object and direction, with the same start-point validity search."""

    name = "random"

    def object_probs(self) -> np.ndarray:
        return np.full(self.num_objects, 1.0 / self.num_objects)

    def direction_scores(self, k: int, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.full(NUM_DIRECTIONS, np.nan), np.full(NUM_DIRECTIONS, 1.0 / NUM_DIRECTIONS)


def make_policy(name: str, rng: np.random.Generator, num_objects: int, large_index: int | None = None,
                scoring: str = "official") -> PushPolicy:
    """A policy by name: "heuristic" (the paper's; scoring "official" or "paper") or "random"."""
    if name == "heuristic":
        return HeuristicPolicy(rng, num_objects, large_index, scoring=scoring)
    if name == "random":
        return RandomPolicy(rng, num_objects, large_index)
    raise ValueError(f"unknown policy {name!r}: choose one of {', '.join(POLICIES)}")
