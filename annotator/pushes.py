"""Robot-logged pushes -> the benchmark's actions `[d, row, col]` (docs/annotator.md, "Real captures in").

A rig logs each push as its start point on the table and its direction; the benchmark knows only NUM_DIRECTIONS
directions (d: angle d * pi / 4 in the table's xy plane, `dsr_bench.geometry.direction_vector`) and starts on the
128 x 128 workspace grid (cell (row along y, col along x) of `dsr_bench.geometry.world_to_pixel`), as the generator
writes them (`generators.episode`: `action = [d, *world_to_pixel(push_start)]`). A push off the eight directions by
more than DIRECTION_TOLERANCE_DEG, or starting outside the grid, is refused, never rounded silently.

The file (`--pushes pushes.json`), table frame, metres:

    {"pushes": [{"start": [x, y], "direction": [dx, dy]},            a unit vector in the table's xy plane
                {"start": [x, y], "angle_deg": 45, "length": 0.12}]}  or an angle (degrees, from +x towards +y)

`length` (m, optional, default PUSH_LENGTH) places the logged end point (`pushes_world`), which the annotator uses to
tell which objects the pusher passed. `between` [N, M] (optional, for every push or for none) gives the step numbers
of the images before and after the push, as in their file names: with it the numbers may have gaps (frame numbers),
and the importer checks push i against the i-th and (i + 1)-th numbers (`annotator.importer.logged_between`,
`check_step_numbers`; docs/annotator.md, "Pushes").
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from dsr_bench.constants import GRID_BOUNDS, GRID_SHAPE, NUM_DIRECTIONS, PUSH_HEIGHT, PUSH_LENGTH
from dsr_bench.errors import UserError
from dsr_bench.geometry import direction_vector, world_to_pixel

#: Largest angle (degrees) between a logged direction and the benchmark direction it is mapped to.
DIRECTION_TOLERANCE_DEG: float = 2.0
#: How far (relative) a logged direction vector's length may be from 1.
UNIT_TOLERANCE: float = 0.01


def _fail(path: Path, message: str) -> UserError:
    return UserError(f"--pushes {path}: {message}")


def nearest_direction(vector_xy: np.ndarray) -> tuple[int, float]:
    """(d, off) of a direction (2,) in the table's xy plane: the nearest benchmark direction d in 0..7 (angle
    d * pi / 4) and the angle (degrees) between them."""
    v = np.asarray(vector_xy, np.float64)
    v = v / float(np.linalg.norm(v))
    dirs = direction_vector(np.arange(NUM_DIRECTIONS))
    cos = np.clip(dirs @ v, -1.0, 1.0)
    d = int(np.argmax(cos))
    return d, math.degrees(math.acos(float(cos[d])))


def push_to_action(start_xy, direction_xy, tolerance_deg: float = DIRECTION_TOLERANCE_DEG
                   ) -> tuple[np.ndarray | None, str | None]:
    """([d, row, col] int64, None) for a push starting at `start_xy` (x, y) m in the table frame along
    `direction_xy` (a unit vector, table xy), or (None, the reason in a few words) when its direction is more than
    `tolerance_deg` from every benchmark direction or its start is outside the grid (GRID_BOUNDS)."""
    start = np.asarray(start_xy, np.float64)
    d, off = nearest_direction(direction_xy)
    problems = []
    if off > tolerance_deg:
        angle = math.degrees(math.atan2(direction_xy[1], direction_xy[0]))
        problems.append(f"direction {angle:.1f} deg is {off:.1f} deg from the nearest benchmark direction "
                        f"d={d} ({d * 360 // NUM_DIRECTIONS} deg; tolerance {tolerance_deg:g} deg)")
    row, col = (int(x) for x in world_to_pixel(start))
    if not (0 <= row < GRID_SHAPE[0] and 0 <= col < GRID_SHAPE[1]):
        (x0, x1), (y0, y1) = GRID_BOUNDS[0], GRID_BOUNDS[1]
        problems.append(f"start ({start[0]:.3f}, {start[1]:.3f}) m is outside the grid (x {x0:g}..{x1:g}, "
                        f"y {y0:g}..{y1:g} m)")
    if problems:
        return None, " and ".join(problems)
    return np.array([d, row, col], np.int64), None


def _vector(path: Path, where: str, value, size: int) -> np.ndarray:
    """`size` finite JSON numbers (not true / false, not strings such as "0.4")."""
    from dsr_bench.annotator.inputs import numbers

    if not numbers(value, (size,)):
        raise _fail(path, f"{where} must be {size} finite numbers")
    return np.asarray(value, dtype=np.float64)


def read_pushes(path: str | Path, num_pushes: int, tolerance_deg: float = DIRECTION_TOLERANCE_DEG
                ) -> tuple[np.ndarray, np.ndarray]:
    """Actions (T, 3) int64 [d, row, col] and pushes_world (T, 2, 3) m (start at PUSH_HEIGHT, end `length` along the
    logged direction) from a pushes file (module docstring) of exactly `num_pushes` pushes. Every push that does not
    map to a benchmark action is named in one UserError line."""
    path = Path(path)
    if not path.is_file():
        raise _fail(path, "no such file; log one push per step change as {\"pushes\": [{\"start\": [x, y], "
                          "\"direction\": [dx, dy]}, ...]} (docs/annotator.md)")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise _fail(path, f"unreadable JSON ({exc}); fix the file") from None
    entries = data.get("pushes") if isinstance(data, dict) else None
    if not isinstance(entries, list):
        raise _fail(path, 'expected {"pushes": [{"start": [x, y], "direction": [dx, dy] or "angle_deg": a}, ...]}')
    if len(entries) != num_pushes:
        raise _fail(path, f"{len(entries)} pushes but the images hold {num_pushes + 1} steps: log exactly one push "
                          f"between consecutive steps ({num_pushes})")
    actions, pushes, bad = [], [], []
    for i, entry in enumerate(entries):
        where = f"push {i}"
        if not isinstance(entry, dict) or "start" not in entry or ("direction" in entry) == ("angle_deg" in entry):
            raise _fail(path, f"{where} needs 'start' [x, y] (m, table) and one of 'direction' [dx, dy] or 'angle_deg'")
        start = _vector(path, f"{where} start", entry["start"], 2)
        if "direction" in entry:
            direction = _vector(path, f"{where} direction", entry["direction"], 2)
            norm = float(np.linalg.norm(direction))
            if abs(norm - 1.0) > UNIT_TOLERANCE:
                raise _fail(path, f"{where} direction {direction.tolist()} has length {norm:.3f}, not 1: give a unit "
                                  "vector (dx, dy) in the table frame, or 'angle_deg'")
            direction = direction / norm
        else:
            angle = math.radians(float(_vector(path, f"{where} angle_deg", [entry["angle_deg"]], 1)[0]))
            direction = np.array([math.cos(angle), math.sin(angle)])
        length = float(_vector(path, f"{where} length", [entry.get("length", PUSH_LENGTH)], 1)[0])
        if not 0 < length < 1:
            raise _fail(path, f"{where} length {length} must be metres in (0, 1)")
        action, reason = push_to_action(start, direction, tolerance_deg)
        if action is None:
            bad.append(f"push {i} {reason}")
            continue
        actions.append(action)
        begin = np.array([start[0], start[1], PUSH_HEIGHT])
        pushes.append([begin, begin + np.r_[direction * length, 0.0]])
    if bad:
        raise _fail(path, f"{len(bad)} of {num_pushes} pushes are no benchmark action: {'; '.join(bad)}; the benchmark "
                          f"pushes along d x {360 // NUM_DIRECTIONS} deg from inside the grid: fix the log or drop "
                          "those steps")
    return np.asarray(actions, np.int64).reshape(-1, 3), np.asarray(pushes, np.float64).reshape(-1, 2, 3)
