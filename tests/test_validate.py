"""`dsr-bench validate`, `info` and `manifest` on synthetic datasets, intact and damaged."""

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from dsr_bench.cli import main
from dsr_bench.dataset.manifest import build_manifest, load_manifest, read_split, resolve_sequence, split_digest
from dsr_bench.dataset.schema import SEQUENCE_SCHEMA
from dsr_bench.testing import write_synthetic_dataset
from dsr_bench.dataset.checks import mask_warp_iou
from dsr_bench.dataset.validate import schema_markdown_table, validate_dataset, validate_sequence


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("ds") / "data", num_sequences=3, num_steps=2)


@pytest.fixture
def dataset(pristine, tmp_path):
    copy = tmp_path / "data"
    shutil.copytree(pristine, copy)
    return copy


def _messages(problems, where):
    return [p.message for p in problems if p.where == where]


def test_intact_dataset_is_valid(pristine, capsys):
    problems, count = validate_dataset(pristine)
    assert problems == [] and count == 3
    assert main(["validate", str(pristine), "--workers", "2"]) == 0
    assert "valid: 3 sequences" in capsys.readouterr().out


def test_every_problem_is_reported_at_once(dataset, capsys):
    with h5py.File(dataset / "seq_0000.h5", "r+") as f:  # tampered flow
        f["scene_flow_3d"][0, 0, 0, 0, 0] = 5.0
    with h5py.File(dataset / "seq_0001.h5", "r+") as f:  # id out of range
        f["mask_3d"][1, 0, 0, 0] = 9
    (dataset / "seq_0002.h5").unlink()  # missing
    shutil.copy(dataset / "seq_0000.h5", dataset / "seq_0099.h5")  # extra
    problems, _ = validate_dataset(dataset)
    text = "\n".join(f"{p.where}: {p.message}" for p in problems)
    assert "seq_0002: listed in the manifest but the file is missing" in text
    assert "seq_0099: file present but not in the manifest" in text
    assert any("SHA-256" in m for m in _messages(problems, "seq_0000"))
    assert any("scene_flow_3d[0]: 1 voxels outside every object have non-zero flow" in m
               for m in _messages(problems, "seq_0000"))
    assert any("scene_flow_3d[0]: differs from the rigid motion" in m for m in _messages(problems, "seq_0000"))
    assert "mask_3d: instance id 9 > num_objects 2" in _messages(problems, "seq_0001")
    assert any("names 'seq_0002', which has no file" in p.message for p in problems)
    assert main(["validate", str(dataset)]) == 1
    assert "problems in" in capsys.readouterr().out


def test_value_ranges_all_reported(dataset):
    path = dataset / "seq_0001.h5"
    with h5py.File(path, "r+") as f:
        f["tsdf"][0, 0, 0, 0] = 1.5
        f["object_poses"][1, 0, 3:] = [0.5, 0.5, 0.5, 0.1]
        f["action"][0, 0] = 9
        f["action"][1, 2] = 128
        f["visible_fraction"][0, 0] = 1.2
        f["push_end"][0, 0] = np.nan
    found = validate_sequence(path, check_gt=False)
    assert "tsdf: values in [-1, 1.5], expected [-1, 1]" in found
    assert any(m.startswith("object_poses: quaternion norms") for m in found)
    assert any(m.startswith("action: direction outside 0..7 (values ") and m.endswith("..9)") for m in found)
    assert "action: row/col outside 0..127" in found
    assert any(m.startswith("visible_fraction: values in [") and m.endswith(", 1.2], expected [0, 1]") for m in found)
    assert "push_end: 1 values are NaN or inf" in found


def test_ground_truth_checks(dataset):
    with h5py.File(dataset / "seq_0000.h5", "r+") as f:  # object 1 vanishes from the final amodal mask
        mask = f["mask_3d"][2]
        mask[mask == 1] = 0
        f["mask_3d"][2] = mask
    with h5py.File(dataset / "seq_0001.h5", "r+") as f:  # TSDF sign flipped: surfaces in free space
        f["tsdf"][1] = -f["tsdf"][1]
    problems, _ = validate_dataset(dataset)
    assert any(m.startswith("mask_3d[2]: object 1 overlaps its voxels at 1 moved by the flow with IoU 0.00")
               for m in _messages(problems, "seq_0000"))
    assert any(m.startswith("tsdf[1]: only") for m in _messages(problems, "seq_0001"))
    assert not any(m.startswith("tsdf[0]") for m in _messages(problems, "seq_0001"))
    # --no-gt skips them; the manifest's digests still catch the change
    fast, _ = validate_dataset(dataset, check_gt=False)
    assert not any("IoU" in p.message or "behind" in p.message for p in fast)
    assert any(m.startswith("ground_truth_sha256 differs from the manifest's") for m in _messages(fast, "seq_0000"))


