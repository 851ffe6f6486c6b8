"""The real track's whole path on recordings librealsense itself wrote (tests/data/realsense): record -> import ->
annotate -> real split -> fine-tune -> evaluate, each step the command a lab runs. The recordings' scene (3 objects,
1 push) is known (truth.json), so step 0 is placed at its true poses and the annotator carries and snaps the rest;
the exported poses are checked against the truth before they become a split."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cv2")
pytest.importorskip("rosbags")
torch = pytest.importorskip("torch")

from dsr_bench.cli import main  # noqa: E402

DATA = Path(__file__).parent / "data" / "realsense"


def _place(truth: dict, out: Path) -> Path:
    """A `--place` file of step 0 at the recording's true poses (object -> table, 4 x 4)."""
    from dsr_bench.geometry import pose_to_matrix

    poses = np.asarray(truth["poses"][0])
    out.write_text(json.dumps({"objects": {str(k + 1): pose_to_matrix(p).tolist() for k, p in enumerate(poses)}}))
    return out


def test_librealsense_recordings_become_a_real_split_that_fine_tunes_and_scores(tmp_path, capsys):
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.models.predictors import shipped_weights

    exports = tmp_path / "exports"
    # three captures: the ROS1 recording (2.55.1), the ROS2 one (2.59.1) and the ROS1 one again as another capture
    for name, release in (("lab_0000", "v2.55.1"), ("lab_0001", "v2.59.1"), ("lab_0002", "v2.55.1")):
        folder = tmp_path / "recordings" / name
        shutil.copytree(DATA / release, folder)
        rig = json.loads((folder / "rig.json").read_text())
        (folder / "rig.json").write_text(json.dumps({**rig, "name": name}))  # the lab names each capture
        truth = json.loads((folder / "truth.json").read_text())
        assert main(["import-capture", str(folder), "--out", str(tmp_path / "captures" / name)]) == 0
        assert main(["annotate", name, "--captures", str(tmp_path / "captures"), "--work",
                     str(tmp_path / "work" / name), "--place", str(_place(truth, tmp_path / f"{name}.json")), "--auto",
                     "--export", str(exports / f"{name}.h5")]) == 0
        with SequenceReader(exports / f"{name}.h5") as seq:
            assert seq.attrs["source"] == "annotated"
            poses = seq.read("object_poses")
        error = np.abs(poses[..., :3] - np.asarray(truth["poses"])[..., :3]).max()
        assert error < 0.005, (name, error)  # every pose within 5 mm of the truth the recording was made from
    capsys.readouterr()

    real = tmp_path / "real"
    assert main(["real-split", str(exports), "--out", str(real), "--fine-tune", "2", "--test", "1", "--name",
                 "lab"]) == 0
    record = json.loads((real / "real_split.json").read_text())
    assert record["parts"] == {"finetune": "lab-finetune", "test": "lab-test"}
    assert main(["validate", str(real)]) == 0
    assert "lab-test" in capsys.readouterr().out

    tuned = tmp_path / "single-ft.pt"
    assert main(["train", "--finetune", "--track", "cpu", "--model", "single", "--init", str(shipped_weights("single")),
                 "--data", str(real), "--epochs", "1", "--batch-size", "2", "--out", str(tuned), "--quiet"]) == 0
    for name, checkpoint in (("zero-shot", []), ("ft", ["--checkpoint", str(tuned)])):
        predictions = tmp_path / f"predictions-{name}"
        assert main(["predict", "--model", "single", "--data", str(real), "--split", "lab-test", "--out",
                     str(predictions), *checkpoint]) == 0
        results = tmp_path / f"{name}.json"
        assert main(["evaluate", str(predictions), "--data", str(real), "--out", str(results)]) == 0
        scored = json.loads(results.read_text())
        assert scored["pinned"] and scored["real_split"]["name"] == "lab" and scored["split"] == "lab-test"
        assert scored["method"] == ("single-cpu-ft" if name == "ft" else "single-cpu")
        assert 0.0 <= scored["metrics"]["iou_ordered"] <= 1.0
