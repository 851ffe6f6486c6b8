"""Real captures in from RealSense `.bag` recordings (issue 18): `dsr-bench import-capture` of a folder of
front.bag / back.bag (ROS1 bags laid out as librealsense's recorder writes them, and which librealsense plays back:
tests/test_realsense_recordings.py; recordings librealsense itself wrote are tested there), depth registered to
colour, frames picked per step by time, and every one-line error on the way.

Fixture: the simulated capture of tests/test_import_capture.py (seed 1, 3 objects, 2 pushes) recorded as a D435
would: per camera a 720 x 1280 colour stream (the PNG tests' true camera: fy = 1.04 fx, off-centre principal point,
the ChArUco board pasted on the table; the front one raw through an "Inverse Brown Conrady" lens with non-zero
coefficients, the back one with zero coefficients) and a 480 x 848 depth stream rendered from its own virtual depth
camera (square pixels, a wider field of view, 15 mm and about 0.7 degrees off the colour camera: the depth ->
colour extrinsics the bag stores; the front bag's extrinsics group is referenced to depth, the back one's to
colour). Around each of the board time and the three step times the bag holds the true frame and decoys 33 ms
before and after it (black colour, no depth); depth frames lag colour by 4 ms, the back camera's by 10 ms more.
Ground truth: the depth rendered from the colour camera itself, the true extrinsics.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")
pytest.importorskip("rosbags")

from test_import_capture import BOARD, SHAPE, _paste_board, _true_camera

from dsr_bench.geometry import Camera

BASE = 1716985200.0  # header stamps: the host's clock (librealsense's global time), s
BOARD_TIME, STEP_TIMES = BASE + 0.5, [BASE + 2.0, BASE + 5.0, BASE + 8.0]
DEPTH_LAG, BACK_LAG, PERIOD = 0.004, 0.010, 1 / 30
FRONT_COEFFS = [0.05, -0.02, 0.0005, -0.0003, 0.0]  # Inverse Brown Conrady: raw -> ideal
DEPTH_SHAPE = (480, 848)


def _rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", [rx, ry, rz], degrees=True).as_matrix()


def _rigid(rotation: np.ndarray, translation) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation, translation
    return m


#: Per camera the depth -> colour transform (p_colour = M p_depth, m).
DEPTH_TO_COLOR = {"front": _rigid(_rotation(0.4, -0.6, 0.3), [0.015, -0.0005, 0.0012]),
                  "back": _rigid(_rotation(-0.3, 0.5, -0.2), [-0.0148, 0.0004, -0.001])}


def _depth_camera(name: str, color: Camera) -> Camera:
    """The virtual depth camera: 480 x 848, square pixels, fx = 0.6 of the colour's, at colour pose x depth->colour."""
    f = 0.6 * color.intrinsics[0, 0]
    k = np.array([[f, 0, 424.3], [0, f, 239.1], [0, 0, 1]])
    return Camera(f"{name}_depth", *DEPTH_SHAPE, k, color.extrinsics @ DEPTH_TO_COLOR[name])


