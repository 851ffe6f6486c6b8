"""A librealsense recording read without librealsense: its colour and depth streams, their intrinsics, distortion
and extrinsics, the depth units, every frame's timestamp and number, frames decoded (`dsr-bench import-capture` of
RealSense recordings: `annotator.realsense`). The containers are `annotator.rosfile`'s, colour undistortion and depth
registration `annotator.registration`'s. The topics of each generation of librealsense's recorder (ROS1 `.bag` up to
2.57: sensor_msgs/Image with 4 undeclared bytes after `data` from 2.54 on, read by hand; CameraInfo, Transform,
Float32 options. ROS2 `.db3` from 2.58: raw or (2.59) PNG images, texts for intrinsics, extrinsics and options, each
frame's timestamp and number in its metadata text) are listed in docs/annotator.md, "RealSense recordings".

Frame times (`Stream.stamps`) are the frames' timestamps in s on librealsense's frame clock (rs2_frame's timestamp:
with global time, on by default, the host's clock) in both generations: the steps file's clock.
"""

from __future__ import annotations

import io
import re
import sqlite3
import struct
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from dsr_bench.annotator.inputs import MAX_IMAGE_SIDE, image_side
from dsr_bench.annotator.registration import SUPPORTED_MODELS, StreamInfo, ideal_rays, undistortion_maps
from dsr_bench.errors import UserError

COLOR_ENCODINGS = {"rgb8": (3, False), "bgr8": (3, True), "rgba8": (4, False), "bgra8": (4, True)}
DEPTH_ENCODINGS = ("mono16", "16UC1")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Where an error about a recording points the user.
HINT = "docs/annotator.md, 'RealSense recordings'"
IMAGE_TOPIC = re.compile(r"(?P<prefix>/device_\d+/sensor_\d+/(?P<stream>Color|Depth)_\d+)/image/data"
                         r"(?P<compressed>/compressed|/compressedDepth)?")
IMAGE, COMPRESSED = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"
STRING = "std_msgs/msg/String"
#: What reading a broken container raises (with rosbags' errors, imported where used): a message cut
#: short, a chunk or zstd frame that does not decompress, a damaged database.
READ_ERRORS: tuple[type[Exception], ...] = (struct.error, sqlite3.Error, UnicodeDecodeError, OSError, EOFError,
                                            ValueError, RuntimeError, KeyError)


@dataclass
class Stream:
    """One image stream of a recording: its topic, info, and per frame (sorted by timestamp) the frame timestamp (s),
    the container's message time (ns, to seek the message), the frame number, and which of the messages at that time
    it is (`nth`); `payload` how its messages hold the image: "ros1" (sensor_msgs/Image, read by hand), "image"
    (a ROS2 sensor_msgs/Image) or "png" (a ROS2 sensor_msgs/CompressedImage)."""

    topic: str
    info: StreamInfo
    stamps: np.ndarray
    log_times: np.ndarray
    seqs: np.ndarray
    payload: str = "ros1"
    nth: np.ndarray | None = None


