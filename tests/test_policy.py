"""Push policies: counter dynamics, direction scores, start-point search, determinism, uniformity."""

import itertools

import numpy as np
import pytest

from dsr_bench.constants import FREE_HEIGHT, GRID_SHAPE, START_BACKOFF, START_STEP, VOXEL_SIZE
from dsr_bench.geometry import direction_vector, pixel_to_world, world_to_pixel
from generators.policy import DIRECTIONS, HeuristicPolicy, PushDecision, RandomPolicy, find_start, make_policy, softmax


def _heightmap_with_discs(centres_xy, radius=0.03, height=0.05):
    rows, cols = np.meshgrid(np.arange(GRID_SHAPE[0]), np.arange(GRID_SHAPE[1]), indexing="ij")
    xy = pixel_to_world(np.stack([rows, cols], -1))
    hm = np.zeros(GRID_SHAPE[:2], np.float32)
    for c in centres_xy:
        hm[np.linalg.norm(xy - np.asarray(c), axis=-1) <= radius] = height
    return hm


def _decision(k):
    return PushDecision(k, 0, (0, 0), np.zeros(2), np.zeros(4), np.zeros(8), np.zeros(8), 1)


def _exact_consecutive_rate(n=4):
    """Stationary probability that the same object is chosen twice in a row, by exact Markov analysis
    of the counter rules (+1; above 2 -> -2; equal to 2 -> -2 with probability 0.5)."""
    values = (-2, -1, 0, 1, 2)
    states = list(itertools.product(values, repeat=n))
    index = {s: i for i, s in enumerate(states)}
    transition = np.zeros((len(states), len(states)))
    outcomes = {}
    for s in states:
        probs = softmax(np.array(s, float))
        outcomes[s] = []
        for k in range(n):
            c = s[k] + 1
            for value, weight in ([(-2, 1.0)] if c > 2 else [(-2, 0.5), (c, 0.5)] if c > 1 else [(c, 1.0)]):
                nxt = list(s)
                nxt[k] = value
                nxt = tuple(nxt)
                transition[index[s], index[nxt]] += probs[k] * weight
                outcomes[s].append((k, nxt, probs[k] * weight))
    evals, evecs = np.linalg.eig(transition.T)
    pi = np.real(evecs[:, np.argmin(np.abs(evals - 1))])
    pi /= pi.sum()
    rate = 0.0
    for s in states:
        for k, nxt, p in outcomes[s]:
            rate += pi[index[s]] * p * softmax(np.array(nxt, float))[k]
    return rate


def test_counter_dynamics_give_the_designed_consecutive_push_rate():
    rng = np.random.default_rng(0)
    policy = HeuristicPolicy(rng, 4)
    policy.reset(np.zeros((4, 2)))
    chosen = []
    for _ in range(20000):
        k = int(rng.choice(4, p=policy.object_probs()))
        policy.accept(_decision(k), np.zeros((4, 2)))
        chosen.append(k)
    rate = np.mean(np.array(chosen[1:]) == np.array(chosen[:-1]))
    expected = _exact_consecutive_rate()
    assert expected > 0.25 + 0.05  # the rules favour pushing the same object again (uniform: 0.25)
    assert abs(rate - expected) < 0.015
    assert set(np.unique(policy.counters)) <= {-2, -1, 0, 1, 2}


def test_large_object_bonus_and_softmax():
    policy = HeuristicPolicy(np.random.default_rng(0), 3, large_index=1)
    policy.reset(np.zeros((3, 2)))
    assert np.allclose(policy.object_probs(), softmax(np.array([0, 0.5, 0])))


def test_outward_directions_are_unlikely_far_from_centre():
    policy = HeuristicPolicy(np.random.default_rng(0), 1)
    far = np.array([[0.72, 0.0]])  # 0.22 m along +x from the centre
    policy.reset(far)
    scores, probs = policy.direction_scores(0, far)
    outward = DIRECTIONS @ np.array([1.0, 0.0]) > 0
    assert probs[outward].sum() < 0.01 and np.isclose(probs.sum(), 1)


