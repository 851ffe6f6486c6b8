"""Simulated captures (`dsr-bench generate-captures`, generators/capture.py) and the capture reader's validation.

The sensor model on synthetic images (z^2 noise law, missing pixels at edges, dark surfaces and stereo
shadows), a generated capture read back, noise none equal to the ideal render within the depth unit,
determinism, the calibration perturbation, and every load_capture error path as one line naming the file.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("pybullet")
pytest.importorskip("open3d")

from dsr_bench.dataset.capture import CaptureCamera, CaptureFormatError, load_capture  # noqa: E402
from dsr_bench.cli import main  # noqa: E402
from dsr_bench.geometry import pinhole_intrinsics, world_to_pixel  # noqa: E402
from dsr_bench.generators.capture import (  # noqa: E402
    DEPTH_SCALE, SensorModel, calibration_error, depth_discontinuities, perturb_calibration, sensor_color,
    sensor_depth, stereo_shadow,
)

ARGS = ["--steps", "2", "--objects-per-scene", "2", "--seed", "3", "-n", "1"]
K = pinhole_intrinsics(240, 320)


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> dict[str, Path]:
    """The same sequence (seed 3, 2 pushes, 2 objects) with realistic noise and with none."""
    root = tmp_path_factory.mktemp("captures")
    assert main(["generate-captures", "--out", str(root / "real"), *ARGS]) == 0
    assert main(["generate-captures", "--out", str(root / "ideal"), "--noise", "none", *ARGS]) == 0
    return {"realistic": root / "real" / "seq_0000", "none": root / "ideal" / "seq_0000"}


# --- the sensor model on synthetic images ------------------------------------------------------------------


def _plane(z: float, shape=(240, 320)) -> tuple[np.ndarray, np.ndarray]:
    return np.full(shape, z), np.full(shape + (3,), 180, np.uint8)


def test_depth_noise_grows_with_range_squared():
    model = SensorModel(speckle=0.0, edge_dropout=0.0, dark_dropout=0.0)
    rng = np.random.default_rng(0)
    sigmas = {}
    for z in (0.5, 1.0):
        depth, color = _plane(z)
        measured = sensor_depth(depth, color, K, rng, model)
        assert measured.dtype == np.float32 and np.all(measured > 0)
        assert np.allclose(measured / DEPTH_SCALE, np.round(measured / DEPTH_SCALE), atol=1e-3)  # whole depth units
        sigmas[z] = float((measured - z).std())
        expected = z**2 * model.disparity_sigma / (K[0, 0] * model.baseline)
        assert 0.7 * expected < sigmas[z] < 1.4 * expected, (z, sigmas[z], expected)
        assert abs(float((measured - z).mean())) < 0.3 * expected + DEPTH_SCALE  # unbiased
    assert 3.0 < sigmas[1.0] / sigmas[0.5] < 5.5  # ~ (1.0 / 0.5)^2


def test_missing_pixels_at_edges_dark_surfaces_and_stereo_shadow():
    depth, color = _plane(1.0)
    depth[80:160, 120:200] = 0.8  # a box in front of a wall
    color[20:60, 20:100] = 10  # a dark patch on the wall
    model = SensorModel()
    measured = sensor_depth(depth, color, K, np.random.default_rng(1), model)
    missing = measured == 0
    edge = depth_discontinuities(depth, model.edge_jump)
    disparity = K[0, 0] * model.baseline / depth
    shadow = stereo_shadow(disparity)
    dark = np.zeros_like(edge)
    dark[20:60, 20:100] = True
    # the stereo shadow is the band left of the box, as wide as the disparity step between box and wall
    width = K[0, 0] * model.baseline * (1 / 0.8 - 1 / 1.0)
    assert shadow[120, 120 - int(width) + 1:120].all() and not shadow[120, :120 - int(np.ceil(width)) - 1].any()
    assert not shadow[120, 120:].any() and not shadow[:80].any()
    plain = ~(edge | dark | shadow)
    assert missing[shadow].all()
    assert missing[dark].mean() > 0.8
    assert 0.4 < missing[edge & ~shadow].mean() < 0.8
    assert missing[plain].mean() < 0.01
    assert missing[edge].mean() > 30 * missing[plain].mean()


def test_ideal_sensor_keeps_depth_within_the_depth_unit():
    depth, color = _plane(0.7)
    depth[50:100, 50:100] = 0.5731234
    depth[0:10] = 0.0
    color[:] = 0  # dark everywhere: an ideal sensor still sees it
    out = sensor_depth(depth, color, K, np.random.default_rng(2), SensorModel.ideal())
    assert np.array_equal(out == 0, depth == 0)
    assert np.abs(out - depth).max() <= DEPTH_SCALE / 2 + 1e-6
    assert np.array_equal(sensor_color(color, np.random.default_rng(2), SensorModel.ideal()), color)


def test_calibration_perturbation_is_small_and_rigid():
    true = CaptureCamera("front", 240, 320, K, np.eye(4), DEPTH_SCALE)
    for seed in range(20):
        stored = perturb_calibration(true, np.random.default_rng(seed), SensorModel())
        dt, dr = calibration_error(stored, true)
        assert 0.001 - 1e-9 <= dt <= 0.002 + 1e-9 and 0.1 - 1e-6 <= dr <= 0.2 + 1e-6
        r = stored.extrinsics[:3, :3]
        assert np.allclose(r @ r.T, np.eye(3)) and np.isclose(np.linalg.det(r), 1.0)
        assert 0 < np.abs(stored.intrinsics - K).max() < 0.05 * K[0, 0]
    ideal = perturb_calibration(true, np.random.default_rng(0), SensorModel.ideal())
    assert np.array_equal(ideal.extrinsics, true.extrinsics) and np.array_equal(ideal.intrinsics, K)


# --- generated captures ------------------------------------------------------------------------------------


def test_round_trip_of_a_generated_capture(captures):
    cap = load_capture(captures["realistic"])
    assert cap.num_steps == 2 and cap.num_observations == 3 and cap.num_objects == 2
    assert list(cap.cameras) == ["front", "back"]
    assert cap.source["kind"] == "simulation" and cap.source["noise"] == "realistic"
    for cam in cap.cameras.values():
        assert (cam.height, cam.width) == (480, 640) and cam.depth_scale == DEPTH_SCALE
    assert cap.color(2, "back").shape == (480, 640, 3) and cap.color(2, "back").dtype == np.uint8
    depth = cap.depth(1, "front")
    assert depth.shape == (480, 640) and depth.dtype == np.float32 and 0.05 < (depth == 0).mean() < 0.6
    assert cap.actions.shape == (2, 3) and cap.pushes_world.shape == (2, 2, 3)
    assert np.array_equal(world_to_pixel(cap.pushes_world[:, 0, :2]), cap.actions[:, 1:])
    poses = cap.truth_poses()
    assert poses.shape == (3, 2, 7) and np.allclose(np.linalg.norm(poses[..., 3:], axis=-1), 1)
    assert {o.identity["category"] for o in cap.objects} and all(o.mesh_path.is_file() for o in cap.objects)
    vertices, faces = cap.mesh(0)
    assert vertices.shape[1] == 3 and faces.shape[1] == 3 and faces.max() < len(vertices)
    # the fused cloud holds both cameras and sees each object near its true surface
    points, colors, index = cap.cloud(0)
    assert set(np.unique(index)) == {0, 1} and colors.min() >= 0 and colors.max() <= 1
    from scipy.spatial import cKDTree

    from dsr_bench.geometry import transform_points, pose_to_matrix

    tree = cKDTree(points)
    for i in range(cap.num_objects):
        v, _ = cap.mesh(i)
        dist, _ = tree.query(transform_points(pose_to_matrix(poses[0, i]), v))
        assert np.median(dist) < 0.02  # vertices are sparse; the cloud lies on the object


def test_stored_calibration_differs_slightly_from_the_truth(captures):
    cap = load_capture(captures["realistic"])
    truth = cap.truth_calibration()
    assert set(truth) == {"front", "back"}
    for name, cam in cap.cameras.items():
        dt, dr = calibration_error(cam, truth[name])
        assert 0.001 - 1e-9 <= dt <= 0.002 + 1e-9 and 0.1 - 1e-6 <= dr <= 0.2 + 1e-6
        assert not np.array_equal(cam.intrinsics, truth[name].intrinsics)
    ideal = load_capture(captures["none"])
    for name, cam in ideal.cameras.items():
        assert np.allclose(cam.extrinsics, ideal.truth_calibration()[name].extrinsics)


def _ideal_depth(cap, step: int, camera: str) -> np.ndarray:
    """Ray-cast z-depth of the capture's meshes at their true poses, with the true calibration."""
    from dsr_bench.render import create_renderer

    objects = [SimpleNamespace(parts=[SimpleNamespace(vertices=v, faces=f)], color=(0.5, 0.5, 0.5))
               for v, f in (cap.mesh(i) for i in range(cap.num_objects))]
    renderer = create_renderer(objects, cameras=(camera,), image_shape=(480, 640))
    scene, ids = renderer.scene(cap.truth_poses()[step])
    return renderer.render_camera(scene, ids, camera).depth


