"""`dsr-bench import-capture` of RealSense `.bag` recordings (docs/annotator.md, "Real captures in", "RealSense
recordings").

The folder:

    SRC/front.bag, SRC/back.bag  one librealsense recording per camera (realsense-viewer, rs-record, rs2::recorder:
                                 ROS1 bag v2.0, read with `rosbags`, no librealsense needed); the stem names the camera
    SRC/steps.json               {"step_times": [t0, ..., tT]}: per step the time (s, the frames' header-stamp clock)
                                 at which the rig saw step N; or {"step_times": {"front": [...], "back": [...]}} per
                                 camera; optional "board_time" (the same forms): when the board lay alone on the table
    SRC/rig.json                 objects, board and/or per-camera "extrinsics" (intrinsics and depth scale: the bags)
    SRC/pushes.json              the robot's push log (annotator.pushes)

Topics read per bag (librealsense's `ros_file_format.h`; `<s>`, `<d>` the colour / depth sensor index, `<g>` an
extrinsics group): `/device_0/sensor_<s>/Color_0/image/data` (sensor_msgs/Image rgb8, bgr8, rgba8 or bgra8),
`/device_0/sensor_<d>/Depth_0/image/data` (sensor_msgs/Image mono16 or 16UC1), `.../<Stream>_0/info/camera_info`
(sensor_msgs/CameraInfo: width, height, K, D, distortion_model), `.../<Stream>_0/tf/<g>` (geometry_msgs/Transform:
the stream's pose from the reference stream of group g, p_stream = R p_reference + t, m) and
`/device_0/sensor_<d>/option/Depth Units/value` (std_msgs/Float32, metres per depth unit).

Per step the colour frame whose header stamp is nearest the step time is taken, and the depth frame nearest that
colour frame; either further than `max_gap` (default DEFAULT_MAX_GAP_MS) is refused. Colour is undistorted onto its
own pinhole (fx, fy, cx, cy); depth is registered to it (`align_depth`): each depth pixel is back-projected with the
depth stream's intrinsics (and distortion), moved into the colour camera by the depth -> colour extrinsics, and
splatted over the colour pixels its footprint covers, the nearest surface winning (z-buffer); 0 = no depth.
"""

from __future__ import annotations

import json
import math
import re
import struct
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from annotator.inputs import MAX_IMAGE_SIDE, finite, image_side, is_number, numbers, resolved_inside
from dsr_bench.errors import UserError

#: A step's colour frame must lie this close (ms) to the step time, and its depth frame this close to the colour.
DEFAULT_MAX_GAP_MS: float = 50.0
STEPS_FILE = "steps.json"
BAG_SUFFIX = ".bag"
#: librealsense's distortion models (`rs2_distortion_to_string`) this importer undistorts.
SUPPORTED_MODELS = ("None", "Brown Conrady", "Inverse Brown Conrady", "Modified Brown Conrady")
COLOR_ENCODINGS = {"rgb8": (3, False), "bgr8": (3, True), "rgba8": (4, False), "bgra8": (4, True)}
DEPTH_ENCODINGS = ("mono16", "16UC1")
#: A depth pixel's footprint larger than this (colour pixels per axis) is dropped (a grazing or broken sample).
MAX_SPLAT = 8
#: Registration's z-buffer: candidates within SAME_SURFACE_M + SAME_SURFACE_REL x z (m) of a colour pixel's nearest
#: one are the same surface (a sloped table's neighbouring samples); anything further behind is hidden by it.
SAME_SURFACE_M, SAME_SURFACE_REL = 0.005, 0.01
_HINT = "docs/annotator.md, 'RealSense recordings'"