def test_mask_warp_iou_tolerates_voxel_rounding_only():
    mask = np.zeros((20, 20, 10), np.uint8)
    mask[5:10, 5:10, 0:4] = 1
    flow = np.zeros((3,) + mask.shape, np.float32)
    flow[1][mask == 1] = 3.4  # moves 3.4 voxels along x
    moved = np.roll(mask, 3, axis=1)
    assert mask_warp_iou(mask, flow, moved, 1) == 1.0
    assert mask_warp_iou(mask, flow, np.roll(mask, 4, axis=1), 1) == 1.0  # off by one voxel: tolerated
    assert mask_warp_iou(mask, flow, np.roll(mask, 6, axis=1), 1) == pytest.approx(0.6)  # 3 of 5 columns match
    assert mask_warp_iou(mask, flow, moved, 2) is None
    assert mask_warp_iou(mask, flow, np.zeros_like(mask), 1) == 0.0


def test_truncated_file_is_a_problem_not_a_crash(dataset):
    path = dataset / "seq_0001.h5"
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    problems, _ = validate_dataset(dataset, check_gt=True)
    assert any("truncated" in m for m in _messages(problems, "seq_0001"))
    assert _messages(problems, "seq_0000") == []


def test_schema_attribute_and_format_problems(dataset):
    with h5py.File(dataset / "seq_0001.h5", "r+") as f:
        tsdf = f["tsdf"][()]
        del f["tsdf"]
        f["tsdf"] = tsdf.astype(np.float64)
        del f["heightmap"]
        del f.attrs["policy"]
        f["mask_3d"][0, 0, 0, 0] = 7  # ranges of the fields that are fine are still checked
    with h5py.File(dataset / "seq_0002.h5", "r+") as f:
        f.attrs["format"] = "something-else"
    problems, _ = validate_dataset(dataset, check_gt=False)
    found = _messages(problems, "seq_0001")
    assert "tsdf: dtype float64, expected float32" in found
    assert "missing dataset 'heightmap'" in found and "missing attribute 'policy'" in found
    assert "mask_3d: instance id 7 > num_objects 2" in found
    assert any("not a dsr-bench sequence" in m for m in _messages(problems, "seq_0002"))


def test_manifest_split_problems(dataset):
    manifest = json.loads((dataset / "manifest.json").read_text())
    manifest["splits"]["test"]["content_sha256"] = "0" * 64
    (dataset / "manifest.json").write_text(json.dumps(manifest))
    (dataset / "splits" / "extra.txt").write_text("seq_0000\n")
    problems, _ = validate_dataset(dataset, check_gt=False)
    assert "split checksum of 'test' in the manifest does not match its sequences' ground-truth digests" in _messages(
        problems, "splits/test.txt")
    assert any("not in the manifest" in m for m in _messages(problems, "splits/extra.txt"))


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
    assert split_digest(load_manifest(pristine), "test") in out  # the full checksum, to copy
    assert "synthetic: 3" in out  # sources
    assert read_split(pristine, None) == ("test", ["seq_0000", "seq_0001", "seq_0002"])
    assert resolve_sequence(pristine, "seq_0001") == pristine / "seq_0001.h5"
    assert main(["info", str(pristine / "nope")]) == 2
    assert "not found" in capsys.readouterr().err


def test_split_checksum_depends_on_the_ground_truth_only(pristine, dataset):
    with h5py.File(dataset / "seq_0000.h5", "r+") as f:
        f.attrs["observations_sha256"] = "0" * 64
    assert split_digest(build_manifest(dataset), "test") == split_digest(load_manifest(pristine), "test")
    with h5py.File(dataset / "seq_0000.h5", "r+") as f:
        f.attrs["ground_truth_sha256"] = "0" * 64
    assert split_digest(build_manifest(dataset), "test") != split_digest(load_manifest(pristine), "test")


def test_docs_carry_the_generated_schema_table():
    table = schema_markdown_table()
    assert table.count("\n") == 2 + len(SEQUENCE_SCHEMA)
    assert "| `cameras/<cam>/depth` | (T+1, H, W) | float32 |" in table
    assert table in (Path(__file__).resolve().parents[1] / "docs" / "format.md").read_text()


def test_generated_dataset_passes_every_check(generated_dataset):
    """The real generator's output (pybullet) is consistent by every ground-truth check."""
    problems, count = validate_dataset(generated_dataset, check_gt=True)
    assert problems == [] and count == 2


def test_own_flow_keeps_its_tight_tolerance(dataset):
    """Our flow is exact: a hundredth of a voxel off is reported (the official release's rounding bound
    applies only to files imported from it)."""
    with h5py.File(dataset / "seq_0000.h5", "r+") as f:
        y, x, z = np.argwhere(f["mask_3d"][0] == 1)[0]
        f["scene_flow_3d"][0, 1, y, x, z] += 0.01
    found = validate_sequence(dataset / "seq_0000.h5")
    assert any(m.startswith("scene_flow_3d[0]: differs from the rigid motion of the stored poses by 0.01 voxels "
                            "(tolerance 0.001)") for m in found), found


