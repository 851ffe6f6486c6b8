"""`dsr-bench import-capture` of RealSense recordings (docs/annotator.md, "Real captures in", "RealSense
recordings").

The folder:

    SRC/front.bag, SRC/back.bag  one librealsense recording per camera (realsense-viewer, rs-record, rs2::recorder),
    (or .db3, or a directory)    the name naming the camera: `<camera>.bag` (ROS1, librealsense up to 2.57),
                                 `<camera>.db3` (ROS2 SQLite, 2.58 on) or `<camera>/` (a ROS2 bag directory with
                                 metadata.yaml); read with `rosbags` and sqlite3 (`annotator.bag`), no librealsense
    SRC/steps.json               {"step_times": [t0, ..., tT]}: per step the time (s, on the frames' timestamp clock:
                                 librealsense's frame timestamp, the ROS1 header stamp, a ROS2 frame's metadata
                                 timestamp) at which the rig saw step N; or {"step_times": {"front": [...], "back":
                                 [...]}} per camera; optional "board_time" (the same forms): when the board lay alone
                                 on the table
    SRC/rig.json                 objects, board and/or per-camera "extrinsics" (intrinsics, depth scale: recordings)
    SRC/pushes.json              the robot's push log (annotator.pushes)

Per step the colour frame whose timestamp is nearest the step time is taken, and the depth frame nearest that
colour frame; either further than `max_gap` (default DEFAULT_MAX_GAP_MS) is refused. Reading the recordings is
`annotator.bag`'s, undistorting colour and registering depth to it `annotator.registration`'s; the rig file and the
board calibration `annotator.rig`'s.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dsr_bench.annotator.bag import HINT, Recording, open_recording, read_frame
from dsr_bench.annotator.inputs import finite, is_number, numbers, resolved_inside
from dsr_bench.annotator.registration import align_depth
from dsr_bench.annotator.rig import (PUSHES_FILE, calibrate_cameras, capture_name, check_out, default_file, load_rig,
                                     read_objects, undistort)
from dsr_bench.constants import CAMERAS
from dsr_bench.dataset.capture import parse_camera, write_capture
from dsr_bench.errors import UserError

#: A step's colour frame must lie this close (ms) to the step time, and its depth frame this close to the colour.
DEFAULT_MAX_GAP_MS: float = 50.0
STEPS_FILE = "steps.json"
#: A camera's recording in SRC: `<camera>.bag`, `<camera>.db3`, or a directory `<camera>/` holding ROS2_METADATA.
RECORDING_SUFFIXES = (".bag", ".db3")
ROS2_METADATA = "metadata.yaml"


def _times(path: Path, key: str, value, names: list[str], count: int | None) -> dict[str, np.ndarray]:
    """Per camera the times (s) of a steps-file entry: one list for all cameras or {"front": [...], ...}."""
    per = value if isinstance(value, dict) else {n: value for n in names}
    if isinstance(value, dict) and sorted(per) != sorted(names):
        raise UserError(f"--steps {path}: {key} names cameras {sorted(per)}, the bags {sorted(names)}: give one list "
                        "for all cameras or one per bag")
    out = {}
    for n in names:
        value = per[n]
        try:
            if not (finite(value) or isinstance(value, list) and all(is_number(v) for v in value)):
                raise TypeError("not JSON numbers")
            t = np.asarray(value, np.float64).reshape(-1 if count is None else count)
        except (TypeError, ValueError):
            what = "a list of times (s)" if count is None else "one time (s)"
            raise UserError(f"--steps {path}: {key}{'' if len(per) == 1 else f' of {n}'} must be {what}, e.g. "
                            '{"step_times": [1716985201.52, 1716985214.03, ...]}') from None
        if not np.all(np.isfinite(t)):
            raise UserError(f"--steps {path}: {key} must be finite numbers (s)")
        if count is None and (len(t) < 2 or np.any(np.diff(t) <= 0)):
            raise UserError(f"--steps {path}: {key} must be 2 or more increasing times (s), one per step (T + 1 for T "
                            f"pushes); got {t.tolist()[:5]}")
        out[n] = t
    return out


def read_step_times(path: Path, names: list[str]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray] | None]:
    """Per camera the step times (T + 1,) s and the board time (1,) s or None, from a steps file (module
    docstring); UserError naming the file and the fix."""
    if not path.is_file():
        raise UserError(f"--steps {path}: no such file; write the time (s, the frames' timestamps) of every step as "
                        '{"step_times": [t0, t1, ...]} (' + HINT + ")")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise UserError(f"--steps {path}: unreadable JSON ({exc}); fix the file") from None
    if not isinstance(data, dict) or "step_times" not in data:
        raise UserError(f'--steps {path}: expected {{"step_times": [t0, t1, ...]}} (s, the frames\' timestamps; or '
                        '{"front": [...], "back": [...]}) and optionally "board_time"')
    steps = _times(path, "step_times", data["step_times"], names, None)
    if len({len(t) for t in steps.values()}) > 1:
        raise UserError(f"--steps {path}: the cameras have different numbers of step times "
                        f"({', '.join(f'{n} {len(t)}' for n, t in steps.items())}); give one per step for every camera")
    board = _times(path, "board_time", data["board_time"], names, 1) if data.get("board_time") is not None else None
    return steps, board


def _nearest(stamps: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Index of the stamp (sorted (N,)) nearest each time (M,)."""
    right = np.clip(np.searchsorted(stamps, times), 1, len(stamps) - 1) if len(stamps) > 1 else np.zeros(
        len(times), np.int64)
    if len(stamps) == 1:
        return right
    left = right - 1
    return np.where(np.abs(stamps[left] - times) <= np.abs(stamps[right] - times), left, right)


