"""scripts/cpu_track_cap.py: the CPU track's ceiling, the ground truth pooled to the model grid and brought back,
written as predictions and scored by `evaluate`; with no pooling (factor 1) it is the ground truth itself."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import cpu_track_cap  # noqa: E402


def _metrics(path: Path) -> dict:
    return json.loads(path.read_text())["metrics"]


def test_the_ceiling_is_the_pooled_truth_scored_and_without_pooling_the_truth(generated_dataset, tmp_path, capsys):
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.models.coarse import pool_labels, unpool_mask

    assert cpu_track_cap.main(["--data", str(generated_dataset), "--work", str(tmp_path / "w4")]) == 0
    assert "mm grid's ceiling: motion_visible" in capsys.readouterr().out
    with SequenceReader(generated_dataset / "seq_0000.h5") as seq:
        truth = seq.read("mask_3d", slice(0, seq.num_steps))
    with h5py.File(tmp_path / "w4" / "oracle-pooled" / "seq_0000.h5", "r") as f:
        written = f["mask"][()]
    assert np.array_equal(written, unpool_mask(pool_labels(truth)))  # the round trip, on the benchmark's grid
    assert not np.array_equal(written, truth)  # 16 mm voxels lose detail: the ceiling is below the truth
    results = json.loads((tmp_path / "w4" / "oracle-pooled.json").read_text())
    assert results["meta"]["parameters"]["command"].startswith("python scripts/cpu_track_cap.py --data ")
    cap = results["metrics"]
    assert 0.3 < cap["iou_ordered"] < 1.0 and cap["iou_ordered"] == cap["iou_unordered"]  # slots are the objects
    assert cap["motion_visible"] > 0.0

    assert cpu_track_cap.main(["--data", str(generated_dataset), "--work", str(tmp_path / "w1"), "--factor", "1",
                               "--out", str(tmp_path / "truth.json")]) == 0
    exact = _metrics(tmp_path / "truth.json")
    assert (exact["iou_ordered"], exact["motion_visible"], exact["motion_full"]) == (1.0, 0.0, 0.0)


def test_a_split_that_is_not_there_is_one_line(generated_dataset, tmp_path, capsys):
    assert cpu_track_cap.main(["--data", str(generated_dataset), "--work", str(tmp_path), "--split", "nope"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: split 'nope' not found") and "\n" not in err
    assert not (tmp_path / "oracle-pooled").exists()