def _raw_inverse_brown(image: np.ndarray, k: np.ndarray, coeffs) -> np.ndarray:
    """What a lens whose "Inverse Brown Conrady" coefficients map raw -> ideal records: raw pixel p shows the ideal
    image at K poly(K^-1 p), poly OpenCV's distortion polynomial (cv2.projectPoints)."""
    h, w = image.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], -1).reshape(-1, 1, 3)
    ideal = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), k, np.asarray(coeffs, np.float64))[0].reshape(h, w, 2)
    return cv2.remap(image, ideal[..., 0].astype(np.float32), ideal[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


# --- writing bags as librealsense does -------------------------------------------------------------------------------


def _store():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("uint32 fps\nstring encoding\nbool is_recommended",  # librealsense's order
                                      "realsense_msgs/msg/StreamInfo"))
    return store


def _stamp(store, seconds: float):
    secs = int(np.floor(seconds))
    return store.types["builtin_interfaces/msg/Time"](sec=secs, nanosec=int(round((seconds - secs) * 1e9)))


def _camera_info(store, k: np.ndarray, shape: tuple[int, int], model: str, coeffs):
    t = store.types
    return t["sensor_msgs/msg/CameraInfo"](
        header=t["std_msgs/msg/Header"](seq=0, stamp=_stamp(store, 0.0), frame_id=""), height=shape[0], width=shape[1],
        distortion_model=model, D=np.asarray(coeffs, np.float64), K=np.asarray(k, np.float64).reshape(9),
        R=np.zeros(9), P=np.zeros(12), binning_x=0, binning_y=0,
        roi=t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def _transform(store, m: np.ndarray):
    from scipy.spatial.transform import Rotation

    t = store.types
    x, y, z, w = Rotation.from_matrix(m[:3, :3]).as_quat()
    return t["geometry_msgs/msg/Transform"](translation=t["geometry_msgs/msg/Vector3"](x=m[0, 3], y=m[1, 3], z=m[2, 3]),
                                            rotation=t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))


def _image(store, stamp: float, seq: int, array: np.ndarray, encoding: str):
    t = store.types
    h, w = array.shape[:2]
    data = np.ascontiguousarray(array).view(np.uint8).reshape(-1)
    return t["sensor_msgs/msg/Image"](header=t["std_msgs/msg/Header"](seq=seq, stamp=_stamp(store, stamp), frame_id=""),
                                      height=h, width=w, encoding=encoding, is_bigendian=0, step=data.size // h,
                                      data=data)


def write_bag(path: Path, *, color: list, depth: list, color_k: np.ndarray, depth_k: np.ndarray, color_model: str,
              color_coeffs, depth_to_color: np.ndarray, reference: str = "depth", depth_units: float = 0.001,
              omit: tuple[str, ...] = ()) -> None:
    """A recording laid out as librealsense 2.55 writes one (D435: depth on sensor_0 "Stereo Module", colour on
    sensor_1 "RGB Camera"; file version 4; each image message followed by the 4 undeclared bytes of its depth units;
    the device, sensor and stream info librealsense's playback needs) of `color` [(stamp s, seq, (H, W, 3) uint8
    RGB)] and `depth` [(stamp s, seq, (h, w) uint16)]; the stream extrinsics in group 0 relative to the `reference`
    stream; topics containing any of `omit` are left out. librealsense plays it back
    (tests/test_realsense_recordings.py)."""
    import struct

    from rosbags.rosbag1 import Writer

    store = _store()
    t = store.types
    to_depth = np.eye(4) if reference == "depth" else np.linalg.inv(depth_to_color)
    to_color = depth_to_color if reference == "depth" else np.eye(4)
    ch, cw = color[0][2].shape[:2]
    dh, dw = depth[0][2].shape
    key_value = t["diagnostic_msgs/msg/KeyValue"]
    static = [
        ("/file_version", "std_msgs/msg/UInt32", t["std_msgs/msg/UInt32"](data=4)),
        ("/device_0/info", "diagnostic_msgs/msg/KeyValue", key_value(key="Name", value="Intel RealSense D435")),
        ("/device_0/sensor_0/info", "diagnostic_msgs/msg/KeyValue", key_value(key="Name", value="Stereo Module")),
        ("/device_0/sensor_1/info", "diagnostic_msgs/msg/KeyValue", key_value(key="Name", value="RGB Camera")),
        ("/device_0/sensor_0/Depth_0/info", "realsense_msgs/msg/StreamInfo",
         t["realsense_msgs/msg/StreamInfo"](encoding="mono16", fps=30, is_recommended=True)),
        ("/device_0/sensor_1/Color_0/info", "realsense_msgs/msg/StreamInfo",
         t["realsense_msgs/msg/StreamInfo"](encoding="rgb8", fps=30, is_recommended=True)),
        ("/device_0/sensor_0/Depth_0/info/camera_info", "sensor_msgs/msg/CameraInfo",
         _camera_info(store, depth_k, (dh, dw), "Brown Conrady", np.zeros(5))),
        ("/device_0/sensor_1/Color_0/info/camera_info", "sensor_msgs/msg/CameraInfo",
         _camera_info(store, color_k, (ch, cw), color_model, color_coeffs)),
        ("/device_0/sensor_0/option/Depth_Units/value", "std_msgs/msg/Float32",
         t["std_msgs/msg/Float32"](data=depth_units)),
        ("/device_0/sensor_0/option/Emitter_Enabled/value", "std_msgs/msg/Float32",
         t["std_msgs/msg/Float32"](data=1.0)),
        ("/device_0/sensor_0/Depth_0/tf/0", "geometry_msgs/msg/Transform", _transform(store, to_depth)),
        ("/device_0/sensor_1/Color_0/tf/0", "geometry_msgs/msg/Transform", _transform(store, to_color)),
    ]
    frames = [(s, "/device_0/sensor_1/Color_0/image/data", _image(store, s, q, a, "rgb8")) for s, q, a in color]
    frames += [(s, "/device_0/sensor_0/Depth_0/image/data", _image(store, s, q, a, "mono16")) for s, q, a in depth]
    frames.sort(key=lambda f: f[0])
    start = min(f[0] for f in frames) - 0.1
    with Writer(path) as writer:
        connections = {}

        def write(topic: str, msgtype: str, message, log_ns: int, extra: bytes = b"") -> None:
            if any(o in topic for o in omit):
                return
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], log_ns, bytes(store.serialize_ros1(message, msgtype)) + extra)

        for topic, msgtype, message in static:
            write(topic, msgtype, message, 1)
        for stamp, topic, message in frames:
            log_ns, units = int(round((stamp - start) * 1e9)), depth_units if "Depth" in topic else 0.0
            write(topic, "sensor_msgs/msg/Image", message, log_ns, struct.pack("<f", units))
            for key, value in (("timestamp_domain", "Global Time"), ("frame_counter", str(message.header.seq))):
                write(topic.replace("/data", "/metadata"), "diagnostic_msgs/msg/KeyValue",
                      key_value(key=key, value=value), log_ns)


