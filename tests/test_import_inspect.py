"""`dsr-bench import-capture SRC --inspect` (issue 32 part 5): what a recording holds, reported before anything is
converted, on the project's own test recordings: the PNG rig of tests/test_import_capture.py and the RealSense bags
of tests/test_import_bag.py (laid out as librealsense writes them; recordings librealsense itself wrote are inspected
in tests/test_realsense_recordings.py). Every problem the import would refuse is reported, not only the first, and
nothing is written.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from test_import_capture import FIRST_STEP, SHAPE, write_rig_folder  # noqa: E402


def _listing(folder: Path) -> list[tuple[str, int]]:
    return sorted((str(p.relative_to(folder)), p.stat().st_mtime_ns) for p in folder.rglob("*"))


@pytest.fixture(scope="module")
def rig(sim, tmp_path_factory):
    folder = tmp_path_factory.mktemp("inspect_rig") / "src"
    return folder, write_rig_folder(sim, folder, sim.truth_poses())


def test_frame_timing_counts_gaps_and_skipped_frame_numbers():
    from dsr_bench.annotator.inspect import frame_timing

    stamps = np.array([0.0, 1, 2, 4, 5, 6]) / 30 + 100.0  # one frame dropped after the third
    line = frame_timing(stamps, np.array([7, 8, 9, 11, 12, 13]))
    assert "6 frames over 0.20 s" in line and "30.0 fps" in line
    assert "1 gap over 1.5 frames (largest 67 ms after 100.067 s)" in line and "1 frame numbers skipped" in line
    assert "no gaps" in frame_timing(np.arange(5) / 30.0, np.arange(5)) and "no frame numbers skipped" in \
        frame_timing(np.arange(5) / 30.0, np.arange(5))


def test_inspect_reports_a_png_rig_and_writes_nothing(rig, capsys):
    from dsr_bench.cli import main

    folder, cameras = rig
    before = _listing(folder)
    assert main(["import-capture", str(folder), "--inspect"]) == 0
    out = capsys.readouterr().out
    assert _listing(folder) == before  # nothing converted, nothing written
    for name, cam in cameras.items():
        k = cam.intrinsics
        section = out.split(f"\n{name}:\n", 1)[1]
        assert f"rig: {SHAPE[1]}x{SHAPE[0]}, intrinsics fx {k[0, 0]:.2f}, fy {k[1, 1]:.2f}" in section
        assert ("distortion OpenCV (Brown-Conrady) [-0.05, 0.03, 0.0005, -0.0004, 0]" if name == "front"
                else "no distortion given") in section
        assert "depth_scale 0.001 m per unit; extrinsics from the board" in section
        # the numbering, the images' sizes and types from their headers
        assert f"color: 3 images, numbers {FIRST_STEP}..{FIRST_STEP + 2} consecutive; {FIRST_STEP}: 1280x720, " \
               "8-bit" in section
        assert f"depth: 3 images, numbers {FIRST_STEP}..{FIRST_STEP + 2} consecutive; {FIRST_STEP}: 1280x720, " \
               "16-bit" in section
        coverage = re.search(r"(\d+)% of pixels measured, median (\d\.\d+) m", section)
        assert coverage and int(coverage[1]) > 50 and 0.3 < float(coverage[2]) < 1.5
        board = re.search(rf"board in {name}_color.png: (\d+) of 24 corners, reprojection (\d\.\d+) px, camera "
                          r"(\d\.\d+) m above the table", section)
        assert board and int(board[1]) >= 20 and float(board[2]) < 1.0
        assert float(board[3]) == pytest.approx(cam.extrinsics[2, 3], abs=0.01)  # the true camera height
    assert "steps: 3 step numbers (2 pushes)" in out and "2 pushes, each a benchmark action" in out
    assert "PROBLEM" not in out and "nothing the import would refuse was found" in out


def test_inspect_lists_every_problem_not_only_the_first(rig, tmp_path, capsys):
    from dsr_bench.cli import main

    copy = tmp_path / "src"
    shutil.copytree(rig[0], copy)
    (copy / f"back_depth_{FIRST_STEP + 1:06d}.png").unlink()  # a missing depth image
    spec = json.loads((copy / "rig.json").read_text())
    spec["board"]["dictionary"] = "DICT_6X6_250"  # a board the cameras cannot find
    (copy / "rig.json").write_text(json.dumps(spec))
    (copy / "pushes.json").unlink()
    assert main(["import-capture", str(copy), "--inspect"]) == 2
    captured = capsys.readouterr()
    problems = [line for line in captured.out.splitlines() if "PROBLEM" in line]
    assert any(f"no back_depth_{FIRST_STEP + 1}.png" in p for p in problems)
    assert sum("ChArUco corners found" in p for p in problems) == 2  # front and back
    assert any("pushes.json" in p for p in problems)
    err = captured.err.strip()
    assert len(err.splitlines()) == 1 and f"{len(problems)} problem(s)" in err
    assert "depth: 2 images" in captured.out  # the rest is still reported


def test_inspect_checks_the_step_numbers_against_the_push_log_as_the_import_does(rig, tmp_path, capsys):
    """A dropped step (the numbers jump from 18 to 20) is a problem, named as the import names it; with each push's
    "between" in the log the same numbers are frame numbers, and fine (issue 42)."""
    from dsr_bench.cli import main

    copy = tmp_path / "src"
    shutil.copytree(rig[0], copy)
    last = FIRST_STEP + 2
    for image in copy.glob(f"*_{last:06d}.png"):
        image.rename(image.with_name(image.name.replace(f"{last:06d}", f"{last + 1:06d}")))
    assert main(["import-capture", str(copy), "--inspect"]) == 2
    out = capsys.readouterr().out
    assert f"PROBLEM: {copy}: step {last} missing (the image numbers jump from {last - 1} to {last + 1}" in out
    log = json.loads((copy / "pushes.json").read_text())
    for push, between in zip(log["pushes"], [[FIRST_STEP, FIRST_STEP + 1], [FIRST_STEP + 1, last + 1]]):
        push["between"] = between
    (copy / "pushes.json").write_text(json.dumps(log))
    assert main(["import-capture", str(copy), "--inspect"]) == 0
    assert "PROBLEM" not in capsys.readouterr().out


def test_inspect_without_out_and_import_without_out(rig, tmp_path, capsys):
    from dsr_bench.cli import main

    assert main(["import-capture", str(rig[0]), "--inspect", "--out", str(tmp_path / "x")]) == 2
    assert "--inspect converts nothing" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    assert main(["import-capture", str(rig[0])]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "needs --out CAPTURE" in err and "--inspect" in err


# --- RealSense bags ---------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bags(sim, tmp_path_factory):
    pytest.importorskip("rosbags")
    from test_import_bag import write_bag_folder

    folder = tmp_path_factory.mktemp("inspect_bags") / "src"
    return folder, write_bag_folder(sim, folder)


def test_inspect_reports_each_bags_streams_units_and_board(bags, capsys):
    from test_import_bag import DEPTH_SHAPE, DEPTH_TO_COLOR

    from dsr_bench.cli import main

    folder, cameras = bags
    before = _listing(folder)
    assert main(["import-capture", str(folder), "--inspect"]) == 0
    out = capsys.readouterr().out
    assert _listing(folder) == before
    for name, cam in cameras.items():
        section = out.split(f"{name}.bag ({name} camera", 1)[1].split(".bag (", 1)[0]
        # the fixture records 3 frames around each of 4 events (board, 3 steps) seconds apart: 12 frames, 3 gaps,
        # and its frame numbers jump by 10 between events (7 skipped each time)
        colour = re.search(r"colour /device_0/sensor_\d/Color_0/image/data: 1280x720, 12 frames over [\d.]+ s .*?, "
                           r"30\.0 fps; 3 gaps over 1\.5 frames .*; 21 frame numbers skipped", section)
        assert colour, section
        assert re.search(rf"depth /device_0/sensor_\d/Depth_0/image/data: {DEPTH_SHAPE[1]}x{DEPTH_SHAPE[0]}, 12 frames",
                         section)
        k = cam.intrinsics
        assert f"intrinsics fx {k[0, 0]:.2f}, fy {k[1, 1]:.2f}, cx {k[0, 2]:.2f}, cy {k[1, 2]:.2f} px; distortion " \
               "model 'Inverse Brown Conrady' " + ("[0.05, -0.02, 0.0005, -0.0003, 0]\n" if name == "front" else
                                                  "[0, 0, 0, 0, 0] (all coefficients 0") in section
        shift = np.linalg.norm(DEPTH_TO_COLOR[name][:3, 3]) * 1000
        assert f"depth units 0.001 m per unit (1 mm); depth -> colour {shift:.1f} mm" in section
        board = re.search(rf"board in {name}.bag board_time frame \d+: (\d+) of 24 corners, reprojection "
                          r"(\d\.\d+) px, camera (\d\.\d+) m above the table", out)
        assert board and int(board[1]) >= 20 and float(board[3]) == pytest.approx(cam.extrinsics[2, 3], abs=0.01)
    assert "3 step times, a board time" in out
    gaps = re.findall(r"(front|back): step time -> colour frame (\d+)\.\.(\d+) ms, colour -> depth frame "
                      r"(\d+)\.\.(\d+) ms \(limit 50 ms\)", out)
    coverage = re.findall(r"step 0 depth frame \d+: (\d+)% of pixels measured, median (\d\.\d+) m", out)
    assert len(coverage) == 2 and all(int(c) > 50 and 0.3 < float(m) < 1.5 for c, m in coverage)
    assert len(gaps) == 2 and all(int(g[2]) <= 20 and int(g[4]) <= 5 for g in gaps)  # jitter 7 ms, back lag 10 ms
    assert "2 pushes, each a benchmark action" in out and "PROBLEM" not in out


def test_inspect_of_broken_bags_names_each_problem(bags, tmp_path, capsys):
    from test_import_bag import STEP_TIMES, _tiny

    from dsr_bench.cli import main

    folder = _tiny(tmp_path / "src", bags[0], omit=("Depth_Units",))  # the front bag lacks its depth units
    (folder / "steps.json").write_text(json.dumps({"step_times": [*STEP_TIMES[:2], STEP_TIMES[2] + 5.0]}))
    assert main(["import-capture", str(folder), "--inspect"]) == 2
    captured = capsys.readouterr()
    problems = [line for line in captured.out.splitlines() if "PROBLEM" in line]
    assert any("front.bag: no topic" in p and "Depth_Units" in p for p in problems)
    assert any("step 2 time" in p and "has no back colour frame within 50 ms" in p for p in problems)
    assert "back.bag (back camera" in captured.out and "depth units 0.001 m per unit" in captured.out  # reported
    assert len(captured.err.strip().splitlines()) == 1
