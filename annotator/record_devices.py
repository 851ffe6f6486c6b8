"""The cameras of `dsr-bench capture` (`annotator.record`; docs/annotator.md, "Recording a session"): RealSense devices
chosen by serial number, opened at the rig's colour and depth modes, hardware-synced where they can be, and recorded
by librealsense itself (`rs.recorder`: one recording per camera, `.bag` up to librealsense 2.57, `.db3` from 2.58).

Two providers of devices, one path after them. `LiveProvider` lists the connected cameras (`rs.context`);
`PlaybackProvider` (`--from-recordings`, the tests' seam) stands recordings in for them: each is loaded as a
playback device (`load_device`, the device `rs.config.enable_device_from_file` opens; `set_real_time(False)`: every
frame, as fast as it can be read), paused until recording starts. librealsense records a playback device neither
through a pipeline ("Configuring both device from file, and record to file is unsupported") nor through
`rs.recorder` (2.59.1 aborts the process: "playback_sensor::unregister_before_start_callback" is not implemented),
so the playback feeds a `software_device` made with the recorded device's info (name, serial, firmware), sensors,
stream profiles (size, rate, format, intrinsics, distortion), depth -> colour extrinsics and depth units, and that
device is what gets recorded. From `open_camera` on (modes, sync, recorder, sensors, frame callbacks, closing) the
path is the same for both. pyrealsense2 (the `realsense` extra) is imported inside the functions.
"""

from __future__ import annotations

import re
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dsr_bench.errors import UserError

#: Where an error about the cameras points the user.
HINT = "docs/annotator.md, 'Recording a session'"
#: The colour formats recorded, in order of preference (all read by `import-capture`), and the depth format.
COLOR_FORMATS = ("rgb8", "bgr8", "rgba8", "bgra8")
DEPTH_FORMAT = "z16"
STOP_WAIT_S = 2.0  # the most a stopped playback waits for librealsense to say so
#: inter_cam_sync_mode values of the D400 depth sensor: 1 master (drives the sync pin), 2 slave (follows it).
SYNC_MASTER, SYNC_SLAVE = 1.0, 2.0
MODE = re.compile(r"(\d+)x(\d+)@(\d+)")
#: A frame's callback arguments: (camera, "color" or "depth", frame number, timestamp (s, the frames' clock),
#: timestamp domain name, e.g. "global_time").
FrameSink = Callable[[str, str, int, float, str], None]


@dataclass(frozen=True)
class Mode:
    """A stream mode: width x height pixels at fps frames per second."""

    width: int
    height: int
    fps: int

    def __str__(self) -> str:
        return f"{self.width}x{self.height}@{self.fps}"


#: The default modes, a D415's (the paper's rig's camera): depth at its full resolution, 1280 x 720 at 30 fps (the
#: mode Intel recommends for its depth accuracy), colour at the same size and rate (the import's example rig).
DEFAULT_COLOR = Mode(1280, 720, 30)
DEFAULT_DEPTH = Mode(1280, 720, 30)


def parse_mode(text: str, option: str) -> Mode:
    """`WIDTHxHEIGHT@FPS` ("1280x720@30") as a Mode; UserError naming the option and the form."""
    found = MODE.fullmatch(text.strip().lower())
    if not found or min(int(v) for v in found.groups()) < 1:
        raise UserError(f"{option} {text!r} is not a mode WIDTHxHEIGHT@FPS, e.g. {option} 1280x720@30")
    return Mode(*(int(v) for v in found.groups()))


def librealsense_release() -> str:
    """The installed pyrealsense2's release ("2.59.1"; read from its wheel's metadata where the module has no
    version, before 2.58)."""
    import pyrealsense2 as rs

    version = getattr(rs, "__version__", None)
    if not version:
        from importlib.metadata import PackageNotFoundError, version as dist_version

        try:
            version = dist_version("pyrealsense2")
        except PackageNotFoundError:
            version = "0.0.0"
    return ".".join(str(version).split(".")[:3])


def recording_suffix(release: str) -> str:
    """The file name suffix librealsense `release` records to (it refuses others from 2.58): ".db3" (ROS2 SQLite)
    from 2.58 on, ".bag" (ROS1) before."""
    major, minor = (int(p) for p in (release.split(".") + ["0"])[:2])
    return ".db3" if (major, minor) >= (2, 58) else ".bag"