def test_noise_none_equals_the_ideal_render_and_realistic_error_grows_with_range(captures):
    ideal_cap, real_cap = load_capture(captures["none"]), load_capture(captures["realistic"])
    assert np.allclose(ideal_cap.truth_poses(), real_cap.truth_poses())  # same seed, same sequence
    ideal = _ideal_depth(ideal_cap, 1, "front")
    stored = ideal_cap.depth(1, "front")
    assert np.array_equal(stored > 0, ideal > 0)
    assert np.abs(stored - ideal).max() <= DEPTH_SCALE / 2 + 1e-5
    real = real_cap.depth(1, "front")
    both = (real > 0) & (ideal > 0) & ~depth_discontinuities(ideal, 0.01)
    error = real[both] - ideal[both]
    near, far = ideal[both] < 0.6, (ideal[both] > 1.0) & (ideal[both] < 1.4)
    mad = [np.median(np.abs(error[sel])) for sel in (near, far)]
    assert mad[1] > 2.5 * mad[0] and mad[0] < 0.002
    # missing pixels concentrate at discontinuities
    edge = depth_discontinuities(ideal, 0.01)
    missing = (real == 0) & (ideal > 0)
    assert missing[edge].mean() > 20 * missing[~edge & (ideal > 0)].mean()


def test_same_seed_gives_identical_bytes(tmp_path):
    from dsr_bench.generators.capture import generate_capture

    def make(name: str, seed: int) -> dict[str, bytes]:
        path = generate_capture(tmp_path / name, name=name, seed=seed, steps=1, objects_per_scene=2,
                                image_shape=(120, 160))
        return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.glob("steps/*/*.png"))}

    a, b, c = make("a", 11), make("b", 11), make("c", 12)
    assert a == b and len(a) == 8
    assert a["steps/000/front_depth.png"] != c["steps/000/front_depth.png"]


