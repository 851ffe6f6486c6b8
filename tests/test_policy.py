"""Push policies: counter dynamics, softmax, direction scores, start-point search, determinism, uniformity."""

import itertools

import numpy as np
import pytest

from dsr_bench.constants import FREE_HEIGHT, GRID_SHAPE, START_BACKOFF, START_FREE_RADIUS_PX, START_STEP, VOXEL_SIZE
from dsr_bench.geometry import direction_vector, pixel_to_world, world_to_pixel
from dsr_bench.generators.policy import (HeuristicPolicy, PushDecision, RandomPolicy, find_start, make_policy, softmax)

ROWS, COLS = np.meshgrid(np.arange(GRID_SHAPE[0]), np.arange(GRID_SHAPE[1]), indexing="ij")
CELL_XY = pixel_to_world(np.stack([ROWS, COLS], -1))  # (128, 128, 2) cell centres, world xy
ANGLES = np.arange(8) * np.pi / 4


def _heightmap_with_discs(centres_xy, radius=0.03, height=0.05):
    hm = np.zeros(GRID_SHAPE[:2], np.float32)
    for c in centres_xy:
        hm[np.linalg.norm(CELL_XY - np.asarray(c), axis=-1) <= radius] = height
    return hm


def _decision(k, direction=0):
    return PushDecision(k, direction, (0, 0), np.zeros(2), np.zeros(4), np.zeros(8), np.zeros(8), 1)


def _exact_consecutive_rate(n=4, bonus=None):
    """Stationary probability that the object pushed at a step is the one pushed at the step before, by
    exact Markov analysis of the counter rules written out independently of the implementation:
    probabilities softmax(counters + bonus); chosen counter + 1; 3 -> -2; 2 -> -2 with probability 0.5."""
    bonus = np.zeros(n) if bonus is None else np.asarray(bonus, float)
    states = list(itertools.product((-2, -1, 0, 1, 2), repeat=n))
    index = {s: i for i, s in enumerate(states)}
    transition = np.zeros((len(states), len(states)))
    moves = []  # (from, chosen, to, probability)
    for s in states:
        probs = softmax(np.array(s, float) + bonus)
        for k in range(n):
            c = s[k] + 1
            for value, weight in ([(-2, 1.0)] if c == 3 else [(-2, 0.5), (2, 0.5)] if c == 2 else [(c, 1.0)]):
                nxt = s[:k] + (value,) + s[k + 1:]
                transition[index[s], index[nxt]] += probs[k] * weight
                moves.append((s, k, nxt, probs[k] * weight))
    assert np.allclose(transition.sum(1), 1)
    a = np.vstack([transition.T - np.eye(len(states)), np.ones(len(states))])
    pi = np.linalg.lstsq(a, np.r_[np.zeros(len(states)), 1.0], rcond=None)[0]
    return sum(pi[index[s]] * p * softmax(np.array(nxt, float) + bonus)[k] for s, k, nxt, p in moves)


def _simulated_consecutive_rate(policy, steps, rng):
    chosen = []
    for _ in range(steps):
        k = int(rng.choice(policy.num_objects, p=policy.object_probs()))
        policy.accept(_decision(k), np.zeros((policy.num_objects, 2)))
        chosen.append(k)
    chosen = np.array(chosen)
    return np.mean(chosen[1:] == chosen[:-1])


# --- object choice ---------------------------------------------------------------------------------


def test_counter_dynamics_give_the_designed_consecutive_push_rate():
    expected = _exact_consecutive_rate(4)
    assert 0.35 < expected < 0.5  # the rules favour pushing the same object again (uniform choice: 0.25)
    rng = np.random.default_rng(0)
    policy = HeuristicPolicy(rng, 4)
    policy.reset(np.zeros((4, 2)))
    rate = _simulated_consecutive_rate(policy, 20000, rng)
    # 20000 correlated steps: standard error ~0.005; 0.02 is about four of them
    assert abs(rate - expected) < 0.02
    assert set(np.unique(policy.counters)) <= {-2, -1, 0, 1, 2}


