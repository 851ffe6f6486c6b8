"""Real captures in (issue 18): `dsr-bench import-capture` of a rig's PNG folder, ChArUco calibration to the table
frame, robot-logged pushes -> benchmark actions, and every one-line error on the way.

Fixture: the simulated capture of tests/test_annotator.py (seed 1, 3 objects, ideal sensor) cut to 2 pushes, its
true poses rendered again as a real rig would record them: 720 x 1280 images with non-square pixels (fy = 1.04 fx)
and an off-centre principal point, the front camera with lens distortion (raw images distorted through OpenCV's
model; depth by nearest pixel), a ChArUco board (`cv2.aruco` generateImage) warped onto the table in the colour
images through the true camera (objects occlude it), steps numbered from 17, the pushes logged as start + direction.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from dsr_bench.errors import UserError
from dsr_bench.geometry import Camera, make_camera, pose_to_matrix

cv2 = pytest.importorskip("cv2")

SHAPE = (720, 1280)
BOARD = {"squares": [7, 5], "square_length": 0.06, "marker_length": 0.045, "dictionary": "DICT_4X4_50",
         "offset": [0.29, 0.15, 0.0]}
DISTORTION = {"front": [-0.05, 0.03, 0.0005, -0.0004, 0.0], "back": None}
FIRST_STEP = 17


def _true_camera(name: str) -> Camera:
    """The rig's true camera: the benchmark's placement at 720 x 1280, fy = 1.04 fx, principal point off centre."""
    cam = make_camera(name, *SHAPE)
    k = np.asarray(cam.intrinsics, np.float64).copy()
    k[1, 1] *= 1.04
    k[:2, 2] += (6.5, -4.25) if name == "front" else (-3.0, 5.0)
    return Camera(name, *SHAPE, k, cam.extrinsics)


def _paste_board(color: np.ndarray, table: np.ndarray, camera: Camera) -> np.ndarray:
    """`color` (H, W, 3) with the ChArUco board (BOARD) drawn onto the table plane where `table` (H, W) bool
    (`dsr_bench.annotator.calibrate.paint_board`)."""
    from dsr_bench.annotator.calibrate import paint_board

    return paint_board(color, table, camera, BOARD)


def _distort(image: np.ndarray, camera: Camera, coefficients, nearest: bool) -> np.ndarray:
    """The raw image a lens with OpenCV `coefficients` records of the ideal (undistorted) `image`."""
    if coefficients is None:
        return image
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float32)
    raw = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    k = np.asarray(camera.intrinsics, np.float64)
    ideal = cv2.undistortPoints(raw, k, np.asarray(coefficients, np.float64), P=k).reshape(camera.height,
                                                                                          camera.width, 2)
    flags = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.remap(image, ideal[..., 0], ideal[..., 1], flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def write_rig_folder(capture, folder: Path, poses: np.ndarray, *, board: bool = True) -> dict[str, Camera]:
    """Render `capture`'s objects at `poses` (T+1, N, 7) as the rig records them into `folder` (PNGs, rig.json,
    meshes, pushes.json from the capture's pushes); returns the true cameras."""
    from dsr_bench.annotator.export import renderer_for

    cameras = {n: _true_camera(n) for n in ("front", "back")}
    renderer = renderer_for(capture, cameras)
    folder.mkdir(parents=True)
    from PIL import Image

    for t, pose in enumerate(poses):
        scene, ids = renderer.scene(pose)
        for name, cam in cameras.items():
            images = renderer.render_camera(scene, ids, name)
            color = images.color
            if board:
                color = _paste_board(color, (images.mask == 0) & (images.depth > 0), cam)
            depth = np.round(images.depth / 0.001).astype(np.uint16)
            Image.fromarray(_distort(color, cam, DISTORTION[name], False)).save(
                folder / f"{name}_color_{FIRST_STEP + t:06d}.png")
            Image.fromarray(_distort(depth, cam, DISTORTION[name], True)).save(
                folder / f"{name}_depth_{FIRST_STEP + t:06d}.png")
    if board:  # the board alone on the table (the objects below it), as a rig is calibrated before a sequence
        (folder / "board").mkdir()
        hidden = poses[0].copy()
        hidden[:, 2] -= 1.0
        scene, ids = renderer.scene(hidden)
        for name, cam in cameras.items():
            images = renderer.render_camera(scene, ids, name)
            color = _paste_board(images.color, images.depth > 0, cam)
            depth = np.round(images.depth / 0.001).astype(np.uint16)
            Image.fromarray(_distort(color, cam, DISTORTION[name], False)).save(folder / "board" / f"{name}_color.png")
            Image.fromarray(_distort(depth, cam, DISTORTION[name], True)).save(folder / "board" / f"{name}_depth.png")
    (folder / "meshes").mkdir()
    objects = []
    for i, obj in enumerate(capture.objects):
        shutil.copy(obj.mesh_path, folder / "meshes" / f"{i}.ply")
        objects.append({"name": obj.name, "mesh": f"meshes/{i}.ply", "identity": obj.identity})
    images = {n: {"color": f"board/{n}_color.png", "depth": f"board/{n}_depth.png"} for n in cameras}
    rig = {"name": "real_000", "objects": objects, "board": {**BOARD, "images": images}, "cameras": {
        n: {"fx": c.intrinsics[0, 0], "fy": c.intrinsics[1, 1], "cx": c.intrinsics[0, 2], "cy": c.intrinsics[1, 2],
            "width": c.width, "height": c.height, "depth_scale": 0.001, "distortion": DISTORTION[n]}
        for n, c in cameras.items()}}
    (folder / "rig.json").write_text(json.dumps(rig, indent=1))
    pushes = []
    for t, (start, end) in enumerate(capture.pushes_world[: len(poses) - 1]):
        step = (end - start)[:2] / np.linalg.norm((end - start)[:2])
        entry = {"start": start[:2].tolist()}
        entry.update({"direction": step.tolist()} if t % 2 == 0 else
                     {"angle_deg": float(np.degrees(np.arctan2(step[1], step[0])))})
        pushes.append(entry)
    (folder / "pushes.json").write_text(json.dumps({"pushes": pushes}))
    return cameras


