"""scripts/train_gpu.py (`dsr-bench train --stage curriculum` with a budget, from the weights committed in
weights/gpu-track/) at toy size on the CPU, end to end: two runs of the full-grid DSR-Net (batch 1, 2 batches
each, on 2 two-push sequences), each resuming from the weights the previous one installed, with the held-out
evaluation, the curve and the summary; the committed file replaced in place, fp16."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from dsr_bench.dataset.manifest import build_manifest, file_sha256, write_manifest  # noqa: E402
from dsr_bench.errors import UserError  # noqa: E402
from dsr_bench.models.training.checkpoints import read_weights  # noqa: E402
from dsr_bench.models.training.config import TrainConfig  # noqa: E402
from dsr_bench.models.training.setup import resolve_stage  # noqa: E402
from dsr_bench.testing import write_synthetic_dataset, write_synthetic_sequence  # noqa: E402

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "train_gpu.py"
OUTPUTS = {"dsr.pt", "curve.json", "curve.png", "evaluation.json", "summary.json"}


def _script():
    spec = importlib.util.spec_from_file_location("train_gpu", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["train_gpu"] = module  # before running it: its dataclass looks its module up
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def script():
    return _script()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("gpu-training")
    train = write_synthetic_dataset(root / "train", num_sequences=2, num_steps=2, split="train")
    heldout = root / "heldout"  # another scene (seed 5) than the training ones (seeds 0, 1)
    write_synthetic_sequence(heldout / "seq_0000.h5", num_steps=2, seed=5)
    (heldout / "splits").mkdir()
    (heldout / "splits" / "heldout.txt").write_text("seq_0000\n")
    write_manifest(heldout, build_manifest(heldout))
    return train, heldout


def _run(script, data, out, committed, evidence, *extra):
    train, heldout = data
    return script.main(["--data", str(train), "--eval-data", str(heldout), "--out", str(out), "--models", "dsr",
                        "--device", "cpu", "--max-steps", "2", "--batch-size", "1", "--workers", "0",
                        "--bn-recalibration", "1", "--eval-workers", "1", "--committed", str(committed),
                        "--curve", str(evidence / "curve.json"), "--evidence", str(evidence), *extra])


def _fp16(weights) -> bool:
    floats = [v for v in weights["model"].values() if v.is_floating_point()]
    return bool(floats) and all(v.dtype == torch.float16 for v in floats)


@pytest.mark.slow
def test_two_runs_resume_from_the_committed_weights(script, data, tmp_path):
    committed, evidence = tmp_path / "committed", tmp_path / "evidence"
    first, second = tmp_path / "run1", tmp_path / "run2"

    # run 1: nothing committed, a new run of the curriculum's first stage
    assert _run(script, data, first, committed, evidence) == 0
    assert {p.name for p in first.iterdir()} == OUTPUTS
    w1 = read_weights(first / "dsr.pt", role="checkpoint")
    assert w1.version == 2 and w1.model_type == "dsr" and w1["stage"]["name"] == "cube-single"
    assert tuple(w1.config.grid) == (128, 128, 48) and _fp16(w1) and w1["optimizer"]["state"] == {}
    assert w1["stage"]["epoch_samples"] == 40_000  # the paper's epoch, whatever data travelled
    with pytest.raises(UserError, match="--epoch-samples 100: .* drop --epoch-samples to resume it"):
        resolve_stage(TrainConfig(model_name="dsr", stage_name="cube-single", data=data[0], out=tmp_path / "x",
                                  resume=first / "dsr.pt", epoch_samples=100))
    params = sum(v.numel() for v in w1["model"].values() if v.is_floating_point())
    assert (first / "dsr.pt").stat().st_size < 2.5 * params  # stored halved: 2 bytes a number and the header
    assert w1["step"] == 2 and w1["progress"]["steps"] == 2 and w1["progress"]["sample_steps"] == 2
    assert [r["run"] for r in w1["progress"]["runs"]] == [0]
    curve1 = json.loads((first / "curve.json").read_text())["models"]["dsr"]
    assert curve1["step"] == [1, 2] and curve1["sample_steps"] == [1, 2] and curve1["run"] == [0, 0]
    assert all(loss > 0 for loss in curve1["loss"]) and set(curve1["lr"]) == {1e-5}  # the stage's warm-up rate
    assert (first / "curve.png").read_bytes()[:4] == b"\x89PNG"
    summary1 = json.loads((first / "summary.json").read_text())
    dsr1 = summary1["models"]["dsr"]
    assert dsr1["resumed_from"] is None and dsr1["sample_steps_run"] == dsr1["sample_steps_total"] == 2
    assert dsr1["weights"]["sha256"] == file_sha256(first / "dsr.pt")
    assert summary1["torch"] == str(torch.__version__) and summary1["device"] and summary1["wall_seconds"] > 0
    assert "--max-steps 2" in summary1["command"] and summary1["command"].startswith("python")
    evaluation = json.loads((first / "evaluation.json").read_text())
    assert set(evaluation) == {"static", "dsr"} and evaluation["dsr"]["meta"]["name"] == "dsr"
    assert evaluation["dsr"]["coverage"]["scored"] == 1 and evaluation["dsr"]["split"] == "heldout"
    assert summary1["evaluation"]["metrics"]["dsr"] == {m: evaluation["dsr"]["metrics"][m] for m in script.METRICS}
    assert summary1["evaluation"]["paired"]["dsr - static"]["iou_unordered"]["n"] == 1

    assert script.main(["--install", str(first), "--committed", str(committed), "--evidence", str(evidence)]) == 0
    assert (committed / "dsr.pt").read_bytes() == (first / "dsr.pt").read_bytes()
    assert {p.name for p in evidence.iterdir()} == {"curve.json", "curve.png", "run-000.json"}

    # run 2: resumes the committed file; the step counter, data position and curve go on
    assert _run(script, data, second, committed, evidence) == 0
    w2 = read_weights(second / "dsr.pt", role="checkpoint")
    assert _fp16(w2) and w2["step"] == 4 and (w2["epoch"], w2["batch_index"]) == (0, 4)
    assert w2["progress"]["steps"] == 4 and w2["progress"]["sample_steps"] == 4
    assert w2["progress"]["runs"][0] == w1["progress"]["runs"][0] and w2["progress"]["runs"][1]["run"] == 1
    changed = [k for k, v in w1["model"].items() if v.is_floating_point() and not torch.equal(v, w2["model"][k])]
    assert any(k.endswith(".weight") for k in changed)  # trained on, not a copy
    summary2 = json.loads((second / "summary.json").read_text())["models"]["dsr"]
    assert summary2["resumed_from"] == {"file": "dsr.pt", "sha256": file_sha256(first / "dsr.pt"), "steps": 2,
                                        "sample_steps": 2}
    assert summary2["sample_steps_run"] == 2 and summary2["sample_steps_total"] == 4
    assert summary2["stages"] == [{"stage": "cube-single", "resumed": True, "steps": [2, 4], "epoch": 0,
                                   "epochs": 30, "sample_steps": 2}]
    curve2 = json.loads((second / "curve.json").read_text())["models"]["dsr"]
    assert curve2["step"] == [1, 2, 3, 4] and curve2["sample_steps"] == [1, 2, 3, 4] and curve2["run"] == [0, 0, 1, 1]
    assert curve2["loss"][:2] == curve1["loss"]

    assert script.main(["--install", str(second), "--committed", str(committed), "--evidence", str(evidence)]) == 0
    assert [p.name for p in committed.iterdir()] == ["dsr.pt"]  # replaced in place, not accumulated
    assert (committed / "dsr.pt").read_bytes() == (second / "dsr.pt").read_bytes()
    assert {p.name for p in evidence.iterdir()} == {"curve.json", "curve.png", "run-000.json", "run-001.json"}
    # a stale run (it does not continue the committed file) is refused and changes nothing
    assert script.main(["--install", str(first), "--committed", str(committed), "--evidence", str(evidence)]) == 1
    assert (committed / "dsr.pt").read_bytes() == (second / "dsr.pt").read_bytes()


@pytest.mark.slow
def test_a_stage_whose_epochs_are_done_hands_its_weights_to_the_next(script, tmp_path):
    """Toy curriculum: cube-single of 1 epoch of 4 sample-steps (the 2 single-step windows, twice), then cube-multi
    on windows of 2 from its weights, in one run of 5 batches; the file records the stage reached and the run's
    stages."""
    train = write_synthetic_dataset(tmp_path / "one", num_sequences=1, num_steps=2, split="train")
    out, committed, evidence = tmp_path / "out", tmp_path / "committed", tmp_path / "evidence"
    assert script.main(["--data", str(train), "--eval-data", str(train), "--out", str(out), "--models", "dsr",
                        "--device", "cpu", "--max-steps", "5", "--epochs", "1", "--epoch-samples", "4",
                        "--window", "2", "--batch-size", "1",
                        "--workers", "0", "--bn-recalibration", "1", "--eval-workers", "1",
                        "--committed", str(committed), "--curve", str(evidence / "curve.json")]) == 0
    weights = read_weights(out / "dsr.pt", role="checkpoint")
    assert weights["stage"]["name"] == "cube-multi" and weights["stage"]["window"] == 2 and weights["step"] == 1
    assert weights["progress"]["steps"] == 5 and weights["progress"]["sample_steps"] == 4 + 2
    assert weights["stage"]["epoch_samples"] == 4
    stages = json.loads((out / "summary.json").read_text())["models"]["dsr"]["stages"]
    assert [(s["stage"], s["resumed"], s["steps"], s["epoch"], s["epochs"]) for s in stages] == [
        ("cube-single", False, [0, 4], 1, 1), ("cube-multi", False, [0, 1], 0, 1)]
    curve = json.loads((out / "curve.json").read_text())["models"]["dsr"]
    assert curve["stage"] == ["cube-single"] * 4 + ["cube-multi"] and curve["sample_steps"] == [1, 2, 3, 4, 6]


def test_a_finished_stage_hands_on_to_the_next():
    from dsr_bench.models.training.curriculum import next_stage

    assert next_stage("dsr", None, 0) == ("cube-single", False)
    assert next_stage("dsr", {"name": "cube-single", "epochs": 30}, 7) == ("cube-single", True)
    assert next_stage("dsr", {"name": "cube-single", "epochs": 30}, 30) == ("cube-multi", False)
    assert next_stage("single", {"name": "cube-multi", "epochs": 20}, 20) == ("shapenet-multi", False)
    assert next_stage("dsr", {"name": "shapenet-multi", "epochs": 20}, 20) == (None, False)
    assert next_stage("dsr", {"name": "shapenet-multi", "epochs": 20}, 20, epochs=40) == ("shapenet-multi", True)
    assert next_stage("dsr", {"name": "cube-single", "epochs": 30}, 10, epochs=10) == ("cube-multi", False)


def test_the_committed_weights_live_beside_the_package():
    """The warm-up weights of the lent-GPU runs are in weights/gpu-track/ (with a README saying what they are), where
    the script finds them, and not in the package (nor in its package data)."""
    root = SCRIPT.parents[1]
    assert _script().COMMITTED == root / "weights" / "gpu-track"
    assert sorted(p.name for p in (root / "weights" / "gpu-track").iterdir()) == ["README.md", "dsr.pt", "single.pt"]
    assert not (root / "dsr_bench" / "models" / "weights" / "gpu-track").exists()
    assert "gpu-track" not in (root / "pyproject.toml").read_text()
    for model in ("dsr", "single"):
        weights = read_weights(root / "weights" / "gpu-track" / f"{model}.pt", role="checkpoint")
        assert weights.model_type == model and _fp16(weights) and weights["progress"]["runs"]


def test_bad_input_is_one_line_before_any_work(script, data, tmp_path, capsys):
    train, heldout = data
    base = ["--data", str(train), "--out", str(tmp_path / "out"), "--device", "cpu"]
    assert script.main(base) == 1
    assert capsys.readouterr().err.strip() == "error: --eval-data is needed (or --install OUT)"
    assert script.main([*base, "--eval-data", str(heldout), "--minutes", "1", "--eval-minutes", "2"]) == 1
    assert "--eval-minutes 2.0" in capsys.readouterr().err
    assert script.main([*base, "--eval-data", str(heldout), "--models", "2dflow"]) == 1
    assert "--model '2dflow'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
