"""`dsr-bench validate` on the authors' own data: their 3D flow is a difference of rounded voxel coordinates of
each object's solid points moved by its poses, and the poses their files store were read at other instants
than the ones the flow was computed from.

tests/data/official_cube_flow.npz holds pushes recorded from the authors' unmodified generator
(columbia-ai-robotics/dsr, `sim_env.SimulationEnv`, object type cube, pybullet 3.2.7; numpy's removed `np.int`
aliased to `int`, the TSDF fusion not run) with the values its files store: per window `masks` (mask_3d, their
int64 ids as uint8), `flow_values` (scene_flow_3d, integer-valued, at the voxels of mask_3d > 0 in `np.argwhere`
order, `flow_counts` per push; zero elsewhere), `positions`, `orientations` and `actions` (the `action` of each
step file), and the poses the generator used for each push's flow and did not store (`used_old`, `used_new`:
position and quaternion (x, y, z, w), read before the push and after the robot went home). Window `a` is pushes
0..2 of one sequence, `b` pushes 4..6 of another; by their stored poses push 1 of each is off the rounding of a
moved point by 0.21 and 0.20 voxels (the check validate applied before rejected both: "up to 1.21 (allowance
1.00)" and "(allowance 1.02)").
"""

import math
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from dsr_bench.cli import main
from dsr_bench.constants import GRID_BOUNDS, GRID_SHAPE, VOXEL_SIZE
from dsr_bench.dataset.checks import OFFICIAL_POSE_DRIFT, official_motion, official_rotation, rounding_excess
from dsr_bench.dataset.official import OFFICIAL_NEXT, OFFICIAL_STEP, import_official
from dsr_bench.dataset.validate import validate_dataset
from dsr_bench.geometry import quat_to_matrix, rotation_angle

FIXTURE = Path(__file__).resolve().parent / "data" / "official_cube_flow.npz"
WINDOWS = {"a": "31", "b": "42"}  # window -> official sequence id


def _recorded(window: str) -> dict[str, np.ndarray]:
    with np.load(FIXTURE) as f:
        rec = {key.split("/", 1)[1]: f[key] for key in f.files if key.startswith(f"{window}/")}
    flows = np.zeros((len(rec["actions"]),) + GRID_SHAPE + (3,), np.float64)
    ends = np.cumsum(rec["flow_counts"])
    for t, (start, end) in enumerate(zip(ends - rec["flow_counts"], ends)):
        flows[t][tuple(np.argwhere(rec["masks"][t] > 0).T)] = rec["flow_values"][start:end]
    rec["flows"] = flows
    return rec


def _step_files(root: Path, seq_id: str, rec: dict[str, np.ndarray]) -> None:
    """The official step files of a recorded window: its masks, flow, poses and actions as the release stores
    them (int64 ids, float64 flow), flat images (depth 0.75 m) and a TSDF of +1 for the rest."""
    steps = len(rec["actions"])

    def observation(s: int) -> dict[str, np.ndarray]:
        data = {name: np.zeros(shape, dtype) for name, (shape, dtype) in OFFICIAL_STEP.items() if None not in shape}
        data["depth_image"][:] = 0.75
        data["depth_image_small"][:] = 0.75
        data["tsdf"][:] = 1.0
        data["mask_3d"] = rec["masks"][s].astype(np.int64)
        data["positions"], data["orientations"] = rec["positions"][s], rec["orientations"][s]
        return data

    for t in range(steps):
        data = observation(t)
        data["scene_flow_3d"] = rec["flows"][t]
        data["action"] = rec["actions"][t].astype(np.int64)
        with h5py.File(root / f"{seq_id}_{t}.hdf5", "w") as f:
            for name, value in data.items():
                f.create_dataset(name, data=value, compression="gzip", compression_opts=4)
            if t == steps - 1:
                final = observation(steps)
                for name in OFFICIAL_NEXT:
                    f.create_dataset(f"next/{name}", data=final[name], compression="gzip", compression_opts=4)


def _import(tmp: Path, change=None) -> Path:
    """The recorded windows in the official layout (after `change(seq_id, rec)`), imported; the dataset directory."""
    src, dst = tmp / "official", tmp / "ours"
    src.mkdir()
    for window, seq_id in WINDOWS.items():
        rec = _recorded(window)
        if change is not None:
            change(seq_id, rec)
        _step_files(src, seq_id, rec)
    (src / "test.txt").write_text("".join(f"{i}\n" for i in WINDOWS.values()))
    import_official(src, dst)
    return dst