def test_last_direction_is_favoured():
    policy = HeuristicPolicy(np.random.default_rng(0), 1)
    p = np.array([[0.5, 0.0]])
    policy.reset(p)
    policy.accept(PushDecision(0, 2, (0, 0), np.zeros(2), np.ones(1), np.zeros(8), np.zeros(8), 1), p)
    _, probs = policy.direction_scores(0, p)
    assert np.argmax(probs) == 2


def test_neighbours_repel_direction():
    policy = HeuristicPolicy(np.random.default_rng(0), 2)
    pos = np.array([[0.5, 0.0], [0.6, 0.0]])  # neighbour 0.1 m along +x
    policy.reset(pos)
    scores, _ = policy.direction_scores(0, pos)
    assert scores[0] < scores[4] and scores[2] > scores[0]


def test_start_point_search():
    obj = np.array([0.5, 0.0])
    hm = _heightmap_with_discs([obj], radius=0.02)
    found = find_start(hm, obj, 0)  # push along +x: start behind the object (smaller x)
    assert found is not None
    rc, xy = found
    assert np.allclose(xy, pixel_to_world(np.array(rc)))
    assert START_BACKOFF - VOXEL_SIZE <= obj[0] - xy[0] <= START_BACKOFF + 5 * START_STEP + VOXEL_SIZE
    # a blocker right behind the object: the start steps back past it
    blocked = _heightmap_with_discs([obj, obj - [0.045, 0.0]], radius=0.02)
    rc2, xy2 = find_start(blocked, obj, 0)
    assert obj[0] - xy2[0] > obj[0] - xy[0]
    disc = blocked[max(rc2[0] - 5, 0):rc2[0] + 6, max(rc2[1] - 5, 0):rc2[1] + 6]
    assert disc.max() <= FREE_HEIGHT
    # nothing ahead within 4 cm: no start
    assert find_start(np.zeros(GRID_SHAPE[:2], np.float32), obj, 0) is None
    # everything blocked: no start
    assert find_start(np.full(GRID_SHAPE[:2], 0.05, np.float32), obj, 3) is None


@pytest.mark.parametrize("name", ["heuristic", "random"])
def test_policies_are_deterministic_and_valid(name):
    objs = np.array([[0.45, -0.05], [0.55, 0.08], [0.5, 0.15]])
    hm = _heightmap_with_discs(objs)
    runs = []
    for _ in range(2):
        policy = make_policy(name, np.random.default_rng(42), 3)
        policy.reset(objs)
        seq = []
        for _ in range(10):
            d = policy.propose(hm, objs)
            assert d is not None and 0 <= d.direction < 8 and np.isclose(d.object_probs.sum(), 1)
            assert tuple(world_to_pixel(d.start_xy)) == d.start_rc
            policy.accept(d, objs)
            seq.append((d.object_index, d.direction, d.start_rc))
        runs.append(seq)
    assert runs[0] == runs[1]


def test_random_policy_is_uniform():
    from scipy.stats import chisquare

    objs = np.array([[0.4, 0.0], [0.6, 0.0]])
    hm = _heightmap_with_discs(objs)
    policy = RandomPolicy(np.random.default_rng(7), 2)
    policy.reset(objs)
    draws = [policy.propose(hm, objs) for _ in range(1600)]
    objects = np.bincount([d.object_index for d in draws], minlength=2)
    directions = np.bincount([d.direction for d in draws], minlength=8)
    assert chisquare(objects).pvalue > 0.01 and chisquare(directions).pvalue > 0.01
    assert np.all(np.isnan(draws[0].direction_scores))


def test_unknown_policy():
    with pytest.raises(ValueError, match="unknown policy"):
        make_policy("greedy", np.random.default_rng(0), 2)
    assert np.allclose(direction_vector(1), DIRECTIONS[1])
