"""The official release layout: a fixture built from its published schema, the validated reader, and
`dsr-bench import-official` round trips every value."""

import h5py
import numpy as np
import pytest

from dsr_bench.cli import main
from dsr_bench.errors import UserError
from dsr_bench.official import OFFICIAL_NEXT, OFFICIAL_STEP, find_official_sequences, official_arrays
from dsr_bench.sequence import SequenceReader
from dsr_bench.validate import validate_dataset

STEPS = 3


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


def write_official_fixture(root, ids=("0", "1", "7"), seed=0):
    rng = np.random.default_rng(seed)
    truth = {}
    for seq_id in ids:
        positions = rng.uniform(0.3, 0.7, (4, 3))
        q = rng.normal(size=(4, 4))
        orientations = q / np.linalg.norm(q, axis=1, keepdims=True)
        truth[seq_id] = []
        for t in range(STEPS):
            data = _official_step(rng, t, positions, orientations)
            with h5py.File(root / f"{seq_id}_{t}.hdf5", "w") as f:
                for name, value in data.items():
                    f.create_dataset(name, data=value, compression="gzip", compression_opts=4)
                if t == STEPS - 1:
                    nxt = _official_step(rng, t + 1, positions, orientations)
                    for name in OFFICIAL_NEXT:
                        f.create_dataset(f"next/{name}", data=nxt[name])
                        data[f"next/{name}"] = nxt[name]
            truth[seq_id].append(data)
    (root / "train.txt").write_text("0\n7\n")
    (root / "test.txt").write_text("1\n")
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


def test_conventions_of_the_converted_fields(imported):
    _, dst, truth = imported
    with SequenceReader(dst / "seq_0000.h5") as seq:
        step0 = truth["0"][0]
        assert seq.read("mask_3d").dtype == np.uint8
        assert np.array_equal(seq.read("mask_3d", 0), step0["mask_3d"])
        assert seq.read("scene_flow_3d").shape == (STEPS, 3, 128, 128, 48)  # components first
        assert np.array_equal(seq.read("cameras/front/points", 0), np.moveaxis(step0["pts_small"], 0, -1).astype(np.float32))
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
    (tmp_path / "3_1.hdf5").unlink()
    with pytest.raises(UserError, match=r"lacks step files \[1\]"):
        find_official_sequences(tmp_path)
    with h5py.File(tmp_path / "3_1.hdf5", "w") as f:
        f["action"] = np.zeros(3, np.int64)
    seq = find_official_sequences(tmp_path)["3"]
    with pytest.raises(UserError, match="missing dataset 'tsdf'"):
        seq.read_step(1)
    with h5py.File(tmp_path / "3_2.hdf5", "r+") as f:
        del f["next"]
    with pytest.raises(UserError, match="no 'next' group"):
        seq.read_step(2)


def test_import_cli_errors(tmp_path, capsys):
    assert main(["import-official", str(tmp_path / "missing"), str(tmp_path / "out")]) == 2
    assert "official data directory not found" in capsys.readouterr().err