def _events(name: str) -> list[tuple[float, int]]:
    """(colour stamp s, seq) of the true frames: the board, then the steps."""
    lag = BACK_LAG if name == "back" else 0.0
    return [(when + lag, 100 + 10 * i) for i, when in enumerate([BOARD_TIME, *STEP_TIMES])]


def write_bag_folder(sim, folder: Path) -> dict[str, Camera]:
    """front.bag, back.bag, rig.json (board, objects), steps.json, pushes.json, meshes; returns the true colour
    cameras."""
    from dsr_bench.annotator.export import renderer_for

    colors = {n: _true_camera(n) for n in ("front", "back")}
    depths = {n: _depth_camera(n, c) for n, c in colors.items()}
    renderer = renderer_for(sim, {**colors, **{c.name: c for c in depths.values()}})
    folder.mkdir(parents=True)
    truth = sim.truth_poses()
    hidden = truth[0].copy()
    hidden[:, 2] -= 1.0
    streams = {n: ([], []) for n in colors}
    for i, poses in enumerate([hidden, *truth]):
        scene, ids = renderer.scene(poses)
        for n, cam in colors.items():
            images = renderer.render_camera(scene, ids, n)
            color = _paste_board(images.color, (images.mask == 0) & (images.depth > 0), cam)
            if n == "front":
                color = _raw_inverse_brown(color, cam.intrinsics, FRONT_COEFFS)
            depth = np.round(renderer.render_camera(scene, ids, depths[n].name).depth / 0.001).astype(np.uint16)
            stamp, seq = _events(n)[i]
            black, empty = np.zeros_like(color), np.zeros_like(depth)
            streams[n][0].extend([(stamp - PERIOD, seq - 1, black), (stamp, seq, color),
                                  (stamp + PERIOD, seq + 1, black)])
            streams[n][1].extend([(stamp + DEPTH_LAG + d * PERIOD, seq + d, depth if d == 0 else empty)
                                  for d in (-1, 0, 1)])
    for n, cam in colors.items():
        write_bag(folder / f"{n}.bag", color=streams[n][0], depth=streams[n][1], color_k=cam.intrinsics,
                  depth_k=depths[n].intrinsics, color_model="Inverse Brown Conrady",
                  color_coeffs=FRONT_COEFFS if n == "front" else np.zeros(5), depth_to_color=DEPTH_TO_COLOR[n],
                  reference="depth" if n == "front" else "color")
    (folder / "meshes").mkdir()
    objects = []
    for i, obj in enumerate(sim.objects):
        shutil.copy(obj.mesh_path, folder / "meshes" / f"{i}.ply")
        objects.append({"name": obj.name, "mesh": f"meshes/{i}.ply", "identity": obj.identity})
    (folder / "rig.json").write_text(json.dumps({"name": "bag_000", "objects": objects, "board": BOARD}))
    jitter = [0.007, -0.004, 0.005]
    (folder / "steps.json").write_text(json.dumps({"step_times": [s + j for s, j in zip(STEP_TIMES, jitter)],
                                                   "board_time": BOARD_TIME + 0.003}))
    pushes = [{"start": s[:2].tolist(), "direction": ((e - s)[:2] / np.linalg.norm((e - s)[:2])).tolist()}
              for s, e in sim.pushes_world]
    (folder / "pushes.json").write_text(json.dumps({"pushes": pushes}))
    return colors


