"""Comparing two scored entries sequence by sequence: what a claim that one model beats another needs."""

from __future__ import annotations

import numpy as np


def paired_difference(a: dict[str, dict], b: dict[str, dict], metric: str) -> dict:
    """Mean over the sequences both scored of a - b for `metric`, its standard error (the standard deviation
    of the per-sequence differences / sqrt(n)) and n. a, b: the `per_sequence` of two results files
    ({sequence: {metric: value}}); sequences where either value is missing or not finite are left out."""
    names = sorted(set(a) & set(b))
    d = np.array([a[n].get(metric, np.nan) - b[n].get(metric, np.nan) for n in names], dtype=np.float64)
    d = d[np.isfinite(d)]
    if len(d) < 2:
        return {"mean": float(d.mean()) if len(d) else float("nan"), "se": float("nan"), "n": int(len(d))}
    return {"mean": float(d.mean()), "se": float(d.std(ddof=1) / np.sqrt(len(d))), "n": int(len(d))}