def _last_line(capsys):
    return capsys.readouterr().out.strip().splitlines()[-1]


def test_summary_says_why_validate_failed(pristine, dataset, tmp_path, capsys):
    # only dataset-level problems: every sequence file is fine, yet validate fails; the last line says why
    manifest = json.loads((dataset / "manifest.json").read_text())
    manifest["splits"]["test"]["content_sha256"] = "0" * 64
    (dataset / "manifest.json").write_text(json.dumps(manifest))
    (dataset / "splits" / "extra.txt").write_text("seq_0000\n")
    assert main(["validate", str(dataset), "--no-gt"]) == 1
    assert _last_line(capsys) == (
        "3 sequence files checked, 0 with problems; 2 dataset-level problems (splits/test.txt: split checksum of "
        "'test' in the manifest does not match its sequences' ground-truth digests; splits/extra.txt: split file not "
        "in the manifest (run `dsr-bench manifest DIR`))")
    # a file listed but missing is not a checked file with problems; a modified file is
    other = tmp_path / "other"
    shutil.copytree(pristine, other)
    (other / "seq_0002.h5").unlink()
    with h5py.File(other / "seq_0000.h5", "r+") as f:
        f["tsdf"][0, 0, 0, 0] = 0.5
    assert main(["validate", str(other), "--no-gt"]) == 1
    assert _last_line(capsys) == (
        "2 sequence files checked, 1 with problems; 2 dataset-level problems (seq_0002: listed in the manifest "
        "but the file is missing; splits/test.txt: names 'seq_0002', which has no file)")
    # only sequence problems: no dataset-level clause
    shutil.copy(pristine / "seq_0002.h5", other / "seq_0002.h5")
    assert main(["validate", str(other), "--no-gt"]) == 1
    assert _last_line(capsys) == "3 sequence files checked, 1 with problems"
    # nothing to check at all
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["validate", str(empty)]) == 1
    last = _last_line(capsys)
    assert last.startswith("0 sequence files checked, 0 with problems; 2 dataset-level problems (manifest.json: ")
    assert f"; dataset: no seq_*.h5 files in {empty})" in last
    # usage errors exit 2 with one line naming the reason
    assert main(["validate", str(tmp_path / "nope")]) == 2
    assert "error: dataset directory not found" in capsys.readouterr().err
    assert main(["validate", str(dataset), "--workers", "0"]) == 2
    assert "error: --workers 0: must be at least 1" in capsys.readouterr().err


def test_summary_names_the_first_dataset_level_problems():
    from dsr_bench.dataset.validate import Problem, summary_line

    problems = [Problem(f"splits/s{i}.txt", "split file not in the manifest") for i in range(5)]
    line = summary_line(problems, 0, "/nonexistent")
    assert line == ("0 sequence files checked, 0 with problems; 5 dataset-level problems (splits/s0.txt: split file "
                    "not in the manifest; splits/s1.txt: split file not in the manifest; splits/s2.txt: split file "
                    "not in the manifest; and 2 more above)")


def test_a_single_sequence_file_is_validated_alone(pristine, tmp_path, capsys):
    """`validate FILE.h5` (an annotator's export): what one file can prove, and it says that the split pins and a
    manifest need a dataset directory; its problems, a missing file and a folder of other .h5 files."""
    from dsr_bench.dataset.validate import validate_file

    path = pristine / "seq_0000.h5"
    assert main(["validate", str(path)]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert out.startswith(f"valid: {path} is a sequence of 2 pushes and 2 objects (source synthetic)")
    assert "ground truth consistent, digests match its arrays" in out
    assert "split pins" in out and "need a dataset directory" in out and "dsr-bench manifest DIR" in out
    copy = tmp_path / "export.h5"
    shutil.copy(path, copy)
    with h5py.File(copy, "r+") as f:
        f["mask_3d"][1, 0, 0, 0] = 9
    problems, about = validate_file(copy)
    assert "mask_3d: instance id 9 > num_objects 2" in problems and about["objects"] == 2
    assert any("digests do not match the arrays" in p for p in problems)  # its own digests, recomputed
    assert main(["validate", str(copy)]) == 1
    assert "instance id 9" in capsys.readouterr().out
    assert main(["validate", str(tmp_path / "missing.h5")]) == 2
    assert "missing.h5: no such file; give a sequence file (.h5) or a dataset directory" in capsys.readouterr().err
    folder = tmp_path / "real"  # a folder holding the export under another name: how to check it alone
    folder.mkdir()
    shutil.copy(path, folder / "out.h5")
    found, count = validate_dataset(folder)
    assert count == 0 and any("out.h5; check one alone with `dsr-bench validate FILE.h5`" in p.message for p in found)