@pytest.fixture(scope="module")
def bags(sim, tmp_path_factory):
    folder = tmp_path_factory.mktemp("bags") / "src"
    return folder, write_bag_folder(sim, folder)


@pytest.fixture(scope="module")
def imported(bags, tmp_path_factory):
    from dsr_bench.cli import main

    out = tmp_path_factory.mktemp("imported") / "bag_000"
    assert main(["import-capture", str(bags[0]), "--out", str(out)]) == 0
    return out


# --- registration and distortion, directly ---------------------------------------------------------------------------


def test_align_depth_registers_a_tilted_plane_without_holes():
    """A plane seen by an 480 x 848 depth camera registered to a 720 x 1280 colour camera 15 mm and 0.7 degrees
    away: the colour camera's z of the plane at every covered pixel (no holes: each depth pixel's footprint is
    splatted), the nearer surface where two overlap."""
    from dsr_bench.annotator.bag import Recording, Stream, StreamInfo
    from dsr_bench.annotator.registration import align_depth

    color_k = _true_camera("front").intrinsics
    depth_cam = _depth_camera("front", Camera("front", *SHAPE, color_k, np.eye(4)))
    info = StreamInfo(DEPTH_SHAPE[1], DEPTH_SHAPE[0], depth_cam.intrinsics, "Brown Conrady", np.zeros(5))
    empty = Stream("d", info, np.zeros(1), np.zeros(1, np.int64), np.zeros(1, np.int64))
    rec = Recording("front", Path("x.bag"), empty, empty, DEPTH_TO_COLOR["front"], 0.001)
    normal, offset = np.array([0.0, -0.3, -1.0]) / np.linalg.norm([0.0, -0.3, -1.0]), -0.75  # n . p = offset (colour)
    # the depth camera's z of the plane along each depth pixel's ray (plane moved into the depth frame)
    d2c = DEPTH_TO_COLOR["front"]
    n_d, off_d = d2c[:3, :3].T @ normal, offset - normal @ d2c[:3, 3]
    v, u = np.mgrid[0:DEPTH_SHAPE[0], 0:DEPTH_SHAPE[1]].astype(np.float64)
    rays = np.stack([(u - info.intrinsics[0, 2]) / info.intrinsics[0, 0], (v - info.intrinsics[1, 2]) /
                     info.intrinsics[1, 1], np.ones_like(u)], -1)
    depth = off_d / (rays @ n_d)
    depth[200:230, 400:440] -= 0.1  # a nearer box: its pixels win
    got = align_depth(depth, rec.depth_corner_rays, d2c, color_k, SHAPE)
    vc, uc = np.mgrid[0:SHAPE[0], 0:SHAPE[1]].astype(np.float64)
    crays = np.stack([(uc - color_k[0, 2]) / color_k[0, 0], (vc - color_k[1, 2]) / color_k[1, 1],
                      np.ones_like(uc)], -1)
    truth = offset / (crays @ normal)
    plane = (got > 0) & (np.abs(got - truth) < 0.05)
    inner = np.zeros(SHAPE, bool)
    inner[20:-20, 20:-20] = True
    box = (got > 0) & (truth - got > 0.05)
    assert 0.8 < box.sum() / (30 * 40 / 0.6 ** 2) < 1.5, box.sum()  # the box, magnified by the focal lengths' ratio
    rows, cols = np.nonzero(box)
    beside = np.zeros(SHAPE, bool)  # the box's parallax shadow: colour pixels the depth camera cannot see
    beside[rows.min() - 10:rows.max() + 10, cols.min() - 10:cols.max() + 10] = True
    assert (got[inner & ~beside] > 0).all() and (got[beside] == 0).sum() < 200  # no holes but the shadow
    err = np.abs(got - truth)[plane & inner]
    assert np.median(err) < 2.5e-4 and np.percentile(err, 99) < 1e-3, (np.median(err), np.percentile(err, 99))


