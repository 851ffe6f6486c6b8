"""The matched loss: equals the official per-permutation cross-entropy, finds the best permutation
from one score matrix, carries the previous step's matching, reduces over the batch as official."""

import itertools

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from torch.nn import functional as F  # noqa: E402

from dsr_bench.scoring.metrics import brute_force_assignment  # noqa: E402
from dsr_bench.models.loss import (MASK_WEIGHT, MaskIdError, best_matching, dsr_loss, matched_target,  # noqa: E402
                                   score_matrix)


def permuted_ce(logits, gt, perm):
    """The official formulation: channels [background, slot perm[0], slot perm[1], ...] against ids."""
    k = logits.shape[0]
    permuted = torch.stack([logits[k - 1]] + [logits[p] for p in perm])
    return float(F.cross_entropy(permuted[None].double(), gt[None]))


def brute_force(logits, gt):
    k = logits.shape[0]
    return min(itertools.permutations(range(k - 1)), key=lambda p: permuted_ce(logits, gt, p))


def _outputs(logits):
    shape = logits.shape[2:]
    return {"mask_logits": logits, "motion": torch.zeros(logits.shape[0], 3, *shape)}


@pytest.mark.parametrize("seed", [0, 1])
def test_best_matching_equals_the_official_search(seed):
    torch.manual_seed(seed)
    logits = torch.randn(3, 5, 6, 6, 4) * 3
    gt = torch.randint(0, 5, (3, 6, 6, 4))
    gt[1][gt[1] == 3] = 0  # an absent object
    matching = best_matching(score_matrix(torch.log_softmax(logits.double(), 1), gt))
    _, terms, best = dsr_loss(_outputs(logits), gt, torch.zeros(3, 3, 6, 6, 4), reduction="sum")
    expected = 0.0
    for b in range(3):
        perm = brute_force(logits[b], gt[b])
        expected += permuted_ce(logits[b], gt[b], perm)
        assert permuted_ce(logits[b], gt[b], tuple(matching[b].tolist())) == pytest.approx(
            permuted_ce(logits[b], gt[b], perm))
    assert torch.equal(best, matching) and best.dtype == torch.int64 and best.shape == (3, 4)
    assert float(terms["mask"]) == pytest.approx(expected, rel=1e-5)  # summed over the batch (official)
    assert float(terms["total"]) == pytest.approx(MASK_WEIGHT * expected, rel=1e-5)


def test_given_matching_is_used_and_reductions():
    torch.manual_seed(2)
    logits = torch.randn(2, 5, 5, 5, 3)
    gt = torch.randint(0, 5, (2, 5, 5, 3))
    fixed = [np.array([3, 2, 1, 0]), np.array([1, 0, 3, 2])]
    _, terms, best = dsr_loss(_outputs(logits), gt, torch.zeros(2, 3, 5, 5, 3), fixed, reduction="mean")
    expected = np.mean([permuted_ce(logits[b], gt[b], tuple(fixed[b])) for b in range(2)])
    assert float(terms["mask"]) == pytest.approx(expected, rel=1e-5)
    # the same matching as a (B, K-1) tensor (what dsr_loss hands on) gives the same loss
    _, as_tensor, _ = dsr_loss(_outputs(logits), gt, torch.zeros(2, 3, 5, 5, 3), torch.tensor(np.stack(fixed)),
                               reduction="mean")
    assert float(as_tensor["mask"]) == float(terms["mask"])
    # the returned matching is the best one for this prediction (for the next step), not the given one
    _, best_terms, _ = dsr_loss(_outputs(logits), gt, torch.zeros(2, 3, 5, 5, 3), best, reduction="mean")
    assert float(best_terms["mask"]) <= float(terms["mask"]) + 1e-6


def test_matched_target_and_motion_term():
    gt = torch.tensor([[0, 1, 2, 3, 4]])
    target = matched_target(gt, [np.array([2, 0, 3, 1])], 5)
    assert target.tolist() == [[4, 2, 0, 3, 1]]  # empty -> background (last), object i -> its slot
    logits = torch.zeros(1, 5, 2, 2, 2)
    motion = torch.zeros(1, 3, 2, 2, 2)
    motion[0, 1, 0, 0, 0] = 2.0
    _, terms, _ = dsr_loss({"mask_logits": logits, "motion": motion}, torch.zeros(1, 2, 2, 2, dtype=torch.long),
                           torch.zeros(1, 3, 2, 2, 2))
    assert float(terms["motion"]) == pytest.approx(4.0 / 24)  # mean over 3 components x 8 voxels
    assert float(terms["mask"]) == pytest.approx(np.log(5))


def test_gradients_reach_logits_and_motion():
    logits = torch.randn(1, 3, 3, 3, 2, requires_grad=True)
    motion = torch.randn(1, 3, 3, 3, 2, requires_grad=True)
    loss, _, _ = dsr_loss({"mask_logits": logits, "motion": motion}, torch.randint(0, 3, (1, 3, 3, 2)),
                          torch.zeros(1, 3, 3, 3, 2))
    loss.backward()
    assert logits.grad.abs().sum() > 0 and motion.grad.abs().sum() > 0


def test_bad_ids_and_reduction():
    logits = torch.zeros(1, 3, 2, 2, 2)
    with pytest.raises(MaskIdError, match="object id 5"):
        dsr_loss(_outputs(logits), torch.full((1, 2, 2, 2), 5), torch.zeros(1, 3, 2, 2, 2))
    with pytest.raises(MaskIdError, match="object id -1"):
        dsr_loss(_outputs(logits), torch.full((1, 2, 2, 2), -1), torch.zeros(1, 3, 2, 2, 2))
    with pytest.raises(ValueError, match=r"matching of shape \(1, 2\)"):
        matched_target(torch.zeros(2, 3, dtype=torch.long), torch.zeros(1, 2, dtype=torch.long), 3)
    with pytest.raises(ValueError, match="reduction"):
        dsr_loss(_outputs(logits), torch.zeros(1, 2, 2, 2, dtype=torch.long), torch.zeros(1, 3, 2, 2, 2),
                 reduction="max")


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6, 7])
def test_device_assignment_equals_the_exact_solver(n):
    """The on-device enumeration (n <= 6) and the scipy fallback (n = 7) find a maximum-score
    matching: its total equals brute-force enumeration's, and it is a permutation."""
    g = torch.Generator().manual_seed(n)
    scores = torch.randn(16, n, n, generator=g, dtype=torch.float64) * 10
    scores[0] = 0.0  # all ties: the first permutation (identity), like the official search
    best = best_matching(scores)
    assert best.shape == (16, n) and best.dtype == torch.int64
    assert best[0].tolist() == list(range(n))
    for s, cols in zip(scores.numpy(), best.numpy()):
        assert sorted(cols.tolist()) == list(range(n))
        rows, ref = brute_force_assignment(s)
        assert s[np.arange(n), cols].sum() == pytest.approx(s[rows, ref].sum(), abs=1e-9)


def test_score_matrix_counts_each_object_once():
    """S[i, j] sums slot j's log-probability over object i+1's voxels; empty voxels count nowhere."""
    log_probs = torch.log_softmax(torch.randn(2, 5, 4, 3, 2, dtype=torch.float64), 1)
    gt = torch.randint(0, 5, (2, 4, 3, 2))
    s = score_matrix(log_probs, gt)
    assert s.shape == (2, 4, 4) and s.dtype == torch.float64
    for b in range(2):
        for i in range(4):
            for j in range(4):
                assert float(s[b, i, j]) == pytest.approx(float(log_probs[b, j][gt[b] == i + 1].sum()))