@dataclass
class Recording:
    """One camera's recording: colour and depth streams, the depth -> colour 4x4 (m, p_colour = M p_depth), metres
    per depth unit, and what the file is (`about`: container, file version, writer, device, sensors, clock)."""

    name: str
    path: Path
    color: Stream
    depth: Stream
    depth_to_color: np.ndarray
    depth_scale: float
    about: dict = field(default_factory=dict)

    @cached_property
    def color_maps(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Remap tables undistorting the colour stream (`undistortion_maps`), None when it needs none."""
        return undistortion_maps(self.color.info)

    @cached_property
    def depth_corner_rays(self) -> np.ndarray:
        """(Hd + 1, Wd + 1, 2) normalised ideal rays (x/z, y/z) through the depth pixels' corners: corner (i, j) is
        pixel (row i - 0.5, col j - 0.5)."""
        info = self.depth.info
        v, u = np.mgrid[0:info.height + 1, 0:info.width + 1].astype(np.float64) - 0.5
        return ideal_rays(info, np.stack([u.ravel(), v.ravel()], 1)).reshape(info.height + 1, info.width + 1, 2)


def _bag_error(path: Path, message: str) -> UserError:
    """One line about a recording: the file, what is wrong and the fix, where the docs say more."""
    return UserError(f"{path}: {message}; see {HINT}")


# --- the topics -------------------------------------------------------------------------------------------------------


def _f32(values) -> np.ndarray:
    """Values as the float32 librealsense holds them (a ROS2 text spells them in decimal), back in float64."""
    return np.asarray(values, np.float64).astype(np.float32).astype(np.float64)


def _check_type(box, path: Path, topic: str, expected: tuple[str, ...], what: str) -> str:
    """The topic's message type, refused (naming the topic and what was expected) unless one of `expected`."""
    kind = box.topics[topic]
    if kind not in expected:
        raise _bag_error(path, f"topic {topic} is {kind}, expected {' or '.join(expected)} ({what})")
    return kind


def _read_one(box, path: Path, topic: str, what: str):
    """The last message of a static topic, decoded."""
    message = None
    for _, raw in box.messages(topic):
        message = box.decode(topic, raw)
    if message is None:
        raise _bag_error(path, f"topic {topic} ({what}) holds no message; re-record the camera")
    return message


def _text(box, path: Path, topic: str, keys: tuple[str, ...], what: str) -> dict[str, str]:
    """A ROS2 text message ("key=value;...") of a static topic, checked to hold `keys`."""
    from dsr_bench.annotator.rosfile import key_values

    _check_type(box, path, topic, (STRING,), what)
    text = str(_read_one(box, path, topic, what).data)
    values = key_values(text)
    missing = [k for k in keys if k not in values]
    if missing:
        raise _bag_error(path, f"topic {topic} ({what}) {text[:120]!r} has no {', '.join(missing)}; expected "
                               f"librealsense's text {';'.join(f'{k}=...' for k in keys)}")
    return values


def _numbers(path: Path, topic: str, values: dict[str, str], key: str, count: int | None = None) -> np.ndarray:
    """A text's comma-separated numbers under `key` (`count` of them), refused unless finite numbers."""
    try:
        out = np.array([float(v) for v in values[key].split(",")], np.float64)
    except ValueError:
        out = np.zeros(0)
    if count is not None and len(out) != count or not len(out) or not np.all(np.isfinite(out)):
        raise _bag_error(path, f"topic {topic}: {key}={values[key][:80]!r} is not {count or 'a'} finite number"
                               f"{'s' if count != 1 else ''}")
    return out


def _image_topics(box, path: Path) -> dict[str, tuple[str, str, str]]:
    """{"Color": (topic, prefix, payload), "Depth": ...} of the recording's colour and depth frames."""
    found: dict[str, list] = {"Color": [], "Depth": []}
    for topic in box.topics:
        match = IMAGE_TOPIC.fullmatch(topic)
        if match:
            found[match["stream"]].append((topic, match["prefix"], match["compressed"]))
    out = {}
    for kind, what in (("Color", "colour"), ("Depth", "depth")):
        if not found[kind]:
            raise _bag_error(path, f"no topic /device_0/sensor_N/{kind}_0/image/data (the {what} frames: "
                                   f"sensor_msgs/Image, or a ROS2 CompressedImage .../image/data/compressed"
                                   f"{'Depth' if kind == 'Depth' else ''}); record the colour and depth streams with "
                                   "realsense-viewer or rs-record (librealsense 2.x), one recording per camera")
        if len(found[kind]) > 1:
            raise _bag_error(path, f"{len(found[kind])} topics hold the {what} frames "
                                   f"({', '.join(t for t, _, _ in found[kind])}); record one device with one colour "
                                   "and one depth stream per recording")
        topic, prefix, compressed = found[kind][0]
        _check_type(box, path, topic, (COMPRESSED,) if compressed else (IMAGE,), f"the {what} frames")
        out[kind] = (topic, prefix, "png" if compressed else "image" if box.ros2 else "ros1")
    return out


def _stream_info(box, path: Path, prefix: str, what: str) -> StreamInfo:
    """A stream's intrinsics: ROS1 `<prefix>/info/camera_info` (CameraInfo) or ROS2 `<prefix>/camera_info` (text)."""
    topic = prefix + "/info/camera_info"
    label = f"the {what} stream's intrinsics"
    if topic in box.topics:
        _check_type(box, path, topic, ("sensor_msgs/msg/CameraInfo",), label)
        msg = _read_one(box, path, topic, label)
        k = np.array(getattr(msg, "K", None) if hasattr(msg, "K") else msg.k, np.float64).reshape(3, 3)
        d = np.asarray(getattr(msg, "D", None) if hasattr(msg, "D") else msg.d, np.float64).reshape(-1)
        width, height, model = int(msg.width), int(msg.height), str(msg.distortion_model)
    elif prefix + "/camera_info" in box.topics:
        topic = prefix + "/camera_info"
        values = _text(box, path, topic, ("width", "height", "fx", "ppx", "fy", "ppy", "model", "coeffs"), label)
        fx, fy, cx, cy, w, h = (float(_numbers(path, topic, values, key, 1)[0]) for key in
                                ("fx", "fy", "ppx", "ppy", "width", "height"))
        k = _f32([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])  # the float32 values the text spells in 9 digits
        d, model = _f32(_numbers(path, topic, values, "coeffs")), values["model"]
        width, height = int(w), int(h)
    else:
        raise _bag_error(path, f"no topic {prefix}/info/camera_info ({label}; {prefix}/camera_info in a ROS2 "
                               "recording); record with realsense-viewer or rs-record")
    coeffs = np.zeros(5)
    if model not in SUPPORTED_MODELS:
        raise _bag_error(path, f"the {what} stream ({topic}) has distortion model {model!r}, which this importer "
                               f"cannot undistort (it handles {', '.join(map(repr, SUPPORTED_MODELS))}); record the "
                               "camera's colour and depth streams, or export PNGs and use the folder form")
    if len(d) > 5 and np.any(d[5:] != 0) or not np.all(np.isfinite(d)):
        raise _bag_error(path, f"the {what} stream's distortion D {d.tolist()} is not 5 finite coefficients "
                               "[k1, k2, p1, p2, k3]")
    coeffs[:min(5, len(d))] = d[:5]
    if not (k[0, 0] > 0 and k[1, 1] > 0 and width > 0 and height > 0 and np.all(np.isfinite(k))):
        raise _bag_error(path, f"the {what} stream's camera_info ({topic}) has no intrinsics (K "
                               f"{k.ravel().tolist()}, {width}x{height}); re-record with a calibrated camera")
    if not (image_side(width) and image_side(height)):
        raise _bag_error(path, f"the {what} stream's camera_info ({topic}) declares {width}x{height} pixels, over "
                               f"the {MAX_IMAGE_SIDE} px per side this importer takes; record at a RealSense "
                               "resolution")
    k[0, 1], k[1, 0], k[2] = 0.0, 0.0, (0.0, 0.0, 1.0)
    return StreamInfo(width, height, k, model, coeffs)


def _extrinsics(box, path: Path, prefix: str, what: str) -> tuple[int, np.ndarray]:
    """The stream's pose from its extrinsics group's reference: ROS1 `<prefix>/tf/<g>` (Transform) or ROS2
    `<prefix>/tf/ref_<g>` (text, rotation column-major)."""
    found = [t for t in box.topics if re.fullmatch(re.escape(prefix) + r"/tf/(ref_)?\d+", t)]
    label = f"the {what} stream's extrinsics"
    if len(found) != 1:
        raise _bag_error(path, f"{'no topic' if not found else f'{len(found)} topics'} {prefix}/tf/<group> ({label}"
                               f"{'' if not found else ': ' + ', '.join(found)}); record both streams of one device")
    topic = found[0]
    group, m = int(topic.rsplit("_", 1)[-1].rsplit("/", 1)[-1]), np.eye(4)
    if box.topics[topic] == STRING:
        values = _text(box, path, topic, ("rotation", "translation"), label)
        m[:3, :3] = _numbers(path, topic, values, "rotation", 9).reshape(3, 3).T  # librealsense's: column-major
        m[:3, 3] = _numbers(path, topic, values, "translation", 3)
        return group, m
    _check_type(box, path, topic, ("geometry_msgs/msg/Transform",), label)
    msg = _read_one(box, path, topic, label)
    q = np.array([msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w], np.float64)
    x, y, z, w = q / np.linalg.norm(q)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = [msg.translation.x, msg.translation.y, msg.translation.z]
    return group, m


def _depth_units(box, path: Path, sensor: str) -> float:
    """The depth sensor's Depth Units option (m per unit): `Depth_Units` (2.54 on) or `Depth Units` (older)."""
    topics = [f"{sensor}/option/{name}/value" for name in ("Depth_Units", "Depth Units")]
    present = [t for t in topics if t in box.topics]
    if not present:
        raise _bag_error(path, f"no topic {topics[0]} (the depth sensor's Depth Units option, metres per depth unit; "
                               f"'{topics[1]}' in older recordings); record the depth sensor with librealsense 2.x")
    topic = present[0]
    msg = _read_one(box, path, topic, "the Depth Units option")
    if box.topics[topic] == STRING:
        try:
            scale = float(_f32(float(str(msg.data))))  # librealsense's options are float32
        except ValueError:
            raise _bag_error(path, f"topic {topic} {str(msg.data)[:40]!r} is not a number of metres per depth "
                                   "unit") from None
    else:
        _check_type(box, path, topic, ("std_msgs/msg/Float32", "std_msgs/msg/Float64"), "the Depth Units option")
        scale = float(msg.data)
    if not 0 < scale < 0.1:
        raise _bag_error(path, f"Depth Units {scale} ({topic}) is not metres per unit")
    return scale


def _frames_ros1(box, path: Path, topic: str, what: str) -> dict:
    """Header stamps (s), message times (ns) and seqs of a ROS1 image topic (the header: seq uint32, stamp secs
    uint32, nsecs uint32)."""
    stamps, times, seqs = [], [], []
    for log_time, raw in box.messages(topic):
        seq, secs, nsecs = struct.unpack_from("<III", raw, 0)
        stamps.append(secs + nsecs * 1e-9)
        times.append(log_time)
        seqs.append(seq)
    domain, meta = None, topic.rsplit("/data", 1)[0] + "/metadata"  # diagnostic_msgs/KeyValue, one key a message
    if box.topics.get(meta) == "diagnostic_msgs/msg/KeyValue":
        for i, (_, raw) in enumerate(box.messages(meta)):
            msg = box.decode(meta, raw)
            if str(msg.key) == "timestamp_domain" or i > 64:
                domain = str(msg.value) if str(msg.key) == "timestamp_domain" else None
                break
    return {"stamps": stamps, "times": times, "seqs": seqs, "nth": [0] * len(seqs), "domain": domain}


def _frames_ros2(box, path: Path, topic: str, prefix: str, what: str) -> dict:
    """Frame timestamps (s) and numbers of a ROS2 image topic from `<prefix>/image/metadata` (the message at the same
    time), message times (ns) and which message at its time each is."""
    from dsr_bench.annotator.rosfile import key_values

    meta = prefix + "/image/metadata"
    if meta not in box.topics:
        raise _bag_error(path, f"no topic {meta} (each {what} frame's number and timestamp, which a ROS2 recording "
                               "keeps there); record with librealsense 2.58 or later")
    _check_type(box, path, meta, (STRING,), f"the {what} frames' metadata")
    by_time: dict[int, list[dict]] = {}
    for log_time, raw in box.messages(meta):
        by_time.setdefault(log_time, []).append(key_values(box.decode(meta, raw).data))
    out: dict = {"stamps": [], "times": [], "seqs": [], "nth": [], "domain": None}
    seen: dict[int, int] = {}
    for log_time in box.times(topic):
        nth = seen[log_time] = seen.get(log_time, -1) + 1
        entries = by_time.get(log_time, [])
        values = entries[nth] if nth < len(entries) else {}
        try:
            out["stamps"].append(float(values["timestamp"]) / 1000.0)
            out["seqs"].append(int(values["Frame number"]))
        except (KeyError, ValueError):
            raise _bag_error(path, f"the {what} frame of {topic} at {log_time} ns has no metadata on {meta} with its "
                                   f"Frame number and timestamp (got {values or 'none'}); expected librealsense's "
                                   "'Frame number=N;timestamp_domain=...;timestamp=<ms>;...'") from None
        out["times"].append(log_time)
        out["nth"].append(nth)
        out["domain"] = out["domain"] or values.get("timestamp_domain")
    return out


def _stream(box, path: Path, topic: str, prefix: str, payload: str, info: StreamInfo, what: str
            ) -> tuple[Stream, str | None]:
    """The stream and its frames' timestamp domain (librealsense's name, from the metadata; None if unrecorded)."""
    got = _frames_ros2(box, path, topic, prefix, what) if box.ros2 else _frames_ros1(box, path, topic, what)
    if not got["stamps"]:
        raise _bag_error(path, f"topic {topic} holds no {what} frames; record the {what} stream")
    order = np.argsort(got["stamps"], kind="stable")
    return Stream(topic, info, np.asarray(got["stamps"], np.float64)[order], np.asarray(got["times"], np.int64)[order],
                  np.asarray(got["seqs"], np.int64)[order], payload, np.asarray(got["nth"], np.int64)[order]), \
        got["domain"]


def _about(box, path: Path, color: Stream, topics: dict, domain: str | None) -> dict:
    """What the file is: container, librealsense's file version, the writer it points to, the device and sensors,
    the timestamp domain and where the recording starts on the frame clock."""
    from dsr_bench.annotator.rosfile import key_values

    def texts(topic: str) -> dict[str, str]:  # informational: a topic of another type is skipped
        if box.topics.get(topic) != (STRING if box.ros2 else "diagnostic_msgs/msg/KeyValue"):
            return {}
        out: dict[str, str] = {}
        for _, raw in box.messages(topic):
            msg = box.decode(topic, raw)
            out.update(key_values(msg.data) if box.ros2 else {str(msg.key): str(msg.value)})
        return out

    version = None
    if box.topics.get("/file_version") in ("std_msgs/msg/UInt32", "std_msgs/msg/UInt16"):
        version = int(_read_one(box, path, "/file_version", "librealsense's file format version").data)
    device = texts(topics["Color"][1].split("/sensor_")[0] + "/info")
    sensors = {what: texts(topics[kind][1].rsplit("/", 1)[0] + "/info").get("Name", "?")
               for kind, what in (("Color", "colour"), ("Depth", "depth"))}
    if not box.ros2:
        writer = "librealsense up to 2.57 (ROS1 bag)"
    else:
        writer = ("librealsense 2.59 or later (ROS2, PNG images)" if color.payload == "png" else
                  "librealsense 2.59 or later (ROS2, raw images)" if "/tf_static" in box.topics else
                  "librealsense 2.58 (ROS2, raw images)")
    first = int(np.argmin(color.log_times))  # the first frame recorded: its timestamp less its message time
    start = float(color.stamps[first] - color.log_times[first] * 1e-9)
    return {"container": box.kind, "file_version": version, "writer": writer, "device": device.get("Name"),
            "serial": device.get("Serial Number"), "firmware": device.get("Firmware Version"), "sensors": sensors,
            "timestamp_domain": domain, "recording_start": start,
            "header_stamps": "from the recording's start" if box.ros2 else "frame timestamps"}


def open_recording(path: Path, name: str) -> Recording:
    """Read a camera's recording (.bag, .db3 or a ROS2 bag directory): its colour and depth streams' intrinsics, the
    depth -> colour extrinsics, the depth units and every frame's timestamp and number; UserError naming the file
    and the missing or bad topic."""
    from rosbags.rosbag1 import ReaderError as Ros1Error
    from rosbags.rosbag2 import ReaderError as Ros2Error
    from rosbags.serde import SerdeError
    from rosbags.typesys import TypesysError

    from dsr_bench.annotator.rosfile import ContainerError, open_container

    try:
        with open_container(path) as box:
            topics = _image_topics(box, path)
            (color_topic, color_prefix, color_payload), (depth_topic, depth_prefix, depth_payload) = \
                topics["Color"], topics["Depth"]
            color_info = _stream_info(box, path, color_prefix, "colour")
            depth_info = _stream_info(box, path, depth_prefix, "depth")
            (gc, ref_to_color), (gd, ref_to_depth) = (_extrinsics(box, path, p, w)
                                                      for p, w in ((color_prefix, "colour"), (depth_prefix, "depth")))
            if gc != gd:
                raise _bag_error(path, f"the colour and depth extrinsics are relative to different groups ({gc}, "
                                       f"{gd}): no depth -> colour transform; record both streams of one device")
            scale = _depth_units(box, path, depth_prefix.rsplit("/", 1)[0])
            color, domain = _stream(box, path, color_topic, color_prefix, color_payload, color_info, "colour")
            depth, _ = _stream(box, path, depth_topic, depth_prefix, depth_payload, depth_info, "depth")
            about = _about(box, path, color, topics, domain)
    except ContainerError as exc:
        raise _bag_error(path, f"{exc}; give the recording librealsense wrote (.bag up to 2.57, .db3 from 2.58, or a "
                               "ROS2 bag directory)") from None
    except READ_ERRORS + (SerdeError, TypesysError, Ros1Error, Ros2Error) as exc:
        raise _bag_error(path, f"unreadable ({type(exc).__name__}: {exc}); give the recording a RealSense recorder "
                               "wrote") from None
    depth_to_color = ref_to_color @ np.linalg.inv(ref_to_depth)
    return Recording(name, path, color, depth, depth_to_color, scale, about)


# --- frames ----------------------------------------------------------------------------------------------------------


def ros1_image(raw: bytes) -> SimpleNamespace:
    """A ROS1 sensor_msgs/Image's fields read by hand (header, height, width, encoding, is_bigendian, step, data);
    bytes after `data` (librealsense 2.54 on: a float32 of the depth units) are ignored."""
    offset = 12
    (length,) = struct.unpack_from("<I", raw, offset)
    offset += 4 + length
    height, width, length = struct.unpack_from("<III", raw, offset)
    encoding = raw[offset + 12:offset + 12 + length].decode("ascii", "replace")
    offset += 12 + length
    is_bigendian, step, length = struct.unpack_from("<BII", raw, offset)
    data = raw[offset + 9:offset + 9 + length]
    if len(data) != length:
        raise struct.error(f"image data cut short ({len(data)} of {length} bytes)")
    return SimpleNamespace(height=height, width=width, encoding=encoding, is_bigendian=is_bigendian, step=step,
                           data=data)


def _decode(msg, stream: Stream, path: Path, kind: str) -> np.ndarray:
    """A sensor_msgs/Image as colour (H, W, 3) uint8 RGB or depth (H, W) uint16 units, checked against the info."""
    info, encoding = stream.info, str(msg.encoding)
    if (msg.height, msg.width) != (info.height, info.width):
        raise _bag_error(path, f"a {kind} frame of {stream.topic} is {msg.width}x{msg.height}, its camera_info "
                               f"{info.width}x{info.height}; re-record without changing the resolution")
    data = np.frombuffer(bytes(msg.data), np.uint8)
    known = encoding in COLOR_ENCODINGS if kind == "colour" else encoding in DEPTH_ENCODINGS  # else refused below
    row = info.width * (COLOR_ENCODINGS[encoding][0] if kind == "colour" and known else 2)
    if known and (not row <= int(msg.step) <= row * 4 or len(data) != info.height * int(msg.step)):
        raise _bag_error(path, f"a {kind} frame of {stream.topic} holds {len(data)} bytes in rows of {msg.step}, not "
                               f"{info.height} rows of at least {row} bytes ({info.width}x{info.height} {encoding}); "
                               "re-record the camera")
    if kind == "colour":
        if encoding not in COLOR_ENCODINGS:
            raise _bag_error(path, f"colour encoding {encoding!r} of {stream.topic} is not one of "
                                   f"{', '.join(COLOR_ENCODINGS)}; record the colour stream as RGB8 or BGR8")
        channels, bgr = COLOR_ENCODINGS[encoding]
        image = data.reshape(info.height, msg.step)[:, :info.width * channels].reshape(info.height, info.width,
                                                                                      channels)[..., :3]
        return np.ascontiguousarray(image[..., ::-1] if bgr else image)
    if encoding not in DEPTH_ENCODINGS:
        raise _bag_error(path, f"depth encoding {encoding!r} of {stream.topic} is not {' or '.join(DEPTH_ENCODINGS)}; "
                               "record the depth stream as Z16")
    rows = data.reshape(info.height, msg.step)[:, :info.width * 2]
    return np.ascontiguousarray(rows).view(">u2" if msg.is_bigendian else "<u2").astype(np.uint16)


def _decode_png(msg, stream: Stream, path: Path, kind: str) -> np.ndarray:
    """A sensor_msgs/CompressedImage PNG (2.59: colour "rgb8; png compressed bgr8", the PNG in RGB order; depth
    "16UC1; compressedDepth png", a 12-byte header before the PNG) as `_decode` returns it; its size is read from
    the PNG header and checked against the info before it is decoded."""
    from PIL import Image

    info, form, data = stream.info, str(msg.format), bytes(msg.data)
    if not data.startswith(PNG_SIGNATURE) and data[12:20] == PNG_SIGNATURE:  # compressedDepth's header
        data = data[12:]
    if not data.startswith(PNG_SIGNATURE) or len(data) < 33:
        raise _bag_error(path, f"a {kind} frame of {stream.topic} is {form!r} and not a PNG (this importer reads "
                               "librealsense's PNG frames); re-record the camera")
    width, height = struct.unpack(">II", data[16:24])
    if (height, width) != (info.height, info.width):
        raise _bag_error(path, f"a {kind} frame of {stream.topic} is {width}x{height}, its camera_info "
                               f"{info.width}x{info.height}; re-record without changing the resolution")
    try:
        image = Image.open(io.BytesIO(data))
        image.load()
    except (OSError, ValueError, SyntaxError) as exc:
        raise _bag_error(path, f"a {kind} frame of {stream.topic} is a broken PNG ({exc}); re-record the "
                               "camera") from None
    if kind == "colour":
        if image.mode not in ("RGB", "RGBA"):
            raise _bag_error(path, f"a colour frame of {stream.topic} is a {image.mode} PNG ({form!r}); record the "
                                   "colour stream as RGB8 or BGR8")
        return np.ascontiguousarray(np.asarray(image)[..., :3], np.uint8)
    if image.mode not in ("I;16", "I;16B", "I;16L", "I"):
        raise _bag_error(path, f"a depth frame of {stream.topic} is a {image.mode} PNG ({form!r}), not 16-bit; "
                               "record the depth stream as Z16")
    return np.asarray(image).astype(np.uint16)


def read_frame(recording: Recording, kind: str, index: int) -> np.ndarray:
    """Frame `index` (in timestamp order) of the colour ("colour": (H, W, 3) uint8 RGB) or depth ("depth": (H, W)
    uint16 depth units) stream, as recorded (raw, not undistorted)."""
    from rosbags.rosbag1 import ReaderError as Ros1Error
    from rosbags.rosbag2 import ReaderError as Ros2Error
    from rosbags.serde import SerdeError

    from dsr_bench.annotator.rosfile import ContainerError, open_container

    stream = recording.color if kind == "colour" else recording.depth
    t, seq = int(stream.log_times[index]), int(stream.seqs[index])
    nth = 0 if stream.nth is None else int(stream.nth[index])
    try:
        with open_container(recording.path) as box:
            for i, (_, raw) in enumerate(box.messages(stream.topic, start=t, stop=t + 1)):
                if stream.payload == "ros1" and struct.unpack_from("<I", raw, 0)[0] == seq:
                    return _decode(ros1_image(raw), stream, recording.path, kind)
                if stream.payload != "ros1" and i == nth:
                    msg = box.decode(stream.topic, raw)
                    decode = _decode_png if stream.payload == "png" else _decode
                    return decode(msg, stream, recording.path, kind)
    except READ_ERRORS + (ContainerError, SerdeError, Ros1Error, Ros2Error) as exc:
        raise _bag_error(recording.path, f"the {kind} frame {seq} of {stream.topic} is unreadable "
                                         f"({type(exc).__name__}: {exc}); re-record the camera") from None
    raise _bag_error(recording.path, f"the {kind} frame {seq} of {stream.topic} could not be read back")