def test_large_object_bonus_changes_the_rate_as_derived():
    bonus = np.array([0.0, 0.5, 0.0])
    expected = _exact_consecutive_rate(3, bonus)
    assert expected != pytest.approx(_exact_consecutive_rate(3), abs=1e-4)
    rng = np.random.default_rng(1)
    policy = HeuristicPolicy(rng, 3, large_index=1)
    policy.reset(np.zeros((3, 2)))
    assert np.allclose(policy.object_probs(), softmax(bonus))
    assert abs(_simulated_consecutive_rate(policy, 15000, rng) - expected) < 0.02


def test_counter_rules_step_by_step():
    policy = HeuristicPolicy(np.random.default_rng(0), 2)
    policy.reset(np.zeros((2, 2)))
    policy.accept(_decision(0), np.zeros((2, 2)))
    assert policy.counters.tolist() == [1, 0]
    assert np.allclose(policy.object_probs(), softmax(np.array([1.0, 0.0])))
    # from 1 the next push gives 2, reset to -2 about half of the time (official p = 0.5 rule)
    resets = 0
    for seed in range(400):
        p = HeuristicPolicy(np.random.default_rng(seed), 1)
        p.reset(np.zeros((1, 2)))
        p.accept(_decision(0), np.zeros((1, 2)))
        p.accept(_decision(0), np.zeros((1, 2)))
        assert p.counters[0] in (2, -2)
        resets += p.counters[0] == -2
        if p.counters[0] == 2:  # above 2 always resets
            p.accept(_decision(0), np.zeros((1, 2)))
            assert p.counters[0] == -2
    assert 160 < resets < 240  # binomial(400, 0.5): mean 200, sd 10


# --- direction choice ------------------------------------------------------------------------------


def test_official_direction_scores_match_the_terms():
    """Object 0.1 m along +x from the centre, started 0.05 m before (along -x), last pushed along +y, a
    neighbour 0.1 m along +y: every term of the authors' generator written out by hand."""
    policy = HeuristicPolicy(np.random.default_rng(0), 2)
    pos = np.array([[0.6, 0.0], [0.6, 0.1]])
    policy.reset(np.array([[0.55, 0.0], [0.6, 0.1]]))
    policy.accept(_decision(0, direction=2), pos)
    scores, probs = policy.direction_scores(0, pos)
    c, s = np.cos(ANGLES), np.sin(ANGLES)
    expected = (1.0 * -c * np.exp(0.1)  # towards the centre (-x), weight 1 after the first push, exp(|o_x| + |o_y|)
                - 3.0 * np.where(s > 0.4, s, 0) + 1.5 * (np.abs(s) < 0.3)  # neighbour along +y
                + 1.5 * np.minimum(c, 0)  # back towards the start (-x) is penalised, within 0.25 m of it
                + 2.0 * s)  # keep going along +y
    assert np.allclose(scores, expected)
    assert np.allclose(probs, softmax(expected / 2.0)) and np.isclose(probs.sum(), 1)


def test_first_push_rewards_the_centre_five_times_more():
    pos = np.array([[0.65, 0.0]])  # 0.15 m along +x from the centre
    policy = HeuristicPolicy(np.random.default_rng(0), 1)
    policy.reset(pos)
    first, probs = policy.direction_scores(0, pos)
    assert np.allclose(first, -5.0 * np.cos(ANGLES) * np.exp(0.15))
    assert np.argmax(probs) == 4  # towards the centre
    policy.accept(_decision(0, direction=4), pos)  # pushed along -x, did not move
    later, _ = policy.direction_scores(0, pos)
    assert np.allclose(later, -1.0 * np.cos(ANGLES) * np.exp(0.15) + 2.0 * np.cos(ANGLES - np.pi))