@pytest.fixture(scope="module")
def rig(sim, tmp_path_factory):
    folder = tmp_path_factory.mktemp("rig") / "src"
    cameras = write_rig_folder(sim, folder, sim.truth_poses())
    return folder, cameras


@pytest.fixture(scope="module")
def imported(rig, tmp_path_factory):
    from dsr_bench.cli import main

    out = tmp_path_factory.mktemp("imported") / "real_000"
    assert main(["import-capture", str(rig[0]), "--out", str(out)]) == 0
    return out


# --- pushes ----------------------------------------------------------------------------------------------------------


def test_pushes_map_to_the_generators_actions_and_off_grid_pushes_are_refused(sim, tmp_path):
    from dsr_bench.annotator.pushes import push_to_action, read_pushes
    from dsr_bench.geometry import direction_vector, pixel_to_world

    # every action the generator wrote comes back from its start and its direction
    for action, (start, end) in zip(sim.actions, sim.pushes_world):
        got, reason = push_to_action(start[:2], (end - start)[:2] / np.linalg.norm((end - start)[:2]))
        assert reason is None and got.tolist() == action.tolist()
    for d in range(8):
        got, _ = push_to_action(pixel_to_world(np.array([5, 120])), direction_vector(d))
        assert got.tolist() == [d, 5, 120]
    turned = np.radians(45 + 1.5)
    assert push_to_action([0.5, 0.0], [np.cos(turned), np.sin(turned)])[0][0] == 1  # within the tolerance
    off = np.radians(45 + 5.0)
    action, reason = push_to_action([0.5, 0.0], [np.cos(off), np.sin(off)])
    assert action is None and "50.0 deg is 5.0 deg from the nearest benchmark direction d=1 (45 deg" in reason
    action, reason = push_to_action([0.8, 0.0], [1.0, 0.0])
    assert action is None and "start (0.800, 0.000) m is outside the grid" in reason
    assert push_to_action([0.756, 0.0], [1.0, 0.0])[0] is None  # the upper bound is outside (cell 128)
    path = tmp_path / "p.json"
    path.write_text(json.dumps({"pushes": [{"start": [0.5, 0.0], "angle_deg": 90, "length": 0.1},
                                           {"start": [0.302, -0.198], "direction": [0.0, -1.0]}]}))
    actions, world = read_pushes(path, 2)
    assert actions.tolist() == [[2, 64, 64], [6, 14, 14]]
    np.testing.assert_allclose(world[0], [[0.5, 0.0, 0.005], [0.5, 0.1, 0.005]], atol=1e-12)


