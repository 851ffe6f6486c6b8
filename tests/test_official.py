"""The official release layout: a fixture built from its published schema, the validated reader, and
`dsr-bench import-official` round trips every value."""

import os
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest

from dsr_bench.atomic import host_name
from dsr_bench.cli import main
from dsr_bench.errors import UserError
from dsr_bench.dataset.manifest import load_manifest
from dsr_bench.dataset.official import (OFFICIAL_NEXT, OFFICIAL_STEP, find_official_sequences, import_official,
                                        official_arrays)
from dsr_bench.dataset.sequence import SequenceReader
from dsr_bench.testing import write_synthetic_dataset
from dsr_bench.dataset.validate import validate_dataset

STEPS = 2


def _official_step(rng, t, positions, orientations):
    """One step's datasets with the published shapes and dtypes (static objects, so flow is 0)."""
    data = {}
    for name, (shape, dtype) in OFFICIAL_STEP.items():
        shape = tuple(4 if s is None else s for s in shape)
        if name in ("color_image", "depth_image"):  # large: low-entropy values keep the fixture fast
            data[name] = np.full(shape, 0.75 if dtype == "float32" else 7 + t, dtype)
            data[name][..., :5] = rng.integers(0, 200, data[name][..., :5].shape)
        elif dtype == "uint8":
            data[name] = rng.integers(0, 256, shape).astype(np.uint8)
        elif name == "mask_3d":
            data[name] = rng.integers(0, 5, shape).astype(np.int64)
        elif name == "mask_2d":
            data[name] = rng.integers(0, 5, shape).astype(np.float64)
        elif name == "tsdf":
            data[name] = rng.uniform(-1, 1, shape).astype(np.float32)
        elif name in ("depth_image", "depth_image_small"):
            data[name] = rng.uniform(0.5, 1.0, shape).astype(np.float32)
        elif name == "scene_flow_3d":
            data[name] = np.zeros(shape)  # integer-valued in the release; static objects here
        else:
            data[name] = rng.uniform(-1, 1, shape).astype(dtype)
    data["action"] = np.array([t % 8, 10 + t, 100 - t], np.int64)
    data["positions"], data["orientations"] = positions, orientations
    return data


def write_official_fixture(root, ids=("0", "1", "7"), seed=0, change=None):
    """A tiny official-layout dataset (STEPS step files per id, train.txt, test.txt); returns the
    arrays written, truth[id][step][name]. `change(data)` may alter each step's arrays before writing."""
    rng = np.random.default_rng(seed)
    truth = {}
    for seq_id in ids:
        positions = rng.uniform(0.3, 0.7, (4, 3))
        q = rng.normal(size=(4, 4))
        orientations = q / np.linalg.norm(q, axis=1, keepdims=True)
        truth[seq_id] = []
        for t in range(STEPS):
            data = _official_step(rng, t, positions, orientations)
            if change is not None:
                change(data)
            with h5py.File(root / f"{seq_id}_{t}.hdf5", "w") as f:
                for name, value in data.items():
                    f.create_dataset(name, data=value, compression="gzip", compression_opts=4)
                if t == STEPS - 1:
                    nxt = _official_step(rng, t + 1, positions, orientations)
                    if change is not None:
                        change(nxt)
                    for name in OFFICIAL_NEXT:
                        f.create_dataset(f"next/{name}", data=nxt[name])
                        data[f"next/{name}"] = nxt[name]
            truth[seq_id].append(data)
    test = list(ids[1:2])  # ("0", "1", "7"): train 0, 7; test 1
    (root / "train.txt").write_text("".join(f"{i}\n" for i in ids if i not in test))
    (root / "test.txt").write_text("".join(f"{i}\n" for i in test))
    return truth


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    src = tmp_path_factory.mktemp("official")
    truth = write_official_fixture(src)
    dst = tmp_path_factory.mktemp("ours") / "data"
    assert main(["import-official", str(src), str(dst)]) == 0
    return src, dst, truth


def test_import_round_trips_every_value(imported):
    _, dst, truth = imported
    for seq_id, name in (("0", "seq_0000"), ("1", "seq_0001"), ("7", "seq_0007")):
        with SequenceReader(dst / f"{name}.h5") as seq:
            assert seq.num_steps == STEPS and seq.attrs["source"] == "official-import"
            for t in range(STEPS):
                rebuilt = official_arrays(seq, t)
                for key, value in truth[seq_id][t].items():
                    assert rebuilt[key].dtype == value.dtype, (key, rebuilt[key].dtype)
                    assert np.array_equal(rebuilt[key], value), key


