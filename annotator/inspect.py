"""`dsr-bench import-capture SRC --inspect`: what a recording holds, before anything is converted (issue 32 part 5).

For a folder of RealSense recordings (front.bag / front.db3, back.bag / back.db3): per recording what it is
(container, librealsense's file version, the writer it points to, the device and its sensors, the frames' clock),
its colour and depth streams (topic, size, frame count, frame rate, gaps between frames and skipped frame numbers),
each stream's intrinsics and distortion model, the depth units, the depth -> colour transform, how much of the first
depth frame is measured, and the ChArUco board's detection in the frame the import would calibrate from; then the
steps file's times and how far each is from its frames. For a folder of step PNGs: the rig file's cameras (size,
intrinsics, distortion, depth scale, extrinsics or board), per camera the step images found (numbers, gaps in the
numbering, missing colour or depth, sizes and types from the PNG headers), the first depth image's coverage and the
board's detection; the step numbers against the push log ("between", as the import checks them); the push log's
count.

Nothing is written. What the import would refuse is collected as problems (each one line naming the file and the
fix) instead of stopping at the first: `inspect` returns the report's lines and the problems.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dsr_bench.errors import UserError

#: An interval between frames longer than this many times the median interval counts as a gap (dropped frames).
GAP_FACTOR = 1.5


@dataclass
class Report:
    """The inspection of a recording: lines to print, and the problems the import would refuse (one line each)."""

    lines: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    def add(self, line: str) -> None:
        self.lines.append(line)

    def problem(self, line: str) -> None:
        self.problems.append(line)
        self.lines.append(f"  PROBLEM: {line}")


def _intrinsics(k: np.ndarray) -> str:
    k = np.asarray(k, np.float64)
    return f"fx {k[0, 0]:.2f}, fy {k[1, 1]:.2f}, cx {k[0, 2]:.2f}, cy {k[1, 2]:.2f} px"


def _coeffs(c) -> str:
    return "[" + ", ".join(f"{float(x):.4g}" for x in np.asarray(c).reshape(-1)) + "]"


def frame_timing(stamps: np.ndarray, seqs: np.ndarray | None = None) -> str:
    """One line on a stream's timing: frame count, span (s), rate (fps, from the median interval), the gaps (intervals
    over GAP_FACTOR x the median: how many, the largest and when) and the frame numbers skipped (seq jumps)."""
    t = np.asarray(stamps, np.float64)
    if len(t) < 2:
        return f"{len(t)} frame{'s' if len(t) != 1 else ''}"
    dt = np.diff(t)
    median = float(np.median(dt))
    gaps = np.nonzero(dt > GAP_FACTOR * median)[0] if median > 0 else np.zeros(0, np.int64)
    line = f"{len(t)} frames over {t[-1] - t[0]:.2f} s ({t[0]:.3f}..{t[-1]:.3f}), {1 / median:.1f} fps" if median > 0 \
        else f"{len(t)} frames, all at one time {t[0]:.3f}"
    if len(gaps):
        worst = int(gaps[np.argmax(dt[gaps])])
        line += (f"; {len(gaps)} gap{'s' if len(gaps) > 1 else ''} over {GAP_FACTOR:g} frames (largest "
                 f"{dt[worst] * 1000:.0f} ms after {t[worst]:.3f} s)")
    else:
        line += "; no gaps"
    if seqs is not None and len(seqs) > 1:
        skipped = int(np.clip(np.diff(np.asarray(seqs, np.int64)) - 1, 0, None).sum())
        line += f"; {skipped} frame numbers skipped" if skipped else "; no frame numbers skipped"
    return line


def _depth_coverage(depth_units: np.ndarray, scale_m: float) -> str:
    valid = depth_units > 0
    if not valid.any():
        return "no pixel measured"
    low, mid, high = np.percentile(depth_units[valid], [5, 50, 95]) * scale_m
    return f"{valid.mean():.0%} of pixels measured, median {mid:.3f} m, {low:.3f}..{high:.3f} m (5-95%)"


def _board(report: Report, spec: dict, where: str, image: np.ndarray, intrinsics: np.ndarray, label: str) -> None:
    """The board's detection in one undistorted colour image: corners, reprojection, the camera's height."""
    import cv2

    from dsr_bench.annotator.calibrate import MIN_CORNERS, board_view, parse_board

    try:
        board = parse_board(where, spec["board"])
        gray = cv2.cvtColor(np.ascontiguousarray(image, np.uint8), cv2.COLOR_RGB2GRAY)
        corners, ids, _, _ = cv2.aruco.CharucoDetector(board.cv_board()).detectBoard(gray)
        count = 0 if ids is None else len(ids)
        total = (board.squares[0] - 1) * (board.squares[1] - 1)
        if count < MIN_CORNERS:
            report.problem(f"{label}: {count} of the board's {total} ChArUco corners found (at least {MIN_CORNERS} "
                           "needed): check the board's squares, dictionary and lengths in the rig file, and that the "
                           "board lies in view")
            return
        view = board_view(image, intrinsics, board, label)
        report.add(f"  board in {label}: {count} of {total} corners, reprojection {view.reprojection_px:.2f} px, "
                   f"camera {view.extrinsics[2, 3]:.3f} m above the table")
    except UserError as exc:
        report.problem(str(exc))


def inspect_source(src: str | Path, rig: str | Path | None = None, pushes: str | Path | None = None,
                   steps: str | Path | None = None, max_gap_ms: float | None = None) -> Report:
    """Inspect SRC, a folder of RealSense recordings or of step PNGs (module docstring), converting nothing. A folder
    that is neither (or both) is a UserError; anything else wrong is a problem in the report."""
    from dsr_bench.annotator.importer import IMAGE_PATTERN
    from dsr_bench.annotator.realsense import recordings_in

    src = Path(src)
    if not src.is_dir():
        raise UserError(f"{src}: no such folder; give the folder of <camera>_color_<N>.png / _depth_<N>.png images or "
                        "of front.bag / back.bag (.db3) recordings")
    has_bags = bool(recordings_in(src))
    has_pngs = any(IMAGE_PATTERN.match(p.name) for p in src.iterdir())
    if has_bags and has_pngs:
        raise UserError(f"{src}: holds both RealSense recordings (.bag, .db3) and <camera>_color_<N>.png images; keep "
                        "one form per folder")
    if has_bags:
        return _inspect_bags(src, rig, pushes, steps, max_gap_ms)
    if not has_pngs:
        raise UserError(f"{src}: holds no RealSense recordings (<camera>.bag, <camera>.db3 or a ROS2 bag directory) "
                        "and no <camera>_color_<N>.png / _depth_<N>.png images; give the folder of a recording "
                        "(docs/annotator.md, 'Real captures in')")
    if steps is not None or max_gap_ms is not None:
        raise UserError(f"{src}: --steps and --max-gap-ms pick frames of .bag recordings; this folder holds none "
                        "(step PNGs are numbered by their names)")
    return _inspect_pngs(src, rig, pushes)


def _rig(report: Report, src: Path, rig) -> tuple[Path | None, dict]:
    from dsr_bench.annotator.rig import load_rig

    try:
        path, spec = load_rig(src, rig)
    except UserError as exc:
        report.problem(str(exc))
        return None, {}
    board = spec.get("board")
    objects = spec.get("objects")
    what = [f"{len(objects)} objects" if isinstance(objects, list) else "no objects"]
    if isinstance(board, dict):
        what.append(f"board {board.get('squares')} squares of {board.get('square_length')} m "
                    f"({board.get('dictionary')})")
    report.add(f"rig file {path}: " + ", ".join(what))
    return path, spec


def _inspect_bags(src: Path, rig, pushes, steps, max_gap_ms) -> Report:
    from dsr_bench.annotator.bag import open_recording, read_frame
    from dsr_bench.annotator.realsense import (DEFAULT_MAX_GAP_MS, STEPS_FILE, find_recordings, load_frames,
                                               pick_frames, read_step_times, recordings_in)
    from dsr_bench.annotator.rig import default_file

    report = Report()
    report.add(f"{src}: RealSense recordings")
    bags = {}
    try:
        bags = find_recordings(src)
    except UserError as exc:
        report.problem(str(exc))
        bags = {p.name if p.is_dir() else p.stem: p for p in recordings_in(src)}
    rig_path, spec = _rig(report, src, rig)
    recordings = {}
    for name, path in bags.items():
        size = sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else path.stat().st_size
        report.add(f"{path.name} ({name} camera, {size / 1e6:.1f} MB):")
        try:
            rec = open_recording(path, name)
        except UserError as exc:
            report.problem(str(exc))
            continue
        recordings[name] = rec
        _about(report, rec)
        for kind, stream in (("colour", rec.color), ("depth", rec.depth)):
            info = stream.info
            timing = frame_timing(stream.stamps, stream.seqs)
            report.add(f"  {kind} {stream.topic}: {info.width}x{info.height}, {timing}")
            note = "" if info.distorted else " (all coefficients 0: no undistortion needed)"
            report.add(f"    intrinsics {_intrinsics(info.intrinsics)}; distortion model {info.model!r} "
                       f"{_coeffs(info.coeffs)}{note}")
        m = rec.depth_to_color
        angle = np.degrees(np.arccos(np.clip((np.trace(m[:3, :3]) - 1) / 2, -1, 1)))
        report.add(f"  depth units {rec.depth_scale:g} m per unit ({rec.depth_scale * 1000:g} mm); depth -> colour "
                   f"{np.linalg.norm(m[:3, 3]) * 1000:.1f} mm, {angle:.2f} deg")
    gap_ms = DEFAULT_MAX_GAP_MS if max_gap_ms is None else max_gap_ms
    times, board_times = None, None
    steps_path = default_file(src, steps, STEPS_FILE, "the steps file")
    if recordings:
        try:
            times, board_times = read_step_times(steps_path, list(recordings))
        except UserError as exc:
            report.problem(str(exc))
    if times is not None:
        report.add(f"steps file {steps_path}: {len(next(iter(times.values())))} step times"
                   + (", a board time" if board_times is not None else ", no board time (step 0 calibrates)"))
        for name, rec in recordings.items():
            c_st, d_st = rec.color.stamps, rec.depth.stamps
            ci = np.abs(c_st[None, :] - times[name][:, None]).argmin(axis=1)
            di = np.abs(d_st[None, :] - c_st[ci][:, None]).argmin(axis=1)
            gaps = np.abs(c_st[ci] - times[name]) * 1000
            dgaps = np.abs(d_st[di] - c_st[ci]) * 1000
            report.add(f"  {name}: step time -> colour frame {gaps.min():.0f}..{gaps.max():.0f} ms, colour -> depth "
                       f"frame {dgaps.min():.0f}..{dgaps.max():.0f} ms (limit {gap_ms:g} ms)")
            try:
                picked = pick_frames(rec, times[name], gap_ms / 1000, f"--steps {steps_path}")
                d0 = int(picked[1][0])
                report.add(f"    step 0 depth frame {int(rec.depth.seqs[d0])}: "
                           f"{_depth_coverage(read_frame(rec, 'depth', d0), rec.depth_scale)}")
            except UserError as exc:
                report.problem(str(exc))
        _pushes(report, src, pushes, len(next(iter(times.values()))) - 1)
    if isinstance(spec.get("board"), dict) and rig_path is not None:
        for name, rec in recordings.items():
            label = f"{rec.path.name} first frame"
            ci, di = 0, 0
            try:
                if board_times is not None:
                    (ci,), (di,) = pick_frames(rec, board_times[name], gap_ms / 1000, f"--steps {steps_path}", "board")
                    label = f"{rec.path.name} board_time frame {int(rec.color.seqs[ci])}"
                elif times is not None:
                    (ci,), (di,) = pick_frames(rec, times[name][:1], gap_ms / 1000, f"--steps {steps_path}")
                    label = f"{rec.path.name} step 0 frame {int(rec.color.seqs[ci])}"
                frames = load_frames(rec, int(ci), int(di))
            except UserError as exc:
                report.problem(str(exc))
                continue
            report.add(f"{name}:")
            _board(report, spec, str(rig_path), frames.color, rec.color.info.intrinsics, label)
    return report


def _about(report: Report, rec) -> None:
    """What a recording is (`annotator.bag.Recording.about`): container and writer, device, sensors, clock."""
    about = rec.about
    version = about.get("file_version")
    report.add(f"  format: {about.get('container')}, librealsense file version "
               f"{'unknown (no /file_version)' if version is None else version}: written by {about.get('writer')}")
    sensors = about.get("sensors") or {}
    report.add(f"  device: {about.get('device') or 'unnamed'} (serial {about.get('serial') or '?'}, firmware "
               f"{about.get('firmware') or '?'}); sensors: depth {sensors.get('depth', '?')!r}, colour "
               f"{sensors.get('colour', '?')!r}")
    clock = f"frame timestamps, domain {about.get('timestamp_domain') or 'not recorded'}"
    if about.get("header_stamps") == "from the recording's start":
        clock += (f"; header stamps count from the recording's start, at frame timestamp "
                  f"{about.get('recording_start', 0.0):.3f} s (step times: frame timestamps)")
    report.add(f"  clock: {clock}")


def _step_numbers(report: Report, src: Path, pushes, numbers: list[int], found: dict) -> None:
    """The step numbers as the import checks them: without "between" in the push log they run without a gap, with it
    each push lies between its two numbers (`annotator.importer.check_step_numbers`)."""
    from dsr_bench.annotator.importer import check_step_numbers, logged_between
    from dsr_bench.annotator.rig import PUSHES_FILE, default_file
    from dsr_bench.constants import MODEL_CAMERA

    front = found.get((MODEL_CAMERA, "color"), {})
    if len(numbers) < 2 or any(n not in front for n in numbers):
        return  # missing images are reported per camera
    try:
        log = default_file(src, pushes, PUSHES_FILE, "the push log")
    except UserError:
        return  # `_pushes` reports it
    try:
        check_step_numbers(src, numbers, {(MODEL_CAMERA, "color", n): p for n, p in front.items()},
                           logged_between(log), log)
    except UserError as exc:
        report.problem(str(exc))


def _pushes(report: Report, src: Path, pushes, count: int) -> None:
    """The push log: how many pushes, and whether each maps to a benchmark action (`annotator.pushes`)."""
    from dsr_bench.annotator.pushes import read_pushes
    from dsr_bench.annotator.rig import PUSHES_FILE, default_file

    try:
        path = default_file(src, pushes, PUSHES_FILE, "the push log")
        read_pushes(path, count)
        report.add(f"push log {path}: {count} pushes, each a benchmark action")
    except UserError as exc:
        report.problem(str(exc))


def _inspect_pngs(src: Path, rig, pushes) -> Report:
    from dsr_bench.annotator.importer import CAMERA_NAMES, IMAGE_PATTERN, read_camera
    from dsr_bench.annotator.inputs import png_shape
    from dsr_bench.annotator.rig import undistort, undistort_maps

    report = Report()
    report.add(f"{src}: step PNGs")
    rig_path, spec = _rig(report, src, rig)
    found: dict[tuple[str, str], dict[int, Path]] = {}
    for entry in sorted(src.iterdir()):
        m = IMAGE_PATTERN.match(entry.name)
        if m is not None:
            found.setdefault((m["camera"], m["kind"]), {})[int(m["step"])] = entry
    cams_spec: dict = spec["cameras"] if isinstance(spec.get("cameras"), dict) else {}
    names = sorted({c for c, _ in found} | set(cams_spec), key=lambda n: (n not in CAMERA_NAMES, n))
    numbers = sorted(set().union(*(set(v) for v in found.values()))) if found else []
    for name in names:
        if name not in CAMERA_NAMES:
            report.problem(f"{src}: camera {name!r} (images or rig file) is not one of {', '.join(CAMERA_NAMES)}; "
                           "rename it")
            continue
        report.add(f"{name}:")
        camera, distortion = None, None
        if rig_path is not None and name in cams_spec:
            try:
                camera, distortion, given = read_camera(rig_path, name, cams_spec[name])
                report.add(f"  rig: {camera.width}x{camera.height}, intrinsics {_intrinsics(camera.intrinsics)}; "
                           + (f"distortion OpenCV (Brown-Conrady) {_coeffs(distortion)}, undistorted on import"
                              if distortion is not None else "no distortion given (pinhole)")
                           + f"; depth_scale {camera.depth_scale:g} m per unit; extrinsics "
                           + ("given" if given else "from the board"))
            except UserError as exc:
                report.problem(str(exc))
        elif rig_path is not None:
            report.problem(f"{rig_path}: no camera {name!r}, but {src} holds its images; add it to \"cameras\"")
        for kind in ("color", "depth"):
            have = found.get((name, kind), {})
            missing = [n for n in numbers if n not in have]
            line = f"  {kind}: {len(have)} images"
            if have:
                ns = sorted(have)
                steps_between = np.diff(ns) if len(ns) > 1 else np.zeros(0, np.int64)
                line += f", numbers {ns[0]}..{ns[-1]}"
                if len(steps_between):
                    line += (" consecutive" if steps_between.max() == 1 else
                             f", spacing {steps_between.min()}..{steps_between.max()}")
                shape, dtype, bits, colour = png_shape(have[ns[0]])
                line += f"; {ns[0]}: {shape[1]}x{shape[0]}, {bits}-bit, PNG colour type {colour}"
                if camera is not None and shape[:2] != (camera.height, camera.width):
                    report.add(line)
                    line = ""
                    report.problem(f"{have[ns[0]]}: {shape[1]}x{shape[0]}, the rig file says {camera.width}x"
                                   f"{camera.height} for {name!r}; fix the rig file or the images")
            if line:
                report.add(line)
            if missing:
                listed = ", ".join(f"{name}_{kind}_{n}.png" for n in missing[:3]) + (" ..." if len(missing) > 3 else "")
                report.problem(f"{src}: no {listed} ({len(missing)} step number(s) held by another camera or kind): "
                               "every camera needs colour and depth at every step")
        depth_files = found.get((name, "depth"), {})
        if camera is not None and depth_files:
            from dsr_bench.annotator.importer import read_image

            first = depth_files[min(depth_files)]
            try:
                report.add(f"  {first.name}: {_depth_coverage(read_image(first, camera, 'depth'), camera.depth_scale)}")
            except UserError as exc:
                report.problem(str(exc))
        if camera is not None and isinstance(spec.get("board"), dict) and rig_path is not None:
            images = spec["board"].get("images") or {}
            given_image = images.get(name) if isinstance(images, dict) else None
            if isinstance(given_image, dict):
                given_image = given_image.get("color")
            colors = found.get((name, "color"), {})
            path = src / given_image if isinstance(given_image, str) else (colors[min(colors)] if colors else None)
            if path is not None and path.is_file():
                from dsr_bench.annotator.importer import read_image

                try:
                    image = read_image(path, camera, "color")
                    if distortion is not None:
                        image = undistort(image, undistort_maps(camera, distortion), nearest=False)
                    _board(report, spec, str(rig_path), image, camera.intrinsics, path.name)
                except UserError as exc:
                    report.problem(str(exc))
    report.add(f"steps: {len(numbers)} step numbers ({len(numbers) - 1} pushes)" if numbers else "steps: none")
    _step_numbers(report, src, pushes, numbers, found)
    _pushes(report, src, pushes, len(numbers) - 1)
    return report