@dataclass
class Device:
    """A camera present: its serial number, product name, firmware, connection (USB type), and `recording`, the file
    standing in for it (None: a connected camera); `handle` is librealsense's device."""

    serial: str
    name: str
    firmware: str = ""
    connection: str = ""
    recording: Path | None = None
    handle: Any = field(default=None, repr=False)

    def describe(self) -> str:
        """"SERIAL (NAME, USB 3.2)" or "SERIAL (NAME, recording front.db3)"."""
        where = f"recording {self.recording.name}" if self.recording is not None else (
            f"USB {self.connection}" if self.connection else "connected")
        return f"{self.serial} ({self.name}, {where})"


def _info(device, key) -> str:
    """A camera_info field of a device or sensor, "" when it has none."""
    return str(device.get_info(key)) if device.supports(key) else ""


def _present_list(present: list[Device]) -> str:
    return ", ".join(d.describe() for d in present) or "none"


def _not_found(camera: str, serial: str, present: list[Device], how: str) -> UserError:
    """The one line for a camera whose serial is not among those present (all of them listed)."""
    if not present:
        return UserError(f"--{camera} {serial}: no RealSense camera is connected ({how} sees none); plug the {camera} "
                         "camera into a USB 3 port (`rs-enumerate-devices -s` lists the serials), or stand recordings "
                         f"in with --from-recordings (see {HINT})")
    return UserError(f"--{camera} {serial}: no RealSense camera with that serial; present: {_present_list(present)}; "
                     "give one of these serials")


class LiveProvider:
    """The connected RealSense cameras (`rs.context().query_devices()`), chosen by serial number."""

    live = True

    def __init__(self) -> None:
        import pyrealsense2 as rs

        self.context = rs.context()
        self._removed: Callable[[str], None] | None = None

    def present(self) -> list[Device]:
        """Every connected camera, in librealsense's order."""
        import pyrealsense2 as rs

        out = []
        for dev in self.context.query_devices():
            out.append(Device(_info(dev, rs.camera_info.serial_number), _info(dev, rs.camera_info.name),
                              _info(dev, rs.camera_info.firmware_version),
                              _info(dev, rs.camera_info.usb_type_descriptor), None, dev))
        return out

    def choose(self, camera: str, serial: str | None, present: list[Device]) -> Device:
        """The camera with `serial`; UserError listing the serials present when none has it (or none was given)."""
        if not serial:
            listed = (f"present: {_present_list(present)}" if present else
                      "no RealSense camera is connected (librealsense sees none)")
            raise UserError(f"the {camera} camera needs --{camera} SERIAL (`rs-enumerate-devices -s` lists the "
                            f"serials); {listed}")
        for dev in present:
            if dev.serial == serial:
                return dev
        raise _not_found(camera, serial, present, "librealsense")

    def recordable(self, device: Device, camera: str, sink: Callable[[str], None]) -> tuple[Any, Any]:
        """(the device to record, None): a connected camera is recorded as it is."""
        return device.handle, None

    def watch_removal(self, devices: list[Device], removed: Callable[[str], None]) -> None:
        """Call `removed(serial)` when one of `devices` is unplugged (librealsense's devices-changed callback)."""

        def changed(info) -> None:
            for device in devices:
                try:
                    gone = info.was_removed(device.handle)
                except RuntimeError:
                    gone = False
                if gone:
                    removed(device.serial)

        self.context.set_devices_changed_callback(changed)


class PlaybackProvider:
    """Recordings standing in for the cameras (`--from-recordings front=PATH,back=PATH`): each a playback device,
    paused, not real time, recorded through a software device that mirrors it (module docstring)."""

    live = False

    def __init__(self, recordings: dict[str, Path]) -> None:
        import pyrealsense2 as rs

        self.context = rs.context()
        self.devices: dict[str, Device] = {}
        for camera, path in recordings.items():
            if not path.is_file():
                raise UserError(f"--from-recordings {camera}={path}: no such file; give the recording to stand in for "
                                f"the {camera} camera")
            try:
                dev = self.context.load_device(str(path))
            except RuntimeError as exc:
                raise UserError(f"--from-recordings {camera}={path}: librealsense {librealsense_release()} cannot play "
                                f"it back ({exc}); give a recording librealsense wrote (.bag or .db3)") from None
            playback = dev.as_playback()
            playback.set_real_time(False)
            playback.pause()  # until every sensor has started: one started after it would miss the first frames
            self.devices[camera] = Device(_info(dev, rs.camera_info.serial_number), _info(dev, rs.camera_info.name),
                                          _info(dev, rs.camera_info.firmware_version), "", path, dev)

    def present(self) -> list[Device]:
        """The playback devices, one per recording."""
        return list(self.devices.values())

    def choose(self, camera: str, serial: str | None, present: list[Device]) -> Device:
        """The recording standing in for `camera`; its serial must be `serial` when one is given."""
        if camera not in self.devices:
            raise UserError(f"--{camera}: no recording stands in for the {camera} camera; give "
                            f"--from-recordings {camera}=PATH (present: {_present_list(present)})")
        device = self.devices[camera]
        if serial and device.serial != serial:
            raise _not_found(camera, serial, present, "--from-recordings")
        return device

    def recordable(self, device: Device, camera: str, sink: Callable[[str], None]) -> tuple[Any, PlaybackFeed]:
        """(a software device mirroring the playback, the feed that plays frames into it); `sink(camera)` is called
        when the recording has been played to its end."""
        feed = PlaybackFeed(device.handle, camera, sink)
        return feed.mirror, feed

    def watch_removal(self, devices: list[Device], removed: Callable[[str], None]) -> None:
        """Recordings are never unplugged."""


