"""Spread: Student-t intervals of a mean and paired differences, computed from per-unit values (NaN left out)."""

import math

import numpy as np
import pytest
from scipy import stats

from dsr_bench.scoring.spread import paired_difference, spread, step_bands, unit_values


def test_interval_is_students_t_of_the_mean():
    values = [0.2, 0.5, 0.3, 0.9, 0.4]
    s = spread(values)
    low, high = stats.t.interval(0.95, len(values) - 1, loc=np.mean(values), scale=stats.sem(values))
    assert s.n == 5 and s.mean == pytest.approx(np.mean(values))
    assert (s.low, s.high) == (pytest.approx(low), pytest.approx(high))
    assert s.se == pytest.approx(stats.sem(values))
    one = spread([0.3, float("nan")])  # one value: a mean, no interval
    assert one.n == 1 and one.mean == 0.3 and math.isnan(one.half) and not one.excludes_zero
    assert spread([]).n == 0


def test_paired_difference_cancels_what_both_rows_share():
    """Two rows that differ by 0.01 on every sequence, whose sequences differ widely: the paired difference is
    0.01 with no spread, and only sequences both scored count."""
    hard = {f"seq_{i}": 0.1 * i for i in range(10)}
    better = {k: v + 0.01 for k, v in hard.items()}
    better["seq_extra"] = 0.99
    d = paired_difference(better, hard)
    assert d.n == 10 and d.mean == pytest.approx(0.01) and d.se == pytest.approx(0.0, abs=1e-12)
    assert spread(list(better.values())).half > 0.05  # unpaired, the rows' intervals overlap widely
    noisy = paired_difference({"a": 1.0, "b": 0.0, "c": 0.5}, {"a": 0.0, "b": 1.0, "c": 0.5})
    assert noisy.mean == 0 and not noisy.excludes_zero


def test_unit_values_and_step_bands_leave_out_what_is_not_a_number():
    per_sequence = {"s0": {"iou": 0.5, "flow": None}, "s1": {"iou": float("nan")}, "s2": {"iou": True}, "s3": {}}
    assert unit_values(per_sequence, "iou") == {"s0": 0.5}
    low, high = step_bands({"a": {"k": [1.0, None]}, "b": {"k": [3.0, 2.0]}, "c": {"other": [9.0]}}, "k")
    s = spread([1.0, 3.0])
    assert (low[0], high[0]) == (s.low, s.high) and math.isnan(low[1])  # one value at step 1: no interval
    assert step_bands({"a": {"other": [1.0]}}, "k") is None
