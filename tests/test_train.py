"""`dsr-bench train`, exact resume and `dsr-bench predict --model ...` end to end on a real dataset
directory (full 128 x 128 x 48 grid, batch 1, a couple of optimisation steps: kept to the minimum)."""

import gc
import json
import warnings

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dsr_bench.cli import main  # noqa: E402
from dsr_bench.testing import write_synthetic_dataset  # noqa: E402


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("train") / "data", num_sequences=2, num_steps=2,
                                   split="train")


def _train(data, out, *extra):
    return main(["train", "--model", "dsr", "--stage", "cube-single", "--data", str(data), "--out", str(out),
                 "--batch-size", "1", "--workers", "0", "--quiet", *extra])


def test_train_resume_exactly_predict_evaluate(data, tmp_path):
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    assert _train(data, straight, "--max-steps", "2") == 0
    assert _train(data, resumed, "--max-steps", "1") == 0
    first = torch.load(resumed / "last.pt", weights_only=True)
    assert first["step"] == 1 and first["batch_index"] == 1 and first["model_config"]["name"] == "dsr"
    assert first["model_config"]["grid"] == [128, 128, 48] and first["stage"]["name"] == "cube-single"
    assert (first["format"], first["model_type"], first["role"]) == ("dsr-bench-weights", "dsr", "checkpoint")
    assert first["data"]["dir"] == "data" and first["data"]["sequences"] == 2  # a name, never a local path
    assert _train(data, resumed, "--max-steps", "2", "--resume", str(resumed / "last.pt")) == 0
    a = torch.load(straight / "last.pt", weights_only=True)
    b = torch.load(resumed / "last.pt", weights_only=True)
    assert b["step"] == 2 and b["batch_index"] == 2  # continued at the data position
    for key, value in a["model"].items():  # same data order, optimizer and BatchNorm state: same weights
        assert torch.equal(value, b["model"][key]), key
    log = [json.loads(line) for line in (resumed / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log if "loss" in r] == [1, 2]
    assert all(r["lr"] == 1e-5 and r["loss"] > 0 and r["samples_per_s"] > 0 for r in log if "loss" in r)  # warm-up lr
    # the CLI recalibrates by default, at every end of the stage: at step 1, and after resuming at step 2
    assert [(r["step"], r["bn_recalibration"]["window"]) for r in log if "bn_recalibration" in r] == [(1, 2), (2, 2)]
    straight_log = [json.loads(line) for line in (straight / "metrics.jsonl").read_text().splitlines()]
    assert [r["loss"] for r in straight_log if "loss" in r] == [r["loss"] for r in log if "loss" in r]
    config = json.loads((resumed / "config.json").read_text())
    assert config["stage"]["betas"] == [0.9, 0.95] and config["stage"]["window"] == 1 and config["git"]
    pred = tmp_path / "pred"
    assert main(["predict", "--model", "dsr", "--checkpoint", str(straight / "last.pt"), "--data", str(data),
                 "--out", str(pred)]) == 0
    assert main(["evaluate", str(pred), "--data", str(data), "--out", str(tmp_path / "r.json")]) == 0
    results = json.loads((tmp_path / "r.json").read_text())
    assert 0 <= results["metrics"]["iou_unordered"] <= 1 and results["meta"]["name"] == "dsr"


def test_max_minutes_ends_the_stage_with_a_resumable_checkpoint(data, tmp_path):
    assert _train(data, tmp_path / "timed", "--max-minutes", "1e-9") == 0  # the budget is checked after each batch
    ckpt = torch.load(tmp_path / "timed" / "last.pt", weights_only=True)
    assert ckpt["step"] == 1 and ckpt["batch_index"] == 1


def test_the_stage_end_recalibrates_batchnorm_on_whole_sequences(data, tmp_path):
    """bn_recalibration = N: when the stage ends (here at max_steps), the running statistics are
    re-estimated on N batches of whole sequences with the state carried, then saved."""
    from dsr_bench.models.training.config import TrainConfig
    from dsr_bench.models.training.trainer import train

    out = tmp_path / "recalibrated"
    ckpt = train(TrainConfig(model_name="dsr", stage_name="cube-single", data=data, out=out, batch_size=1,
                             max_steps=1, workers=0, progress=False, bn_recalibration=2))
    state = torch.load(ckpt, weights_only=True)
    # 2 batches of one 2-push sequence: 4 forward passes, each counted once (a cumulative average)
    counts = {int(v) for k, v in state["model"].items() if k.endswith("num_batches_tracked")}
    assert counts == {4}
    log = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert log[-1] == {"step": 1, "bn_recalibration": {"window": 2, "batch_size": 1, "forward_passes": 4}}


def test_predictor_carries_the_state_as_in_training(data, tmp_path):
    from dsr_bench.models import DSRNet, ModelConfig
    from dsr_bench.models.inference import load_predictor
    from dsr_bench.models.warp import forward_warp
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.models.data import action_map
    from dsr_bench.models.training.checkpoints import save_checkpoint
    from dsr_bench.models.training.schedules import STAGES

    torch.manual_seed(0)
    cfg = ModelConfig.for_model("gtwarp")
    net = DSRNet(cfg)
    opt = torch.optim.Adam(net.parameters())
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda e: 1.0)
    ckpt = save_checkpoint(tmp_path / "g.pt", net, opt, sched, cfg, STAGES["cube-multi"], 0, 0, 0)
    predictor = load_predictor("gtwarp", ckpt, "cpu", fast=False)  # the eager network, bit for bit (the fast path's
    # agreement with it is tests/test_fast_inference.py's)
    assert predictor.name == "gtwarp" and predictor.num_slots == 4
    with SequenceReader(data / "seq_0000.h5") as seq:
        pred = predictor.predict_sequence(seq)
        tsdf, actions = seq.read("tsdf"), seq.read("action")
        flow, steps = seq.read("scene_flow_3d"), seq.num_steps
        gt_mask = seq.read("mask_3d")
    in_memory = predictor.predict_arrays(tsdf[:steps], actions[:steps], flow[:steps], gt_mask[:steps])
    assert all(np.array_equal(in_memory[key], pred[key]) for key in ("mask", "motion"))  # the same steps, from memory
    assert pred["mask"].shape == (steps, 128, 128, 48) and pred["mask"].dtype == np.uint8
    assert pred["motion"].shape == (steps, 3, 128, 128, 48) and pred["motion"].dtype == np.float32
    net.eval()  # BatchNorm in eval mode at evaluation
    maps = action_map(actions)
    with torch.no_grad():
        state = net.initial_state(1, "cpu")
        for t in range(steps):
            out = net(torch.from_numpy(tsdf[t:t + 1]), maps[t:t + 1], state)
            labels = out["mask"].argmax(1)[0]
            expected = torch.where(labels == 4, 0, labels + 1).numpy()  # background (last) -> 0, slot k -> k + 1
            assert np.array_equal(pred["mask"][t], expected)
            assert np.allclose(pred["motion"][t], out["motion"][0].numpy(), atol=1e-5)
            fg = out["mask"][:, :-1].sum(1)
            state = forward_warp(out["representation"], torch.from_numpy(flow[t:t + 1]).float(), fg)
    with pytest.raises(Exception, match="holds a 'gtwarp' model"):
        load_predictor("dsr", ckpt, "cpu")