class PlaybackFeed:
    """A playback device played into a `software_device` that mirrors it: the mirror's sensors, profiles,
    extrinsics, depth units and info copied from the playback's; each played frame injected into the mirror's
    sensor (its pixels copied, its number, timestamp and domain kept)."""

    def __init__(self, playback_device, camera: str, ended: Callable[[str], None]) -> None:
        import pyrealsense2 as rs

        self.device, self.playback = playback_device, playback_device.as_playback()
        self.mirror = rs.software_device()
        for key in (rs.camera_info.name, rs.camera_info.serial_number, rs.camera_info.firmware_version,
                    rs.camera_info.product_line, rs.camera_info.product_id):
            if playback_device.supports(key):
                self.mirror.register_info(key, playback_device.get_info(key))
        self.sensors = playback_device.query_sensors()
        self.targets: dict[int, tuple[Any, Any, float | None]] = {}  # playback profile uid -> (sensor, profile, units)
        self.profiles: dict[int, Any] = {}  # playback profile uid -> playback profile
        mirrored = []
        for sensor in self.sensors:
            target = self.mirror.add_sensor(_info(sensor, rs.camera_info.name))
            units = None
            if sensor.supports(rs.option.depth_units):
                units = float(sensor.get_option(rs.option.depth_units))
                target.add_read_only_option(rs.option.depth_units, units)
            for profile in sensor.get_stream_profiles():
                if not profile.is_video_stream_profile():
                    continue
                video = profile.as_video_stream_profile()
                stream = rs.video_stream()
                stream.type, stream.index, stream.uid = profile.stream_type(), profile.stream_index(), \
                    profile.unique_id()
                stream.width, stream.height, stream.fps = video.width(), video.height(), profile.fps()
                stream.bpp, stream.fmt, stream.intrinsics = profile.bytes_per_pixel(), profile.format(), \
                    video.get_intrinsics()
                copy = target.add_video_stream(stream)
                depth = profile.stream_type() == rs.stream.depth
                self.targets[profile.unique_id()] = (target, copy, units if depth else None)
                self.profiles[profile.unique_id()] = profile
                mirrored.append((profile, copy))
        for a, copy_a in mirrored:
            for b, copy_b in mirrored:
                if a.unique_id() != b.unique_id():
                    try:
                        copy_a.register_extrinsics_to(copy_b, a.get_extrinsics_to(b))
                    except RuntimeError:  # streams of no common extrinsics group: none recorded
                        pass
        self._stopped = threading.Event()  # set once librealsense has said the playback stopped

        def on_status(status) -> None:
            if status == rs.playback_status.stopped:
                self._stopped.set()
                ended(camera)

        self.playback.set_status_changed_callback(on_status)
        self._started: list = []

    def _inject(self, frame) -> None:
        """Frame of the playback -> the mirror's sensor (pixels copied by pyrealsense2's setter)."""
        import numpy as np
        import pyrealsense2 as rs

        target, profile, units = self.targets[frame.profile.unique_id()]
        video = frame.as_video_frame()
        copy = rs.software_video_frame()
        copy.pixels = np.asanyarray(video.get_data())
        copy.stride, copy.bpp = video.get_stride_in_bytes(), video.get_bytes_per_pixel()
        copy.timestamp, copy.domain = frame.get_timestamp(), frame.get_frame_timestamp_domain()
        copy.frame_number = frame.get_frame_number()
        copy.profile = profile.as_video_stream_profile()
        if units is not None and hasattr(copy, "depth_units"):  # 2.55 on
            copy.depth_units = units
        target.on_video_frame(copy)

    def start(self, chosen_uids: set[int]) -> None:
        """Start the playback's sensors of the chosen profiles (the mirror's uids are the playback's), then play."""
        for sensor in self.sensors:
            profiles = [p for p in sensor.get_stream_profiles() if p.unique_id() in chosen_uids]
            if profiles:
                sensor.open(profiles)
                sensor.start(self._inject)
                self._started.append(sensor)
        self.playback.resume()

    def stop(self) -> None:
        """Stop and close the playback's sensors, and wait (at most STOP_WAIT_S) for librealsense's own thread to say
        the playback stopped: a callback into Python after the interpreter has begun to exit aborts the process."""
        started, self._started = self._started, []
        for sensor in started:
            try:
                sensor.stop()
                sensor.close()
            except RuntimeError:  # already stopped at the end of the file
                pass
        if started:
            self._stopped.wait(STOP_WAIT_S)