def test_both_readers_agree_bit_for_bit(imported):
    src, dst, _ = imported
    official = find_official_sequences(src)
    with SequenceReader(dst / "seq_0007.h5") as seq:
        for t in range(STEPS):
            ours, theirs = official_arrays(seq, t), official["7"].read_step(t)
            assert sorted(ours) == sorted(theirs)
            for key in theirs:
                assert ours[key].dtype == theirs[key].dtype and np.array_equal(ours[key], theirs[key]), key
        assert np.array_equal(official["7"].read(STEPS - 1, "next/mask_3d"), seq.read("mask_3d", STEPS))


def test_conventions_of_the_converted_fields(imported):
    _, dst, truth = imported
    with SequenceReader(dst / "seq_0000.h5") as seq:
        step0 = truth["0"][0]
        assert seq.read("mask_3d").dtype == np.uint8
        assert np.array_equal(seq.read("mask_3d", 0), step0["mask_3d"])
        assert seq.read("scene_flow_3d").shape == (STEPS, 3, 128, 128, 48)  # components first
        points = np.moveaxis(step0["pts_small"], 0, -1).astype(np.float32)
        assert np.array_equal(seq.read("cameras/front/points", 0), points)
        poses = seq.read("object_poses", 0)
        assert np.array_equal(poses[:, :3], step0["positions"]) and np.array_equal(poses[:, 3:], step0["orientations"])
        assert seq.read("tsdf").shape == (STEPS + 1, 128, 128, 48)  # the final TSDF is integrated on import
        assert "visible_fraction" not in seq and "policy/chosen_object" not in seq


def test_splits_manifest_and_validation(imported):
    _, dst, _ = imported
    assert (dst / "splits" / "train.txt").read_text().split() == ["seq_0000", "seq_0007"]
    assert (dst / "splits" / "test.txt").read_text().split() == ["seq_0001"]
    problems, count = validate_dataset(dst, check_gt=False)
    assert problems == [] and count == 3


def test_reader_errors(tmp_path):
    with pytest.raises(UserError, match="no <seq>_<step>.hdf5"):
        find_official_sequences(tmp_path)
    write_official_fixture(tmp_path, ids=("3",))
    (tmp_path / "3_0.hdf5").rename(tmp_path / "kept.h5")
    with pytest.raises(UserError, match=r"lacks step files \[0\]"):
        find_official_sequences(tmp_path)
    (tmp_path / "kept.h5").rename(tmp_path / "3_0.hdf5")
    (tmp_path / "3_1.hdf5").rename(tmp_path / "last.h5")  # the final step lost: 3_0 has no 'next'
    with pytest.raises(UserError, match="3_0.hdf5: the last step file of sequence 3 has no 'next' group"):
        find_official_sequences(tmp_path)
    (tmp_path / "last.h5").rename(tmp_path / "3_1.hdf5")
    seq = find_official_sequences(tmp_path)["3"]
    with h5py.File(tmp_path / "3_0.hdf5", "r+") as f:
        del f["tsdf"]
    with pytest.raises(UserError, match="3_0.hdf5: missing dataset 'tsdf'"):
        seq.read_step(0)
    with h5py.File(tmp_path / "3_1.hdf5", "r+") as f:
        del f["next/mask_3d"]
    with pytest.raises(UserError, match="missing dataset 'next/mask_3d'"):
        seq.read_step(1)
    (tmp_path / "3_1.hdf5").write_bytes(b"garbage")
    with pytest.raises(UserError, match="3_1.hdf5: unreadable HDF5 file"):
        find_official_sequences(tmp_path)


def test_other_dtypes_and_inexact_values_survive(tmp_path):
    """float32 heightmaps, float64 TSDFs with values float32 cannot hold and int32 masks round-trip
    through official/ or exact casts, keeping the release's dtypes."""
    def change(data):
        data["depth_heightmap"] = data["depth_heightmap"].astype(np.float32)
        data["mask_3d"] = data["mask_3d"].astype(np.int32)
        if "tsdf" in data:
            data["tsdf"] = data["tsdf"].astype(np.float64) + 1e-12

    src, dst = tmp_path / "src", tmp_path / "dst"
    src.mkdir()
    truth = write_official_fixture(src, ids=("5",), change=change)
    import_official(src, dst)
    with SequenceReader(dst / "seq_0005.h5") as seq:
        assert "official/tsdf" in seq and "official/depth_heightmap" not in seq  # float32 holds it exactly
        for t in range(STEPS):
            rebuilt = official_arrays(seq, t)
            for key, value in truth["5"][t].items():
                assert rebuilt[key].dtype == value.dtype and np.array_equal(rebuilt[key], value), key


