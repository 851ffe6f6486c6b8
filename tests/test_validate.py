"""`dsr-bench validate`, `info` and `manifest` on synthetic datasets, intact and damaged."""

import shutil

import h5py
import numpy as np
import pytest

from dsr_bench.cli import main
from dsr_bench.manifest import build_manifest, load_manifest, read_split, resolve_sequence, split_digest
from dsr_bench.testing import write_synthetic_dataset
from dsr_bench.validate import validate_dataset


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("ds") / "data", num_sequences=3, num_steps=2)


@pytest.fixture
def dataset(pristine, tmp_path):
    copy = tmp_path / "data"
    shutil.copytree(pristine, copy)
    return copy


def test_intact_dataset_is_valid(pristine, capsys):
    problems, count = validate_dataset(pristine)
    assert problems == [] and count == 3
    assert main(["validate", str(pristine)]) == 0
    assert "valid: 3 sequences" in capsys.readouterr().out


def test_every_problem_is_reported_at_once(dataset, capsys):
    with h5py.File(dataset / "seq_0000.h5", "r+") as f:  # tampered flow
        f["scene_flow_3d"][0, 0, 0, 0, 0] = 5.0
    with h5py.File(dataset / "seq_0001.h5", "r+") as f:  # id out of range
        f["mask_3d"][1, 0, 0, 0] = 9
    (dataset / "seq_0002.h5").unlink()  # missing
    shutil.copy(dataset / "seq_0000.h5", dataset / "seq_0099.h5")  # extra
    problems, _ = validate_dataset(dataset)
    found = {(p.where, p.message.split(":")[0].split(" ")[0]) for p in problems}
    text = "\n".join(f"{p.where}: {p.message}" for p in problems)
    assert "seq_0002: listed in the manifest but the file is missing" in text
    assert "seq_0099: file present but not in the manifest" in text
    assert any(p.where == "seq_0000" and "SHA-256" in p.message for p in problems)
    assert any(p.where == "seq_0000" and "scene_flow_3d[0]" in p.message for p in problems)
    assert any(p.where == "seq_0001" and "instance id 9" in p.message for p in problems)
    assert any("names 'seq_0002', which has no file" in p.message for p in problems)
    assert len(found) >= 5
    assert main(["validate", str(dataset)]) == 1
    assert "problems in" in capsys.readouterr().out


def test_truncated_file_is_a_problem_not_a_crash(dataset):
    path = dataset / "seq_0001.h5"
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    problems, _ = validate_dataset(dataset, check_gt=False)
    assert any(p.where == "seq_0001" and ("unreadable" in p.message) for p in problems)


def test_wrong_dtype_and_digest(dataset):
    with h5py.File(dataset / "seq_0001.h5", "r+") as f:
        tsdf = f["tsdf"][()]
        del f["tsdf"]
        f["tsdf"] = tsdf.astype(np.float64)
    problems, _ = validate_dataset(dataset, check_gt=False)
    assert any("tsdf: dtype float64, expected float32" in p.message for p in problems)


def test_missing_manifest_and_rebuild(dataset, capsys):
    (dataset / "manifest.json").unlink()
    problems, _ = validate_dataset(dataset)
    assert any("dsr-bench manifest" in p.message for p in problems)
    assert main(["manifest", str(dataset)]) == 0
    assert validate_dataset(dataset)[0] == []
    manifest = load_manifest(dataset)
    assert manifest == build_manifest(dataset)
    assert len(split_digest(manifest, "test")) == 64


def test_info_and_split_helpers(pristine, capsys):
    assert main(["info", str(pristine)]) == 0
    out = capsys.readouterr().out
    assert "3 / 6" in out and "split test" in out
    assert read_split(pristine, None) == ("test", ["seq_0000", "seq_0001", "seq_0002"])
    assert resolve_sequence(pristine, "seq_0001") == pristine / "seq_0001.h5"
    assert main(["info", str(pristine / "nope")]) == 2
    assert "not found" in capsys.readouterr().err


def test_split_checksum_depends_on_content(pristine, dataset):
    with h5py.File(dataset / "seq_0000.h5", "r+") as f:
        f.attrs["content_sha256"] = "0" * 64
    assert split_digest(build_manifest(dataset), "test") != split_digest(load_manifest(pristine), "test")