# --- one camera, opened and recorded ---------------------------------------------------------------------------------


def _modes_offered(handle, kind: str) -> str:
    """The modes of the device's `kind` ("color", "depth") streams in the formats recorded, largest first."""
    import pyrealsense2 as rs

    formats = COLOR_FORMATS if kind == "color" else (DEPTH_FORMAT,)
    found = set()
    for sensor in handle.query_sensors():
        for p in sensor.get_stream_profiles():
            if p.is_video_stream_profile() and p.stream_type() == getattr(rs.stream, kind) and \
                    str(p.format()).split(".")[-1] in formats:
                v = p.as_video_stream_profile()
                found.add((v.width(), v.height(), p.fps()))
    return ", ".join(str(Mode(*m)) for m in sorted(found, key=lambda m: (-m[0] * m[1], -m[2]))) or "none"


def _profile(handle, kind: str, mode: Mode) -> tuple[int, Any]:
    """(sensor index, stream profile) of the device's `kind` stream at `mode`, in the first format of COLOR_FORMATS
    (colour) or Z16 (depth) it offers; None when it has none."""
    import pyrealsense2 as rs

    formats = COLOR_FORMATS if kind == "color" else (DEPTH_FORMAT,)
    best: tuple[int, int, Any] | None = None
    for index, sensor in enumerate(handle.query_sensors()):
        for p in sensor.get_stream_profiles():
            fmt = str(p.format()).split(".")[-1]
            if not (p.is_video_stream_profile() and p.stream_type() == getattr(rs.stream, kind) and fmt in formats):
                continue
            v = p.as_video_stream_profile()
            if (v.width(), v.height(), p.fps()) == (mode.width, mode.height, mode.fps):
                rank = formats.index(fmt)
                if best is None or rank < best[0]:
                    best = (rank, index, p)
    return (best[1], best[2]) if best is not None else (-1, None)


@dataclass
class Camera:
    """A camera prepared for recording and, once `start`ed, being recorded: its device, the device recorded (the
    camera itself or the software mirror of a recording), the chosen (sensor index, profile) per stream, the
    recording's path, and its sync role."""

    name: str
    device: Device
    handle: Any
    feed: PlaybackFeed | None
    profiles: dict[str, tuple[int, Any]]
    modes: dict[str, str]
    fps: dict[str, int]
    sync: str = "none"
    restore: list = field(default_factory=list)  # (sensor, option, value) set back when the camera stops
    path: Path | None = None
    recorder: Any = None
    sensors: list = field(default_factory=list)

    def start(self, path: Path, compress: bool, sink: FrameSink) -> None:
        """Record to `path` with librealsense (`rs.recorder`), open and start the chosen streams, each frame reported
        to `sink` (in librealsense's threads: keep it short)."""
        import pyrealsense2 as rs

        self.path = path
        self.recorder = rs.recorder(str(path), self.handle, compress)
        recorded = self.recorder.query_sensors()
        by_sensor: dict[int, list] = {}
        for index, profile in self.profiles.values():
            by_sensor.setdefault(index, []).append(profile)
        name = self.name

        def on_frame(frame) -> None:
            try:
                kind = "depth" if frame.profile.stream_type() == rs.stream.depth else "color"
                sink(name, kind, int(frame.get_frame_number()), float(frame.get_timestamp()) / 1000.0,
                     str(frame.get_frame_timestamp_domain()).split(".")[-1])
            except Exception as exc:  # noqa: BLE001 - an exception must not escape into librealsense's thread
                sink(name, "error", -1, 0.0, f"{type(exc).__name__}: {exc}")

        for index, profiles in by_sensor.items():
            sensor = recorded[index]
            sensor.open(profiles)
            self.sensors.append(sensor)
            sensor.start(on_frame)
        if self.feed is not None:
            self.feed.start({p.unique_id() for _, p in self.profiles.values()})

    def stop(self) -> None:
        """Stop the streams and release the recorder: librealsense then completes the recording's file."""
        if self.feed is not None:
            self.feed.stop()
        for sensor in self.sensors:
            try:
                sensor.stop()
                sensor.close()
            except RuntimeError:  # a sensor of an unplugged camera
                pass
        self.sensors = []
        self.recorder = None  # the last reference: the recorder closes its file
        for sensor, option, value in self.restore:  # a camera left a sync slave waits for a master's trigger
            try:
                sensor.set_option(option, value)
            except RuntimeError:  # unplugged
                pass
        self.restore = []


