"""`dsr-bench train`, resume and `dsr-bench predict --model dsr` end to end on a real dataset
directory (full grid, one optimisation step each: slow on a CPU, so kept to the minimum)."""

import json

import pytest

torch = pytest.importorskip("torch")

from dsr_bench.cli import main  # noqa: E402
from dsr_bench.testing import write_synthetic_dataset  # noqa: E402


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("train") / "data", num_sequences=2, num_steps=2,
                                   split="train")


def test_train_resume_predict_evaluate(data, tmp_path):
    run = tmp_path / "run"
    common = ["train", "--model", "dsr", "--stage", "cube-single", "--data", str(data), "--out", str(run),
              "--batch-size", "1", "--workers", "0"]
    assert main([*common, "--max-steps", "1"]) == 0
    first = torch.load(run / "last.pt", weights_only=True)
    assert first["step"] == 1 and first["batch_index"] == 1 and first["model_config"]["name"] == "dsr"
    assert main([*common, "--max-steps", "2", "--resume", str(run / "last.pt")]) == 0
    second = torch.load(run / "last.pt", weights_only=True)
    assert second["step"] == 2 and second["batch_index"] == 2  # continued at the data position
    log = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log if "loss" in r] == [1, 2]
    assert all(r["lr"] == 1e-3 and r["loss"] > 0 for r in log if "loss" in r)
    config = json.loads((run / "config.json").read_text())
    assert config["stage"]["betas"] == [0.9, 0.95] and config["stage"]["window"] == 1
    pred = tmp_path / "pred"
    assert main(["predict", "--model", "dsr", "--checkpoint", str(run / "last.pt"), "--data", str(data),
                 "--out", str(pred)]) == 0
    assert main(["evaluate", str(pred), "--data", str(data), "--out", str(tmp_path / "r.json")]) == 0
    results = json.loads((tmp_path / "r.json").read_text())
    assert 0 <= results["metrics"]["iou_unordered"] <= 1 and results["meta"]["name"] == "dsr"


def test_train_errors(data, tmp_path, capsys):
    assert main(["train", "--model", "dsr", "--stage", "cube-multi", "--data", str(data), "--out", str(tmp_path / "r")]) == 2
    assert "fewer than the window 10" in capsys.readouterr().err
    assert main(["train", "--model", "gpt", "--stage", "cube-single", "--data", str(data), "--out", str(tmp_path / "r")]) == 2
    assert main(["train", "--stage", "warmup", "--data", str(data), "--out", str(tmp_path / "r")]) == 2
    assert "--stage 'warmup'" in capsys.readouterr().err
    assert main(["predict", "--model", "single", "--checkpoint", str(tmp_path / "missing.pt"), "--data", str(data),
                 "--out", str(tmp_path / "p")]) == 2
