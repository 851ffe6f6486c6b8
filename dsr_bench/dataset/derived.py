"""Schema arrays that a file imported from the official release leaves out: they are its `official/` arrays, cast.

An import (`dsr-bench import-official`, `dsr_bench.dataset.official`) keeps every release dataset that does not
convert exactly to our schema under `official/` (float64, as the release stores it) beside the schema's float32
array made from it. Two of those schema arrays are nothing but the `official/` array cast (and, for the points,
moved to our axis order), so the file stores the original once and the reader casts it again:

- `cameras/front/points` (T + 1, H, W, 3) float32: `official/pts_small` (T, 3, H, W) float64 with its axis 1 moved
  last, cast; the last observation, which the release holds no points of, from the depth as a generated file's
  points are (`dsr_bench.dataset.sequence.derive_points`);
- `cameras/front/scene_flow_2d` (T, H, W, 3) float32: `official/scene_flow_2d` cast.

The writer leaves one out only where the rule gives the array bit for bit (NaN payloads included) and names it in
the root attribute `derived_from` ({name: its source}); a reader that does not know the attribute finds the array
missing (an error), never wrong values. A camera's points derived from its depth alone (every generated file) are
listed in `derived_arrays` instead (`dsr_bench.dataset.sequence.DERIVED_ATTR`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

#: The root attribute: JSON {array: the `official/` dataset it is derived from}.
DERIVED_FROM_ATTR = "derived_from"
#: The arrays that may be derived, and their sources.
SOURCES: dict[str, str] = {"cameras/front/points": "official/pts_small",
                           "cameras/front/scene_flow_2d": "official/scene_flow_2d"}


def derived_shape(name: str, source_shape: tuple[int, ...]) -> tuple[int, ...]:
    """The shape of derived array `name` given its source's."""
    if name.endswith("/points"):  # (T, 3, H, W) -> (T + 1, H, W, 3): the last observation from the depth
        return (source_shape[0] + 1,) + tuple(source_shape[2:]) + (source_shape[1],)
    return tuple(source_shape)


def derive_steps(name: str, source: Callable[[int, int], np.ndarray], num_source_steps: int,
                 last_points: Callable[[], np.ndarray], start: int, stop: int) -> np.ndarray:
    """Steps [start, stop) of derived array `name` (float32): `source(a, b)` reads the source's steps [a, b) and
    `last_points()` gives the points of the last observation (the points' step `num_source_steps`)."""
    if not name.endswith("/points"):
        return np.asarray(source(start, stop)).astype(np.float32)
    parts = []
    if start < min(stop, num_source_steps):
        parts.append(np.moveaxis(np.asarray(source(start, min(stop, num_source_steps))), 1, -1).astype(np.float32))
    if start <= num_source_steps < stop:
        parts.append(np.asarray(last_points(), dtype=np.float32)[None])
    if not parts:
        raise IndexError(f"{name}: steps [{start}, {stop}) out of range")
    return np.concatenate(parts) if len(parts) > 1 else parts[0]


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def derivable_from(arrays: Mapping[str, np.ndarray], extras: Mapping[str, np.ndarray],
                   last_points: Callable[[], np.ndarray] | None) -> dict[str, str]:
    """{array: source} of the arrays that their `official/` source in `extras` gives bit for bit; `last_points()`:
    the camera's points of the last observation derived from its depth (None: the points are not derivable)."""
    out = {}
    for name, source_name in SOURCES.items():
        array, source = arrays.get(name), extras.get(source_name)
        if array is None or source is None or np.asarray(array).dtype != np.float32:
            continue
        if name.endswith("/points") and last_points is None:
            continue
        source = np.asarray(source)
        if source.ndim < 2 or derived_shape(name, source.shape) != np.shape(array):
            continue
        steps = derived_shape(name, source.shape)[0]

        def steps_of(a: int, b: int, whole: np.ndarray = source) -> np.ndarray:
            return whole[a:b]

        derived = derive_steps(name, steps_of, source.shape[0], last_points or (lambda: np.zeros(0)), 0, steps)
        if _same_bits(derived, array):
            out[name] = source_name
    return out