@dataclass(frozen=True)
class StreamInfo:
    """A stream's sensor_msgs/CameraInfo: image width and height (px), intrinsics (3, 3) px, librealsense's distortion
    model name and its coefficients (5,) [k1, k2, p1, p2, k3]."""

    width: int
    height: int
    intrinsics: np.ndarray
    model: str
    coeffs: np.ndarray

    @property
    def distorted(self) -> bool:
        """Whether the coefficients bend rays at all (all-zero coefficients are a pinhole in every model)."""
        return self.model != "None" and bool(np.any(self.coeffs != 0))


@dataclass
class Stream:
    """One image stream of a bag: its topic, info, and per frame (sorted by stamp) the header stamp (s), the bag's
    log time (ns, to seek the message) and the header seq (the frame number)."""

    topic: str
    info: StreamInfo
    stamps: np.ndarray
    log_times: np.ndarray
    seqs: np.ndarray


@dataclass
class Recording:
    """One camera's bag: colour and depth streams, the depth -> colour 4x4 (m, p_colour = M p_depth), metres per
    depth unit."""

    name: str
    path: Path
    color: Stream
    depth: Stream
    depth_to_color: np.ndarray
    depth_scale: float

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
    return UserError(f"{path}: {message}; see {_HINT}")


# --- distortion ------------------------------------------------------------------------------------------------------


def _brown(xy: np.ndarray, c: np.ndarray, modified: bool) -> np.ndarray:
    """Brown-Conrady polynomial of normalised points (N, 2) with c = [k1, k2, p1, p2, k3]: OpenCV's (tangential terms
    of the original point) or librealsense's "Modified" form (tangential terms of the radially scaled point)."""
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    f = 1 + c[0] * r2 + c[1] * r2 * r2 + c[4] * r2 * r2 * r2
    tx, ty = (x * f, y * f) if modified else (x, y)
    return np.stack([x * f + 2 * c[2] * tx * ty + c[3] * (r2 + 2 * tx * tx),
                     y * f + 2 * c[3] * tx * ty + c[2] * (r2 + 2 * ty * ty)], 1)


def _invert(function, target: np.ndarray, iterations: int = 50, tolerance: float = 1e-12) -> np.ndarray:
    """Points p (N, 2) with function(p) = target (fixed-point iteration, until every point is within `tolerance`;
    the polynomials are near the identity)."""
    p = target.copy()
    for _ in range(iterations):
        error = function(p) - target
        if np.max(np.abs(error)) < tolerance:
            break
        p = p - error
    return p


def _raw_of_ideal(info: StreamInfo, xy: np.ndarray) -> np.ndarray:
    """Where ideal (pinhole) normalised points (N, 2) lie in the raw image, normalised."""
    c = info.coeffs
    if not info.distorted:
        return xy
    if info.model == "Inverse Brown Conrady":  # its polynomial maps raw -> ideal
        return _invert(lambda p: _brown(p, c, False), xy)
    return _brown(xy, c, info.model == "Modified Brown Conrady")


def ideal_rays(info: StreamInfo, pixels: np.ndarray) -> np.ndarray:
    """Normalised ideal rays (N, 2) (x/z, y/z) of raw pixels (N, 2) (u along columns, v along rows) of a stream."""
    k = info.intrinsics
    xy = (pixels - k[:2, 2]) / np.array([k[0, 0], k[1, 1]])
    c = info.coeffs
    if not info.distorted:
        return xy
    if info.model == "Inverse Brown Conrady":
        return _brown(xy, c, False)
    return _invert(lambda p: _brown(p, c, info.model == "Modified Brown Conrady"), xy)