@pytest.mark.parametrize("scoring", ["official", "paper"])
def test_outward_directions_are_unlikely_far_from_centre(scoring):
    policy = HeuristicPolicy(np.random.default_rng(0), 1, scoring=scoring)
    far = np.array([[0.5, 0.22]])  # 0.22 m along +y from the centre
    policy.reset(far)
    _, probs = policy.direction_scores(0, far)
    assert probs[[1, 2, 3]].sum() < 0.01  # directions with a +y component
    near = np.array([[0.5, 0.18]])
    policy.reset(near)
    _, probs_near = policy.direction_scores(0, near)
    assert probs_near[[1, 2, 3]].sum() > probs[[1, 2, 3]].sum() * 10


def test_last_direction_is_favoured():
    policy = HeuristicPolicy(np.random.default_rng(0), 1)
    p = np.array([[0.5, 0.0]])
    policy.reset(p)
    _, before = policy.direction_scores(0, p)
    assert np.allclose(before, 1 / 8)  # at the centre, at its start, no neighbours: uniform
    policy.accept(_decision(0, direction=2), p)
    scores, probs = policy.direction_scores(0, p)
    assert np.allclose(scores, 2.0 * np.sin(ANGLES))
    assert np.argmax(probs) == 2 and probs[2] > probs[1] > probs[0] > probs[6]


def test_neighbours_repel_ahead_and_favour_beside():
    policy = HeuristicPolicy(np.random.default_rng(0), 3)
    pos = np.array([[0.5, 0.0], [0.6, 0.0], [0.5, -0.2]])  # a neighbour 0.1 m along +x; one 0.2 m away
    policy.reset(pos)
    scores, _ = policy.direction_scores(0, pos)
    c = np.cos(ANGLES)
    assert np.allclose(scores, -3.0 * np.where(c > 0.4, c, 0) + 1.5 * (np.abs(c) < 0.3))
    assert np.argmax(scores) in (2, 6) and scores[0] == scores.min()


def test_moving_back_towards_the_start_is_penalised_only_near_it():
    policy = HeuristicPolicy(np.random.default_rng(0), 1)
    policy.reset(np.array([[0.5, 0.0]]))
    near = np.array([[0.5, 0.1]])  # moved 0.1 m along +y
    scores, _ = policy.direction_scores(0, near)
    towards = -np.cos(ANGLES) * 0.0 + (-1.0) * np.sin(ANGLES)  # centre is along -y: u . v = -sin
    expected = 5.0 * towards * np.exp(0.1) + 1.5 * np.minimum(np.sin(ANGLES), 0)
    assert np.allclose(scores, expected)
    far = np.array([[0.5, 0.0]])
    policy.reset(np.array([[0.5, -0.26]]))  # 0.26 m from its start: the term is gone
    scores, _ = policy.direction_scores(0, far)
    assert np.allclose(scores, 0.0)


def test_paper_scoring_is_the_appendix_q():
    policy = HeuristicPolicy(np.random.default_rng(0), 2, scoring="paper")
    policy.reset(np.array([[0.5, 0.0], [0.55, 0.0]]))  # the close neighbour plays no part in Q(v)
    policy.accept(_decision(0, 2), np.array([[0.5, 0.1], [0.55, 0.0]]))  # moved +y
    policy.accept(_decision(1, 0), np.array([[0.5, 0.1], [0.6, 0.0]]))  # another object
    pos = np.array([[0.6, 0.1], [0.6, 0.0]])
    policy.accept(_decision(0, 0), pos)  # moved +x: p0 -> p along 45 deg, p_prev -> p along +x
    scores, probs = policy.direction_scores(0, pos)
    q = 1.5 * np.cos(ANGLES - np.pi / 4) + 2.0 * np.cos(ANGLES)
    assert np.allclose(scores, q) and np.allclose(probs, softmax(q))
    with pytest.raises(ValueError, match="scoring"):
        HeuristicPolicy(np.random.default_rng(0), 2, scoring="greedy")


