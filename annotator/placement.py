"""Placing step 0 without the window: a small JSON file of poses or picked point pairs (`dsr-bench annotate CAPTURE
--place POSES.json`), so that `--auto` and `--export` work headless.

The file (docs/annotator.md, "Placing step 0 without the window"):

    {"objects": {
        "1": [[r00, r01, r02, tx], [r10, r11, r12, ty], [r20, r21, r22, tz], [0, 0, 0, 1]],
        "can_02": {"mesh": [[x, y, z], ...], "cloud": [[x, y, z], ...]}
    }}

Keys: an object's number (from 1, as the panel and the messages number them) or its name in the capture. Values:
the object's 4x4 pose (object frame -> table frame, metres, row-major: a list of 4 rows) or three or more picked
point pairs (`mesh`: points in the object's mesh frame, `cloud`: the matching points in the table frame, metres).
Objects left out keep their pose. Each listed object is placed at step 0 (`Session.place` or
`Session.init_from_picks`) and then snapped (`Session.snap`; a rejected snap keeps the placed pose).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dsr_bench.errors import UserError

#: How far (max abs entry of R^T R - I, and |det R - 1|) a given rotation may be from a proper rotation.
ROTATION_TOLERANCE = 1e-4


def _fail(path: Path, message: str) -> UserError:
    return UserError(f"--place {path}: {message}; see docs/annotator.md, 'Placing step 0 without the window'")


def pose_matrix(path: Path, where: str, value) -> np.ndarray:
    """A 4x4 object-to-table pose from a JSON value (4 rows of 4 numbers), checked (UserError naming `where`)."""
    from dsr_bench.annotator.inputs import numbers

    if not numbers(value, (4, 4)):  # JSON numbers: true or "0.5" is refused, not converted
        raise _fail(path, f"{where}: a pose must be 4 rows of 4 finite numbers (object -> table, metres)")
    m = np.asarray(value, dtype=np.float64)
    rot = m[:3, :3]
    if not np.allclose(m[3], [0, 0, 0, 1]):
        raise _fail(path, f"{where}: the pose's last row must be [0, 0, 0, 1]")
    if np.abs(rot.T @ rot - np.eye(3)).max() > ROTATION_TOLERANCE or abs(np.linalg.det(rot) - 1) > ROTATION_TOLERANCE:
        raise _fail(path, f"{where}: the pose's upper-left 3x3 is not a rotation (orthonormal, det +1); write R, not "
                          "a scaled or mirrored matrix, row-major")
    if np.abs(m[:3, 3]).max() > 5.0:
        raise _fail(path, f"{where}: translation {m[:3, 3].tolist()} is not in metres on the table")
    return m


def _object_index(path: Path, session, key: str) -> int:
    names = [o.name for o in session.capture.objects]
    if key in names:
        return names.index(key)
    if key.isdigit() and 1 <= int(key) <= session.num_objects:
        return int(key) - 1
    raise _fail(path, f"object {key!r} is not in capture {session.capture.name!r}: use its number "
                      f"1..{session.num_objects} or its name ({', '.join(names)})")


def read_placements(path: str | Path, session) -> dict[int, tuple[str, np.ndarray | tuple[np.ndarray, np.ndarray]]]:
    """The placements of a file: {object index: ("pose", 4x4) or ("picks", (mesh (k, 3), cloud (k, 3)))}."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"--place {path}: no such file; give the JSON file of step 0's poses or picks") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise _fail(path, f"unreadable JSON ({exc})") from None
    objects = data.get("objects") if isinstance(data, dict) else None
    if not isinstance(objects, dict) or not objects:
        raise _fail(path, 'expected {"objects": {"1": 4x4 pose or {"mesh": ..., "cloud": ...}, ...}}')
    out: dict[int, tuple[str, np.ndarray | tuple[np.ndarray, np.ndarray]]] = {}
    for key, value in objects.items():
        obj = _object_index(path, session, str(key))
        where = f"object {key!r}"
        if obj in out:
            raise _fail(path, f"{where}: object {obj + 1} is given twice (by number and by name)")
        if isinstance(value, dict):
            if set(value) != {"mesh", "cloud"}:
                raise _fail(path, f"{where}: picks must be {{\"mesh\": [[x, y, z], ...], \"cloud\": [[x, y, z], ...]}}")
            from dsr_bench.annotator.inputs import numbers

            if not all(isinstance(value[k], list) and value[k] and all(numbers(p, (3,)) for p in value[k])
                       for k in ("mesh", "cloud")):
                raise _fail(path, f"{where}: mesh and cloud must be lists of [x, y, z] points (finite numbers, "
                                  "metres)")
            mesh, cloud = (np.asarray(value[k], dtype=np.float64) for k in ("mesh", "cloud"))
            out[obj] = ("picks", (mesh, cloud))
        else:
            out[obj] = ("pose", pose_matrix(path, where, value))
    return out


def place_step0(session, path: str | Path) -> list[str]:
    """Place the file's objects at step 0 and snap each; returns one summary line per object."""
    placements = read_placements(path, session)
    session.go_to(0)  # step 0 is always visited: only the cursor moves
    lines = []
    for obj, (kind, value) in sorted(placements.items()):
        try:
            if kind == "pose":
                session.place(obj, value)
            else:
                session.init_from_picks(obj, *value)
        except UserError as exc:
            raise UserError(f"--place {path}: object {obj + 1}: {exc}") from None
        score = session.snap(obj)
        what = "snapped" if score.kept and score.accepted else ("snap kept, fit poor" if score.kept else
                                                                 "placed, snap rejected")
        lines.append(f"object {obj + 1} ({session.capture.objects[obj].name}): {what} ({score.reason})")
    return lines
