"""Write RealSense recordings with librealsense itself, from a simulated capture whose truth is known.

A two-camera capture of the toolkit (`dsr-bench generate-captures`, or one made here with the tests' arguments) is
rendered as a D400 records it: per camera a colour stream (the capture's true camera pose, fy = 1.02 fx, an
off-centre principal point, a ChArUco board on the table, the raw image of a lens with non-zero distortion: the
front camera "Inverse Brown Conrady" as a D435's colour sensor reports it, the back one "Brown Conrady") and a
depth stream from its own virtual depth camera (square pixels, a wider field of view, ~15 mm and ~0.7 degrees off the
colour camera: the depth -> colour extrinsics), depth rounded to the depth unit. Around the board time and each step
time the recording holds the true frame and a decoy 33 ms before and after it (black colour, no depth); depth lags
colour by 4 ms, the back camera by 10 ms more; frame numbers jump between the events (dropped frames). The frames
are fed to a pyrealsense2 `software_device` (sensors "Stereo Module" and "RGB Camera", as a D415 / D435 / D455
names them; intrinsics, distortion, extrinsics, the Depth Units option) recorded by `rs.recorder`: a ROS1 `.bag`
with librealsense up to 2.57, a ROS2 SQLite `.db3` from 2.58 on. Every written frame is played back through
librealsense and counted.

    python scripts/write_realsense_fixture.py OUT [--capture CAPTURE | --steps 1] [--size 360x640]
                                              [--depth-size 240x424] [--device NAME] [--uncompressed]

OUT/ then holds front.<bag|db3>, back.<bag|db3>, rig.json (board, objects), steps.json (step and board times on the
frames' timestamp clock), pushes.json, meshes/ and truth.json (what the recordings were made from: per camera the
colour and depth intrinsics, distortion, depth -> colour, colour camera-to-table, depth units, each frame's stream,
number and timestamp; the release that wrote them). Run it with the pyrealsense2 release to record with, e.g. one
installed beside the project's packages (tests/data/realsense/README.md):

    .venv/bin/pip install --no-deps --target /tmp/rs255 pyrealsense2==2.55.1.6486
    PYTHONPATH=/tmp/rs255 .venv/bin/python scripts/write_realsense_fixture.py tests/data/realsense/v2.55.1
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script from a checkout
    sys.path.insert(0, str(ROOT))

#: The ChArUco board on the table (the rig file's "board"), centred on the workspace: 10 cm squares, large enough
#: for both cameras to find all 12 inner corners in 640 x 360 images (7 x 5 squares of 6 cm: 6 and 8 of 24).
BOARD = {"squares": [5, 4], "square_length": 0.1, "marker_length": 0.075, "dictionary": "DICT_4X4_50",
         "offset": [0.25, 0.2, 0.0]}
BASE_S = 1716985200.0  # frame timestamps: the host's clock (librealsense's global time), s
BOARD_TIME_S, STEP_START_S, STEP_EVERY_S = BASE_S + 0.5, BASE_S + 2.0, 3.0
DEPTH_LAG_S, BACK_LAG_S, PERIOD_S = 0.004, 0.010, 1 / 30
DEPTH_UNITS = 0.001
#: Per camera the colour stream's distortion model (librealsense's name) and coefficients [k1, k2, p1, p2, k3].
DISTORTION = {"front": ("Inverse Brown Conrady", [0.05, -0.02, 0.0005, -0.0003, 0.0]),
              "back": ("Brown Conrady", [-0.04, 0.02, 0.0004, -0.0002, 0.0])}
#: Per camera the depth -> colour transform: rotation (degrees about x, y, z) and translation (m).
DEPTH_TO_COLOR = {"front": ((0.4, -0.6, 0.3), (0.015, -0.0005, 0.0012)),
                  "back": ((-0.3, 0.5, -0.2), (-0.0148, 0.0004, -0.001))}
#: Jitter (s) of the logged step times from their colour frames, and of the board time.
STEP_JITTER_S, BOARD_JITTER_S = (0.007, -0.004, 0.005, -0.006, 0.003), 0.003


@dataclass
class Frame:
    """One frame as fed to librealsense: its stream ("color" or "depth"), number, timestamp (s) and image (colour
    (H, W, 3) uint8 RGB, depth (H, W) uint16 depth units)."""

    stream: str
    number: int
    timestamp_s: float
    image: np.ndarray


@dataclass
class CameraRecording:
    """What one camera's recording is made of: the colour and depth cameras (float32-exact intrinsics), the colour
    distortion, depth -> colour (4x4, p_colour = M p_depth), the colour camera-to-table, and the frames."""

    name: str
    color_k: np.ndarray
    color_shape: tuple[int, int]
    model: str
    coeffs: list[float]
    depth_k: np.ndarray
    depth_shape: tuple[int, int]
    depth_to_color: np.ndarray
    color_to_table: np.ndarray
    frames: list[Frame] = field(default_factory=list)


def _f32(values) -> np.ndarray:
    """Values as librealsense stores them (float32), back in float64."""
    return np.asarray(values, np.float64).astype(np.float32).astype(np.float64)


def _rotation(degrees) -> np.ndarray:
    """The rotation R = Rz Ry Rx of angles (degrees) about x, y, z."""
    rx, ry, rz = (math.radians(d) for d in degrees)
    x = np.array([[1, 0, 0], [0, math.cos(rx), -math.sin(rx)], [0, math.sin(rx), math.cos(rx)]])
    y = np.array([[math.cos(ry), 0, math.sin(ry)], [0, 1, 0], [-math.sin(ry), 0, math.cos(ry)]])
    z = np.array([[math.cos(rz), -math.sin(rz), 0], [math.sin(rz), math.cos(rz), 0], [0, 0, 1]])
    return z @ y @ x


def paint_board(color: np.ndarray, table: np.ndarray, camera) -> np.ndarray:
    """`color` (H, W, 3) with BOARD drawn onto the table where `table` (H, W) bool, through `camera`
    (`dsr_bench.annotator.calibrate.paint_board`)."""
    from dsr_bench.annotator.calibrate import paint_board as paint

    return paint(color, table, camera, BOARD)


def distort(image: np.ndarray, k: np.ndarray, model: str, coeffs) -> np.ndarray:
    """The raw image a lens of librealsense's `model` records of the ideal (pinhole) `image`: "Brown Conrady"
    (OpenCV's: ideal -> raw is the polynomial) or "Inverse Brown Conrady" (raw -> ideal is the polynomial)."""
    import cv2

    h, w = image.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    c = np.asarray(coeffs, np.float64)
    if model == "Inverse Brown Conrady":  # raw pixel p shows the ideal image at K poly(K^-1 p)
        rays = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], -1).reshape(-1, 1, 3)
        ideal = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), k, c)[0].reshape(h, w, 2)
    else:  # raw pixel p shows the ideal image where the polynomial's inverse takes it
        raw = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2).astype(np.float32)
        ideal = cv2.undistortPoints(raw, k, c, P=k).reshape(h, w, 2)
    return cv2.remap(image, ideal[..., 0].astype(np.float32), ideal[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def event_times(name: str, steps: int) -> list[float]:
    """Colour timestamps (s) of the true frames of camera `name`: the board, then steps 0..steps."""
    lag = BACK_LAG_S if name == "back" else 0.0
    return [BOARD_TIME_S + lag] + [STEP_START_S + STEP_EVERY_S * i + lag for i in range(steps + 1)]


def render(capture, size: tuple[int, int], depth_size: tuple[int, int]) -> dict[str, CameraRecording]:
    """Per camera what its recording is made of (module docstring), from `capture` (a `Capture` with truth)."""
    from dsr_bench.annotator.export import renderer_for
    from dsr_bench.geometry import Camera, make_camera

    truth, poses = capture.truth_calibration(), capture.truth_poses()
    if truth is None or poses is None:
        raise SystemExit(f"{capture.path}: not a simulated capture (no truth.json); make one with "
                         "`dsr-bench generate-captures --noise none`")
    recordings, cameras = {}, {}
    for name in ("front", "back"):
        base = Camera(name, *size, make_camera(name, *size).intrinsics, truth[name].extrinsics)
        k = np.asarray(base.intrinsics, np.float64).copy()
        k[1, 1] *= 1.02
        k[:2, 2] += (3.25, -2.5) if name == "front" else (-1.5, 2.75)
        k = _f32(k)
        f = 0.9 * k[0, 0] * depth_size[1] / size[1]  # a wider field of view than the colour camera's
        dk = _f32([[f, 0, depth_size[1] / 2 + 0.3], [0, f, depth_size[0] / 2 - 0.9], [0, 0, 1]])
        rot, shift = DEPTH_TO_COLOR[name]
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = _f32(_rotation(rot)), _f32(shift)
        model, coeffs = DISTORTION[name]
        recordings[name] = CameraRecording(name, k, size, model, list(_f32(coeffs)), dk, depth_size, m,
                                           np.asarray(base.extrinsics, np.float64))
        cameras[name] = Camera(name, *size, k, base.extrinsics)
        cameras[f"{name}_depth"] = Camera(f"{name}_depth", *depth_size, dk, base.extrinsics @ m)
    renderer = renderer_for(capture, cameras)
    hidden = poses[0].copy()
    hidden[:, 2] -= 1.0  # the board alone: the objects below the table
    for i, pose in enumerate([hidden, *poses]):
        scene, ids = renderer.scene(pose)
        for name, rec in recordings.items():
            images = renderer.render_camera(scene, ids, name)
            color = paint_board(images.color, (images.mask == 0) & (images.depth > 0), cameras[name])
            color = distort(color, rec.color_k, rec.model, rec.coeffs)
            depth_m = renderer.render_camera(scene, ids, f"{name}_depth").depth.astype(np.float64)
            depth = np.round(depth_m / DEPTH_UNITS).astype(np.uint16)
            stamp, number = event_times(name, len(poses) - 1)[i], 100 + 10 * i
            for d in (-1, 0, 1):
                rec.frames.append(Frame("color", number + d, stamp + d * PERIOD_S,
                                        color if d == 0 else np.zeros_like(color)))
                rec.frames.append(Frame("depth", number + d, stamp + DEPTH_LAG_S + d * PERIOD_S,
                                        depth if d == 0 else np.zeros_like(depth)))
    for rec in recordings.values():
        rec.frames.sort(key=lambda f: f.timestamp_s)
    return recordings


def layout_sample() -> CameraRecording:
    """A tiny recording of known content, for reading each release's layout exactly: colour 32 x 24 (R = 40 x frame,
    G = 8 x column, B = 10 x row), depth 16 x 12 (500 + 7 x frame + pixel index), frames 7 and 9 (8 dropped) 40 ms
    apart; "Inverse Brown Conrady" colour, depth -> colour of the front camera."""
    rot, shift = DEPTH_TO_COLOR["front"]
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = _f32(_rotation(rot)), _f32(shift)
    rec = CameraRecording("sample", _f32([[30.5, 0, 16.25], [0, 31.75, 11.5], [0, 0, 1]]), (24, 32),
                          "Inverse Brown Conrady", list(_f32(DISTORTION["front"][1])),
                          _f32([[14.5, 0, 8.25], [0, 14.5, 5.75], [0, 0, 1]]), (12, 16), m, np.eye(4))
    v, u = np.mgrid[0:24, 0:32]
    for i, number in enumerate((7, 9)):
        t = BASE_S + 0.04 * i
        color = np.stack([np.full_like(u, 40 * i), 8 * u, 10 * v], -1).astype(np.uint8)
        rec.frames += [Frame("color", number, t, color),
                       Frame("depth", number, t + DEPTH_LAG_S, (500 + 7 * i + np.arange(192)).reshape(12, 16)
                             .astype(np.uint16))]
    return rec


# --- librealsense ---------------------------------------------------------------------------------------------------


def release() -> str:
    """The pyrealsense2 release in use (e.g. "2.55.1"; its wheel's version before 2.58 is not in the module)."""
    import pyrealsense2 as rs

    version = getattr(rs, "__version__", None)
    if version:
        return str(version)
    from importlib.metadata import PackageNotFoundError, version as dist_version

    try:
        return ".".join(dist_version("pyrealsense2").split(".")[:3])
    except PackageNotFoundError:  # installed with --target: read the wheel's metadata beside the module
        found = sorted(Path(rs.__file__).parents[1].glob("pyrealsense2-*.dist-info"))
        return ".".join(found[0].name.split("-")[1].split(".")[:3]) if found else "unknown"


def suffix() -> str:
    """The file name suffix the installed librealsense records to: ".bag" (ROS1) up to 2.57, ".db3" (ROS2) after."""
    major, minor = (int(p) for p in release().split(".")[:2])
    return ".db3" if (major, minor) >= (2, 58) else ".bag"


def write_recording(path: Path, rec: CameraRecording, device: str = "Intel RealSense D435",
                    compress: bool = True) -> None:
    """Record `rec`'s frames with librealsense: a software_device with a "Stereo Module" (depth, Z16, the Depth
    Units option) and an "RGB Camera" (colour, RGB8), the depth -> colour extrinsics registered, recorded by
    `rs.recorder` (compressed as realsense-viewer records, unless `compress` is False)."""
    import pyrealsense2 as rs

    dev = rs.software_device()
    for key, value in ((rs.camera_info.name, device), (rs.camera_info.serial_number, "000000000042"),
                       (rs.camera_info.firmware_version, "5.16.0.1"), (rs.camera_info.product_line, "D400")):
        dev.register_info(key, value)
    depth_sensor, color_sensor = dev.add_sensor("Stereo Module"), dev.add_sensor("RGB Camera")

    def stream(kind, k, shape, fmt, bpp, model, coeffs, uid):
        intrinsics = rs.intrinsics()
        intrinsics.width, intrinsics.height = shape[1], shape[0]
        intrinsics.fx, intrinsics.fy, intrinsics.ppx, intrinsics.ppy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        intrinsics.model, intrinsics.coeffs = model, [float(c) for c in coeffs]
        s = rs.video_stream()
        s.type, s.index, s.uid, s.width, s.height, s.fps, s.bpp, s.fmt = kind, 0, uid, shape[1], shape[0], 30, bpp, fmt
        s.intrinsics = intrinsics
        return s

    models = {"Brown Conrady": rs.distortion.brown_conrady,
              "Inverse Brown Conrady": rs.distortion.inverse_brown_conrady}
    depth_profile = depth_sensor.add_video_stream(stream(rs.stream.depth, rec.depth_k, rec.depth_shape, rs.format.z16,
                                                         2, rs.distortion.brown_conrady, [0.0] * 5, 0))
    color_profile = color_sensor.add_video_stream(stream(rs.stream.color, rec.color_k, rec.color_shape,
                                                         rs.format.rgb8, 3, models[rec.model], rec.coeffs, 1))
    depth_sensor.add_read_only_option(rs.option.depth_units, DEPTH_UNITS)
    extrinsics = rs.extrinsics()
    extrinsics.rotation = [float(v) for v in rec.depth_to_color[:3, :3].T.ravel()]  # column-major
    extrinsics.translation = [float(v) for v in rec.depth_to_color[:3, 3]]
    depth_profile.register_extrinsics_to(color_profile, extrinsics)
    path.unlink(missing_ok=True)
    recorder = rs.recorder(str(path), dev, compress)
    recorded = {s.get_info(rs.camera_info.name): s for s in recorder.query_sensors()}
    profiles = {"depth": (depth_sensor, depth_profile, 2), "color": (color_sensor, color_profile, 3)}
    for sensor_name, (_, profile, _) in zip(("Stereo Module", "RGB Camera"), profiles.values()):
        recorded[sensor_name].open(profile)
        recorded[sensor_name].start(lambda frame: None)
    keep = []
    for frame in rec.frames:
        sensor, profile, bpp = profiles[frame.stream]
        pixels = np.ascontiguousarray(frame.image)
        keep.append(pixels)
        f = rs.software_video_frame()
        f.pixels, f.stride, f.bpp = pixels, pixels.shape[1] * bpp, bpp
        f.timestamp, f.domain, f.frame_number = frame.timestamp_s * 1000.0, rs.timestamp_domain.global_time, \
            frame.number
        f.profile = profile.as_video_stream_profile()
        if frame.stream == "depth" and hasattr(f, "depth_units"):  # 2.55 on
            f.depth_units = DEPTH_UNITS
        sensor.on_video_frame(f)
        time.sleep(0.005)  # the recorder writes from the sensors' threads: let each frame through in order
    time.sleep(0.3)
    for s in recorded.values():
        s.stop()
        s.close()
    del recorded, recorder  # the recording is finished when the recorder is released
    time.sleep(0.2)


#: librealsense objects kept alive until the process leaves (their teardown may hang; see play_back_isolated).
_KEPT: list = []


def play_back(path: Path, index: int) -> dict:
    """What librealsense's playback reads of sensor `index` of a recording: {"sensors": count, "streams": {name:
    {"intrinsics": (fx, fy, ppx, ppy), "size": (w, h), "model": str, "coeffs": [...], "format": str}}, "frames":
    {name: [(number, timestamp ms), ...]}, "depth_units": float or None}: every frame, not in real time. One sensor
    per playback: it starts with the first sensor started, and a second one started after it misses the frames read
    before it starts."""
    import pyrealsense2 as rs

    out: dict = {"streams": {}, "frames": {}, "depth_units": None}
    context = rs.context()
    dev = context.load_device(str(path))
    playback = dev.as_playback()
    playback.set_real_time(False)
    sensors = dev.query_sensors()
    out["sensors"], sensor = len(sensors), sensors[index]
    profiles = sensor.get_stream_profiles()
    for p in profiles:
        i = p.as_video_stream_profile().get_intrinsics()
        out["streams"][p.stream_name()] = {"intrinsics": (i.fx, i.fy, i.ppx, i.ppy), "size": (i.width, i.height),
                                           "model": str(i.model), "coeffs": list(i.coeffs), "format": str(p.format())}
    if sensor.supports(rs.option.depth_units):
        out["depth_units"] = sensor.get_option(rs.option.depth_units)
    lock, done = threading.Lock(), threading.Event()

    def on_frame(frame) -> None:
        with lock:
            out["frames"].setdefault(frame.profile.stream_name(), []).append((frame.get_frame_number(),
                                                                              frame.get_timestamp()))

    sensor.open(profiles)
    playback.set_status_changed_callback(lambda status: done.set() if status == rs.playback_status.stopped else None)
    sensor.start(on_frame)
    done.wait(60)
    sensor.stop()
    sensor.close()
    _KEPT.append((context, dev, playback, sensors, sensor, profiles))  # never torn down (play_back_isolated)
    return out


def play_back_isolated(path: Path, timeout_s: float = 600.0) -> dict:
    """`play_back` of every sensor, each in a child process (this script's --play-back) that leaves without tearing
    librealsense down: librealsense 2.55 sometimes hangs destroying a playback device (about 1 run in 4 here).
    `timeout_s` only guards against such a hang before the answer is printed. The sensors' answers merged."""
    import subprocess

    merged: dict = {"streams": {}, "frames": {}, "depth_units": None}
    index = count = 0
    while index == 0 or index < count:
        done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--play-back", str(path), str(index)],
                              capture_output=True, text=True, timeout=timeout_s, check=False)
        lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
        if done.returncode != 0 or not lines:
            raise RuntimeError(f"librealsense could not play back {path}: {done.stderr.strip()[-500:]}")
        answer = json.loads(lines[-1])
        count, index = answer["sensors"], index + 1
        merged["streams"].update(answer["streams"])
        merged["frames"].update(answer["frames"])
        merged["depth_units"] = answer["depth_units"] if answer["depth_units"] is not None else merged["depth_units"]
    return merged


# --- the folder ------------------------------------------------------------------------------------------------------


def write_folder(out: Path, capture, recordings: dict[str, CameraRecording], device: str = "Intel RealSense D435",
                 compress: bool = True) -> dict:
    """OUT/ as the module docstring says; returns truth.json's content. Every frame is played back and counted."""
    from dsr_bench.atomic import write_text

    out.mkdir(parents=True, exist_ok=True)
    ext, written = suffix(), {}
    for name, rec in recordings.items():
        path = out / f"{name}{ext}"
        write_recording(path, rec, device, compress)
        played = play_back_isolated(path)["frames"]
        for stream, label in (("color", "Color"), ("depth", "Depth")):
            fed = [(f.number, round(f.timestamp_s * 1000, 3)) for f in rec.frames if f.stream == stream]
            got = sorted((n, round(t, 3)) for n, t in played.get(label, []))
            if got != fed:
                raise SystemExit(f"{path}: librealsense plays back {len(got)} {stream} frames of the {len(fed)} "
                                 f"written ({got[:3]} ... vs {fed[:3]} ...); run it again on a less loaded machine")
        written[name] = path.name
    (out / "meshes").mkdir(exist_ok=True)
    objects = []
    for i, obj in enumerate(capture.objects):
        shutil.copy(obj.mesh_path, out / "meshes" / f"{i}{obj.mesh_path.suffix}")
        objects.append({"name": obj.name, "mesh": f"meshes/{i}{obj.mesh_path.suffix}", "identity": obj.identity})
    write_text(out / "rig.json", json.dumps({"name": out.name, "objects": objects, "board": BOARD}, indent=1))
    steps = len(capture.truth_poses()) - 1
    times = {n: [t + STEP_JITTER_S[i % len(STEP_JITTER_S)] for i, t in enumerate(event_times(n, steps)[1:])]
             for n in recordings}
    write_text(out / "steps.json", json.dumps({"step_times": times, "board_time": {
        n: event_times(n, steps)[0] + BOARD_JITTER_S for n in recordings}}, indent=1))
    pushes = [{"start": s[:2].tolist(), "direction": ((e - s)[:2] / np.linalg.norm((e - s)[:2])).tolist()}
              for s, e in capture.pushes_world]
    write_text(out / "pushes.json", json.dumps({"pushes": pushes}, indent=1))
    truth = {"release": release(), "device": device, "compressed": compress, "depth_units": DEPTH_UNITS,
             "files": written, "poses": capture.truth_poses().tolist(), "cameras": {
                 n: {"color_intrinsics": r.color_k.tolist(), "color_size": list(r.color_shape), "model": r.model,
                     "coeffs": r.coeffs, "depth_intrinsics": r.depth_k.tolist(), "depth_size": list(r.depth_shape),
                     "depth_to_color": r.depth_to_color.tolist(), "color_to_table": r.color_to_table.tolist(),
                     "frames": [[f.stream, f.number, f.timestamp_s] for f in r.frames],
                     "steps": [[100 + 10 * i, t] for i, t in enumerate(event_times(n, steps))]}
                 for n, r in recordings.items()}}
    write_text(out / "truth.json", json.dumps(truth, indent=1))
    return truth


def make_capture(folder: Path, steps: int = 1):
    """A simulated capture as the tests make theirs (tests/conftest.py `sim`: seed 1, 3 objects, no sensor noise),
    with `steps` pushes."""
    from dsr_bench.dataset.capture import load_capture
    from dsr_bench.generators.capture import generate_capture

    generate_capture(folder / "seq_000", name="seq_000", seed=1, steps=steps, objects_per_scene=3, noise="none",
                     image_shape=(240, 320))
    return load_capture(folder / "seq_000")


def _size(text: str) -> tuple[int, int]:
    """"HxW" -> (H, W)."""
    h, w = (int(v) for v in text.lower().split("x"))
    return h, w


def main(argv: list[str] | None = None) -> int:
    """The command line (module docstring)."""
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--play-back"]:  # play_back_isolated's child: the answer, then out without librealsense's teardown
        print(json.dumps(play_back(Path(argv[1]), int(argv[2]))), flush=True)
        os._exit(0)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="folder to write (front.<bag|db3>, back.<bag|db3>, rig.json, ...)")
    parser.add_argument("--capture", type=Path, help="a simulated capture (default: one made here, seed 1)")
    parser.add_argument("--steps", type=int, default=1, help="pushes of the capture made here (default 1)")
    parser.add_argument("--size", type=_size, default=(360, 640), help="colour HxW (default 360x640)")
    parser.add_argument("--depth-size", type=_size, default=(240, 424), help="depth HxW (default 240x424)")
    parser.add_argument("--device", default="Intel RealSense D435", help="the device name recorded")
    parser.add_argument("--uncompressed", action="store_true", help="record without the recorder's compression")
    parser.add_argument("--layout-sample", action="store_true", help="write only OUT/<release>[-uncompressed]"
                        ".<bag|db3>: `layout_sample`'s two tiny frames per stream")
    args = parser.parse_args(argv)
    if args.layout_sample:
        args.out.mkdir(parents=True, exist_ok=True)
        path = args.out / f"{release()}{'-uncompressed' if args.uncompressed else ''}{suffix()}"
        write_recording(path, layout_sample(), args.device, not args.uncompressed)
        print(f"{path}: librealsense {release()}, {path.stat().st_size / 1e3:.0f} kB")
        return 0
    from dsr_bench.dataset.capture import load_capture

    with tempfile.TemporaryDirectory() as tmp:
        capture = load_capture(args.capture) if args.capture else make_capture(Path(tmp), args.steps)
        truth = write_folder(args.out, capture, render(capture, args.size, args.depth_size), args.device,
                             not args.uncompressed)
    sizes = ", ".join(f"{p.name} {p.stat().st_size / 1e3:.0f} kB" for p in sorted(args.out.iterdir()) if p.is_file())
    print(f"{args.out}: librealsense {truth['release']}: {sizes}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