def test_distortion_models_round_trip_and_inverse_brown_matches_opencv():
    from dsr_bench.annotator.registration import StreamInfo, _raw_of_ideal, ideal_rays, undistortion_maps

    k = _true_camera("front").intrinsics
    h, w = 72, 128
    k_small = k.copy()
    k_small[:2] /= 10
    ideal = np.random.default_rng(0).uniform(-0.6, 0.6, (200, 2))
    for model in ("Brown Conrady", "Inverse Brown Conrady", "Modified Brown Conrady"):
        info = StreamInfo(w, h, k_small, model, np.asarray(FRONT_COEFFS))
        raw = _raw_of_ideal(info, ideal) * [k_small[0, 0], k_small[1, 1]] + k_small[:2, 2]
        np.testing.assert_allclose(ideal_rays(info, raw), ideal, atol=1e-9)
    info = StreamInfo(w, h, k_small, "Inverse Brown Conrady", np.asarray(FRONT_COEFFS))
    maps = undistortion_maps(info)
    # the ideal pixel of each raw pixel the map names is the undistorted pixel itself
    raw = np.stack([maps[0].ravel(), maps[1].ravel()], 1).astype(np.float64)
    rays = np.c_[(raw - k_small[:2, 2]) / [k_small[0, 0], k_small[1, 1]], np.ones(len(raw))].reshape(-1, 1, 3)
    back = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), k_small, np.asarray(FRONT_COEFFS))[0].reshape(-1, 2)
    v, u = np.mgrid[0:h, 0:w]
    np.testing.assert_allclose(back, np.stack([u.ravel(), v.ravel()], 1), atol=1e-3)
    assert undistortion_maps(StreamInfo(w, h, k_small, "Inverse Brown Conrady", np.zeros(5))) is None


def test_step_times_pick_the_nearest_frames_per_camera_and_refuse_ambiguity(tmp_path):
    from dsr_bench.annotator.bag import Recording, Stream, StreamInfo
    from dsr_bench.annotator.realsense import pick_frames, read_step_times
    from dsr_bench.errors import UserError

    path = tmp_path / "steps.json"
    path.write_text(json.dumps({"step_times": {"front": [10.0, 12.0], "back": [20.0, 22.0]}, "board_time": [9.0]}))
    steps, board = read_step_times(path, ["front", "back"])
    assert steps["back"].tolist() == [20.0, 22.0] and board["front"].tolist() == [9.0]
    info = StreamInfo(4, 3, np.eye(3), "None", np.zeros(5))
    color_st = 10.0 + np.arange(0, 90) / 30  # 30 fps from t = 10 s
    rec = Recording("front", Path("front.bag"), Stream("c", info, color_st, color_st.astype(np.int64), np.arange(90)),
                    Stream("d", info, color_st + 0.004, color_st.astype(np.int64), np.arange(90)), np.eye(4), 0.001)
    color, depth = pick_frames(rec, np.array([10.0, 10.51, 12.0]), 0.05, "steps.json")
    assert color.tolist() == [0, 15, 60] and depth.tolist() == [0, 15, 60]
    with pytest.raises(UserError, match=r"steps.json: steps 0 and 1 both take front colour frame 10.000 s"):
        pick_frames(rec, np.array([10.0, 10.01]), 0.05, "steps.json")
    with pytest.raises(UserError, match=r"steps.json: the board time 8.000 s has no front colour frame within 50 ms"):
        pick_frames(rec, np.array([8.0]), 0.05, "steps.json", "board")
    for data, message in [({"step_times": [1.0, 1.0]}, "must be 2 or more increasing times"),
                          ({"step_times": {"front": [1, 2]}}, "step_times names cameras ['front'], the bags"),
                          ({"step_times": {"front": [1, 2], "back": [1, 2, 3]}}, "different numbers of step times"),
                          ({"times": [1, 2]}, 'expected {"step_times": [t0, t1, ...]}')]:
        path.write_text(json.dumps(data))
        with pytest.raises(UserError, match=re.escape(message)):
            read_step_times(path, ["front", "back"])