def test_workers_write_the_same_captures_as_one_process(captures, tmp_path):
    """`generate-captures --workers 2` of two captures: the first is the one-process capture, byte for byte."""
    assert main(["generate-captures", "--out", str(tmp_path), *ARGS[:-1], "2", "--workers", "2"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq_0000", "seq_0001"]
    one = captures["realistic"]
    files = sorted(p.relative_to(one) for p in one.rglob("*") if p.is_file())
    assert len(files) > 8 and files == sorted(p.relative_to(tmp_path / "seq_0000")
                                              for p in (tmp_path / "seq_0000").rglob("*") if p.is_file())
    assert all((one / f).read_bytes() == (tmp_path / "seq_0000" / f).read_bytes() for f in files)
    assert (tmp_path / "seq_0001" / "truth.json").read_bytes() != (one / "truth.json").read_bytes()


def test_command_skips_existing_and_refuses_other_arguments(captures, capsys):
    out = captures["realistic"].parent
    before = (captures["realistic"] / "steps/000/front_depth.png").stat().st_mtime_ns
    assert main(["generate-captures", "--out", str(out), *ARGS]) == 0
    assert (captures["realistic"] / "steps/000/front_depth.png").stat().st_mtime_ns == before
    assert main(["generate-captures", "--out", str(out), *ARGS, "--noise", "none"]) == 2
    assert "--overwrite" in capsys.readouterr().err


@pytest.mark.parametrize("args, message", [
    (["-n", "0"], "--num-sequences 0"),
    (["--steps", "0"], "--steps 0"),
    (["--objects-per-scene", "9"], "--objects-per-scene 9"),
    (["--noise", "loud"], "--noise 'loud'"),
    (["--objects", "spheres"], "--objects 'spheres'"),
])
def test_command_bad_inputs_are_one_line_errors(tmp_path, capsys, args, message):
    assert main(["generate-captures", "--out", str(tmp_path / "c"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and message in err and "\n" not in err
    assert not (tmp_path / "c").exists()


# --- load_capture's validation -------------------------------------------------------------------------------


def _break_step(root: Path) -> str:
    (root / "steps/002/back_depth.png").unlink()
    return "steps/002/back_depth.png"


def _break_size(root: Path) -> str:
    from PIL import Image

    Image.fromarray(np.zeros((240, 320, 3), np.uint8)).save(root / "steps/001/front_color.png")
    return "front_color.png"


def _break_calibration(root: Path) -> str:
    calib = json.loads((root / "calibration.json").read_text())
    calib["back"]["extrinsics"][0][0] = 2.0  # not a rotation
    (root / "calibration.json").write_text(json.dumps(calib))
    return "calibration.json"


def _break_intrinsics(root: Path) -> str:
    calib = json.loads((root / "calibration.json").read_text())
    calib["front"]["intrinsics"] = [[500, 0], [0, 500]]
    (root / "calibration.json").write_text(json.dumps(calib))
    return "calibration.json"


def _break_json(root: Path) -> str:
    (root / "objects.json").write_text('{"objects": [')
    return "objects.json"


def _break_mesh(root: Path) -> str:
    (root / "meshes/1.ply").unlink()
    return "meshes/1.ply"


def _break_actions(root: Path) -> str:
    act = json.loads((root / "actions.json").read_text())
    act["actions"] = act["actions"][:1]
    (root / "actions.json").write_text(json.dumps(act))
    return "actions.json"


@pytest.mark.parametrize("breaker", [_break_step, _break_size, _break_calibration, _break_intrinsics, _break_json,
                                     _break_mesh, _break_actions])
def test_load_capture_errors_name_the_file_in_one_line(captures, tmp_path, breaker):
    root = tmp_path / "broken"
    shutil.copytree(captures["realistic"], root)
    load_capture(root)  # intact copy loads
    named = breaker(root)
    with pytest.raises(CaptureFormatError) as info:
        load_capture(root)
    message = str(info.value)
    assert named in message and "\n" not in message, message


def test_stored_mesh_digest_names_the_stored_mesh(captures):
    """PLY keeps float32 vertices: objects.json's mesh_sha256 is that of the mesh read back, the source's kept aside."""
    from dsr_bench.dataset.capture import load_capture
    from dsr_bench.dataset.manifest import mesh_sha256

    capture = load_capture(captures["realistic"])
    for i, obj in enumerate(capture.objects):
        assert obj.identity["mesh_sha256"] == mesh_sha256(*capture.mesh(i))
        assert len(obj.identity["source_mesh_sha256"]) == 64  # the generator's float64 mesh, kept for provenance


def test_prepare_captures_skips_refuses_overwrites_and_cleans_abandoned_temporaries(captures):
    import subprocess
    import sys

    from dsr_bench.atomic import host_name
    from dsr_bench.errors import UserError
    from dsr_bench.generators.capture import CapturePlan, prepare_captures

    out = captures["realistic"].parent
    plan = CapturePlan(out=out, num=2, steps=2, objects_per_scene=2, seed=3)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    abandoned = out / f".seq_0001.tmp-{host_name()}-{dead.pid}-00aa00aa"  # a killed writer's temporary directory
    (abandoned / "steps").mkdir(parents=True)
    jobs = prepare_captures(plan)
    assert jobs.skipped == ["seq_0000"] and [name for name, _ in jobs.todo] == ["seq_0001"]
    assert not abandoned.exists()
    with pytest.raises(UserError, match="seq_0000 exists with other arguments; pass --overwrite"):
        prepare_captures(CapturePlan(out=out, num=1, steps=2, objects_per_scene=2, seed=4))
    jobs = prepare_captures(CapturePlan(out=out, num=1, steps=2, objects_per_scene=2, seed=4, overwrite=True))
    assert jobs.skipped == [] and [name for name, _ in jobs.todo] == ["seq_0000"]
