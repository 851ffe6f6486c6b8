"""`dsr-bench capture` (issue 42 part 3): a session recorded by librealsense, with the robot's step marks and pushes,
into a folder `dsr-bench import-capture` reads.

No camera is connected here, so librealsense's playback devices stand in for them (`--from-recordings`, the seam of
`annotator.record_devices.PlaybackProvider`): the committed recordings of tests/data/realsense (written by
librealsense 2.55.1 and 2.59.1 from a simulated capture of known truth) are played back, recorded again by the
installed librealsense through the path a connected camera takes, and the folder is imported to that truth. A missing
camera, a wrong serial and a dropped stream (a stream that stops, a frame-number jump) are one line, exit 2, with
what was recorded until then kept, closed and importable. Host-clock timeouts, which only connected cameras have, are
checked with a clock the test moves.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("pyrealsense2", reason="pyrealsense2 is not installed (pip install -e '.[realsense]')")
pytest.importorskip("rosbags")
pytest.importorskip("cv2")

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "realsense"
FIXTURES = {"v2.55.1": ".bag", "v2.59.1": ".db3"}
#: Marks on the recordings' clock (s): the board alone at frame 100, step 0 at frame 110, step 1 (after the push) at
#: frame 120 of both cameras (the back camera's frames are 10 ms later: each mark picks the first frame after it).
BOARD_S, STEP0_S, STEP1_S = 1716985200.49, 1716985201.99, 1716985204.99


def _playable() -> str:
    """The committed release whose recordings the installed librealsense plays and writes alike (.db3 from 2.58)."""
    from dsr_bench.annotator.record_devices import librealsense_release, recording_suffix

    return "v2.59.1" if recording_suffix(librealsense_release()) == ".db3" else "v2.55.1"


def _push(release: str = "v2.59.1") -> dict:
    return json.loads((DATA / release / "pushes.json").read_text())["pushes"][0]


def _recordings(release: str) -> str:
    return ",".join(f"{n}={DATA / release / (n + FIXTURES[release])}" for n in ("front", "back"))


def _main(argv: list[str], capsys) -> tuple[int, str, str]:
    from dsr_bench.cli import main

    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


# --- the committed recordings, recorded again, import to their truth -------------------------------------------------


@pytest.mark.parametrize("release", sorted(FIXTURES))
def test_a_session_from_the_committed_recordings_imports_to_the_truth(release, tmp_path):
    """`dsr-bench capture` with the recordings standing in for the cameras and the robot's marks appended to its
    file once the command says it is recording: the folder holds librealsense's recordings of every frame,
    steps.json with the true frames' timestamps, pushes.json, rig.json with what was recorded, and imports to the
    truth the recordings were made from (tests/test_realsense_recordings.py's check)."""
    from test_realsense_recordings import _check_against_truth, _import

    from dsr_bench.annotator.record_devices import librealsense_release, recording_suffix

    out, robot = tmp_path / "run_07", tmp_path / "robot.log"
    command = [sys.executable, "-m", "dsr_bench", "capture", "--out", str(out), "--from-recordings",
               _recordings(release), "--color", "640x360@30", "--depth", "424x240@30", "--rig",
               str(DATA / release / "rig.json"), "--robot-file", str(robot)]
    with subprocess.Popen(command, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        assert proc.stdout is not None and proc.stderr is not None
        first = proc.stdout.readline()  # the command is recording: the robot may mark
        failed = proc.stderr.read() if not first else ""  # it ended before recording
        if "cannot play it back" in failed:
            pytest.skip(f"librealsense {librealsense_release()} does not play {release}'s recordings")
        assert first.startswith("recording front (000000000042 (Intel RealSense D435, recording front"), failed
        with robot.open("a") as log:  # as a robot's script appends: a line per event, a time on the frames' clock
            for line in [{"event": "board", "time": BOARD_S}, {"event": "step", "time": STEP0_S},
                         {"event": "step", "push": _push(release), "time": STEP1_S}, "done"]:
                log.write((line if isinstance(line, str) else json.dumps(line)) + "\n")
                log.flush()
        rest, err = proc.communicate(timeout=600)  # a guard against a hang only
    said = first + rest
    assert proc.returncode == 0, (said, err)
    assert "step 1: front colour frame 120 at 1716985205.000 s, back colour frame 120 at 1716985205.010 s" in said
    assert f"next: dsr-bench import-capture {out} --out captures/run_07" in said
    suffix = recording_suffix(librealsense_release())
    assert sorted(p.name for p in out.iterdir()) == sorted([f"back{suffix}", f"front{suffix}", "meshes",
                                                            "pushes.json", "rig.json", "steps.json"])
    assert not (out / "steps.json").is_symlink() and not (out / "pushes.json").is_symlink()
    steps = json.loads((out / "steps.json").read_text())
    assert steps["step_times"] == {"front": [1716985202.0, 1716985205.0], "back": [1716985202.01, 1716985205.01]}
    assert steps["board_time"] == {"front": 1716985200.5, "back": 1716985200.51}
    assert steps["frames"] == {"steps": {"front": [110, 120], "back": [110, 120]}, "board": {"front": 100, "back": 100}}
    assert json.loads((out / "pushes.json").read_text()) == {"pushes": [_push(release)]}
    rig = json.loads((out / "rig.json").read_text())
    front = rig["capture"]["cameras"]["front"]
    assert front["serial"] == "000000000042" and front["color"] == "640x360@30 RGB8" and front["depth"] == \
        "424x240@30 Z16" and front["recording"] == f"front{suffix}"
    assert rig["capture"]["sync"].startswith("skipped: front, back offer(s) no inter_cam_sync_mode option")
    truth = json.loads((DATA / release / "truth.json").read_text())
    truth["files"] = {n: f"{n}{suffix}" for n in ("front", "back")}
    (out / "truth.json").write_text(json.dumps(truth))
    _check_against_truth(out, _import(out, tmp_path / "captures" / "run_07"))


def test_the_python_api_marks_steps_checks_its_calls_and_ends_on_the_steps_count(tmp_path):
    """`CaptureSession` as a Python robot script uses it: marks made before the frames come are resolved by them,
    step 0 takes no push and every later step one, `steps=1` ends the session after the first push, and a mark after
    the end is refused."""
    from dsr_bench.annotator.record import CaptureSession
    from dsr_bench.errors import UserError

    release = _playable()
    heard: list[str] = []
    session = CaptureSession.open(
        tmp_path / "run", color="640x360@30", depth="424x240@30", steps=1, start=False, on_event=heard.append,
        from_recordings={n: DATA / release / f"{n}{FIXTURES[release]}" for n in ("front", "back")})
    with pytest.raises(UserError, match="step 0 is the scene before the first push: mark it without a push"):
        session.step_done(push=_push(), time=STEP0_S)
    assert session.step_done(time=STEP0_S) == 0
    with pytest.raises(UserError, match=r'step 1 follows a push: give the push done, \{"start"'):
        session.step_done(time=STEP1_S)
    with pytest.raises(UserError, match=r"push direction \[1, 1\] must be a unit vector"):
        session.step_done(push={"start": [0.5, 0.0], "direction": [1, 1]}, time=STEP1_S)
    assert session.step_done(push=_push(), time=STEP1_S) == 1
    session.start()
    summary = session.wait()
    assert summary.steps == 2 and summary.importable
    assert heard == ["step 0: front colour frame 110 at 1716985202.000 s, back colour frame 110 at 1716985202.010 s",
                     "step 1: front colour frame 120 at 1716985205.000 s, back colour frame 120 at 1716985205.010 s"]
    assert json.loads((tmp_path / "run" / "steps.json").read_text())["frames"]["steps"]["back"] == [110, 120]
    with pytest.raises(UserError, match="the session has ended"):
        session.step_done(push=_push(), time=STEP1_S + 3)
    rig = json.loads((tmp_path / "run" / "rig.json").read_text())
    assert rig["objects"] == [] and "a template" in rig["todo"]  # no --rig: a template to complete


def test_steps_and_pushes_agree_at_every_instant_and_end_as_plain_files(tmp_path):
    """While recording both files are links into one version directory swapped by one rename, so a crash at any
    instant leaves T + 1 step times beside T pushes; at the end they are plain files and the versions are gone."""
    from dsr_bench.annotator.pushes import read_pushes
    from dsr_bench.annotator.realsense import read_step_times
    from dsr_bench.annotator.record_files import MarkFiles

    files = MarkFiles(tmp_path)
    for count in range(2, 5):
        files.write({"step_times": [1.0 * t for t in range(count)]}, {"pushes": [_push()] * (count - 1)})
        # what a crash here leaves: the import reads both, and they agree
        steps, _ = read_step_times(tmp_path / "steps.json", ["front"])
        actions, _ = read_pushes(tmp_path / "pushes.json", len(steps["front"]) - 1)
        assert len(actions) == count - 1 and (tmp_path / "steps.json").is_symlink()
        assert sorted(p.name for p in (tmp_path / ".steps").iterdir()) == [str(count - 2), "current"]
    files.finish()
    assert not (tmp_path / "steps.json").is_symlink() and not (tmp_path / ".steps").exists()
    assert json.loads((tmp_path / "steps.json").read_text()) == {"step_times": [0.0, 1.0, 2.0, 3.0]}


def test_sigterm_ends_the_session_with_its_files_complete(tmp_path):
    """SIGTERM (as Ctrl-C) ends the session: exit 0, the recordings closed (librealsense completes them), the
    files plain, and the command says that 0 steps are not importable."""
    from dsr_bench.annotator.rosfile import open_container

    out = tmp_path / "run"
    command = [sys.executable, "-m", "dsr_bench", "capture", "--out", str(out), "--from-recordings",
               _recordings(_playable()), "--color", "640x360@30", "--depth", "424x240@30"]
    with subprocess.Popen(command, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        assert proc.stdout is not None
        assert proc.stdout.readline().startswith("recording front")
        proc.send_signal(signal.SIGTERM)
        rest, err = proc.communicate(timeout=600)  # a guard against a hang only
    assert proc.returncode == 0, err
    assert f"{out} holds 0 step(s): not importable (import-capture needs 2 steps or more)" in rest
    assert json.loads((out / "steps.json").read_text())["step_times"] == {"front": [], "back": []}
    for camera in ("front", "back"):  # complete containers, whether or not a frame came before the signal
        with open_container(next(out.glob(f"{camera}.*"))) as box:
            assert "/file_version" in box.topics and any("/Color_0/" in t for t in box.topics), box.topics


def test_a_session_killed_after_a_step_leaves_a_folder_that_imports(tmp_path, capsys):
    """SIGKILL once the command has said step 1 (it says a step once the files hold it): steps.json and pushes.json
    are still the links into one version, they agree, and librealsense's .db3 recordings hold every frame given, so
    the folder imports as it is (the board at frame 100 as step 0, step 1 at frame 110)."""
    release = _playable()
    if FIXTURES[release] != ".db3":
        pytest.skip("a killed ROS1 recorder leaves a .bag without its index")
    out, robot = tmp_path / "run", tmp_path / "robot.log"
    command = [sys.executable, "-m", "dsr_bench", "capture", "--out", str(out), "--from-recordings",
               _recordings(release), "--color", "640x360@30", "--depth", "424x240@30", "--rig",
               str(DATA / release / "rig.json"), "--robot-file", str(robot)]
    with subprocess.Popen(command, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        assert proc.stdout is not None
        assert proc.stdout.readline().startswith("recording front")
        robot.write_text(json.dumps({"event": "step", "time": BOARD_S}) + "\n" +
                         json.dumps({"event": "step", "push": _push(release), "time": STEP0_S}) + "\n")
        for line in proc.stdout:
            if line.startswith("step 1:"):
                break
        proc.kill()
        proc.communicate(timeout=600)  # a guard against a hang only
    assert (out / "steps.json").is_symlink() and (out / ".steps").is_dir()
    assert json.loads((out / "steps.json").read_text())["frames"]["steps"] == {"front": [100, 110],
                                                                             "back": [100, 110]}
    rc, said, err = _main(["import-capture", str(out), "--out", str(tmp_path / "capture")], capsys)
    assert rc == 0, err
    assert "front: extrinsics from the board: 12 corners" in said


# --- errors: one line, exit 2 -----------------------------------------------------------------------------------------


def test_no_camera_connected_is_one_line_and_writes_nothing(tmp_path, capsys):
    import pyrealsense2 as rs

    if len(rs.context().query_devices()):
        pytest.skip("a RealSense camera is connected here")
    rc, _, err = _main(["capture", "--front", "819612070593", "--back", "819612071104", "--out",
                        str(tmp_path / "run")], capsys)
    assert rc == 2 and err.count("\n") == 1
    assert "--front 819612070593: no RealSense camera is connected (librealsense sees none); plug the front camera " \
           "into a USB 3 port" in err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("args, expected", [
    (["--front", "819612070593"], "--front 819612070593: no RealSense camera with that serial; present: 000000000042 "
                                  "(Intel RealSense D435, recording front.EXT), 000000000042 (Intel RealSense D435, "
                                  "recording back.EXT); give one of these serials"),
    (["--color", "1280x720@30", "--depth", "424x240@30"],
     "--color 1280x720@30: the front camera 000000000042 (Intel RealSense D435, recording front.EXT) has no colour "
     "(RGB8, BGR8) stream at 1280x720@30; it offers 640x360@30; give one of them"),
    (["--color", "640x360"], "--color '640x360' is not a mode WIDTHxHEIGHT@FPS, e.g. --color 1280x720@30"),
    (["--steps", "0"], "--steps 0: give the number of pushes to record (1 or more)"),
])
def test_a_wrong_serial_or_mode_is_one_line_listing_what_is_there(tmp_path, capsys, args, expected):
    release = _playable()
    argv = ["capture", "--out", str(tmp_path / "run"), "--from-recordings", _recordings(release),
            "--color", "640x360@30", "--depth", "424x240@30", *args]
    expected = expected.replace(".EXT", FIXTURES[release])
    rc, _, err = _main(argv, capsys)
    assert rc == 2 and err.count("\n") == 1 and expected in err, err
    assert not (tmp_path / "run").exists()


def test_an_existing_out_a_used_robot_file_and_a_bad_recordings_option_are_refused(tmp_path, capsys):
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "front.db3").write_bytes(b"x")
    (tmp_path / "robot.log").write_text("step\n")
    base = ["capture", "--from-recordings", _recordings(_playable())]
    for argv, expected in [
        ([*base, "--out", str(tmp_path / "used")], f"--out {tmp_path / 'used'}: exists and is not empty"),
        ([*base, "--out", str(tmp_path / "r"), "--robot-file", str(tmp_path / "robot.log")],
         f"--robot-file {tmp_path / 'robot.log'}: is not empty; give a new (or empty) file for this session"),
        (["capture", "--out", str(tmp_path / "r"), "--from-recordings", "left=a.db3"],
         "--from-recordings 'left=a.db3': give CAMERA=PATH for each camera once, cameras front and back"),
    ]:
        rc, _, err = _main(argv, capsys)
        assert rc == 2 and err.count("\n") == 1 and expected in err, err
    assert not (tmp_path / "r").exists()


def _source(tmp_path: Path, camera: str, *, depth_until: int | None = None, depth_jump: int | None = None,
            extra: int = 40) -> Path:
    """The 2.59.1 recording of `camera` recorded again by the installed librealsense (scripts/
    write_realsense_fixture.py's software device and recorder), `extra` colour and depth frames added after its
    last (its images, 1/30 s apart): the depth stream stops after frame `depth_until`, or its frame number jumps
    to `depth_jump` after the recording's last frame."""
    from test_realsense_recordings import _script

    from dsr_bench.annotator.bag import open_recording, read_frame

    script = _script()
    truth = json.loads((DATA / "v2.59.1" / "truth.json").read_text())["cameras"][camera]
    rec = open_recording(DATA / "v2.59.1" / f"{camera}.db3", camera)
    frames = []
    for kind, stream in (("color", rec.color), ("depth", rec.depth)):
        images = [read_frame(rec, "colour" if kind == "color" else "depth", i) for i in range(len(stream.seqs))]
        numbers, stamps = [int(n) for n in stream.seqs], [float(t) for t in stream.stamps]
        numbers += [numbers[-1] + 1 + i for i in range(extra)]
        stamps += [stamps[-1] + (1 + i) / 30 for i in range(extra)]
        images += [images[-1]] * extra
        if kind == "depth" and depth_jump is not None:
            numbers[len(stream.seqs):] = [depth_jump + i for i in range(extra)]
        for number, stamp, image in zip(numbers, stamps, images, strict=True):
            if kind == "depth" and depth_until is not None and number > depth_until:
                continue
            frames.append(script.Frame(kind, number, stamp, image))
    frames.sort(key=lambda f: f.timestamp_s)
    recording = script.CameraRecording(camera, np.asarray(truth["color_intrinsics"]), tuple(truth["color_size"]),
                                       truth["model"], truth["coeffs"], np.asarray(truth["depth_intrinsics"]),
                                       tuple(truth["depth_size"]), np.asarray(truth["depth_to_color"]),
                                       np.asarray(truth["color_to_table"]), frames)
    path = tmp_path / f"{camera}-source{script.suffix()}"
    script.write_recording(path, recording)
    return path


def test_a_stream_that_stops_ends_the_session_and_what_was_recorded_imports(tmp_path, capsys):
    """The back camera's depth stream stops after frame 110 while its colour goes on: more than --timeout-frames
    colour frames over more than that many periods later the session stops, one line says which stream stopped and
    that the recordings are kept, and the folder (board and step 0 at frame 100, step 1 at 110) imports."""
    from dsr_bench.annotator.record import CaptureSession
    from dsr_bench.errors import UserError

    back = _source(tmp_path, "back", depth_until=110)
    out = tmp_path / "run"
    release = _playable()
    front = DATA / release / f"front{FIXTURES[release]}"
    session = CaptureSession.open(out, color="640x360@30", depth="424x240@30", rig=DATA / release / "rig.json",
                                  from_recordings={"front": front, "back": back}, start=False)
    session.step_done(time=BOARD_S)  # step 0: the board alone (calibrated from it)
    session.step_done(push=_push(), time=STEP0_S)
    session.done()
    session.start()
    with pytest.raises(UserError) as caught:
        session.wait()
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith("the back depth stream stopped delivering frames (last frame 110 at 1716985202.014 s; "
                              "the colour stream went on"), message
    assert f"what was recorded until then is kept, closed cleanly, in {out} (2 steps; importable: dsr-bench " \
           f"import-capture {out} --out captures/run)" in message
    rc, out_text, err = _main(["import-capture", str(out), "--out", str(tmp_path / "capture")], capsys)
    assert rc == 0, err
    assert "back: extrinsics from the board: 12 corners" in out_text


def test_a_frame_number_jump_is_a_dropped_stream_in_one_line(tmp_path, capsys):
    """The back depth stream's frame numbers jump by more than --timeout-frames (frames lost in a stall): exit 2,
    one line naming the stream and the numbers, and the recordings closed and readable up to there."""
    from dsr_bench.annotator.bag import open_recording

    back = _source(tmp_path, "back", depth_jump=200, extra=3)
    out = tmp_path / "run"
    front = DATA / _playable() / f"front{FIXTURES[_playable()]}"
    rc, said, err = _main(["capture", "--out", str(out), "--color", "640x360@30", "--depth", "424x240@30",
                           "--from-recordings", f"front={front},back={back}"], capsys)
    assert rc == 2 and err.count("\n") == 1, err
    assert "error: the back depth stream dropped: its frame numbers jump from 121 to 200 (78 frames lost, over " \
           "--timeout-frames 30); what was recorded until then is kept, closed cleanly, in" in err
    assert "0 steps; not importable: the import needs 2 steps or more" in err
    assert "back: back" in said  # the summary of what was recorded, on stdout
    suffix = back.suffix
    assert 121 in open_recording(out / f"back{suffix}", "back").depth.seqs.tolist()


def _stub_session(tmp_path: Path, clock):
    """A session of connected cameras without librealsense: stub cameras, the test's clock."""
    from dsr_bench.annotator.record import CaptureSession

    stopped = threading.Event()
    camera = SimpleNamespace(fps={"color": 30, "depth": 30}, path=None, stop=stopped.set,
                             device=SimpleNamespace(describe=lambda: "819612070593 (Intel RealSense D415, USB 3.2)"))
    tmp_path.mkdir(exist_ok=True)
    session = CaptureSession(tmp_path, {"front": camera}, True, steps=None, settle_s=0.0, timeout_frames=30,
                             robot_file=None, clock=clock, on_event=None)
    return session, stopped


def test_a_connected_camera_silent_for_the_timeout_is_a_dropped_stream(tmp_path):
    """Connected cameras: a stream with no frame for --timeout-frames frame periods of the host's clock (1 s at 30
    fps) stops the session; a global-time frame clock is the host's, so a mark picks the first frame after it."""
    from dsr_bench.errors import UserError

    now = [1000.0]
    session, stopped = _stub_session(tmp_path / "run", lambda: now[0])
    for i in range(5):
        session._frame("front", "color", 10 + i, 1000.0 + i / 30, "global_time")
        session._frame("front", "depth", 10 + i, 1000.004 + i / 30, "global_time")
    session.step_done(time=1000.05)
    session._thread.start()
    now[0] = 1002.0  # the colour and depth streams silent for 1.87 s
    with pytest.raises(UserError, match=r"the front colour stream stopped delivering frames \(none for 2\.0 s after "
                                        r"frame 14, over --timeout-frames 30 at 30 fps"):
        session.wait()
    assert stopped.is_set()
    assert json.loads((tmp_path / "run" / "steps.json").read_text())["frames"]["steps"] == {"front": [12]}


def test_capture_help_imports_no_librealsense():
    sys.path.insert(0, str(ROOT / "bench"))
    import bench_startup

    report = bench_startup.probe([["capture", "--help"]], ("pyrealsense2", "rosbags"), cwd=ROOT)
    assert report[0]["rc"] == 0 and report[0]["loaded"] == [], report


def test_the_docs_describe_every_option_of_the_command():
    """docs/annotator.md's section names every option `capture --help` lists."""
    from typer.main import get_command

    from dsr_bench.cli import app

    text = (ROOT / "docs" / "annotator.md").read_text()
    section = text.split("## Recording a session: `dsr-bench capture`", 1)[1].split("\n## ", 1)[0]
    command = get_command(app).commands["capture"]  # type: ignore[attr-defined]
    options = [o for p in command.params for o in p.opts if o.startswith("--")]
    assert "--from-recordings" in options and [o for o in options if o not in section] == []