def test_images_decode_bgr_padded_rows_and_big_endian_depth():
    from dsr_bench.annotator.bag import Stream, StreamInfo, _decode
    from dsr_bench.errors import UserError

    store = _store()
    info = StreamInfo(5, 3, np.eye(3), "None", np.zeros(5))
    stream = Stream("/device_0/sensor_1/Color_0/image/data", info, np.zeros(1), np.zeros(1, np.int64),
                    np.zeros(1, np.int64))
    rgb = np.arange(45, dtype=np.uint8).reshape(3, 5, 3)
    padded = np.zeros((3, 16), np.uint8)  # rows of 15 bytes padded to a 16-byte step
    padded[:, :15] = rgb[..., ::-1].reshape(3, 15)
    msg = _image(store, 1.0, 1, padded, "bgr8")
    msg.width = 5
    np.testing.assert_array_equal(_decode(msg, stream, Path("front.bag"), "colour"), rgb)
    depth = np.arange(15, dtype=np.uint16).reshape(3, 5) * 300
    msg = _image(store, 1.0, 1, depth.astype(">u2"), "16UC1")
    msg.is_bigendian = 1
    np.testing.assert_array_equal(_decode(msg, stream, Path("front.bag"), "depth"), depth)
    msg = _image(store, 1.0, 1, padded, "yuyv")
    msg.width = 5
    with pytest.raises(UserError, match="colour encoding 'yuyv' of /device_0/sensor_1/Color_0/image/data is not one"):
        _decode(msg, stream, Path("front.bag"), "colour")


# --- the import -------------------------------------------------------------------------------------------------------


def test_bag_import_picks_the_frames_nearest_each_step_time(imported):
    from dsr_bench.dataset.capture import load_capture

    capture = load_capture(imported)
    assert capture.name == "bag_000" and capture.num_steps == 2 and list(capture.cameras) == ["front", "back"]
    source = capture.source
    assert source["format"] == "realsense-bag"
    for name in ("front", "back"):
        events = _events(name)[1:]
        for t, (stamp, seq) in enumerate(events):
            f = source["frames"][t][name]
            assert f["color_seq"] == seq and f["depth_seq"] == seq, (t, name, f)
            assert abs(f["color_stamp"] - stamp) < 1e-6 and abs(f["depth_stamp"] - stamp - DEPTH_LAG) < 1e-6
        s = source["streams"][name]
        assert s["color_topic"] == "/device_0/sensor_1/Color_0/image/data" and s["undistorted"] == (name == "front")
        np.testing.assert_allclose(s["depth_to_color"], DEPTH_TO_COLOR[name], atol=1e-6)


def test_bag_import_matches_the_ground_truth(sim, bags, imported):
    """Intrinsics from the bag exactly, extrinsics from the board within 3 mm / 0.5 degrees; over the grid the
    registered depth covers 99% of the pixels the colour camera sees, within 1 mm (median) and 3 mm (99%) of its true
    depth (the depth stream is rounded to 1 mm and sampled at the depth camera's pixels). Measured: coverage 99.8%,
    median 0.57-0.61 mm, 99.5% within 3 mm."""
    from dsr_bench.annotator.align import pose_delta
    from dsr_bench.annotator.export import renderer_for
    from dsr_bench.dataset.capture import load_capture

    capture = load_capture(imported)
    true = bags[1]
    report = capture.source["calibration"]
    assert report["extrinsics"] == {"front": "board", "back": "board"}
    renderer = renderer_for(sim, true)
    poses = sim.truth_poses()
    measured = {}
    for name, cam in true.items():
        got = capture.cameras[name]
        np.testing.assert_allclose(got.intrinsics, cam.intrinsics, rtol=1e-6)  # float32 in the bag
        assert (got.height, got.width) == SHAPE and abs(got.depth_scale - 0.001) < 1e-9
        dt, angle = pose_delta(cam.extrinsics, got.extrinsics)
        assert dt < 0.003 and np.degrees(angle) < 0.5, (name, dt)
        r = report["cameras"][name]
        assert r["corners"] >= 12 and r["board_mm"] < 1.0 and abs(r["depth_mm"]) < 2.0, r
    assert report["between_cameras_mm"] < 2.0
    for t in (0, 2):
        scene, ids = renderer.scene(poses[t])
        for name in ("front", "back"):
            images = renderer.render_camera(scene, ids, name)
            depth = capture.depth(t, name)
            x, y = images.points[..., 0], images.points[..., 1]
            grid = (images.depth > 0) & (np.abs(x - 0.5) < 0.256) & (np.abs(y) < 0.256)  # what the benchmark sees
            both = grid & (depth > 0)
            err = np.abs(depth[both] - images.depth[both])
            measured[f"{t} {name}"] = (both.sum() / grid.sum(), np.median(err) * 1000, np.mean(err < 0.003))
            assert both.sum() / grid.sum() > 0.99 and np.median(err) < 0.001 and np.mean(err < 0.003) > 0.99, \
                measured
            if name == "front":  # undistorted back onto the pinhole: the ideal image but for the rim, blurred once
                color = capture.color(t, name).astype(np.float64)
                ideal = _paste_board(images.color, (images.mask == 0) & (images.depth > 0), true[name])
                inner = (slice(30, -30), slice(30, -30))
                assert np.mean(np.abs(color[inner] - ideal[inner])) < 4.0