@pytest.mark.parametrize("change, match", [
    (lambda d: d.__setitem__("scene_flow_3d", d["scene_flow_3d"] + 0.1), "float32 cannot represent exactly"),
    (lambda d: d["mask_3d"].__setitem__((0, 0, 0), 300), r"mask_3d ids in 0..300"),
])
def test_import_refuses_what_cannot_be_held(tmp_path, change, match):
    def alter(data):
        if "scene_flow_3d" in data:
            change(data)
    write_official_fixture(tmp_path, ids=("2",), change=alter)
    with pytest.raises(UserError, match=match):
        import_official(tmp_path, tmp_path / "out")
    assert not list((tmp_path / "out").glob("*.h5")) if (tmp_path / "out").exists() else True


def test_split_resume_parallel_and_foreign_destination(imported, tmp_path, capsys):
    src, full, _ = imported
    only_test = tmp_path / "only_test"
    assert main(["import-official", str(src), str(only_test), "--split", "test"]) == 0
    assert sorted(p.name for p in only_test.glob("*.h5")) == ["seq_0001.h5"]
    assert sorted(load_manifest(only_test)["splits"]) == ["test"]
    # resume an interrupted import: two files lost, a killed writer's partial file left (removed: its pid is
    # gone), a live writer's temporary kept (`dsr_bench.atomic.clean_temporaries`); redo them with 2 workers
    dst = tmp_path / "resumed"
    shutil.copytree(full, dst)
    (dst / "seq_0000.h5").unlink()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (dst / "seq_0007.h5").rename(dst / f".seq_0007.h5.tmp-{host_name()}-{dead.pid}-00aa00aa")
    live = dst / f".seq_0009.h5.tmp-{host_name()}-{os.getpid()}-00bb00bb"
    live.write_bytes(b"being written")
    before = (dst / "seq_0001.h5").stat().st_mtime_ns
    done = []
    assert import_official(src, dst, workers=2, progress=done.append) == ["seq_0000", "seq_0001", "seq_0007"]
    assert sorted(done) == ["seq_0000", "seq_0007"] and (dst / "seq_0001.h5").stat().st_mtime_ns == before
    assert list(dst.glob(".*tmp*")) == [live]
    live.unlink()

    # the resumed import holds exactly the uninterrupted one's content and records; the files' bytes are not
    # compared (a full-suite run once saw seq_0007's bytes differ with identical arrays and attributes)
    def records(manifest):
        return {**manifest, "toolkit_version": "", "sequences": [{k: v for k, v in e.items() if k != "sha256"}
                                                                  for e in manifest["sequences"]]}
    assert records(load_manifest(dst)) == records(load_manifest(full))
    for name in ("seq_0000", "seq_0007"):
        with SequenceReader(dst / f"{name}.h5") as a, SequenceReader(full / f"{name}.h5") as b:
            assert a.attrs.keys() == b.attrs.keys()
            assert all(np.array_equal(a.attrs[k], b.attrs[k]) for k in a.attrs if k != "toolkit_version")
    with pytest.raises(UserError, match="not found; the official release lists its splits"):
        import_official(src, dst, split="val")
    other = tmp_path / "other"
    write_synthetic_dataset(other, num_sequences=1, num_steps=1)
    with pytest.raises(UserError, match="already holds seq_0000.h5, which is not an import"):
        import_official(src, other)


def test_wrong_shape_and_dtype_are_named(tmp_path):
    write_official_fixture(tmp_path, ids=("3",))
    seq = find_official_sequences(tmp_path)["3"]
    with h5py.File(tmp_path / "3_0.hdf5", "r+") as f:
        del f["tsdf"]
        f["tsdf"] = np.zeros((128, 128, 40), np.float32)
        del f["color_image_small"]
        f["color_image_small"] = np.zeros((240, 320, 3), np.float32)
    with pytest.raises(UserError, match=r"3_0.hdf5: tsdf has shape \(128, 128, 40\), expected \(128, 128, 48\)"):
        seq.read_step(0)
    with pytest.raises(UserError, match="color_image_small has dtype float32, expected uint8"):
        seq.read(0, "color_image_small")
    assert seq.read(1, "tsdf").shape == (128, 128, 48)
    with pytest.raises(UserError, match="step 5 outside 0..1"):
        seq.read(5, "tsdf")


