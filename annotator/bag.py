"""A librealsense recording (`.bag`) read without librealsense: its colour and depth streams, their intrinsics,
distortion and extrinsics, frames decoded, colour undistorted and depth registered to colour
(`dsr-bench import-capture` of RealSense bags: `annotator.realsense`; docs/annotator.md, "RealSense recordings").

Topics read per bag (librealsense's `ros_file_format.h`; `<s>`, `<d>` the colour / depth sensor index, `<g>` an
extrinsics group): `/device_0/sensor_<s>/Color_0/image/data` (sensor_msgs/Image rgb8, bgr8, rgba8 or bgra8),
`/device_0/sensor_<d>/Depth_0/image/data` (sensor_msgs/Image mono16 or 16UC1), `.../<Stream>_0/info/camera_info`
(sensor_msgs/CameraInfo: width, height, K, D, distortion_model), `.../<Stream>_0/tf/<g>` (geometry_msgs/Transform:
the stream's pose from the reference stream of group g, p_stream = R p_reference + t, m) and
`/device_0/sensor_<d>/option/Depth Units/value` (std_msgs/Float32, metres per depth unit).

Colour is undistorted onto its own pinhole (fx, fy, cx, cy) (`undistortion_maps`); depth is registered to it
(`align_depth`): each depth pixel is back-projected with the depth stream's intrinsics (and distortion), moved into
the colour camera by the depth -> colour extrinsics, and splatted over the colour pixels its footprint covers, the
nearest surface winning (z-buffer); 0 = no depth.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from annotator.inputs import MAX_IMAGE_SIDE, image_side
from annotator.rig import undistort_maps
from dsr_bench.dataset.capture import CaptureCamera
from dsr_bench.errors import UserError

#: librealsense's distortion models (`rs2_distortion_to_string`) this importer undistorts.
SUPPORTED_MODELS = ("None", "Brown Conrady", "Inverse Brown Conrady", "Modified Brown Conrady")
COLOR_ENCODINGS = {"rgb8": (3, False), "bgr8": (3, True), "rgba8": (4, False), "bgra8": (4, True)}
DEPTH_ENCODINGS = ("mono16", "16UC1")
#: A depth pixel's footprint larger than this (colour pixels per axis) is dropped (a grazing or broken sample).
MAX_SPLAT = 8
#: Registration's z-buffer: candidates within SAME_SURFACE_M + SAME_SURFACE_REL x z (m) of a colour pixel's nearest
#: one are the same surface (a sloped table's neighbouring samples); anything further behind is hidden by it.
SAME_SURFACE_M, SAME_SURFACE_REL = 0.005, 0.01
#: Where an error about a recording points the user.
HINT = "docs/annotator.md, 'RealSense recordings'"


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
    return UserError(f"{path}: {message}; see {HINT}")


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
    ("Brown Conrady") goes through `annotator.rig.undistort_maps`."""
    if not info.distorted:
        return None
    if info.model == "Brown Conrady":
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
    indices, values, misses = [], [], []
    for du in range(int(span[0])):  # a few offsets within a footprint, each vectorised over all pixels
        for dv in range(int(span[1])):
            inside = (lo[:, 0] + du <= hi[:, 0]) & (lo[:, 1] + dv <= hi[:, 1])
            u, v = lo[inside, 0] + du, lo[inside, 1] + dv
            indices.append(v * wc + u)
            values.append(zc[inside])
            misses.append((uc[inside, 0] - u) ** 2 + (uc[inside, 1] - v) ** 2)
    out = np.zeros(hc * wc)
    if not indices:
        return out.reshape(hc, wc)
    index, value, miss = np.concatenate(indices), np.concatenate(values), np.concatenate(misses)
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