# --- one-line errors -------------------------------------------------------------------------------------------------


def _tiny(folder: Path, bags_folder: Path, **bag_options) -> Path:
    """A folder with the fixture's rig, pushes, steps and meshes but small 48 x 64 bags (front and back) around the
    step times; `bag_options` go to the front bag's `write_bag`."""
    folder.mkdir()
    for entry in ("rig.json", "pushes.json", "steps.json"):  # copies: links leading outside SRC are refused
        shutil.copy(bags_folder / entry, folder / entry)
    shutil.copytree(bags_folder / "meshes", folder / "meshes")
    k = np.array([[46.2, 0, 32.0], [0, 48.0, 24.0], [0, 0, 1]])
    color = [(s, 10 + i, np.full((48, 64, 3), 128, np.uint8)) for i, s in enumerate([BOARD_TIME, *STEP_TIMES])]
    depth = [(s + DEPTH_LAG, 10 + i, np.full((48, 64), 700, np.uint16))
             for i, s in enumerate([BOARD_TIME, *STEP_TIMES])]
    for name in ("front", "back"):
        options = dict(color=color, depth=depth, color_k=k, depth_k=k, color_model="Inverse Brown Conrady",
                       color_coeffs=np.zeros(5), depth_to_color=DEPTH_TO_COLOR[name])
        write_bag(folder / f"{name}.bag", **{**options, **(bag_options if name == "front" else {})})
    return folder


def _with_rig(folder: Path, edit) -> Path:
    rig = json.loads((folder / "rig.json").read_text())
    (folder / "rig.json").unlink()
    edit(rig)
    (folder / "rig.json").write_text(json.dumps(rig))
    return folder


def _no_depth_units(tmp, src):
    return _tiny(tmp, src, omit=("Depth_Units",))


def _no_color_info(tmp, src):
    return _tiny(tmp, src, omit=("Color_0/info/camera_info",))


def _ftheta(tmp, src):
    return _tiny(tmp, src, color_model="Ftheta", color_coeffs=[0.4, 0, 0, 0, 0])


def _far_step(tmp, src):
    folder = _tiny(tmp, src)
    (folder / "steps.json").unlink()
    (folder / "steps.json").write_text(json.dumps({"step_times": [*STEP_TIMES[:2], STEP_TIMES[2] + 5.0]}))
    return folder


def _late_depth(tmp, src):
    color = [(s, 10 + i, np.zeros((48, 64, 3), np.uint8)) for i, s in enumerate(STEP_TIMES)]
    depth = [(s + 0.2, 10 + i, np.zeros((48, 64), np.uint16)) for i, s in enumerate(STEP_TIMES)]
    return _tiny(tmp, src, color=color, depth=depth)


def _left_bag(tmp, src):
    folder = _tiny(tmp, src)
    (folder / "back.bag").rename(folder / "left.bag")
    return folder


def _turned_away(tmp, src):
    from dsr_bench.geometry import look_at

    def edit(rig):
        del rig["board"]
        away = look_at((0.2, -0.7, 0.3), (0.2, 0.0, 0.0), (0.0, 0.3, 0.7)).tolist()
        rig["cameras"] = {"front": {"extrinsics": away},
                          "back": {"extrinsics": _true_camera("back").extrinsics.tolist()}}

    return _with_rig(_tiny(tmp, src), edit)


def _intrinsics_in_rig(tmp, src):
    return _with_rig(_tiny(tmp, src), lambda rig: rig.update(cameras={"front": {"fx": 900.0}}))


def _mixed_forms(tmp, src):
    folder = _tiny(tmp, src)
    (folder / "front_color_0.png").write_bytes(b"")
    return folder