def test_import_cli_errors(tmp_path, capsys):
    assert main(["import-official", str(tmp_path / "missing"), str(tmp_path / "out")]) == 2
    assert "official data directory not found" in capsys.readouterr().err


# --- flow by the release's own definition ------------------------------------------------------------
def _yaw(angle_deg, axis=(0.0, 0.0, 1.0)):
    """Quaternion (x, y, z, w) of a turn about `axis`."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    half = np.radians(angle_deg) / 2
    return np.concatenate([axis * np.sin(half), [np.cos(half)]])


def _quat_mul(a, b):
    (ax, ay, az, aw), (bx, by, bz, bw) = a, b
    return np.array([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz])


#: Four boxes (half extents, metres), their first poses and, per push, (translation, turn) in the world.
#: Push 0 translates (object 2 also turns 15 degrees, object 3 stays); push 1 turns objects 1, 2 and 4.
MOVING_BOXES = [
    ((0.020, 0.014, 0.018), (0.40, -0.10, 0.05), 10, [((0.040, 0.0, 0.0), None),
                                                      ((0.0, 0.030, 0.0), (40, (0, 0, 1)))]),
    ((0.014, 0.020, 0.022), (0.60, -0.09, 0.05), 35, [((0.0, -0.020, 0.0), (15, (0, 0, 1))),
                                                      ((0.010, 0.0, 0.004), (25, (1, 0.3, 0)))]),
    ((0.018, 0.018, 0.018), (0.42, 0.11, 0.05), 60, [((0.0, 0.0, 0.0), None), ((0.0, 0.0, 0.0), None)]),
    ((0.012, 0.024, 0.015), (0.60, 0.10, 0.05), 80, [((0.012, 0.020, 0.0), None),
                                                     ((0.0, -0.010, 0.0), (-60, (0, 0, 1)))]),
]


def _official_voxels(points_world):
    """The release's rounded voxel coordinates (x, y, z) of world points: round((p - bound_min) / voxel)."""
    from dsr_bench.constants import GRID_BOUNDS, VOXEL_SIZE
    return np.round((points_world - GRID_BOUNDS[:, 0]) / VOXEL_SIZE).astype(np.int64)


def write_moving_official_fixture(root, seq_id="4", seed=3):
    """One official sequence (STEPS pushes) whose mask_3d and scene_flow_3d follow the authors' definition
    exactly: each box is a set of solid points (a half-voxel lattice in the box, jittered); mask_3d[t] holds
    object k at the rounded voxel coordinates of its points under pose t, and scene_flow_3d[t] there the
    difference of the rounded coordinates after and before push t, components (dy, dx, dz), as integers.
    The images are flat (depth 0.75 m) and the TSDF +1, so every other check of `validate` passes too."""
    from dsr_bench.constants import GRID_SHAPE
    from dsr_bench.geometry import quat_to_matrix

    rng = np.random.default_rng(seed)
    solids, positions, orientations = [], np.zeros((STEPS + 1, 4, 3)), np.zeros((STEPS + 1, 4, 4))
    for k, (half, start, yaw, pushes) in enumerate(MOVING_BOXES):
        axes = [np.arange(-h, h + 1e-9, 0.002) for h in half]
        lattice = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        solids.append(lattice + rng.uniform(-0.0005, 0.0005, lattice.shape))
        positions[0, k], orientations[0, k] = start, _yaw(yaw)
        for t, (shift, turn) in enumerate(pushes):
            positions[t + 1, k] = positions[t, k] + shift
            orientations[t + 1, k] = orientations[t, k] if turn is None else _quat_mul(_yaw(*turn), orientations[t, k])
    voxels = [[_official_voxels(solids[k] @ quat_to_matrix(orientations[s, k]).T + positions[s, k])
               for k in range(4)] for s in range(STEPS + 1)]
    masks, flows = np.zeros((STEPS + 1,) + GRID_SHAPE, np.int64), np.zeros((STEPS,) + GRID_SHAPE + (3,))
    for s in range(STEPS + 1):
        for k in range(4):
            old = voxels[s][k]
            masks[s][old[:, 1], old[:, 0], old[:, 2]] = k + 1  # volumes are (y, x, z)
            if s < STEPS:
                flows[s][old[:, 1], old[:, 0], old[:, 2]] = (voxels[s + 1][k] - old)[:, [1, 0, 2]]
    for t in range(STEPS):
        data = _official_step(rng, t, positions[t], orientations[t])
        data.update(mask_3d=masks[t], scene_flow_3d=flows[t], tsdf=np.ones(GRID_SHAPE, np.float32),
                    depth_image=np.full((960, 1280), 0.75, np.float32),
                    depth_image_small=np.full((240, 320), 0.75, np.float32))
        with h5py.File(root / f"{seq_id}_{t}.hdf5", "w") as f:
            for name, value in data.items():
                f.create_dataset(name, data=value, compression="gzip", compression_opts=4)
            if t == STEPS - 1:
                nxt = _official_step(rng, t + 1, positions[t + 1], orientations[t + 1])
                nxt.update(mask_3d=masks[t + 1], depth_image=np.full((960, 1280), 0.75, np.float32),
                           depth_image_small=np.full((240, 320), 0.75, np.float32))
                for name in OFFICIAL_NEXT:
                    f.create_dataset(f"next/{name}", data=nxt[name], compression="gzip", compression_opts=4)
    (root / "test.txt").write_text(f"{seq_id}\n")
    return masks, flows


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    src = tmp_path_factory.mktemp("official_moving")
    write_moving_official_fixture(src)
    dst = tmp_path_factory.mktemp("ours_moving") / "data"
    import_official(src, dst)
    return dst