def pick_frames(recording: Recording, times: np.ndarray, max_gap_s: float, where: str, label: str = "step"
                ) -> tuple[np.ndarray, np.ndarray]:
    """(colour, depth) frame indices (M,) for the times (M,) s: the colour frame nearest each time, the depth frame
    nearest that colour frame. UserError naming `where` when a gap exceeds `max_gap_s` or two times share a frame."""
    c_st, d_st = recording.color.stamps, recording.depth.stamps
    color = _nearest(c_st, times)
    gap = np.abs(c_st[color] - times)

    def what(i: int) -> str:
        return f"step {i}" if label == "step" else f"the {label}"

    for i in np.nonzero(gap > max_gap_s)[0].tolist():
        raise UserError(f"{where}: {what(i)} time {times[i]:.3f} s has no {recording.name} colour frame within "
                        f"{max_gap_s * 1000:g} ms (nearest {c_st[color[i]]:.3f} s, {gap[i] * 1000:.0f} ms away; its "
                        f"colour frames span {c_st[0]:.3f}..{c_st[-1]:.3f} s in {recording.path.name}): give times on "
                        "the frames' timestamp clock, or raise --max-gap-ms")
    depth = _nearest(d_st, c_st[color])
    dgap = np.abs(d_st[depth] - c_st[color])
    for i in np.nonzero(dgap > max_gap_s)[0].tolist():
        raise UserError(f"{where}: the {recording.name} colour frame of {what(i)} ({c_st[color[i]]:.3f} s) has no "
                        f"depth frame within {max_gap_s * 1000:g} ms (nearest {dgap[i] * 1000:.0f} ms away in "
                        f"{recording.path.name}): record depth and colour together, or raise --max-gap-ms")
    shared = np.nonzero(np.diff(color) == 0)[0]
    if len(shared):
        i = int(shared[0])
        raise UserError(f"{where}: steps {i} and {i + 1} both take {recording.name} colour frame "
                        f"{c_st[color[i]]:.3f} s (their times are closer than a frame apart); give each step its own "
                        "time")
    return color, depth


@dataclass
class Frames:
    """A step's images of one camera: undistorted colour (H, W, 3) uint8 RGB, registered depth (H, W) m, and where
    they came from (frame timestamps s, frame numbers)."""

    color: np.ndarray
    depth: np.ndarray
    source: dict