def test_train_errors(data, tmp_path, capsys):
    out = str(tmp_path / "r")
    assert main(["train", "--model", "dsr", "--stage", "cube-multi", "--data", str(data), "--out", out]) == 2
    assert "fewer than the window 10" in capsys.readouterr().err
    assert main(["train", "--model", "gpt", "--stage", "cube-single", "--data", str(data), "--out", out]) == 2
    assert "--model 'gpt'" in capsys.readouterr().err
    assert main(["train", "--stage", "warmup", "--data", str(data), "--out", out]) == 2
    assert "--stage 'warmup'" in capsys.readouterr().err
    assert _train(data, out, "--max-minutes", "0") == 2
    assert "--max-minutes 0.0: must be positive" in capsys.readouterr().err
    assert _train(data, out, "--compile") == 2
    assert "--compile needs --device cuda" in capsys.readouterr().err
    assert _train(data, out, "--grid-size", "64", "64", "32") == 2
    assert "differs from the data's grid" in capsys.readouterr().err
    assert _train(data, out, "--resume", str(tmp_path / "missing.pt")) == 2
    assert "checkpoint not found" in capsys.readouterr().err
    (tmp_path / "junk.pt").write_bytes(b"junk")
    assert _train(data, out, "--init", str(tmp_path / "junk.pt")) == 2
    assert "not a loadable" in capsys.readouterr().err
    assert main(["predict", "--model", "single", "--checkpoint", str(tmp_path / "missing.pt"), "--data", str(data),
                 "--out", str(tmp_path / "p")]) == 2


