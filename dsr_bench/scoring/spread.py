"""Spread of a score over the sequences (tasks) it averages: 95% confidence intervals and paired differences.

A table's or plot's spread is computed from per-unit values (the per-sequence means of a results file's
`per_sequence`, the per-task IoUs of planning results' `per_task`, or one step's values over the sequences),
never from a stored summary. Intervals are Student-t intervals of the mean (two-sided 95%, n - 1 degrees of
freedom); a paired difference is the mean of the per-unit differences over the units both sides scored, with
its standard error (sample standard deviation / sqrt(n)). NaN values (a sequence without a value) are left out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

#: the two-sided coverage of every interval drawn or printed
LEVEL = 0.95


def t_quantile(n: int, level: float = LEVEL) -> float:
    """The two-sided Student-t quantile for a mean over `n` values (n - 1 degrees of freedom); NaN for n < 2."""
    if n < 2:
        return math.nan
    from scipy.stats import t  # lazily: scipy is slow to import and only tables and plots need it

    return float(t.ppf(0.5 + level / 2, n - 1))


@dataclass(frozen=True)
class Spread:
    """The mean of `n` values, its standard error and the half-width of its 95% interval (NaN when n < 2)."""

    mean: float
    se: float
    half: float
    n: int

    @property
    def low(self) -> float:
        return self.mean - self.half

    @property
    def high(self) -> float:
        return self.mean + self.half

    @property
    def excludes_zero(self) -> bool:
        """Whether the 95% interval lies wholly on one side of 0 (never for n < 2)."""
        return self.n >= 2 and (self.low > 0 or self.high < 0)


def spread(values: Sequence[float] | np.ndarray) -> Spread:
    """Mean, standard error and 95% half-width of `values` (NaN left out)."""
    x = np.asarray(values, dtype=np.float64).ravel()
    x = x[np.isfinite(x)]
    n = int(x.size)
    if n == 0:
        return Spread(math.nan, math.nan, math.nan, 0)
    mean = float(x.mean())
    if n < 2:
        return Spread(mean, math.nan, math.nan, n)
    se = float(x.std(ddof=1) / math.sqrt(n))
    return Spread(mean, se, se * t_quantile(n), n)


def unit_values(per_unit: Mapping[str, Mapping[str, float]] | None, key: str) -> dict[str, float]:
    """{unit name: value of `key`} of a `per_sequence` (or `per_task`) mapping; units without a number left out."""
    out = {}
    for name, values in (per_unit or {}).items():
        value = values.get(key) if isinstance(values, Mapping) else None
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            out[name] = float(value)
    return out


def paired_difference(a: Mapping[str, float], b: Mapping[str, float]) -> Spread:
    """The spread of a[u] - b[u] over the units `u` both hold (a paired comparison: the sequences' own
    difficulty cancels)."""
    common = sorted(set(a) & set(b))
    return spread([a[u] - b[u] for u in common])


def step_bands(per_sequence_steps: Mapping[str, Mapping[str, Sequence]], key: str
               ) -> tuple[list[float], list[float]] | None:
    """The per-step 95% interval (low, high) of the mean over sequences of metric `key`, from each sequence's
    per-step values (`evaluate`'s per-sequence lists, None or NaN where a step has no value); None when no
    sequence holds `key`."""
    rows = [list(v[key]) for v in per_sequence_steps.values() if isinstance(v, Mapping) and key in v]
    if not rows:
        return None
    steps = max(len(r) for r in rows)
    table = np.full((len(rows), steps), np.nan)
    for i, r in enumerate(rows):
        table[i, : len(r)] = [np.nan if x is None else x for x in r]
    spreads = [spread(table[:, t]) for t in range(steps)]
    return [s.low for s in spreads], [s.high for s in spreads]
