"""scripts/reduced_grid_ablation.py: the downsampling to a coarse grid and one tiny run end to end."""

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dsr_bench.dataset.sequence import SequenceReader  # noqa: E402
from dsr_bench.testing import write_synthetic_dataset  # noqa: E402

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "reduced_grid_ablation.py"


@pytest.fixture(scope="module")
def ablation():
    spec = importlib.util.spec_from_file_location("reduced_grid_ablation", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_downsample_blocks_centres_and_units(ablation, tmp_path):
    data = write_synthetic_dataset(tmp_path / "d", num_sequences=1, num_steps=2, num_objects=2)
    q = ablation.downsample(data / "seq_0000.h5", (4, 4, 3))
    with SequenceReader(data / "seq_0000.h5") as seq:
        tsdf, mask = seq.read("tsdf")[:2], seq.read("mask_3d")[:2]
        flow, action = seq.read("scene_flow_3d")[:2], seq.read("action")[:2]
    assert q["tsdf"].shape == (2, 32, 32, 16) and q["mask"].shape == (2, 32, 32, 16) and q["mask"].dtype == np.uint8
    assert q["flow"].shape == (2, 3, 32, 32, 16) and q["num_objects"] == 2
    block_mean = tsdf.reshape(2, 32, 4, 32, 4, 16, 3).mean((2, 4, 6))
    assert np.allclose(q["tsdf"], block_mean, atol=1e-6)
    assert np.array_equal(q["mask"], mask[:, 2::4, 2::4, 1::3])
    assert np.allclose(q["flow"][:, 0], flow[:, 0, 2::4, 2::4, 1::3] / 4)  # dy in coarse voxels
    assert np.allclose(q["flow"][:, 2], flow[:, 2, 2::4, 2::4, 1::3] / 3)  # dz
    assert q["mask"].any() and np.abs(q["flow"]).sum() > 0
    assert np.array_equal(q["action"], np.stack([action[:, 0], action[:, 1] // 4, action[:, 2] // 4], 1))


def test_a_tiny_run_writes_its_summary(tmp_path, monkeypatch):
    data = write_synthetic_dataset(tmp_path / "d", num_sequences=2, num_steps=10, num_objects=2)
    out = tmp_path / "ablation.json"
    monkeypatch.setattr(sys, "argv", ["reduced_grid_ablation.py", "--train-data", str(data), "--test-data", str(data),
                                      "--factor", "8", "8", "3", "--batch-size", "2", "--steps-single", "1",
                                      "--steps-multi", "1", "--models", "dsr", "single", "--history-variants",
                                      "--out", str(out)])
    spec = importlib.util.spec_from_file_location("reduced_grid_ablation_main", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main()
    summary = json.loads(out.read_text())
    assert summary["grid"] == [16, 16, 16] and summary["ordering_holds"] is None and summary["zero_motion_mse"] > 0
    assert summary["models"]["dsr"]["stage_multi"]["window"] == 10
    assert summary["models"]["single"]["stage_multi"] == {**summary["models"]["single"]["stage_multi"], "window": 1,
                                                          "batches": 10, "sample_steps": 20}
    for name in ("dsr", "single"):
        scores = summary["models"][name]
        # both in [0, 1]; ordered is not bounded by unordered: the mean runs over the matched non-empty pairs,
        # so a sequence-wide matching can count fewer pairs at a step than that step's best-sum matching
        assert 0 <= scores["iou_ordered"] <= 1 and 0 <= scores["iou_unordered"] <= 1
    # DSR-Net's weights also scored with its history zeroed and unwarped at test time; SingleStep has none
    assert set(summary["models"]) == {"dsr", "single", "dsr/test-history-none", "dsr/test-history-nowarp"}
    assert set(summary["paired_ordered_iou"]) == {"dsr-single", "dsr-dsr/test-history-none",
                                                  "dsr-dsr/test-history-nowarp"}
