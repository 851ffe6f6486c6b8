"""Fine-tuning on a real split (`dsr-bench train --finetune`, `dsr_bench.models.training.finetune`): the shipped
CPU-track weights fine-tuned on a real split's fine-tune part by the paper's rate, recorded in the weights, resumable
to the same bytes, scored as `NAME-ft` on the held-out part; the inputs it refuses, in one line each."""

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dsr_bench.cli import main  # noqa: E402
from dsr_bench.dataset.manifest import file_sha256  # noqa: E402
from dsr_bench.models.predictors import shipped_weights  # noqa: E402
from dsr_bench.models.training.checkpoints import read_weights  # noqa: E402
from dsr_bench.models.training.finetune import FinetuneRecipe, epoch_batches, partial_path  # noqa: E402
from test_real_split import real_split  # noqa: E402


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    """A real split of 5 synthetic annotated exports (2 pushes each): 2 to fine-tune on, 3 held out."""
    _, out = real_split(tmp_path_factory.mktemp("real"), count=5, finetune=2, test=3)
    return out


def _finetune(real, model: str, out, *extra: str) -> int:
    return main(["train", "--finetune", "--track", "cpu", "--model", model, "--init", str(shipped_weights(model)),
                 "--data", str(real), "--out", str(out), "--epochs", "2", "--batch-size", "2", "--quiet", *extra])


def _tensors(path) -> dict:
    return read_weights(path).state()


def test_the_papers_rate_halves_after_every_three_epochs_and_epochs_redraw_the_order():
    recipe = FinetuneRecipe("dsr", "dsr.pt", "0" * 64)
    assert (recipe.epochs, recipe.lr) == (20, 1e-4)
    assert [recipe.lr_at(e) for e in (0, 2, 3, 5, 6, 19)] == [1e-4, 1e-4, 5e-5, 5e-5, 2.5e-5, 1e-4 / 64]
    units = np.arange(10)[:, None].repeat(2, 1)
    first, again, other = (epoch_batches(units, 3, 0, e) for e in (0, 0, 1))
    assert [b.tolist() for b in first] == [b.tolist() for b in again]
    assert [b.tolist() for b in first] != [b.tolist() for b in other]
    assert [len(b) for b in first] == [3, 3, 4]  # a last batch of one joins the one before (BatchNorm)


def test_a_voxel_model_fine_tuned_on_the_real_split_is_recorded_and_scored_as_ft(real, tmp_path, capsys):
    init = shipped_weights("dsr")
    out = tmp_path / "dsr-ft.pt"
    assert _finetune(real, "dsr", out) == 0
    assert f"weights: {out}" in capsys.readouterr().out
    assert not partial_path(out).exists()
    weights = read_weights(out, model="dsr", role="weights")
    record = weights["finetune"]
    pins = json.loads((real / "real_split.json").read_text())["pins"]
    assert record["from"] == "dsr.pt" and record["from_sha256"] == file_sha256(init)
    assert record["real_split"] == {"name": "real", "part": "finetune", "checksum": pins["real-finetune"]["checksum"]}
    assert record["data"]["split"] == "real-finetune" and record["epochs"] == 2 and len(record["loss_per_epoch"]) == 2
    assert record["window"] == 2 and record["windows_per_epoch"] == 2  # 2 sequences, one window of their 2 pushes
    assert record["sample_steps"] == 2 * 2 * 2 and record["bn_recalibration_passes"] > 0
    assert weights.get("data") == read_weights(init).get("data")  # what it was trained on in simulation, kept
    before, after = _tensors(init), _tensors(out)
    assert before.keys() == after.keys()
    assert any(not torch.equal(before[k], after[k]) for k in before)  # it learned something

    predictions = tmp_path / "predictions"
    assert main(["predict", "--model", "dsr", "--checkpoint", str(out), "--data", str(real), "--split", "real-test",
                 "--out", str(predictions)]) == 0
    meta = json.loads((predictions / "meta.json").read_text())
    assert meta["name"] == "dsr-cpu-ft" and "fine-tuned from dsr.pt" in meta["description"]
    assert sorted(p.name for p in predictions.glob("*.h5")) == sorted(
        f"{s}.h5" for s in pins["real-test"]["sequences"])
    results = tmp_path / "results.json"
    assert main(["evaluate", str(predictions), "--data", str(real), "--out", str(results)]) == 0
    scored = json.loads(results.read_text())
    assert scored["method"] == "dsr-cpu-ft" and scored["pinned"] and scored["real_split"]["part"] == "test"


