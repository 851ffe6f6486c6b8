"""Key coalescing of the annotator window (annotator.keys.KeyCoalescer / coalesce): what a held, fast or stuck key
does, without a display."""

from __future__ import annotations

import numpy as np

from dsr_bench.annotator.keys import MAX_LAG, MAX_REPEAT, KeyAction, KeyCoalescer, coalesce, is_nudge


def _held(key: str, rate: float, seconds: float, start: float = 0.0) -> list[tuple[str, float]]:
    """Key repeat events of a key held for `seconds` at `rate` repeats per second."""
    return [(key, start + k / rate) for k in range(round(rate * seconds))]


def _frames(period: float, until: float) -> list[float]:
    return list(np.arange(period, until + 1e-9, period))


def test_a_held_key_keeps_up_and_stops_at_release():
    """30 repeats/s for 3 s, 100 ms frames: every repeat is applied, merged 3 to a nudge; nothing after release."""
    events = _held("D", 30.0, 3.0)
    applied = coalesce(events, _frames(0.1, 5.0))
    assert all(a.key == "D" and a.count <= MAX_REPEAT for _, a in applied)
    assert sum(a.count for _, a in applied) == len(events)
    assert len(applied) <= 31  # one nudge per frame, not one per repeat
    release = events[-1][1]
    assert all(t <= release + 0.1 for t, _ in applied)  # motion stops within one frame of the last repeat


def test_a_slow_window_moves_at_most_max_repeat_per_frame():
    """A frame of 2 s (the next step) while the key repeats: one nudge of MAX_REPEAT steps, the rest dropped."""
    keys = KeyCoalescer()
    for key, t in _held("D", 30.0, 2.0):
        keys.push(key, t)
    assert keys.pending == 60
    actions = keys.drain(2.0)
    assert actions == [KeyAction("D", MAX_REPEAT)] and keys.dropped == 60 - MAX_REPEAT
    assert keys.pending == 0 and keys.drain(2.1) == []


def test_a_stuck_key_is_capped():
    """865 repeats at 300/s (a stuck key) with 60 Hz frames: at most MAX_REPEAT steps per frame, none after."""
    events = _held("L", 300.0, 865 / 300.0)
    frames = _frames(1 / 60, 4.0)
    applied = coalesce(events, frames)
    per_frame: dict[float, int] = {}
    for t, a in applied:
        per_frame[t] = per_frame.get(t, 0) + a.count
    assert max(per_frame.values()) <= MAX_REPEAT
    assert max(per_frame) <= events[-1][1] + 1 / 60


def test_other_keys_are_kept_in_order_and_never_merged():
    events = [("D", 0.0), ("D", 0.01), ("G", 0.02), ("D", 0.03), ("Tab", 0.04), ("Tab", 0.05), ("a", 0.06),
              ("A", 0.07), ("Space", 0.08)]
    actions = [a for _, a in coalesce(events, [0.1])]
    assert actions == [KeyAction("D", 2), KeyAction("G"), KeyAction("D"), KeyAction("Tab"), KeyAction("Tab"),
                       KeyAction("A", 2), KeyAction("Space")]


def test_stale_nudges_are_dropped_other_keys_are_not():
    keys = KeyCoalescer()
    keys.push("D", 0.0)
    keys.push("Enter", 0.0)
    keys.push("D", MAX_LAG + 0.9)
    assert keys.drain(MAX_LAG + 1.0) == [KeyAction("Enter"), KeyAction("D")] and keys.dropped == 1


def test_is_nudge():
    assert all(is_nudge(k) for k in "DAWSEQLJIKOU") and is_nudge("d")
    assert not any(is_nudge(k) for k in ("G", "T", "N", "Space", "Tab", "1", "?"))