@pytest.mark.parametrize("make, expected", [
    (_no_depth_units, "front.bag: no topic /device_0/sensor_0/option/Depth_Units/value (the depth sensor's Depth "
                      "Units option, metres per depth unit; '/device_0/sensor_0/option/Depth Units/value' in older "
                      "recordings); record"),
    (_no_color_info, "front.bag: no topic /device_0/sensor_1/Color_0/info/camera_info (the colour stream's "
                     "intrinsics; /device_0/sensor_1/Color_0/camera_info in a ROS2 recording)"),
    (_ftheta, "front.bag: the colour stream (/device_0/sensor_1/Color_0/info/camera_info) has distortion model "
              "'Ftheta', which this importer cannot undistort"),
    (_far_step, "steps.json: step 2 time 1716985213.000 s has no front colour frame within 50 ms (nearest "
                "1716985208.000 s, 5000 ms away"),
    (_late_depth, "the front colour frame of step 0 (1716985202.000 s) has no depth frame within 50 ms (nearest 200 "
                  "ms away in front.bag)"),
    (_left_bag, "the recordings (front.bag, left.bag) must be front.bag (or front.db3, or a ROS2 bag directory "
                "front/: the view models see; required) and back.bag: rename left.bag"),
    (_turned_away, "rig.json camera 'front': the grid's table corner (0.756, -0.256, 0) m projects to pixel"),
    (_intrinsics_in_rig, "camera 'front' gives fx, but with bags the intrinsics, distortion and depth scale come from "
                         "front.bag"),
    (_mixed_forms, "holds both RealSense recordings (.bag, .db3) and <camera>_color_<N>.png images; keep one form "
                   "per folder"),
])
def test_bag_errors_are_one_line_naming_the_input_and_the_fix(bags, tmp_path, capsys, make, expected):
    from dsr_bench.cli import main

    folder = make(tmp_path / "src", bags[0])
    out = tmp_path / "out"
    assert main(["import-capture", str(folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err, err
    assert not out.exists() and not list(tmp_path.glob(".out.tmp-*"))


def test_bag_options_are_documented_and_png_folders_refuse_them(tmp_path, capsys, monkeypatch):
    from dsr_bench.cli import main

    monkeypatch.setenv("COLUMNS", "200")
    assert main(["import-capture", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--steps" in out and "--max-gap-ms" in out
    docs = (Path(__file__).parents[1] / "docs" / "annotator.md").read_text()
    assert "dsr-bench import-capture SRC --out CAPTURE [--steps STEPS.json] [--max-gap-ms MS]" in docs
    for topic in ("/device_0/sensor_<d>/option/Depth_Units/value", "Color_0/info/camera_info", "Depth_0/tf/<g>"):
        assert topic in docs
    (tmp_path / "src").mkdir()
    assert main(["import-capture", str(tmp_path / "src"), "--out", str(tmp_path / "o"), "--max-gap-ms", "20"]) == 2
    assert "--steps and --max-gap-ms pick frames of .bag recordings" in capsys.readouterr().err


def test_a_bag_capture_goes_through_annotate_and_both_exports_from_the_cli(sim, imported, tmp_path, capsys):
    """The whole real-rig path from the command line, headless: import (the fixture) -> annotate --place (step 0 from
    poses, as a person's picks would give them) --auto -> --export (a DSR sequence that validates, with the logged
    pushes as actions) and --bop (scene_gt / scene_camera per camera, translations in mm)."""
    import json

    from dsr_bench.cli import main
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.dataset.validate import validate_sequence

    from dsr_bench.geometry import pose_to_matrix

    truth = sim.truth_poses()
    place = tmp_path / "place.json"
    place.write_text(json.dumps({"objects": {str(i + 1): pose_to_matrix(truth[0, i]).tolist()
                                             for i in range(truth.shape[1])}}))
    out, bop = tmp_path / "bag_000.h5", tmp_path / "bop"
    assert main(["annotate", str(imported), "--work", str(tmp_path / "work"), "--place", str(place), "--auto",
                 "--export", str(out), "--bop", str(bop), "--allow-unchecked"]) == 0
    assert validate_sequence(out) == []
    with SequenceReader(out) as seq:
        assert seq.num_steps == 2 and seq.read("action").shape == (2, 3)
        assert np.abs(seq.read("object_poses")[0, :, :3] - truth[0, :, :3]).max() < 0.005  # metres
    for scene in ("000000", "000001"):  # front, back
        gt = json.loads((bop / "test" / scene / "scene_gt.json").read_text())
        cameras = json.loads((bop / "test" / scene / "scene_camera.json").read_text())
        assert sorted(gt) == sorted(cameras) == ["0", "1", "2"]
        assert all(len(entry["cam_t_m2c"]) == 3 and max(map(abs, entry["cam_t_m2c"])) > 100 for entry in gt["0"])