def test_object_ids_beyond_the_slots_are_refused(tmp_path, capsys):
    """Scenes with more objects than the K - 1 = 4 slots are refused up front (from the manifest), and a
    mask id beyond the slots inside a file is caught on the CPU copy of the batch: one line, exit 2."""
    import h5py

    crowded = write_synthetic_dataset(tmp_path / "crowded", num_sequences=1, num_steps=1, num_objects=5, split="train")
    assert _train(crowded, tmp_path / "r1", "--max-steps", "1") == 2
    err = capsys.readouterr().err
    assert "1 sequences (e.g. seq_0000) have more than 4 objects" in err and "--objects-per-scene" in err
    assert len(err.strip().splitlines()) == 1
    broken = write_synthetic_dataset(tmp_path / "broken", num_sequences=1, num_steps=1, num_objects=2, split="train")
    with h5py.File(broken / "seq_0000.h5", "r+") as f:
        f["mask_3d"][0, 0, 0, 0] = 7
    assert _train(broken, tmp_path / "r2", "--max-steps", "1") == 2
    err = capsys.readouterr().err
    assert "batch 1 of epoch 1 (seq_0000): mask_3d has object id 7" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "r2" / "last.pt").exists()


def test_bad_actions_read_in_a_worker_give_one_line(tmp_path, capsys):
    """A bad file met by a DataLoader worker process: the message names the file, on one line
    (not the worker's re-raised traceback), exit 2."""
    import h5py

    data = write_synthetic_dataset(tmp_path / "d", num_sequences=1, num_steps=2, split="train")
    with h5py.File(data / "seq_0000.h5", "r+") as f:
        f["action"][0] = [9, 0, 0]
    for workers in ("0", "1"):
        assert main(["train", "--model", "dsr", "--stage", "cube-single", "--data", str(data), "--out",
                     str(tmp_path / "r"), "--batch-size", "1", "--workers", workers, "--quiet",
                     "--max-steps", "1"]) == 2
        err = capsys.readouterr().err.strip()
        assert err == (f"error: {data / 'seq_0000.h5'}: action: direction outside 0..7 (values 9..9); "
                       "check it with `dsr-bench validate`"), workers
        # its workers ended with the loop, not in some later garbage collection (where an interruption shows as
        # "Exception ignored in _MultiProcessingDataLoaderIter.__del__")
        from torch.utils.data.dataloader import _MultiProcessingDataLoaderIter as WorkerIterator

        with warnings.catch_warnings():  # isinstance over every live object touches torch's deprecated aliases
            warnings.simplefilter("ignore", FutureWarning)
            left = [o for o in gc.get_objects() if isinstance(o, WorkerIterator) and not o._shutdown]
        assert not left, workers