@pytest.fixture(scope="module")
def imported(tmp_path_factory) -> Path:
    return _import(tmp_path_factory.mktemp("authors"))


def test_authors_flow_is_the_rounding_of_the_poses_they_used():
    """Every recorded flow voxel is round(c') - round(c) for a point c of the voxel moved by the poses the
    generator used, taken the authors' way (`official_motion`); by the stored poses it is off by up to
    OFFICIAL_POSE_DRIFT, which is why validate allows that much (no allowance would reject these files)."""
    worst_used, worst_stored = -1.0, -1.0
    for window in WINDOWS:
        rec = _recorded(window)
        stored = np.concatenate([rec["positions"], rec["orientations"]], -1)
        for t in range(len(rec["actions"])):
            for k in range(1, stored.shape[1] + 1):
                idx = np.argwhere(rec["masks"][t] == k)
                flow = rec["flows"][t][tuple(idx.T)]
                used = official_motion(rec["used_old"][t, k - 1], rec["used_new"][t, k - 1])
                worst_used = max(worst_used, rounding_excess(idx, flow, used).max())
                moved = official_motion(stored[t, k - 1], stored[t + 1, k - 1])
                worst_stored = max(worst_stored, rounding_excess(idx, flow, moved).max())
    assert worst_used <= 1e-6
    assert 0.2 < worst_stored < OFFICIAL_POSE_DRIFT


def test_authors_data_imported_validates(imported, capsys):
    problems, count = validate_dataset(imported, check_gt=True)
    assert problems == [] and count == len(WINDOWS)
    assert main(["validate", str(imported)]) == 0
    assert f"valid: {len(WINDOWS)} sequences" in capsys.readouterr().out


def _flow_plus_three(seq_id, rec):
    if seq_id == WINDOWS["a"]:
        y, x, z = np.argwhere(rec["masks"][1] == 2)[100]
        rec["flows"][1][y, x, z, 1] += 3  # dx


def _pose_plus_1cm(axis):
    def change(seq_id, rec):
        if seq_id == WINDOWS["b"]:
            rec["positions"][0, 2, axis] += 0.01  # object 3 at the first observation: only push 0 uses it
    return change


@pytest.mark.parametrize("change, where", [
    (_flow_plus_three, ("seq_0031", "scene_flow_3d[1]: object 2: 1 of ")),
    (_pose_plus_1cm(0), ("seq_0042", "scene_flow_3d[0]: object 3: ")),
    (_pose_plus_1cm(1), ("seq_0042", "scene_flow_3d[0]: object 3: ")),
    (_pose_plus_1cm(2), ("seq_0042", "scene_flow_3d[0]: object 3: ")),
], ids=["flow-voxel+3", "pose-x+1cm", "pose-y+1cm", "pose-z+1cm"])
def test_corruption_of_the_authors_data_is_reported(tmp_path, change, where):
    """The same data altered before the import (so its digests hold): one flow voxel +3 or one stored position
    moved 1 cm is one problem, naming the array, the push and the object."""
    problems, _ = validate_dataset(_import(tmp_path, change), check_gt=True)
    assert [(p.where, p.message[:len(where[1])]) for p in problems] == [where], problems
    assert "voxels off (allowance 0.5 " in problems[0].message and "matches" not in problems[0].message


def test_corruption_of_the_imported_file_is_reported(imported, tmp_path):
    """Altered after the import too: the flow problem is named beside the digests that no longer match."""
    data = tmp_path / "data"
    shutil.copytree(imported, data)
    with h5py.File(data / "seq_0042.h5", "r+") as f:
        y, x, z = np.argwhere(f["mask_3d"][2] == 1)[0]
        f["scene_flow_3d"][2, 2, y, x, z] -= 3
    problems, _ = validate_dataset(data, check_gt=True)
    found = [p.message for p in problems if p.where == "seq_0042" and p.message.startswith("scene_flow_3d")]
    assert len(found) == 1 and found[0].startswith("scene_flow_3d[2]: object 1: 1 of "), problems