# --- start-point search ----------------------------------------------------------------------------


def _disc_free(hm, rc):
    d = np.hypot(ROWS - rc[0], COLS - rc[1]) <= START_FREE_RADIUS_PX
    return hm[d].max() <= FREE_HEIGHT


@pytest.mark.parametrize("direction", range(8))
def test_start_point_behind_the_object_in_every_direction(direction):
    obj = np.array([0.5, 0.02])
    v = direction_vector(direction)
    small = _heightmap_with_discs([obj], radius=0.012)
    rc, xy = find_start(small, obj, direction)
    assert np.array_equal(rc, world_to_pixel(obj - START_BACKOFF * v))  # the first candidate
    assert np.allclose(xy, pixel_to_world(np.array(rc))) and _disc_free(small, rc)
    big = _heightmap_with_discs([obj], radius=0.035)  # the first candidates' discs overlap it
    rc2, xy2 = find_start(big, obj, direction)
    backoff = (obj - xy2) @ v
    assert START_BACKOFF + START_STEP - VOXEL_SIZE < backoff < START_BACKOFF + 5 * START_STEP + VOXEL_SIZE
    assert _disc_free(big, rc2)
    steps = int(np.round((backoff - START_BACKOFF) / START_STEP))
    closer = world_to_pixel(obj - (START_BACKOFF + (steps - 1) * START_STEP) * v)
    assert not _disc_free(big, closer)  # the candidate one step closer was blocked


def test_blocked_discs_are_skipped_and_the_start_steps_back():
    obj = np.array([0.5, 0.0])
    rc, xy = find_start(_heightmap_with_discs([obj], radius=0.02), obj, 0)
    blocked = _heightmap_with_discs([obj, obj - [0.05, 0.0]], radius=0.02)  # a second object behind
    rc2, xy2 = find_start(blocked, obj, 0)
    assert obj[0] - xy2[0] > obj[0] - xy[0] + START_STEP / 2 and _disc_free(blocked, rc2)
    assert rc2[0] == rc[0]  # stepped back along the direction only
    wall = _heightmap_with_discs([obj, obj - [0.07, 0.0], obj - [0.1, 0.0]], radius=0.025)
    assert find_start(wall, obj, 0) is None  # every candidate is blocked
    assert find_start(np.full(GRID_SHAPE[:2], 0.05, np.float32), obj, 3) is None


def test_nothing_ahead_rejects_the_start():
    obj = np.array([0.5, 0.0])
    assert find_start(np.zeros(GRID_SHAPE[:2], np.float32), obj, 0) is None
    flat = _heightmap_with_discs([obj], radius=0.02, height=FREE_HEIGHT * 0.8)  # too low to be seen
    assert find_start(flat, obj, 0) is None
    # something beyond 0.04 m ahead of every candidate: rejected
    far_ahead = _heightmap_with_discs([obj + [0.06, 0.0]], radius=0.005)
    assert find_start(far_ahead, obj, 0) is None


def test_start_outside_the_grid_is_rejected():
    edge = np.array([0.25, 0.0])  # 6 mm inside the grid's x minimum: every start along +x is outside
    hm = _heightmap_with_discs([edge], radius=0.01)
    assert find_start(hm, edge, 0) is None
    assert find_start(hm, edge, 4) is not None  # pushing towards the edge starts inside


# --- propose / accept ------------------------------------------------------------------------------


