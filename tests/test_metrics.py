"""Metric definitions: exact matching, IoU conventions, motion errors on hand-checked arrays."""

import numpy as np
import pytest

from dsr_bench.scoring.metrics import (
    assignment, brute_force_assignment, matched_iou, motion_2d_error, motion_errors, overlap, prediction_minus_truth,
    sequence_scores,
)

GRID = (128, 128, 48)


@pytest.mark.parametrize("shape", [(4, 4), (5, 3), (3, 6), (6, 6)])
def test_hungarian_equals_brute_force(shape):
    rng = np.random.default_rng(sum(shape))
    for _ in range(40):
        score = rng.random(shape)
        if rng.random() < 0.3:
            score = np.round(score, 1)  # ties
        r1, c1 = assignment(score)
        r2, c2 = brute_force_assignment(score)
        assert np.isclose(score[r1, c1].sum(), score[r2, c2].sum())
        assert len(r1) == min(shape) and len(set(c1)) == len(c1)


def test_overlap_matches_direct_counts():
    rng = np.random.default_rng(0)
    pred = rng.integers(0, 5, (16, 16, 8)).astype(np.uint8)
    gt = rng.integers(0, 4, (16, 16, 8)).astype(np.uint8)
    ov = overlap(pred, gt, 4, 3)
    for s in range(1, 5):
        for g in range(1, 4):
            inter = np.sum((pred == s) & (gt == g))
            union = np.sum((pred == s) | (gt == g))
            assert ov.inter[s - 1, g - 1] == inter and ov.union[s - 1, g - 1] == union
            assert np.isclose(ov.iou[s - 1, g - 1], inter / max(union, 1))


def _blocks(ids, shape=(8, 8, 4)):
    vol = np.zeros(shape, np.uint8)
    for k, i in enumerate(ids):
        if i:
            vol[2 * k:2 * k + 2] = i
    return vol


def test_slot_numbers_do_not_matter_and_empty_pairs_are_not_counted():
    gt = _blocks([1, 2, 3])
    pred = _blocks([4, 1, 2])  # same objects, other slot numbers, slot 3 empty
    ov = overlap(pred, gt, 4, 3)
    score, per_object = matched_iou(ov, *assignment(ov.iou))
    assert score == 1.0 and np.all(per_object == 1.0)
    half = gt.copy()
    half[4:6] = 0  # object 3 missed entirely
    ov = overlap(half, gt, 4, 3)
    score, per_object = matched_iou(ov, *assignment(ov.iou))
    assert np.isclose(score, 2 / 3) and per_object[2] == 0


def test_extra_predicted_slot_counts_as_zero():
    gt = _blocks([1, 2, 0, 0])
    pred = _blocks([1, 2, 3, 0])  # a phantom object
    ov = overlap(pred, gt, 4, 2)
    score, _ = matched_iou(ov, *assignment(ov.iou))
    assert np.isclose(score, 2 / 3)


def test_ordered_iou_penalises_identity_swaps():
    gt = np.stack([_blocks([1, 2])] * 3)
    pred = np.stack([_blocks([1, 2]), _blocks([2, 1]), _blocks([1, 2])])
    scores = sequence_scores(pred, gt, 4, 2)
    assert np.allclose(scores["iou_unordered"], 1.0)
    assert np.allclose(scores["iou_ordered"], [1.0, 0.0, 1.0])


def test_occlusion_breakdown_splits_objects_by_visibility():
    gt = np.stack([_blocks([1, 2])] * 2)
    pred = np.stack([_blocks([1, 0])] * 2)
    visible = np.array([[0.9, 0.2], [0.9, 0.8]])
    scores = sequence_scores(pred, gt, 4, 2, visible)
    assert [list(x) for x in scores["iou_occluded_objects"]] == [[0.0], []]
    assert [list(x) for x in scores["iou_visible_objects"]] == [[1.0], [1.0, 0.0]]


def test_motion_errors_follow_the_official_definitions():
    gt_mask = np.zeros(GRID, np.uint8)
    gt_mask[10:12, 10:12, 0:3] = 1  # 12 voxels, 4 of them at z index 0
    gt_mask[50, 50, 5] = 2
    tsdf = np.ones(GRID, np.float32)
    tsdf[10:12, 10:12, 0:3] = -0.5  # visible band, but z = 0 is excluded
    tsdf[50, 50, 5] = -0.995  # below -0.99: not visible surface
    gt = np.zeros((3,) + GRID, np.float32)
    gt[1][gt_mask == 1] = 2.0  # object 1 moves 2 voxels in x
    pred = np.zeros_like(gt)
    err = motion_errors(pred, gt, tsdf, gt_mask, 2)
    assert np.isclose(err["motion_visible"], 4.0 * 0.16)  # squared EPE 4 voxel^2 x 0.16
    assert np.isclose(err["motion_full"], 12 * 4.0 / (3 * np.prod(GRID)) * 0.16)
    assert np.isclose(err["motion_moved"], 4.0 * 0.16) and err["motion_static"] == 0.0
    perfect = motion_errors(gt, gt, tsdf, gt_mask, 2)
    assert perfect["motion_visible"] == 0 and perfect["motion_full"] == 0