def test_a_stopped_fine_tuning_resumes_to_the_same_weights(real, tmp_path, capsys):
    whole, halves = tmp_path / "whole" / "single-ft.pt", tmp_path / "halves" / "single-ft.pt"
    assert _finetune(real, "single", whole) == 0
    assert _finetune(real, "single", halves, "--max-steps", "1") == 0
    assert "resumable checkpoint" in capsys.readouterr().out
    assert partial_path(halves).is_file() and not halves.exists()
    assert _finetune(real, "single", halves, "--max-steps", "1") == 0  # epoch 1's second batch
    assert _finetune(real, "single", halves) == 0
    assert not partial_path(halves).exists()
    a, b = _tensors(whole), _tensors(halves)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert read_weights(whole)["finetune"]["loss_per_epoch"] == read_weights(halves)["finetune"]["loss_per_epoch"]
    # a resumed run with other settings is refused, not mixed
    assert _finetune(real, "single", halves, "--max-steps", "1") == 0
    capsys.readouterr()
    assert _finetune(real, "single", halves, "--lr", "0.001") == 2
    assert "other settings" in capsys.readouterr().err


def test_an_image_model_fine_tunes_on_the_same_split(real, tmp_path):
    out = tmp_path / "2dflow-ft.pt"
    assert main(["train", "--finetune", "--model", "2dflow", "--init", str(shipped_weights("2dflow")), "--data",
                 str(real), "--out", str(out), "--epochs", "1", "--batch-size", "2", "--quiet"]) == 0
    record = read_weights(out, model="2dflow", role="weights")["finetune"]
    assert record["epochs"] == 1 and record["window"] == 1 and record["windows_per_epoch"] == 4  # 2 x 2 single steps
    assert record["real_split"]["name"] == "real"


@pytest.mark.parametrize("args, message", [
    (["--model", "dsr"], "--finetune needs --init"),
    (["--model", "dsr", "--init", "INIT:dsr", "--split", "real-test"], "held-out test part"),
    (["--model", "dsr", "--init", "INIT:dsr", "--multi-batches", "4"], "--multi-batches"),
    (["--model", "dsr", "--init", "INIT:dsr", "--track", "full"], "--finetune fine-tunes the CPU track"),
    (["--model", "dsr", "--init", "INIT:single"], "--init"),
    (["--model", "dsr", "--init", "missing.pt"], "missing.pt: not found"),
])
def test_fine_tuning_refuses_bad_inputs_in_one_line(real, tmp_path, capsys, args, message):
    args = [str(shipped_weights(a[5:])) if a.startswith("INIT:") else a for a in args]
    track = [] if "--track" in args else ["--track", "cpu"]
    code = main(["train", "--finetune", *track, *args, "--data", str(real), "--out", str(tmp_path / "ft.pt")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "ft.pt").exists()


def test_the_out_file_may_not_be_the_init(real, tmp_path, capsys):
    init = tmp_path / "dsr.pt"
    init.write_bytes(shipped_weights("dsr").read_bytes())
    assert main(["train", "--finetune", "--track", "cpu", "--model", "dsr", "--init", str(init), "--data", str(real),
                 "--out", str(init)]) == 2
    assert "is the --init file" in capsys.readouterr().err
    assert init.read_bytes() == shipped_weights("dsr").read_bytes()