def load_frames(recording: Recording, color_index: int, depth_index: int) -> Frames:
    """The colour frame undistorted (`annotator.registration.undistortion_maps`, bilinear) and the depth frame
    registered to it (`align_depth`)."""
    color = read_frame(recording, "colour", color_index)
    if recording.color_maps is not None:
        color = undistort(color, recording.color_maps, nearest=False)
    raw = read_frame(recording, "depth", depth_index).astype(np.float64) * recording.depth_scale
    info = recording.color.info
    depth = align_depth(raw, recording.depth_corner_rays, recording.depth_to_color, info.intrinsics,
                        (info.height, info.width))
    source = {"color_stamp": float(recording.color.stamps[color_index]),
              "color_seq": int(recording.color.seqs[color_index]),
              "depth_stamp": float(recording.depth.stamps[depth_index]),
              "depth_seq": int(recording.depth.seqs[depth_index])}
    return Frames(color, depth, source)


def recordings_in(src: Path) -> list[Path]:
    """SRC's RealSense recordings: `*.bag` and `*.db3` files and ROS2 bag directories (holding metadata.yaml)."""
    return sorted(p for p in src.iterdir() if p.is_dir() and (p / ROS2_METADATA).is_file()
                  or p.suffix in RECORDING_SUFFIXES and not p.is_dir())


def find_recordings(src: Path) -> dict[str, Path]:
    """SRC's recordings by camera name (a file's stem, a directory's name), the names checked as the PNG form's:
    `front` required, `back` optional, nothing else, one recording per camera."""
    found: dict[str, list[Path]] = {}
    for path in recordings_in(src):
        found.setdefault(path.name if path.is_dir() else path.stem, []).append(path)
    twice = {n: ps for n, ps in found.items() if len(ps) > 1}
    if twice:
        name, paths = next(iter(twice.items()))
        raise UserError(f"{src}: {' and '.join(p.name for p in paths)} both record camera {name!r}; keep one "
                        "recording per camera")
    recordings = {n: resolved_inside(src, ps[0], "recording", src) for n, ps in found.items()}
    bad = [n for n in recordings if n not in CAMERAS]  # the benchmark's cameras (the PNG form's rig cameras too)
    if bad or "front" not in recordings:
        listed = ", ".join(p.name for p in recordings.values())
        raise UserError(f"{src}: the recordings ({listed}) must be front.bag (or front.db3, or a ROS2 bag directory "
                        f"front/: the view models see; required) and back.bag: rename "
                        f"{', '.join(recordings[n].name for n in bad) or 'one of them to front.bag'} (the name names "
                        "the camera)")
    return {n: recordings[n] for n in CAMERAS if n in recordings}


