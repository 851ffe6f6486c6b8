"""Recordings librealsense itself wrote, imported to the truth they were made from (issue 42).

tests/data/realsense (README.md there): the simulated capture of scripts/write_realsense_fixture.py recorded through
a pyrealsense2 software_device by librealsense 2.55.1 (ROS1 .bag) and 2.59.1 (ROS2 .db3, PNG images), and tiny
layout samples of 2.54.1 (ROS1, LZ4), 2.58.4 (ROS2, zstd messages) and 2.59.1 recording uncompressed (ROS2, raw
images). Each import must give back the truth: intrinsics exactly (librealsense's float32), the depth unit, every
frame in order with its number and timestamp, the frames each step time picks, the board calibration within the
error measured here (camera positions 0.61 mm / 0.047 degrees and 0.86 mm / 0.038 degrees from the true ones: under
1.5 mm and 0.1 degrees) and the depth registered to colour (640 x 360 colour from 424 x 240 depth: 99.9% of the grid
covered, median 1.0-1.1 mm, 93-95% within 3 mm of the true colour-camera depth; half the resolution of
tests/test_import_bag.py's bags, twice their error). A fresh recording by the pyrealsense2 installed here (the
`realsense` extra) is made and imported the same way, and the toolkit's own test bags play back in librealsense.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")
pytest.importorskip("rosbags")

DATA = Path(__file__).parent / "data" / "realsense"
SCRIPT = Path(__file__).parents[1] / "scripts" / "write_realsense_fixture.py"
FIXTURES = {"v2.55.1": ".bag", "v2.59.1": ".db3"}
LAYOUTS = {"2.54.1.bag": "librealsense up to 2.57 (ROS1 bag)", "2.58.4.db3": "librealsense 2.58 (ROS2, raw images)",
           "2.59.1-uncompressed.db3": "librealsense 2.59 or later (ROS2, raw images)"}


def _script():
    """scripts/write_realsense_fixture.py as a module (its dataclasses need it in sys.modules)."""
    import sys

    if "write_realsense_fixture" not in sys.modules:
        spec = importlib.util.spec_from_file_location("write_realsense_fixture", SCRIPT)
        module = importlib.util.module_from_spec(spec)
        sys.modules["write_realsense_fixture"] = module
        spec.loader.exec_module(module)
    return sys.modules["write_realsense_fixture"]


def _import(folder: Path, out: Path) -> Path:
    from dsr_bench.cli import main

    assert main(["import-capture", str(folder), "--out", str(out)]) == 0
    return out


def _check_against_truth(folder: Path, out: Path) -> dict:
    """The imported capture `out` of `folder` against folder/truth.json; returns what was measured."""
    from dsr_bench.annotator.align import pose_delta
    from dsr_bench.annotator.bag import open_recording
    from dsr_bench.annotator.export import renderer_for
    from dsr_bench.dataset.capture import load_capture
    from dsr_bench.geometry import Camera

    truth = json.loads((folder / "truth.json").read_text())
    capture = load_capture(out)
    source, measured = capture.source, {}
    assert source["calibration"]["extrinsics"] == {"front": "board", "back": "board"}
    for name, cam in truth["cameras"].items():
        got = capture.cameras[name]
        assert got.intrinsics.tolist() == cam["color_intrinsics"]  # librealsense's float32, exactly
        assert [got.height, got.width] == cam["color_size"]
        assert got.depth_scale == float(np.float32(truth["depth_units"]))
        stream = source["streams"][name]
        assert stream["depth_intrinsics"] == cam["depth_intrinsics"] and stream["distortion_model"] == cam["model"]
        np.testing.assert_allclose(stream["depth_to_color"], cam["depth_to_color"], atol=2e-6)  # ROS2 text: 6 decimals
        # every frame, in order, with its number and timestamp
        rec = open_recording(folder / truth["files"][name], name)
        for kind, stream_of in (("color", rec.color), ("depth", rec.depth)):
            frames = [(n, t) for s, n, t in cam["frames"] if s == kind]
            assert stream_of.seqs.tolist() == [n for n, _ in frames]
            np.testing.assert_allclose(stream_of.stamps, [t for _, t in frames], rtol=0, atol=2e-6)
        # the frames the step times pick: the true ones
        for t, (number, stamp) in enumerate(cam["steps"][1:]):
            f = source["frames"][t][name]
            assert f["color_seq"] == number and f["depth_seq"] == number, (name, t, f)
            assert abs(f["color_stamp"] - stamp) < 2e-6
        dt, angle = pose_delta(np.asarray(cam["color_to_table"]), got.extrinsics)
        measured[name] = {"mm": dt * 1000, "deg": float(np.degrees(angle))}
        assert dt < 0.0015 and np.degrees(angle) < 0.1, measured
        assert source["calibration"]["cameras"][name]["board_mm"] < 1.0
    # the depth registered to colour, against the depth rendered from the true colour camera
    cameras = {n: Camera(n, *c["color_size"], np.asarray(c["color_intrinsics"]), np.asarray(c["color_to_table"]))
               for n, c in truth["cameras"].items()}
    renderer = renderer_for(capture, cameras)
    for t, poses in enumerate(np.asarray(truth["poses"])):
        scene, ids = renderer.scene(poses)
        for name in cameras:
            images = renderer.render_camera(scene, ids, name)
            depth = capture.depth(t, name)
            x, y = images.points[..., 0], images.points[..., 1]
            grid = (images.depth > 0) & (np.abs(x - 0.5) < 0.256) & (np.abs(y) < 0.256)
            both = grid & (depth > 0)
            err = np.abs(depth[both] - images.depth[both])
            measured[f"depth {t} {name}"] = (both.sum() / grid.sum(), np.median(err) * 1000, np.mean(err < 0.003))
            assert both.sum() / grid.sum() > 0.99 and np.median(err) < 0.0015 and np.mean(err < 0.003) > 0.9, \
                measured
    return measured


# --- the committed recordings ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("release", sorted(FIXTURES))
def test_librealsense_recordings_import_to_the_truth(release, tmp_path, capsys):
    """What 2.55.1 (ROS1) and 2.59.1 (ROS2) wrote imports to the truth; before issue 42 the first was refused
    (`Depth Units` looked for, `Depth_Units` written; then a SerdeError on the image's trailing bytes) and the second
    not found ("holds no .bag recordings")."""
    folder = tmp_path / release
    shutil.copytree(DATA / release, folder)
    measured = _check_against_truth(folder, _import(folder, tmp_path / "capture"))
    out = capsys.readouterr().out
    assert "wrote" in out and set(measured) >= {"front", "back"}


@pytest.mark.parametrize("release", sorted(FIXTURES))
def test_inspect_reports_each_recordings_format_writer_and_clock(release, capsys):
    from dsr_bench.cli import main

    folder = DATA / release
    assert main(["import-capture", str(folder), "--inspect"]) == 0
    out = capsys.readouterr().out
    suffix = FIXTURES[release]
    for name in ("front", "back"):
        section = out.split(f"{name}{suffix} ({name} camera", 1)[1].split(f"{suffix} (", 1)[0]
        if suffix == ".bag":
            assert "format: ROS1 bag v2.0 (LZ4 chunks), librealsense file version 4: written by librealsense up to " \
                   "2.57 (ROS1 bag)" in section
            assert "clock: frame timestamps, domain Global Time\n" in section
        else:
            assert "format: ROS2 SQLite database, librealsense file version 4: written by librealsense 2.59 or later " \
                   "(ROS2, PNG images)" in section
            assert "clock: frame timestamps, domain Global Time; header stamps count from the recording's start" \
                   in section
        assert "device: Intel RealSense D435 (serial 000000000042, firmware 5.16.0.1); sensors: depth 'Stereo " \
               "Module', colour 'RGB Camera'" in section
        assert "12 of 12 corners" in out and "9 frames over" in section and "14 frame numbers skipped" in section
    assert "PROBLEM" not in out


@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_each_generations_layout_reads_exactly(name):
    """The tiny samples (`layout_sample`) of 2.54.1, 2.58.4 (zstd) and 2.59.1 uncompressed: every pixel, number,
    timestamp, intrinsic and the extrinsics as written."""
    from dsr_bench.annotator.bag import open_recording, read_frame

    sample = _script().layout_sample()
    rec = open_recording(DATA / "layouts" / name, "front")
    assert rec.about["writer"] == LAYOUTS[name] and rec.about["sensors"] == {"colour": "RGB Camera",
                                                                             "depth": "Stereo Module"}
    assert rec.color.info.intrinsics.tolist() == sample.color_k.tolist()
    assert rec.depth.info.intrinsics.tolist() == sample.depth_k.tolist()
    assert rec.color.info.model == "Inverse Brown Conrady" and rec.color.info.coeffs.tolist() == sample.coeffs
    assert rec.depth_scale == float(np.float32(0.001))
    np.testing.assert_allclose(rec.depth_to_color, sample.depth_to_color, atol=2e-6)
    for kind, stream in (("colour", rec.color), ("depth", rec.depth)):
        frames = [f for f in sample.frames if f.stream == ("color" if kind == "colour" else "depth")]
        assert stream.seqs.tolist() == [7, 9]
        np.testing.assert_allclose(stream.stamps, [f.timestamp_s for f in frames], rtol=0, atol=2e-6)
        for i, frame in enumerate(frames):
            np.testing.assert_array_equal(read_frame(rec, kind, i), frame.image)


def _rewrite_ros1(src: Path, dst: Path, compression=None, edit=None) -> None:
    """A copy of a ROS1 bag through rosbags (its stored definitions kept), chunks `compression` (None: none),
    each raw message through `edit(topic, raw)` (None drops it)."""
    from rosbags.rosbag1 import Reader, Writer

    with Reader(src) as reader:
        writer = Writer(dst)
        if compression is not None:
            writer.set_compression(compression)
        with writer:
            out = {c.id: writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest)
                   for c in reader.connections}
            for conn, time, raw in reader.messages():
                data = raw if edit is None else edit(conn.topic, raw)
                if data is not None:
                    writer.write(out[conn.id], time, data)


def test_bz2_and_uncompressed_chunks_mcap_directories_and_renamed_files_read_the_same(tmp_path):
    """The same recording in the other containers the importer takes: a ROS1 bag with bz2 chunks (`rosbag
    compress`) or none, a ROS2 bag directory with MCAP storage (metadata.yaml), and a .db3 named .bag (read by
    content: before issue 42 a UnicodeDecodeError traceback)."""
    from rosbags.rosbag1 import Writer as Ros1Writer
    from rosbags.rosbag2 import StoragePlugin, Writer as Ros2Writer
    from rosbags.typesys import Stores, get_typestore

    from dsr_bench.annotator.bag import open_recording, read_frame

    def same(a, b) -> None:
        assert a.color.seqs.tolist() == b.color.seqs.tolist() and np.array_equal(a.depth.stamps, b.depth.stamps)
        assert a.color.info.intrinsics.tolist() == b.color.info.intrinsics.tolist() and a.depth_scale == b.depth_scale
        np.testing.assert_allclose(a.depth_to_color, b.depth_to_color, atol=1e-12)
        for kind in ("colour", "depth"):
            np.testing.assert_array_equal(read_frame(a, kind, 4), read_frame(b, kind, 4))

    bag = DATA / "v2.55.1" / "front.bag"
    original = open_recording(bag, "front")
    for compression, label in ((Ros1Writer.CompressionFormat.BZ2, "bz2"), (None, "uncompressed")):
        copy = tmp_path / f"{label}.bag"
        _rewrite_ros1(bag, copy, compression)
        rec = open_recording(copy, "front")
        assert rec.about["container"] == f"ROS1 bag v2.0 ({label} chunks)"
        same(rec, original)
    db3 = DATA / "v2.59.1" / "front.db3"
    original = open_recording(db3, "front")
    renamed = tmp_path / "front.bag"
    shutil.copy(db3, renamed)
    same(open_recording(renamed, "front"), original)
    store = get_typestore(Stores.ROS2_HUMBLE)
    directory = tmp_path / "front"
    with sqlite3.connect(db3) as db, Ros2Writer(directory, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        topics = {i: writer.add_connection(name, kind, typestore=store)
                  for i, name, kind in db.execute("SELECT id, name, type FROM topics")}
        for topic_id, time, data in db.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY id"):
            writer.write(topics[topic_id], time, bytes(data))
    rec = open_recording(directory, "front")
    assert rec.about["container"].startswith("ROS2 bag directory (mcap")
    same(rec, original)


def test_the_capture_name_from_outs_directory_is_checked_as_a_plain_name(tmp_path, capsys):
    """Without --name or a rig file "name" the capture is named after --out's directory, which must then be a plain
    name too (before issue 42 the recordings' import took any)."""
    from dsr_bench.cli import main

    folder = tmp_path / "src"
    shutil.copytree(DATA / "v2.59.1", folder)
    rig = json.loads((folder / "rig.json").read_text())
    del rig["name"]
    (folder / "rig.json").write_text(json.dumps(rig))
    out = tmp_path / "tab\tname"
    assert main(["import-capture", str(folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"--out {out}: its directory name" in err and "is not a plain name" in err
    assert not out.exists()


# --- unknown layouts: one line naming the file, the topic and what was expected -------------------------------------


def _db3(tmp_path: Path, sql: str, args=()) -> Path:
    folder = tmp_path / "src"
    shutil.copytree(DATA / "v2.59.1", folder)
    with sqlite3.connect(folder / "front.db3") as db:
        db.execute(sql, args)
    return folder


def _camera_info_without_fx(tmp_path):
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    text = store.types["std_msgs/msg/String"](data="width=640;height=360;ppx=323.25;fy=471.4;ppy=177.5;"
                                                   "model=Inverse Brown Conrady;coeffs=0,0,0,0,0")
    return _db3(tmp_path, "UPDATE messages SET data = ? WHERE topic_id = (SELECT id FROM topics WHERE name = "
                          "'/device_0/sensor_1/Color_0/camera_info')",
                (bytes(store.serialize_cdr(text, "std_msgs/msg/String")),))


def _no_metadata(tmp_path):
    return _db3(tmp_path, "DELETE FROM messages WHERE topic_id = (SELECT id FROM topics WHERE name = "
                          "'/device_0/sensor_1/Color_0/image/metadata')")


def _both_forms_of_one_camera(tmp_path):
    folder = tmp_path / "src"
    shutil.copytree(DATA / "v2.59.1", folder)
    shutil.copy(DATA / "v2.55.1" / "front.bag", folder / "front.bag")
    return folder


def _not_a_recording(tmp_path):
    folder = tmp_path / "src"
    shutil.copytree(DATA / "v2.55.1", folder)
    (folder / "front.bag").write_bytes(b"RIFF\x00\x00\x00\x00WAVEfmt " + bytes(64))
    return folder


def _a_database_of_something_else(tmp_path):
    folder = tmp_path / "src"
    shutil.copytree(DATA / "v2.59.1", folder)
    (folder / "front.db3").unlink()
    with sqlite3.connect(folder / "front.db3") as db:
        db.execute("CREATE TABLE notes (id INTEGER)")
    return folder


def _image_cut_short(tmp_path):
    folder = tmp_path / "src"
    shutil.copytree(DATA / "v2.55.1", folder)
    (folder / "front.bag").unlink()
    _rewrite_ros1(DATA / "v2.55.1" / "front.bag", folder / "front.bag",
                  edit=lambda topic, raw: raw[:-5000] if topic.endswith("Color_0/image/data") else raw)
    return folder


@pytest.mark.parametrize("make, expected", [
    (_camera_info_without_fx, "front.db3: topic /device_0/sensor_1/Color_0/camera_info (the colour stream's "
                              "intrinsics) 'width=640;height=360;ppx=323.25;"),
    (_camera_info_without_fx, "has no fx; expected librealsense's text width=...;height=...;fx=...;ppx=...;fy=...;"
                              "ppy=...;model=...;coeffs=..."),
    (_no_metadata, "front.db3: the colour frame of /device_0/sensor_1/Color_0/image/data/compressed at"),
    (_no_metadata, "has no metadata on /device_0/sensor_1/Color_0/image/metadata with its Frame number and timestamp"),
    (_both_forms_of_one_camera, "front.bag and front.db3 both record camera 'front'; keep one recording per camera"),
    (_not_a_recording, "front.bag: is neither a ROS1 bag v2.0, a ROS2 SQLite database nor a ROS2 bag directory; give "
                       "the recording librealsense wrote"),
    (_a_database_of_something_else, "front.db3: an SQLite database without a ROS2 bag's topics and messages tables"),
    (_image_cut_short, "front.bag: the colour frame 110 of /device_0/sensor_1/Color_0/image/data is unreadable"),
])
def test_unknown_layouts_are_one_line_naming_the_file_topic_and_expectation(tmp_path, capsys, make, expected):
    from dsr_bench.cli import main

    folder = make(tmp_path)
    out = tmp_path / "out"
    assert main(["import-capture", str(folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err, err
    assert not out.exists()


# --- librealsense installed here ------------------------------------------------------------------------------------


def test_a_fresh_recording_by_the_installed_librealsense_imports_to_the_truth(tmp_path):
    """scripts/write_realsense_fixture.py with the pyrealsense2 of this environment (the `realsense` extra; CI
    installs it): whatever release it is, ROS1 or ROS2, the import gives back the truth."""
    pytest.importorskip("pyrealsense2", reason="pyrealsense2 is not installed (pip install -e '.[realsense]')")
    pytest.importorskip("pybullet")
    import subprocess
    import sys

    folder = tmp_path / "fresh"
    done = subprocess.run([sys.executable, str(SCRIPT), str(folder)], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    truth = json.loads((folder / "truth.json").read_text())
    assert sorted(truth["files"].values()) == sorted(f"{n}{_script().suffix()}" for n in ("back", "front"))
    _check_against_truth(folder, _import(folder, tmp_path / "capture"))


def test_the_toolkits_own_test_bags_play_back_in_librealsense(tmp_path):
    """tests/test_import_bag.py's `write_bag` writes what librealsense's playback reads (before issue 42: "No
    streams are selected!"): both streams with their intrinsics and distortion, the depth units, every frame with its
    number and timestamp."""
    pytest.importorskip("pyrealsense2", reason="pyrealsense2 is not installed (pip install -e '.[realsense]')")
    from test_import_bag import DEPTH_TO_COLOR, write_bag

    k = np.array([[46.25, 0, 32.5], [0, 48.0, 24.25], [0, 0, 1]])
    stamps = 1716985200.0 + np.array([0.0, 1 / 30, 3 / 30])
    color = [(s, 10 + i, np.full((48, 64, 3), 40 * i, np.uint8)) for i, s in enumerate(stamps)]
    depth = [(s + 0.004, 10 + i, np.full((48, 64), 700 + i, np.uint16)) for i, s in enumerate(stamps)]
    path = tmp_path / "front.bag"
    write_bag(path, color=color, depth=depth, color_k=k, depth_k=k, color_model="Inverse Brown Conrady",
              color_coeffs=[0.05, -0.02, 0.0005, -0.0003, 0.0], depth_to_color=DEPTH_TO_COLOR["front"])
    played = _script().play_back_isolated(path)
    assert sorted(played["streams"]) == ["Color", "Depth"]
    colour = played["streams"]["Color"]
    assert colour["intrinsics"] == [46.25, 48.0, 32.5, 24.25] and colour["size"] == [64, 48]
    assert colour["model"] == "distortion.inverse_brown_conrady" and colour["format"] == "format.rgb8"
    np.testing.assert_allclose(colour["coeffs"], [0.05, -0.02, 0.0005, -0.0003, 0.0], atol=1e-7)
    assert played["depth_units"] == pytest.approx(0.001, rel=1e-6)
    for name, frames in (("Color", color), ("Depth", depth)):
        got = sorted(played["frames"][name])
        assert [n for n, _ in got] == [n for _, n, _ in frames]
        np.testing.assert_allclose([t for _, t in got], [s * 1000 for s, _, _ in frames], atol=1e-3)