def test_release_flow_passes_validate(moving, capsys):
    """The authors' rounded flow passes every check, including push 1, whose turns the check validate
    applied before (the rigid motion at voxel centres, within 1.001 voxels) rejects."""
    from dsr_bench.constants import GRID_BOUNDS, VOXEL_SIZE
    from dsr_bench.geometry import relative_motion, transform_points

    with SequenceReader(moving / "seq_0004.h5") as seq:
        flow, mask, poses = seq.read("scene_flow_3d"), seq.read("mask_3d"), seq.read("object_poses")
    assert np.array_equal(flow, np.rint(flow)) and np.abs(flow).max() >= 10
    idx = np.argwhere(mask[1] == 1)
    centres = GRID_BOUNDS[:, 0] + (idx[:, [1, 0, 2]] + 0.5) * VOXEL_SIZE
    old_check = (transform_points(relative_motion(poses[1, 0], poses[2, 0]), centres) - centres)[:, [1, 0, 2]]
    assert np.abs(flow[1][:, mask[1] == 1].T - old_check / VOXEL_SIZE).max() > 1.001
    problems, count = validate_dataset(moving, check_gt=True)
    assert problems == [] and count == 1
    assert main(["validate", str(moving)]) == 0
    assert "valid: 1 sequences" in capsys.readouterr().out


def _flip(flow, mask):
    flow[1] = -flow[1]


def _swap(flow, mask):
    flow[0, [0, 1]] = flow[0, [1, 0]]


def _wrong_object(flow, mask):  # push 0: object 1's motion written at object 3's voxels (object 3 stays)
    moved = np.rint(flow[0][:, mask[0] == 1].mean(axis=1))
    flow[0][:, mask[0] == 1] = 0
    flow[0][:, mask[0] == 3] = moved[:, None]


def _fraction(flow, mask):
    y, x, z = np.argwhere(mask[1] == 2)[0]
    flow[1, 1, y, x, z] += 0.5


@pytest.mark.parametrize("corrupt, expected", [
    (_flip, ["scene_flow_3d[1]: object 1: ", "it matches with the sign flipped"]),
    (_swap, ["scene_flow_3d[0]: object 1: ", "it matches with dy and dx swapped"]),
    (_wrong_object, ["scene_flow_3d[0]: object 3: ", "it matches object 1's motion (flow of the wrong object?)",
                     "scene_flow_3d[0]: object 1: "]),
    (_fraction, ["scene_flow_3d[1]: 1 voxels hold non-integer flow (e.g. dx = ", "so integer-valued"]),
])
def test_corrupted_release_flow_is_caught(moving, tmp_path, corrupt, expected):
    data = tmp_path / "data"
    shutil.copytree(moving, data)
    with h5py.File(data / "seq_0004.h5", "r+") as f:
        flow, mask = f["scene_flow_3d"][()], f["mask_3d"][()]
        corrupt(flow, mask)
        f["scene_flow_3d"][...] = flow
    problems, _ = validate_dataset(data, check_gt=True)
    found = [p.message for p in problems if p.where == "seq_0004" and p.message.startswith("scene_flow_3d")]
    for text in expected:
        assert any(text in m for m in found), (text, found)
    if corrupt is _fraction:  # within the rounding bound: only the integer check can see it
        assert len(found) == 1