@pytest.mark.parametrize("pushes, expected", [
    ([{"start": [0.5, 0.0], "angle_deg": 30}, {"start": [0.9, 0.0], "direction": [1, 0]}],
     "2 of 2 pushes are no benchmark action: push 0 direction 30.0 deg is 15.0 deg from the nearest benchmark "
     "direction d=1 (45 deg; tolerance 2 deg); push 1 start (0.900, 0.000) m is outside the grid"),
    ([{"start": [0.5, 0.0], "direction": [1, 1]}, {"start": [0.5, 0.0], "angle_deg": 0}],
     "push 0 direction [1.0, 1.0] has length 1.414, not 1: give a unit vector"),
    ([{"start": [0.5, 0.0]}, {"start": [0.5, 0.0], "angle_deg": 0}], "push 0 needs 'start' [x, y] (m, table) and one"),
    ([{"start": [0.5, 0.0], "angle_deg": 0}], "1 pushes but the images hold 3 steps: log exactly one push"),
])
def test_push_log_errors_are_one_line_naming_the_file_and_the_push(rig, tmp_path, capsys, pushes, expected):
    from dsr_bench.cli import main

    path = tmp_path / "pushes.json"
    path.write_text(json.dumps({"pushes": pushes}))
    assert main(["import-capture", str(rig[0]), "--out", str(tmp_path / "c"), "--pushes", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"--pushes {path}" in err and expected in err, err
    assert not (tmp_path / "c").exists() and not list(tmp_path.glob(".c.tmp-*"))


# --- import and calibration ------------------------------------------------------------------------------------------


def test_board_calibration_recovers_the_true_extrinsics(rig, imported):
    from dsr_bench.annotator.align import pose_delta
    from dsr_bench.dataset.capture import load_capture

    _, true = rig
    capture = load_capture(imported)
    report = capture.source["calibration"]
    assert report["extrinsics"] == {"front": "board", "back": "board"}
    for name, cam in true.items():
        got = capture.cameras[name]
        np.testing.assert_allclose(got.intrinsics, cam.intrinsics)  # fx != fy kept; undistorted onto the same K
        assert (got.height, got.width) == SHAPE
        dt, angle = pose_delta(cam.extrinsics, got.extrinsics)
        assert dt < 0.003 and np.degrees(angle) < 0.5, (name, dt)
        r = report["cameras"][name]
        assert r["corners"] >= 12 and r["board_mm"] < 1.0 and abs(r["depth_mm"]) < 2.0, r
    assert report["between_cameras_mm"] < 2.0 and report["shared_corners"] >= 3


def test_import_undistorts_renumbers_and_keeps_the_measured_depth(sim, rig, imported):
    from dsr_bench.annotator.export import renderer_for
    from dsr_bench.dataset.capture import load_capture

    capture = load_capture(imported)
    assert capture.name == "real_000" and capture.num_steps == 2 and list(capture.cameras) == ["front", "back"]
    assert capture.source["step_numbers"] == [FIRST_STEP, FIRST_STEP + 1, FIRST_STEP + 2]
    assert capture.source["undistorted"] == ["front"]
    assert capture.actions.tolist() == sim.actions.tolist()
    np.testing.assert_allclose(capture.pushes_world[:, 0], sim.pushes_world[:, 0], atol=1e-12)
    renderer = renderer_for(sim, rig[1])
    poses = sim.truth_poses()
    for t in (0, 2):
        scene, ids = renderer.scene(poses[t])
        for name in ("front", "back"):
            ideal = renderer.render_camera(scene, ids, name).depth
            depth = capture.depth(t, name)
            valid = (depth > 0) & (ideal > 0)
            assert valid.sum() / (ideal > 0).sum() > 0.97  # undistortion loses only the image's rim
            # nearest-pixel undistortion: depths are measured values (an edge pixel may take its neighbour's)
            assert np.mean(np.abs(depth[valid] - ideal[valid]) <= 0.0006) > 0.97
            if name == "back":  # no distortion: the depth PNG as recorded
                np.testing.assert_allclose(depth, np.round(ideal / 0.001) * 0.001, atol=1e-7)


def test_non_square_720p_capture_annotates_and_exports_like_the_simulated_one(sim, imported, tmp_path):
    from dsr_bench.annotator.align import pose_delta
    from dsr_bench.annotator.session import Session
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.dataset.validate import validate_sequence

    truth = sim.truth_poses()
    sessions = {}
    for key, path in (("sim", sim.path), ("real", imported)):
        session = Session.open(path, tmp_path / f"work_{key}")
        for i in range(session.num_objects):
            v, _ = session.capture.mesh(i)
            idx = np.linspace(0, len(v) - 1, 4).astype(int)
            m = pose_to_matrix(truth[0, i])
            session.init_from_picks(i, v[idx], v[idx] @ m[:3, :3].T + m[:3, 3])
            session.snap(i)
        session.auto()
        session.export(tmp_path / f"{key}.h5", allow_unchecked=True)
        sessions[key] = session
    from scipy.spatial import cKDTree

    def errors(session, t: int, i: int) -> tuple[float, float]:
        """(translation m, ADD-S m: the mesh at the annotated pose lies on the mesh at the true pose; a can's spin
        is invisible) of object i at step t."""
        got, true = pose_to_matrix(session.poses(t)[i]), pose_to_matrix(truth[t, i])
        v, _ = session.capture.mesh(i)
        add_s = cKDTree(v @ true[:3, :3].T + true[:3, 3]).query(v @ got[:3, :3].T + got[:3, 3])[0].mean()
        return pose_delta(got, true)[0], float(add_s)

    for t in range(truth.shape[0]):
        for i in range(truth.shape[1]):
            (dt, add_s), (dt_sim, add_s_sim) = errors(sessions["real"], t, i), errors(sessions["sim"], t, i)
            # as accurate as the simulated capture's annotation (whose limits tests/test_annotator.py explains)
            assert dt < max(0.004, dt_sim + 0.0015) and add_s < max(0.004, add_s_sim + 0.0015), (t, i, dt, add_s)
    assert validate_sequence(tmp_path / "real.h5") == []
    with SequenceReader(tmp_path / "real.h5") as real, SequenceReader(tmp_path / "sim.h5") as simulated:
        assert real.read("action").tolist() == simulated.read("action").tolist()
        front = real.camera("front")
        full = sessions["real"].capture.cameras["front"].intrinsics
        # 720 x 1280 -> 240 x 320: every third row and fourth column; fx / 4 and fy / 3 (pixels stay non-square)
        np.testing.assert_allclose(front.intrinsics[0], [full[0, 0] / 4, 0, full[0, 2] / 4])
        np.testing.assert_allclose(front.intrinsics[1], [0, full[1, 1] / 3, full[1, 2] / 3])
        depth_full = sessions["real"].capture.depth(1, "front")
        np.testing.assert_array_equal(real.read("cameras/front/depth", 1), depth_full[::3, ::4])
        points = real.read("cameras/front/points", 1)
        expected = front.backproject(real.read("cameras/front/depth", 1).astype(np.float64))
        np.testing.assert_allclose(points, expected, atol=2e-6)
        for t in range(truth.shape[0]):
            a, b = real.read("mask_3d", t) > 0, simulated.read("mask_3d", t) > 0
            assert (a & b).sum() / (a | b).sum() > 0.9
            # the stored front mask lies where the stored camera sees the objects
            mask = real.read("cameras/front/mask", t)
            assert set(np.unique(mask)) == set(range(real.num_objects + 1))


# --- one-line errors --------------------------------------------------------------------------------------------------


def _edit_rig(rig_folder: Path, tmp_path: Path, edit) -> Path:
    copy = tmp_path / "src"
    shutil.copytree(rig_folder, copy)
    spec = json.loads((copy / "rig.json").read_text())
    edit(spec, copy)
    (copy / "rig.json").write_text(json.dumps(spec))
    return copy


def _rename_camera(spec, folder):
    spec["cameras"]["left"] = spec["cameras"].pop("back")


def _wrong_board(spec, folder):
    spec["board"]["dictionary"] = "DICT_6X6_250"


def _board_from_step_0(spec, folder):  # without board images: step 0's, where the objects hide most of it
    del spec["board"]["images"]


def _wrong_square(spec, folder):
    spec["board"]["square_length"] = 0.066
    spec["board"]["marker_length"] = 0.0495


def _turned_away(spec, folder):  # the front camera's given extrinsics look past the grid's +x corners
    from dsr_bench.geometry import look_at

    spec["cameras"]["front"]["extrinsics"] = look_at((0.2, -0.7, 0.3), (0.2, 0.0, 0.0), (0.0, 0.3, 0.7)).tolist()


def _no_board(spec, folder):
    del spec["board"]


def _missing_depth(spec, folder):
    (folder / f"back_depth_{FIRST_STEP + 1:06d}.png").unlink()


def _stray_camera(spec, folder):
    shutil.copy(folder / f"back_depth_{FIRST_STEP:06d}.png", folder / f"side_depth_{FIRST_STEP:06d}.png")


def _bad_distortion(spec, folder):
    spec["cameras"]["front"]["distortion"] = [0.1, 0.2]


def _not_rigid(spec, folder):
    spec["cameras"]["back"]["extrinsics"] = np.diag([2.0, 1.0, 1.0, 1.0]).tolist()


def _twice(spec, folder):
    shutil.copy(folder / f"front_color_{FIRST_STEP:06d}.png", folder / f"front_color_{FIRST_STEP}.png")


def _wrong_size(spec, folder):
    spec["cameras"]["back"]["width"] = 640


def _dropped_step(spec, folder):  # step 18's images and its push both lost: 2 steps, 1 push, the counts agree
    for name in ("front", "back"):
        for kind in ("color", "depth"):
            (folder / f"{name}_{kind}_{FIRST_STEP + 1:06d}.png").unlink()
    log = json.loads((folder / "pushes.json").read_text())
    (folder / "pushes.json").write_text(json.dumps({"pushes": log["pushes"][:1]}))


def _rgba_board(spec, folder):  # a board image saved with alpha: refused, not silently dropped
    from PIL import Image

    path = folder / "board" / "back_color.png"
    with Image.open(path) as im:
        im.convert("RGBA").save(path)


@pytest.mark.parametrize("edit, expected", [
    (_rename_camera, "rig.json: camera names ['front', 'left'] must be 'front' (the view models see; required) and "
                     "'back': rename 'left'"),
    (_wrong_board, "board/front_color.png ("),
    (_board_from_step_0, "back_color_000017.png ("),
    (_wrong_square, "depth disagrees with the board by"),
    (_turned_away, "the grid's table corner (0.756, -0.256, 0) m projects to pixel"),
    (_no_board, "have no 'extrinsics' (4x4 camera-to-table, m) and there is no 'board'"),
    (_missing_depth, "no back_depth_18.png (step number 18 exists for another camera or kind)"),
    (_stray_camera, "side_depth_000017.png names camera 'side', which the rig file does not list"),
    (_bad_distortion, "camera 'front' distortion must be OpenCV's 5 coefficients [k1, k2, p1, p2, k3]"),
    (_not_rigid, "camera 'back': extrinsics must be a rigid 4x4 camera-to-table transform"),
    (_twice, "front_color_000017.png and front_color_17.png are both step 17; keep one"),
    (_wrong_size, "back_color_000017.png: expected an 8-bit RGB PNG of 640x720 (the rig file's 'back' width x "
                 "height), got shape (720, 1280, 3)"),
    (_dropped_step, "step 18 missing (the image numbers jump from 17 to 19: no front_color_000018.png; a dropped "
                    "frame"),
    (_rgba_board, "board/back_color.png: an 8-bit RGBA PNG (with an alpha channel), where colour images are 8-bit RGB"),
])
def test_import_errors_are_one_line_naming_the_input_and_the_fix(rig, tmp_path, capsys, edit, expected):
    from dsr_bench.cli import main

    folder = _edit_rig(rig[0], tmp_path, edit)
    out = tmp_path / "out"
    assert main(["import-capture", str(folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err and str(folder) in err, err
    assert not out.exists() and not list(tmp_path.glob(".out.tmp-*"))


def test_given_extrinsics_skip_the_board_and_an_existing_capture_is_kept(rig, imported, tmp_path, capsys):
    from dsr_bench.cli import main
    from dsr_bench.dataset.capture import load_capture

    true = rig[1]

    def given(spec, folder):
        del spec["board"]
        for name, cam in true.items():
            spec["cameras"][name]["extrinsics"] = cam.extrinsics.tolist()

    folder = _edit_rig(rig[0], tmp_path, given)
    out = tmp_path / "given"
    assert main(["import-capture", str(folder), "--out", str(out), "--name", "given_000"]) == 0
    assert "front: extrinsics from the rig file" in capsys.readouterr().out
    capture = load_capture(out)
    assert capture.name == "given_000"
    np.testing.assert_allclose(capture.cameras["back"].extrinsics, true["back"].extrinsics)
    before = (imported / "capture.json").read_bytes()
    assert main(["import-capture", str(folder), "--out", str(imported)]) == 2
    assert "already exists; pass --overwrite" in capsys.readouterr().err
    assert (imported / "capture.json").read_bytes() == before


def test_wrong_intrinsics_and_disagreeing_cameras_are_refused(rig, imported, tmp_path, capsys):
    from dsr_bench.annotator.calibrate import check_residuals
    from dsr_bench.cli import main
    from dsr_bench.dataset.capture import load_capture

    def wrong_fx(spec, folder):
        spec["cameras"]["back"]["fx"] *= 1.03

    folder = _edit_rig(rig[0], tmp_path, wrong_fx)
    assert main(["import-capture", str(folder), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "back camera's depth disagrees with the board" in err and "fx, fy" in err
    good = {"cameras": {"front": {"board_mm": 0.2, "depth_mm": 0.5}}, "between_cameras_mm": 0.3}
    check_residuals("rig.json board", good)
    with pytest.raises(UserError, match="rig.json board: the front camera's board residual is 4.0 mm .*intrinsics"):
        check_residuals("rig.json board", {**good, "cameras": {"front": {"board_mm": 4.0, "depth_mm": 0.5}}})
    with pytest.raises(UserError, match="the cameras disagree by 5.0 mm on the board .*neither moved"):
        check_residuals("rig.json board", {**good, "between_cameras_mm": 5.0})
    # a capture's intrinsics with a skew are refused (every tool projects with fx, fy, cx, cy alone)
    skewed = tmp_path / "skewed"
    shutil.copytree(imported, skewed)
    calib = json.loads((skewed / "calibration.json").read_text())
    calib["back"]["intrinsics"][0][1] = 0.5
    (skewed / "calibration.json").write_text(json.dumps(calib))
    with pytest.raises(UserError, match="camera 'back': intrinsics skew 0.5 must be 0 .*fx != fy is fine"):
        load_capture(skewed)


def test_import_capture_is_a_dsr_bench_command_with_documented_options(capsys, monkeypatch):
    from dsr_bench.cli import main

    monkeypatch.setenv("COLUMNS", "200")
    assert main(["import-capture", "--help"]) == 0
    out = capsys.readouterr().out
    assert all(o in out for o in ("--out", "--rig", "--pushes", "--name", "--overwrite"))
    docs = (Path(__file__).parents[1] / "docs" / "annotator.md").read_text()
    assert "dsr-bench import-capture SRC --out CAPTURE [--rig RIG.json] [--pushes PUSHES.json]" in docs
    assert main(["import-capture", "/no/such/folder", "--out", "/tmp/x"]) == 2
    assert "/no/such/folder: no such folder" in capsys.readouterr().err