@pytest.mark.parametrize("field, value, message", [
    ("stage_name", None, "--stage is needed on the full track"),
    ("bn_recalibration", -1, "--bn-recalibration -1: must be >= 0"),
    ("max_steps", 0, "--max-steps 0: must be at least 1"),
    ("max_seconds", 0.0, "--max-minutes 0.0: must be positive"),
    ("max_seconds", -60.0, "--max-minutes -1.0: must be positive"),
    ("workers", -1, "--workers and --checkpoint-every must be >= 0"),
    ("checkpoint_every", -2, "--workers and --checkpoint-every must be >= 0"),
    ("log_every", 0, "log_every 0: must be at least 1"),
    ("init", "a.pt", "--resume continues a run with its own weights; drop --init"),
])
def test_train_config_checks_its_own_values(tmp_path, field, value, message):
    from dsr_bench.errors import UserError
    from dsr_bench.models.training.config import TrainConfig

    base = dict(model_name="dsr", stage_name="cube-single", data=tmp_path, out=tmp_path / "run")
    if field == "init":
        base["resume"] = tmp_path / "last.pt"
    TrainConfig(**base)  # the defaults are valid
    with pytest.raises(UserError, match=message):
        TrainConfig(**{**base, field: value})


def _curriculum(data, other, out, *extra):
    """`dsr-bench train --stage curriculum` at toy size: every stage one epoch of 2 sample-steps at batch 1 (cube-single
    2 batches, the multi-step stages one window of 2), shapenet-multi on its own data."""
    return main(["train", "--model", "dsr", "--stage", "curriculum", "--data", str(data), "--stage-data",
                 f"shapenet-multi={other}", "--out", str(out), "--epochs", "1", "--epoch-samples", "2", "--window", "2",
                 "--batch-size", "1", "--workers", "0", "--bn-recalibration", "1", "--quiet", *extra])


@pytest.mark.slow
def test_the_curriculum_runs_its_stages_in_turn_and_resumes_as_if_uninterrupted(data, tmp_path, capsys):
    """The paper's three stages in one command, each in OUT/STAGE from the weights the one before finished with,
    shapenet-multi on its --stage-data; interrupted (--max-steps 1, mid cube-single) and run again, it ends with the
    weights of the uninterrupted run, bit for bit; run once more, it trains nothing; --eval-data scores the result."""
    other = write_synthetic_dataset(tmp_path / "shapenet-like", num_sequences=1, num_steps=2, num_objects=3,
                                    split="shapenet")
    straight, interrupted = tmp_path / "straight", tmp_path / "interrupted"
    assert _curriculum(data, other, straight, "--eval-data", str(data)) == 0
    out = capsys.readouterr().out
    assert f"checkpoint: {straight / 'shapenet-multi' / 'last.pt'}" in out and "held-out train (2 sequences)" in out
    stages = ("cube-single", "cube-multi", "shapenet-multi")
    saved = {stage: torch.load(straight / stage / "last.pt", weights_only=True) for stage in stages}
    assert [(saved[s]["stage"]["name"], saved[s]["epoch"], saved[s]["step"]) for s in stages] == [
        ("cube-single", 1, 2), ("cube-multi", 1, 1), ("shapenet-multi", 1, 1)]
    assert [saved[s]["stage"]["window"] for s in stages] == [1, 2, 2]
    assert [saved[s]["data"]["dir"] for s in stages] == ["data", "data", "shapenet-like"]  # each stage's own data
    config = json.loads((straight / "cube-multi" / "config.json").read_text())
    assert config["init"].endswith("cube-single/last.pt") and config["resume"] is None  # handed on, not resumed
    log = [json.loads(line) for line in (straight / "cube-multi" / "metrics.jsonl").read_text().splitlines()]
    assert [r["lr"] for r in log if "loss" in r] == [5e-4]  # the fine-tuning table
    results = json.loads((straight / "evaluation.json").read_text())
    assert results["meta"]["name"] == "dsr" and results["coverage"]["scored"] == 2
    assert (straight / "predictions" / "meta.json").is_file()

    assert _curriculum(data, other, interrupted, "--max-steps", "1") == 0
    first = torch.load(interrupted / "cube-single" / "last.pt", weights_only=True)
    assert (first["epoch"], first["step"]) == (0, 1) and not (interrupted / "cube-multi").exists()
    assert _curriculum(data, other, interrupted) == 0  # the same command again: goes on from OUT
    resumed = json.loads((interrupted / "cube-single" / "config.json").read_text())["resume"]
    assert resumed.endswith("cube-single/last.pt")
    last = torch.load(interrupted / "shapenet-multi" / "last.pt", weights_only=True)
    for key, value in saved["shapenet-multi"]["model"].items():
        assert torch.equal(value, last["model"][key]), key
    capsys.readouterr()
    assert _curriculum(data, other, interrupted) == 0  # done: nothing trained, the final checkpoint named
    assert capsys.readouterr().out.strip() == f"checkpoint: {interrupted / 'shapenet-multi' / 'last.pt'}"
    assert len((interrupted / "shapenet-multi" / "metrics.jsonl").read_text().splitlines()) == 3  # batch, recal., epoch