def undistortion_maps(info: StreamInfo) -> tuple[np.ndarray, np.ndarray] | None:
    """OpenCV remap tables (H, W) float32 x, y: for each pixel of the undistorted image (same fx, fy, cx, cy, no
    distortion) where it lies in the raw one; None when the stream needs no undistortion. OpenCV's own model
    ("Brown Conrady") goes through `annotator.importer.undistort_maps`."""
    if not info.distorted:
        return None
    if info.model == "Brown Conrady":
        from annotator.importer import undistort_maps
        from dsr_bench.dataset.capture import CaptureCamera

        camera = CaptureCamera("stream", info.height, info.width, info.intrinsics, np.eye(4), 0.001)
        return undistort_maps(camera, info.coeffs)
    k = info.intrinsics
    v, u = np.mgrid[0:info.height, 0:info.width].astype(np.float64)
    xy = (np.stack([u.ravel(), v.ravel()], 1) - k[:2, 2]) / np.array([k[0, 0], k[1, 1]])
    raw = _raw_of_ideal(info, xy) * np.array([k[0, 0], k[1, 1]]) + k[:2, 2]
    shape = (info.height, info.width)
    return raw[:, 0].reshape(shape).astype(np.float32), raw[:, 1].reshape(shape).astype(np.float32)


# --- depth registration ----------------------------------------------------------------------------------------------