def test_motion_2d_error_in_cm2():
    gt = np.zeros((4, 4, 3), np.float32)
    pred = gt.copy()
    pred[0, 0] = [0.01, 0.0, 0.0]  # 1 cm on a visible pixel
    mask = np.zeros((4, 4), np.uint8)
    mask[0, :2] = 1
    assert np.isclose(motion_2d_error(pred, gt, mask), 0.5)
    assert np.isnan(motion_2d_error(pred, gt, np.zeros((4, 4), np.uint8)))


def _official_loop(pred, gt, slots):
    """The official evaluation's approach: every permutation, a reduction per (slot, object) pair,
    GT objects 1..slots, mean over slots (empty-empty pairs count 0)."""
    import itertools

    best = 0.0
    for perm in itertools.permutations(range(1, slots + 1)):
        total = 0.0
        for i in range(slots):
            a, b = pred == perm[i], gt == i + 1
            total += (a & b).sum() / max((a | b).sum(), 1)
        best = max(best, total / slots)
    return best


@pytest.mark.parametrize("num_objects", [4, 3, 2])
def test_official_iou_equals_the_official_loop(num_objects):
    from dsr_bench.scoring.metrics import official_iou

    rng = np.random.default_rng(num_objects)
    for _ in range(10):
        gt = rng.integers(0, num_objects + 1, (12, 12, 6)).astype(np.uint8)
        pred = np.where(rng.random(gt.shape) < 0.6, (gt + rng.integers(0, 4)) % 5, rng.integers(0, 5, gt.shape))
        pred = pred.astype(np.uint8)
        ov = overlap(pred, gt, 4, num_objects)
        assert np.isclose(official_iou(ov), _official_loop(pred, gt, 4))
    perfect = overlap(gt, gt, 4, num_objects)
    assert official_iou(perfect) == (1.0 if num_objects == 4 else num_objects / 4)  # empty-empty = 0
    assert matched_iou(perfect, *assignment(perfect.iou))[0] == 1.0


def test_ordered_official_iou_uses_one_matching():
    gt = np.stack([_blocks([1, 2, 3, 4])] * 2)
    pred = np.stack([_blocks([1, 2, 3, 4]), _blocks([2, 1, 3, 4])])
    scores = sequence_scores(pred, gt, 4, 4)
    assert np.allclose(scores["iou_unordered_official"], 1.0)
    ordered = scores["iou_ordered_official"]
    assert np.allclose(ordered, [1.0, 0.5]) or np.allclose(ordered, [0.5, 1.0])
    assert np.allclose(scores["iou_ordered"], scores["iou_ordered_official"])


def test_paired_difference_uses_the_sequences_both_scored():
    from dsr_bench.scoring.compare import paired_difference

    a = {"s0": {"m": 3.0}, "s1": {"m": 5.0}, "s2": {"m": 4.0}, "only_a": {"m": 100.0}}
    b = {"s0": {"m": 1.0}, "s1": {"m": 2.0}, "s2": {"m": float("nan")}, "only_b": {"m": -100.0}}
    out = paired_difference(a, b, "m")
    assert out["n"] == 2 and out["mean"] == 2.5  # differences 2 and 3; s2 is not finite, the rest unpaired
    assert out["se"] == pytest.approx(np.std([2.0, 3.0], ddof=1) / np.sqrt(2))


@pytest.mark.parametrize("nonzero_fraction", [0.0, 0.01, 0.2, 0.3, 1.0])
def test_sparse_float16_subtraction_gives_the_same_squares_and_metrics(nonzero_fraction):
    rng = np.random.default_rng(3)
    gt = np.zeros((3,) + GRID, np.float32)
    moving = rng.random(GRID) < 0.05
    gt[:, moving] = rng.normal(0, 3, (3, int(moving.sum())))
    gt[0, 0, 0, :4] = [-0.0, np.inf, -np.inf, 1e-30]
    pred = np.zeros(gt.shape, np.float16)
    chosen = rng.random(gt.shape) < nonzero_fraction
    pred[chosen] = rng.normal(0, 3, int(chosen.sum())).astype(np.float16)
    pred[1, 0, 0, :5] = [-0.0, np.nan, np.inf, 6e-8, 65504]  # signed zero, NaN, inf, subnormal, max
    plain = np.subtract(pred, gt, dtype=np.float32)
    diff = prediction_minus_truth(pred, gt)
    assert diff.dtype == np.float32 and diff.shape == gt.shape
    np.testing.assert_array_equal(diff ** 2, plain ** 2)  # NaNs in the same places
    assert (np.abs(diff).view(np.uint32) == np.abs(plain).view(np.uint32)).all()  # equal but for a zero's sign
    tsdf = np.full(GRID, -0.5, np.float32)
    gt_mask = moving.astype(np.uint8) * 2
    pred[1, 0, 0, 1:3] = 0  # finite metrics to compare
    got = motion_errors(pred, gt, tsdf, gt_mask, 2)
    ref = motion_errors(pred.astype(np.float32), gt, tsdf, gt_mask, 2)
    assert {k: np.float64(v).hex() for k, v in got.items()} == {k: np.float64(v).hex() for k, v in ref.items()}