@pytest.mark.parametrize("extra, message", [
    (["--single-batches", "5"], "--single-batches is not an option of the full track; drop it"),
    (["--same-windows"], "--same-windows is not an option of the full track; drop it"),
    (["--track", "cpu", "--bf16"], "--bf16 is not an option of the CPU track; drop it"),
    (["--track", "cpu", "--max-minutes", "3"], "--max-minutes is not an option of the CPU track; drop it"),
    (["--track", "cpu", "--device", "cuda"], "--device cuda: the CPU track trains on the CPU; drop --device"),
    (["--model", "se3net", "--bn-recalibration", "0"], "--bn-recalibration is not an option of the 2D track's models "
     "(single-step, one stage); drop it"),
    (["--model", "2dflow", "--track", "cpu", "--resume", "x.pt"], "--resume is not an option of the 2D track's "
     "models (single-step, one stage); drop it"),
    (["--stage", "nope"], "--stage 'nope': choose one of cube-single, cube-multi, shapenet-multi or curriculum"),
    (["--stage", "cube-single", "--stage-data", "cube-multi=x"], "--stage-data gives the data of the curriculum's "
     "stages (--stage curriculum); a single stage trains on --data"),
    (["--stage", "curriculum", "--stage-data", "warmup=x"], "--stage-data 'warmup=x': give STAGE=DIR, STAGE one of "
     "cube-single, cube-multi, shapenet-multi"),
    (["--stage", "curriculum", "--resume", "missing.pt"], "checkpoint not found: missing.pt"),
    (["--stage", "cube-single", "--eval-data", "missing"], "missing"),
])
def test_each_track_refuses_what_it_does_not_read_before_any_work(data, tmp_path, capsys, monkeypatch, extra,
                                                                  message):
    monkeypatch.chdir(tmp_path)
    assert main(["train", "--data", str(data), "--out", "out", *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and message in err and len(err.splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_an_option_at_its_default_is_no_option_given(tmp_path, capsys):
    """`--device cpu` on the CPU track and `--multi-batches 300` on the full track are what those tracks do anyway:
    not refused (the run then stops at its data, which is missing here)."""
    for extra in (["--track", "cpu", "--device", "cpu"], ["--stage", "cube-single", "--multi-batches", "300"]):
        assert main(["train", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "w.pt"), *extra]) == 2
        err = capsys.readouterr().err
        assert "not found" in err and "--device" not in err and "--multi-batches" not in err


def test_the_help_groups_the_options_by_track(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "400")
    assert main(["train", "--help"]) == 0
    text = capsys.readouterr().out
    for panel in ("Every track", "Held-out evaluation (every track)", "The full track (--track full, the default)",
                  "Budget and checkpoints", "Device (the full track; --device also the 2D track)",
                  "The CPU track (--track cpu)"):
        assert panel in text, panel
    lines = {line.split()[1]: line for line in text.splitlines() if line.startswith("│ ") and "--" in line[:30]}
    assert "Tracks: full, cpu, fine-tuning." in lines["--init"] and "Tracks: cpu, 2D." in lines["--single-batches"]
    assert "Tracks: full, 2D, fine-tuning." in lines["--device"] and "Tracks: full." in lines["--max-minutes"]
    assert "Tracks:" not in lines["--lr"]  # every track reads it
    assert "Fine-tuning on a real split" in text and "Tracks: fine-tuning." in lines["--finetune"]