def test_propose_is_pure_and_counts_attempts():
    objs = np.array([[0.45, -0.05], [0.55, 0.08]])
    hm = _heightmap_with_discs(objs[1:])  # object 0 is invisible: no start for it is ever valid
    policy = HeuristicPolicy(np.random.default_rng(3), 2)
    policy.reset(objs)
    state = (policy.counters.copy(), policy.last_direction.copy(), policy.pushes.copy(), policy.previous.copy())
    decisions = [policy.propose(hm, objs) for _ in range(40)]
    for before, after in zip(state, (policy.counters, policy.last_direction, policy.pushes, policy.previous)):
        assert np.array_equal(before, after)
    assert all(d.object_index == 1 for d in decisions)
    assert max(d.attempts for d in decisions) > 1 and min(d.attempts for d in decisions) == 1
    assert policy.propose(np.zeros(GRID_SHAPE[:2], np.float32), objs) is None  # bounded search


def test_accept_updates_state():
    policy = HeuristicPolicy(np.random.default_rng(0), 2)
    start = np.array([[0.45, 0.0], [0.55, 0.0]])
    policy.reset(start)
    after = start + [[0.0, 0.05], [0.0, 0.0]]
    policy.accept(_decision(0, direction=2), after)
    assert policy.last_direction.tolist() == [2, -1] and policy.pushes.tolist() == [1, 0]
    assert np.array_equal(policy.previous, after) and np.array_equal(policy.before_push[0], start[0])
    policy.reset(start)
    assert policy.counters.tolist() == [0, 0] and policy.last_direction.tolist() == [-1, -1]


@pytest.mark.parametrize("name", ["heuristic", "random"])
def test_policies_are_deterministic_and_valid(name):
    objs = np.array([[0.45, -0.05], [0.55, 0.08], [0.5, 0.15]])
    hm = _heightmap_with_discs(objs)
    runs = []
    for seed in (42, 42, 43):
        policy = make_policy(name, np.random.default_rng(seed), 3)
        policy.reset(objs)
        seq = []
        for _ in range(10):
            d = policy.propose(hm, objs)
            assert d is not None and 0 <= d.direction < 8 and np.isclose(d.object_probs.sum(), 1)
            assert np.isclose(d.direction_probs.sum(), 1) and d.attempts >= 1
            assert tuple(world_to_pixel(d.start_xy)) == d.start_rc and _disc_free(hm, d.start_rc)
            policy.accept(d, objs)
            seq.append((d.object_index, d.direction, d.start_rc, d.direction_probs.tobytes()))
        runs.append(seq)
    assert runs[0] == runs[1] and runs[0] != runs[2]


def test_random_policy_is_uniform():
    from scipy.stats import chisquare

    objs = np.array([[0.4, 0.0], [0.6, 0.0], [0.5, 0.15]])
    hm = _heightmap_with_discs(objs)
    policy = RandomPolicy(np.random.default_rng(7), 3)
    policy.reset(objs)
    draws = []
    for _ in range(1200):
        d = policy.propose(hm, objs)
        policy.accept(d, objs)  # executing pushes does not bias the random policy
        draws.append(d)
    objects = np.bincount([d.object_index for d in draws], minlength=3)
    directions = np.bincount([d.direction for d in draws], minlength=8)
    assert chisquare(objects).pvalue > 0.01 and chisquare(directions).pvalue > 0.01
    assert np.all(np.isnan(draws[0].direction_scores)) and np.allclose(draws[0].direction_probs, 1 / 8)
    assert np.allclose(draws[-1].object_probs, 1 / 3)


def test_bad_inputs():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="unknown policy 'greedy'"):
        make_policy("greedy", rng, 2)
    with pytest.raises(ValueError, match="large_index=2"):
        make_policy("heuristic", rng, 2, large_index=2)
    with pytest.raises(ValueError, match="num_objects=0"):
        make_policy("random", rng, 0)
    policy = make_policy("heuristic", rng, 2, scoring="paper")
    assert policy.scoring == "paper"
    with pytest.raises(ValueError, match=r"initial_positions.*\(2, 2\)"):
        policy.reset(np.zeros((3, 2)))
    policy.reset(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="heightmap"):
        policy.propose(np.zeros((64, 64)), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="positions"):
        policy.propose(np.zeros(GRID_SHAPE[:2]), np.full((2, 2), np.nan))