def prepare_camera(provider, name: str, device: Device, color: Mode, depth: Mode,
                   ended: Callable[[str], None]) -> Camera:
    """The camera `name` on `device` with its colour and depth streams at `color` and `depth`; UserError naming the
    option and listing the modes it offers when it has no such stream. Nothing is recorded yet."""
    handle, feed = provider.recordable(device, name, ended)
    profiles = {}
    for kind, mode, option in (("color", color, "--color"), ("depth", depth, "--depth")):
        index, profile = _profile(handle, kind, mode)
        if profile is None:
            what = "colour (RGB8, BGR8)" if kind == "color" else "depth (Z16)"
            raise UserError(f"{option} {mode}: the {name} camera {device.describe()} has no {what} stream at {mode}; "
                            f"it offers {_modes_offered(handle, kind)}; give one of them")
        profiles[kind] = (index, profile)
    modes = {k: f"{m} {str(p.format()).split('.')[-1].upper()}" for (k, (_, p)), m in
             zip(profiles.items(), (color, depth), strict=True)}
    return Camera(name, device, handle, feed, profiles, modes, {"color": color.fps, "depth": depth.fps})


def set_sync(cameras: list[Camera], enabled: bool) -> str:
    """Inter-camera hardware sync: the first camera the master, the others slaves (the depth sensors'
    inter_cam_sync_mode; the sync cable between the cameras' sync pins), where every camera supports it; and
    librealsense's global time (frame timestamps on the host's clock) wherever a sensor offers it. Returns what was
    done, or why it was skipped."""
    import pyrealsense2 as rs

    for camera in cameras:
        for sensor in camera.handle.query_sensors():
            if sensor.supports(rs.option.global_time_enabled):
                try:
                    sensor.set_option(rs.option.global_time_enabled, 1)
                except RuntimeError:  # read-only on some sensors: the default (on) stays
                    pass
    if len(cameras) < 2:
        return "skipped: one camera"
    if not enabled:
        return "off (--no-sync): the cameras run free; each step's frames are matched by timestamp"
    syncing = {}
    for camera in cameras:
        found = [s for s in camera.handle.query_sensors() if s.supports(rs.option.inter_cam_sync_mode)]
        if not found:
            names = ", ".join(c.name for c in cameras if not any(
                s.supports(rs.option.inter_cam_sync_mode) for s in c.handle.query_sensors()))
            return (f"skipped: {names} offer(s) no inter_cam_sync_mode option (a recording standing in, or a camera "
                    "without the sync pins); the cameras run free, each step's frames are matched by timestamp")
        syncing[camera.name] = found[0]
    for i, camera in enumerate(cameras):
        value, sensor = SYNC_MASTER if i == 0 else SYNC_SLAVE, syncing[camera.name]
        try:
            camera.restore.append((sensor, rs.option.inter_cam_sync_mode,
                                   sensor.get_option(rs.option.inter_cam_sync_mode)))
            sensor.set_option(rs.option.inter_cam_sync_mode, value)
        except RuntimeError as exc:
            for done in cameras[:i + 1]:  # back to free running, all of them
                for sensor_set, option, old in done.restore:
                    sensor_set.set_option(option, old)
                done.restore, done.sync = [], "none"
            return f"skipped: {camera.name} refused inter_cam_sync_mode {value:g} ({exc}); the cameras run free"
        camera.sync = "master" if i == 0 else "slave"
    roles = ", ".join(f"{c.name} {c.sync}" for c in cameras)
    return (f"hardware: {roles} (inter_cam_sync_mode {SYNC_MASTER:g} / {SYNC_SLAVE:g}: depth frames on the master's "
            "trigger)")