# --- the definition, on its own --------------------------------------------------------------------------
def _quat(angle_deg, axis):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    half = math.radians(angle_deg) / 2
    return np.concatenate([axis * math.sin(half), [math.cos(half)]])


def test_rounding_excess_is_exact():
    """rounding_excess <= 0 for every flow some point of the voxel produces (checked on 100,000 points), and a
    flow it finds possible with 0.1 voxel to spare is produced by some point; for an unturned push it is
    |f - m| - 1 per component (two roundings of at most half a voxel)."""
    rng = np.random.default_rng(0)
    voxel = np.array([[60, 64, 20]])  # (y, x, z)
    centre = voxel[0, [1, 0, 2]]
    neighbours = np.stack(np.meshgrid(*[[-1, 0, 1]] * 3, indexing="ij"), -1).reshape(-1, 3)
    for trial in range(12):
        motion = np.eye(4)
        motion[:3, :3] = quat_to_matrix(_quat(rng.uniform(0, 180) if trial else 0.0, rng.normal(size=3)))
        motion[:3, 3] = rng.uniform(-0.02, 0.02, 3)
        c = centre + rng.uniform(-0.5, 0.5, (100_000, 3))
        moved = (((GRID_BOUNDS[:, 0] + c * VOXEL_SIZE) @ motion[:3, :3].T + motion[:3, 3] - GRID_BOUNDS[:, 0])
                 / VOXEL_SIZE)
        produced = np.unique(np.round(moved).astype(np.int64) - centre, axis=0)
        candidates = np.unique((produced[:, None] + neighbours).reshape(-1, 3), axis=0)
        excess = rounding_excess(np.repeat(voxel, len(candidates), 0), candidates[:, [1, 0, 2]].astype(float), motion)
        seen = {tuple(f) for f in produced}
        is_seen = np.array([tuple(f) in seen for f in candidates])
        assert excess[is_seen].max() <= 1e-9
        assert not np.any(~is_seen & (excess < -0.1)), candidates[~is_seen & (excess < -0.1)]
        assert excess[~is_seen].min() > -0.1 and np.any(excess[~is_seen] > 0)
        if trial == 0:
            m = (motion[:3, 3] / VOXEL_SIZE)
            assert np.allclose(excess, np.abs(candidates - m).max(axis=1) - 1)


def test_official_rotation_is_the_authors_euler_round_trip():
    """Away from a vertical pitch it is the quaternion's rotation; within 1e-5 of it (sin) the pitch becomes
    exactly +-90 degrees and roll 0, as pybullet's getEulerFromQuaternion gives them."""
    q = _quat(37, (0.3, -0.5, 0.8))
    assert np.allclose(official_rotation(q), quat_to_matrix(q), atol=1e-12)
    for sign in (1, -1):
        tilted = _quat(sign * 89.9, (0, 1, 0))  # a pitch 0.1 degree short of vertical: sin = 0.9999985
        rot = official_rotation(tilted)
        assert rot[2, 0] == -sign * 1.0 and rot[2, 1] == 0.0 and rot[2, 2] == pytest.approx(0.0, abs=1e-16)
        assert math.degrees(rotation_angle(rot @ quat_to_matrix(tilted).T)) == pytest.approx(0.1, abs=1e-6)
    p = pytest.importorskip("pybullet")
    rng = np.random.default_rng(1)
    for trial in range(400):
        if trial % 2:
            pitch = rng.choice([-1, 1]) * (math.pi / 2 - abs(rng.normal()) * 10 ** rng.uniform(-8, -1))
            q = np.array(p.getQuaternionFromEuler([rng.uniform(-3, 3), pitch, rng.uniform(-3, 3)]))
        else:
            q = rng.normal(size=4)
            q /= np.linalg.norm(q)
        roll, pitch, yaw = p.getEulerFromQuaternion(q)
        rx = np.array([[1, 0, 0], [0, math.cos(roll), -math.sin(roll)], [0, math.sin(roll), math.cos(roll)]])
        ry = np.array([[math.cos(pitch), 0, math.sin(pitch)], [0, 1, 0], [-math.sin(pitch), 0, math.cos(pitch)]])
        rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
        assert np.allclose(official_rotation(q), rz @ ry @ rx, atol=1e-12)