def _project(points: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) (u, v) of camera-frame points (N, 3) m through the pinhole k (3, 3)."""
    return points[:, :2] / points[:, 2:] * [k[0, 0], k[1, 1]] + k[:2, 2]


def align_depth(depth_m: np.ndarray, corner_rays: np.ndarray, depth_to_color: np.ndarray, color_k: np.ndarray,
                color_shape: tuple[int, int]) -> np.ndarray:
    """Depth (Hd, Wd) m (0 = none) of the depth stream registered to the undistorted colour image: (Hc, Wc) z-depth
    m in the colour camera, 0 = no depth.

    corner_rays: (Hd + 1, Wd + 1, 2) the depth pixels' corner rays (`Recording.depth_corner_rays`); depth_to_color
    4x4 m; color_k (3, 3) px of the pinhole colour image, color_shape (Hc, Wc). Each depth pixel's two opposite
    corners (at its depth) are moved into the colour camera and projected; the colour pixels between them (rounded,
    inclusive, as librealsense's align) are candidates for the z of the pixel's centre point in the colour camera.
    Per colour pixel a z-buffer keeps the nearest surface (candidates further than SAME_SURFACE behind the nearest
    are hidden) and, of its candidates, the one whose centre projects closest to the pixel (taking the nearest z
    outright would bias sloped surfaces towards the camera)."""
    hc, wc = color_shape
    rows, cols = np.nonzero(depth_m > 0)
    z = depth_m[rows, cols]
    rot, t = depth_to_color[:3, :3], depth_to_color[:3, 3]

    def to_color(rays: np.ndarray) -> np.ndarray:  # (N, 3) m in the colour camera of the rays (N, 2) at depth z
        x, y = rays[:, 0] * z, rays[:, 1] * z
        return np.stack([rot[i, 0] * x + rot[i, 1] * y + rot[i, 2] * z + t[i] for i in range(3)], 1)

    a, b = to_color(corner_rays[rows, cols]), to_color(corner_rays[rows + 1, cols + 1])
    centre = (a + b) / 2  # the transform is affine and both corners lie at the pixel's depth
    ok = (a[:, 2] > 0) & (b[:, 2] > 0)
    ua = np.floor(_project(a[ok], color_k) + 0.5).astype(np.int64)
    ub = np.floor(_project(b[ok], color_k) + 0.5).astype(np.int64)
    uc, zc = _project(centre[ok], color_k), centre[ok, 2]
    lo, hi = np.minimum(ua, ub), np.maximum(ua, ub)
    keep = np.all(lo >= 0, 1) & (hi[:, 0] < wc) & (hi[:, 1] < hc) & np.all(hi - lo < MAX_SPLAT, 1)
    lo, hi, uc, zc = lo[keep], hi[keep], uc[keep], zc[keep]
    span = (hi - lo).max(0) + 1 if len(zc) else np.zeros(2, np.int64)
    index, value, miss = [], [], []
    for du in range(int(span[0])):  # a few offsets within a footprint, each vectorised over all pixels
        for dv in range(int(span[1])):
            inside = (lo[:, 0] + du <= hi[:, 0]) & (lo[:, 1] + dv <= hi[:, 1])
            u, v = lo[inside, 0] + du, lo[inside, 1] + dv
            index.append(v * wc + u)
            value.append(zc[inside])
            miss.append((uc[inside, 0] - u) ** 2 + (uc[inside, 1] - v) ** 2)
    out = np.zeros(hc * wc)
    if not index:
        return out.reshape(hc, wc)
    index, value, miss = np.concatenate(index), np.concatenate(value), np.concatenate(miss)
    nearest = np.full(hc * wc, np.inf)
    np.minimum.at(nearest, index, value)  # the z-buffer
    front = value <= nearest[index] * (1 + SAME_SURFACE_REL) + SAME_SURFACE_M
    index, value, miss = index[front], value[front], miss[front]
    closest = np.full(hc * wc, np.inf)
    np.minimum.at(closest, index, miss)
    best = miss == closest[index]
    out[index[best]] = value[best]  # ties (equally near centres) are equally good
    return out.reshape(hc, wc)


# --- reading a bag ---------------------------------------------------------------------------------------------------


def _typestore(connection):
    """A rosbags typestore of the connection's own message definition (as recorded)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(connection.msgdef.data, connection.msgtype))
    return store


def _read_one(reader, connection, path: Path, what: str):
    """The last message of a static topic, deserialised."""
    store = _typestore(connection)
    message = None
    for _, _, raw in reader.messages(connections=[connection]):
        message = store.deserialize_ros1(raw, connection.msgtype)
    if message is None:
        raise _bag_error(path, f"topic {connection.topic} ({what}) holds no message; re-record the camera")
    return message


def _find(connections: dict, path: Path, pattern: str, what: str, msgtype: str):
    """The connection whose topic matches `pattern` (a regex), checked to be of `msgtype`."""
    found = [c for t, c in connections.items() if re.fullmatch(pattern, t)]
    if not found:
        shown = pattern.replace("\\d+", "N").replace("\\", "")
        raise _bag_error(path, f"no topic {shown} ({what}); record the colour and depth streams with realsense-viewer "
                               "or rs-record (librealsense 2.x), one bag per camera")
    if len(found) > 1:
        raise _bag_error(path, f"{len(found)} topics hold the {what} ({', '.join(c.topic for c in found)}); record one "
                               "device with one colour and one depth stream per bag")
    if found[0].msgtype != msgtype:
        raise _bag_error(path, f"topic {found[0].topic} is {found[0].msgtype}, expected {msgtype}")
    return found[0]


def _stream_info(reader, connections: dict, path: Path, prefix: str, what: str) -> StreamInfo:
    conn = _find(connections, path, re.escape(prefix) + "/info/camera_info", f"the {what} stream's intrinsics",
                 "sensor_msgs/msg/CameraInfo")
    msg = _read_one(reader, conn, path, f"the {what} stream's intrinsics")
    k = np.array(msg.K, np.float64).reshape(3, 3)
    coeffs = np.zeros(5)
    d = np.asarray(msg.D, np.float64).reshape(-1)
    model = str(msg.distortion_model)
    if model not in SUPPORTED_MODELS:
        raise _bag_error(path, f"the {what} stream ({conn.topic}) has distortion model {model!r}, which this importer "
                               f"cannot undistort (it handles {', '.join(map(repr, SUPPORTED_MODELS))}); record the "
                               "camera's colour and depth streams, or export PNGs and use the folder form")
    if len(d) > 5 and np.any(d[5:] != 0) or not np.all(np.isfinite(d)):
        raise _bag_error(path, f"the {what} stream's distortion D {d.tolist()} is not 5 finite coefficients "
                               "[k1, k2, p1, p2, k3]")
    coeffs[:min(5, len(d))] = d[:5]
    if not (k[0, 0] > 0 and k[1, 1] > 0 and msg.width > 0 and msg.height > 0 and np.all(np.isfinite(k))):
        raise _bag_error(path, f"the {what} stream's camera_info ({conn.topic}) has no intrinsics (K "
                               f"{k.ravel().tolist()}, {msg.width}x{msg.height}); re-record with a calibrated camera")
    if not (image_side(int(msg.width)) and image_side(int(msg.height))):
        raise _bag_error(path, f"the {what} stream's camera_info ({conn.topic}) declares {msg.width}x{msg.height} "
                               f"pixels, over the {MAX_IMAGE_SIDE} px per side this importer takes; record at a "
                               "RealSense resolution")
    k[0, 1], k[1, 0], k[2] = 0.0, 0.0, (0.0, 0.0, 1.0)
    return StreamInfo(int(msg.width), int(msg.height), k, model, coeffs)


def _transform(msg) -> np.ndarray:
    """4x4 of a geometry_msgs/Transform (unit quaternion x, y, z, w; translation m)."""
    q = np.array([msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w], np.float64)
    x, y, z, w = q / np.linalg.norm(q)
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = [msg.translation.x, msg.translation.y, msg.translation.z]
    return m


def _extrinsics(reader, connections: dict, path: Path, prefix: str, what: str) -> tuple[int, np.ndarray]:
    conn = _find(connections, path, re.escape(prefix) + r"/tf/\d+", f"the {what} stream's extrinsics",
                 "geometry_msgs/msg/Transform")
    return int(conn.topic.rsplit("/", 1)[1]), _transform(_read_one(reader, conn, path, f"the {what} extrinsics"))


def _frames(reader, connection, path: Path, what: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Header stamps (s), log times (ns) and seqs of an image topic's messages, sorted by stamp (the header is read
    from the message's first bytes: seq uint32, stamp secs uint32, nsecs uint32)."""
    stamps, times, seqs = [], [], []
    for _, log_time, raw in reader.messages(connections=[connection]):
        seq, secs, nsecs = struct.unpack_from("<III", raw, 0)
        stamps.append(secs + nsecs * 1e-9)
        times.append(log_time)
        seqs.append(seq)
    if not stamps:
        raise _bag_error(path, f"topic {connection.topic} holds no {what} frames; record the {what} stream")
    order = np.argsort(stamps, kind="stable")
    return np.asarray(stamps)[order], np.asarray(times, np.int64)[order], np.asarray(seqs, np.int64)[order]


def open_recording(path: Path, name: str) -> Recording:
    """Read a camera's bag: its colour and depth streams' intrinsics, the depth -> colour extrinsics, the depth
    units and every frame's stamp; UserError naming the bag and the missing or bad topic."""
    from rosbags.rosbag1 import Reader, ReaderError
    from rosbags.serde import SerdeError
    from rosbags.typesys import TypesysError

    try:
        with Reader(path) as reader:
            connections = {c.topic: c for c in reader.connections}
            color_conn = _find(connections, path, r"/device_\d+/sensor_\d+/Color_0/image/data", "the colour frames",
                               "sensor_msgs/msg/Image")
            depth_conn = _find(connections, path, r"/device_\d+/sensor_\d+/Depth_0/image/data", "the depth frames",
                               "sensor_msgs/msg/Image")
            color_prefix, depth_prefix = (c.topic.rsplit("/image/data", 1)[0] for c in (color_conn, depth_conn))
            color_info = _stream_info(reader, connections, path, color_prefix, "colour")
            depth_info = _stream_info(reader, connections, path, depth_prefix, "depth")
            (gc, ref_to_color), (gd, ref_to_depth) = (_extrinsics(reader, connections, path, p, w)
                                                      for p, w in ((color_prefix, "colour"), (depth_prefix, "depth")))
            if gc != gd:
                raise _bag_error(path, f"the colour and depth extrinsics are relative to different groups ({gc}, "
                                       f"{gd}): no depth -> colour transform; record both streams of one device")
            sensor = depth_prefix.rsplit("/", 1)[0]
            units_conn = _find(connections, path, re.escape(sensor + "/option/Depth Units/value"),
                               "the depth sensor's Depth Units option, metres per depth unit", "std_msgs/msg/Float32")
            scale = float(_read_one(reader, units_conn, path, "Depth Units").data)
            if not 0 < scale < 0.1:
                raise _bag_error(path, f"Depth Units {scale} ({units_conn.topic}) is not metres per unit")
            color = Stream(color_conn.topic, color_info, *_frames(reader, color_conn, path, "colour"))
            depth = Stream(depth_conn.topic, depth_info, *_frames(reader, depth_conn, path, "depth"))
    except (ReaderError, SerdeError, TypesysError, struct.error) as exc:  # a broken or foreign file
        raise _bag_error(path, f"unreadable as a ROS1 bag ({type(exc).__name__}: {exc}); give the .bag a RealSense "
                               "recorder wrote") from None
    depth_to_color = ref_to_color @ np.linalg.inv(ref_to_depth)
    return Recording(name, path, color, depth, depth_to_color, scale)


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


def read_frame(recording: Recording, kind: str, index: int) -> np.ndarray:
    """Frame `index` (in stamp order) of the colour ("colour": (H, W, 3) uint8 RGB) or depth ("depth": (H, W) uint16
    depth units) stream, as recorded (raw, not undistorted)."""
    from rosbags.rosbag1 import Reader

    stream = recording.color if kind == "colour" else recording.depth
    t, seq = int(stream.log_times[index]), int(stream.seqs[index])
    with Reader(recording.path) as reader:
        conn = next(c for c in reader.connections if c.topic == stream.topic)
        store = _typestore(conn)
        for _, _, raw in reader.messages(connections=[conn], start=t, stop=t + 1):
            if struct.unpack_from("<I", raw, 0)[0] == seq:
                return _decode(store.deserialize_ros1(raw, conn.msgtype), stream, recording.path, kind)
    raise _bag_error(recording.path, f"the {kind} frame {seq} of {stream.topic} could not be read back")


# --- step times and frames -------------------------------------------------------------------------------------------


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
        raise UserError(f"--steps {path}: no such file; write the time (s, the bags' header stamps) of every step as "
                        '{"step_times": [t0, t1, ...]} (' + _HINT + ")")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise UserError(f"--steps {path}: unreadable JSON ({exc}); fix the file") from None
    if not isinstance(data, dict) or "step_times" not in data:
        raise UserError(f'--steps {path}: expected {{"step_times": [t0, t1, ...]}} (s, the bags\' header stamps; or '
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

    for i in np.nonzero(gap > max_gap_s)[0]:
        raise UserError(f"{where}: {what(i)} time {times[i]:.3f} s has no {recording.name} colour frame within "
                        f"{max_gap_s * 1000:g} ms (nearest {c_st[color[i]]:.3f} s, {gap[i] * 1000:.0f} ms away; its "
                        f"colour frames span {c_st[0]:.3f}..{c_st[-1]:.3f} s in {recording.path.name}): give times on "
                        "the frames' header-stamp clock, or raise --max-gap-ms")
    depth = _nearest(d_st, c_st[color])
    dgap = np.abs(d_st[depth] - c_st[color])
    for i in np.nonzero(dgap > max_gap_s)[0]:
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
    they came from (header stamps s, seqs)."""

    color: np.ndarray
    depth: np.ndarray
    source: dict


def load_frames(recording: Recording, color_index: int, depth_index: int) -> Frames:
    """The colour frame undistorted (`undistortion_maps`, bilinear) and the depth frame registered to it
    (`align_depth`)."""
    from annotator.importer import undistort

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


def find_bags(src: Path) -> dict[str, Path]:
    """SRC's `<camera>.bag` files by camera name, the names checked as the PNG form's: `front` required, `back`
    optional, nothing else."""
    from annotator.importer import CAMERA_NAMES

    bags = {p.stem: resolved_inside(src, p, "recording", src) for p in sorted(src.glob("*" + BAG_SUFFIX))}
    bad = [n for n in bags if n not in CAMERA_NAMES]
    if bad or "front" not in bags:
        listed = ", ".join(p.name for p in bags.values())
        raise UserError(f"{src}: the bags ({listed}) must be front.bag (the view models see; required) and back.bag: "
                        f"rename {', '.join(bags[n].name for n in bad) or 'one of them to front.bag'} (the file's stem "
                        "names the camera)")
    return {n: bags[n] for n in CAMERA_NAMES if n in bags}


def import_bags(src: str | Path, out: str | Path, *, rig: str | Path | None = None, pushes: str | Path | None = None,
                steps: str | Path | None = None, max_gap_ms: float = DEFAULT_MAX_GAP_MS, name: str | None = None,
                overwrite: bool = False) -> tuple[Path, dict]:
    """Import SRC's RealSense bags (module docstring) into the capture directory `out`; returns (out, calibration
    report). Everything is read and checked first (one-line UserErrors), then written at once."""
    from annotator.importer import PUSHES_FILE, calibrate_cameras, check_out, default_file, load_rig, read_objects
    from annotator.pushes import read_pushes
    from dsr_bench.dataset.capture import parse_camera, write_capture

    src, out = Path(src), Path(out)
    check_out(out, overwrite)
    if not (math.isfinite(max_gap_ms) and max_gap_ms > 0):
        raise UserError(f"--max-gap-ms {max_gap_ms} must be a positive number of milliseconds")
    bags = find_bags(src)
    names = list(bags)
    rig_path, spec = load_rig(src, rig)
    rig_cameras = spec.get("cameras", {}) or {}
    if not isinstance(rig_cameras, dict) or any(n not in bags for n in rig_cameras):
        raise UserError(f"{rig_path}: \"cameras\" {list(rig_cameras)} must name only the bags' cameras "
                        f"({', '.join(names)}); see {_HINT}")
    for n, entry in rig_cameras.items():
        extra = sorted(set(entry) - {"extrinsics"}) if isinstance(entry, dict) else ["(not an object)"]
        if extra:
            raise UserError(f"{rig_path}: camera {n!r} gives {', '.join(extra)}, but with bags the intrinsics, "
                            f"distortion and depth scale come from {bags[n].name}: keep only \"extrinsics\" (4x4 "
                            "camera-to-table, m)")
        if entry.get("extrinsics") is not None and not numbers(entry["extrinsics"], (4, 4)):
            raise UserError(f"{rig_path}: camera {n!r} extrinsics must be a 4x4 matrix of numbers (camera-to-table, "
                            f"metres, row-major); see {_HINT}")
    if isinstance(spec.get("board"), dict) and spec["board"].get("images"):
        raise UserError(f"{rig_path}: board \"images\" are PNGs of the folder form; with bags give \"board_time\" (s) "
                        "in the steps file (the board alone on the table), or let the first step's frames be used")
    objects = read_objects(rig_path, src, spec.get("objects"))
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
              "step_times": {n: t.tolist() for n, t in step_times.items()}, "max_gap_ms": max_gap_ms,
              "frames": [{n: f[n].source for n in names} for f in frames], "calibration": report,
              "policy": "recorded"}
    written = write_capture(out, name=name or str(spec.get("name") or out.name), cameras=cameras,
                            colors=[{n: f[n].color for n in names} for f in frames],
                            depths=[{n: f[n].depth for n in names} for f in frames], actions=actions,
                            pushes_world=pushes_world, objects=objects, source=source, overwrite=overwrite)
    return written, report