def import_bags(src: str | Path, out: str | Path, *, rig: str | Path | None = None, pushes: str | Path | None = None,
                steps: str | Path | None = None, max_gap_ms: float = DEFAULT_MAX_GAP_MS, name: str | None = None,
                overwrite: bool = False) -> tuple[Path, dict]:
    """Import SRC's RealSense recordings (module docstring) into the capture directory `out`; returns (out,
    calibration report). Everything is read and checked first (one-line UserErrors), then written at once."""
    from dsr_bench.annotator.pushes import read_pushes

    src, out = Path(src), Path(out)
    check_out(out, overwrite)
    if not (math.isfinite(max_gap_ms) and max_gap_ms > 0):
        raise UserError(f"--max-gap-ms {max_gap_ms} must be a positive number of milliseconds")
    bags = find_recordings(src)
    names = list(bags)
    rig_path, spec = load_rig(src, rig)
    rig_cameras = spec.get("cameras", {}) or {}
    if not isinstance(rig_cameras, dict) or any(n not in bags for n in rig_cameras):
        raise UserError(f"{rig_path}: \"cameras\" {list(rig_cameras)} must name only the bags' cameras "
                        f"({', '.join(names)}); see {HINT}")
    for n, entry in rig_cameras.items():
        extra = sorted(set(entry) - {"extrinsics"}) if isinstance(entry, dict) else ["(not an object)"]
        if extra:
            raise UserError(f"{rig_path}: camera {n!r} gives {', '.join(extra)}, but with bags the intrinsics, "
                            f"distortion and depth scale come from {bags[n].name}: keep only \"extrinsics\" (4x4 "
                            "camera-to-table, m)")
        if entry.get("extrinsics") is not None and not numbers(entry["extrinsics"], (4, 4)):
            raise UserError(f"{rig_path}: camera {n!r} extrinsics must be a 4x4 matrix of numbers (camera-to-table, "
                            f"metres, row-major); see {HINT}")
    if isinstance(spec.get("board"), dict) and spec["board"].get("images"):
        raise UserError(f"{rig_path}: board \"images\" are PNGs of the folder form; with bags give \"board_time\" (s) "
                        "in the steps file (the board alone on the table), or let the first step's frames be used")
    objects = read_objects(rig_path, src, spec.get("objects"))
    title = capture_name(name, spec, rig_path, out)
    steps_path = default_file(src, steps, STEPS_FILE, "the steps file")
    step_times, board_times = read_step_times(steps_path, names)
    count = len(step_times["front"])
    actions, pushes_world = read_pushes(default_file(src, pushes, PUSHES_FILE, "the push log"), count - 1)

    recordings = {n: open_recording(bags[n], n) for n in names}
    gap = max_gap_ms / 1000
    picks = {n: pick_frames(recordings[n], step_times[n], gap, f"--steps {steps_path}") for n in names}
    cameras, given = {}, {}
    for n in names:
        info = recordings[n].color.info
        given[n] = n in rig_cameras and rig_cameras[n].get("extrinsics") is not None
        full = {"height": info.height, "width": info.width, "intrinsics": info.intrinsics.tolist(),
                "extrinsics": rig_cameras[n]["extrinsics"] if given[n] else np.eye(4).tolist(),
                "depth_scale": recordings[n].depth_scale}
        try:
            cameras[n] = parse_camera(rig_path, n, full)
        except UserError as exc:
            raise UserError(f"{rig_path}: {str(exc).split(': ', 1)[-1]} (extrinsics: camera-to-table, metres, "
                            "row-major)") from None
    frames = [{n: load_frames(recordings[n], int(picks[n][0][t]), int(picks[n][1][t])) for n in names}
              for t in range(count)]

    def board_image(n: str) -> tuple[str, np.ndarray, np.ndarray]:
        if board_times is None:
            f = frames[0][n]
            return f"{bags[n]} step 0 (colour frame {f.source['color_seq']})", f.color, f.depth
        (ci,), (di,) = pick_frames(recordings[n], board_times[n], gap, f"--steps {steps_path}", "board")
        f = load_frames(recordings[n], int(ci), int(di))
        return f"{bags[n]} board_time (colour frame {f.source['color_seq']})", f.color, f.depth

    report = calibrate_cameras(rig_path, spec, cameras, given, board_image)
    streams = {n: {"color_topic": r.color.topic, "depth_topic": r.depth.topic, "distortion_model": r.color.info.model,
                   "undistorted": r.color_maps is not None, "depth_intrinsics": r.depth.info.intrinsics.tolist(),
                   "depth_to_color": r.depth_to_color.tolist(), "depth_scale": r.depth_scale}
               for n, r in recordings.items()}
    source = {"kind": "real", "importer": "annotator.realsense", "format": "realsense-bag", "src": str(src),
              "rig": spec, "bags": {n: str(p) for n, p in bags.items()}, "streams": streams,
              "recordings": {n: r.about for n, r in recordings.items()},
              "clock": "frame timestamps (s): librealsense's frame clock; ROS1 header stamps, ROS2 frame metadata",
              "step_times": {n: t.tolist() for n, t in step_times.items()}, "max_gap_ms": max_gap_ms,
              "frames": [{n: f[n].source for n in names} for f in frames], "calibration": report,
              "policy": "recorded"}
    written = write_capture(out, name=title, cameras=cameras,
                            colors=[{n: f[n].color for n in names} for f in frames],
                            depths=[{n: f[n].depth for n in names} for f in frames], actions=actions,
                            pushes_world=pushes_world, objects=objects, source=source, overwrite=overwrite)
    return written, report
