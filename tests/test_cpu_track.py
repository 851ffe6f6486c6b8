"""The CPU track: pooling to 16 mm voxels and back, the model that works on them (loss weighting,
predictions on the benchmark's grid), its recipe from the CLI, the pooled-split cache, its named splits."""

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dsr_bench.cli import main  # noqa: E402
from dsr_bench.constants import GRID_SHAPE  # noqa: E402
from dsr_bench.models import DSRNet, ModelConfig, coarse  # noqa: E402
from dsr_bench.testing import write_synthetic_dataset  # noqa: E402

CPU = dict(grid=(32, 32, 16), voxel_factor=4, width=2)


def _box(y0=8, x0=16, z0=0, size=(8, 12, 8), oid=1):
    mask = np.zeros(GRID_SHAPE, np.uint8)
    mask[y0:y0 + size[0], x0:x0 + size[1], z0:z0 + size[2]] = oid
    return mask


def test_coarse_grid_and_config():
    assert coarse.coarse_grid(4) == (32, 32, 16)
    assert coarse.coarse_grid(2) == (64, 64, 32)
    ModelConfig.for_model("dsr", **CPU)
    with pytest.raises(ValueError, match="needs the grid"):
        ModelConfig.for_model("dsr", grid=(32, 32, 32), voxel_factor=4)
    with pytest.raises(ValueError, match="width 3"):
        ModelConfig.for_model("dsr", width=3)


def test_a_block_aligned_box_pools_and_comes_back_exactly():
    mask = _box()
    flow = np.zeros((3,) + GRID_SHAPE, np.float32)
    flow[:, mask > 0] = np.array([2.0, -4.0, 0.5], np.float32)[:, None]  # benchmark voxels
    labels = coarse.pool_labels(mask)
    assert labels.shape == (32, 32, 16) and labels.dtype == np.uint8
    assert (labels == 1).sum() == 2 * 3 * 2 and labels[2:4, 4:7, 0:2].all() and not labels[..., 12:].any()
    pooled = coarse.pool_flow(flow, mask)
    assert np.allclose(pooled[:, labels == 1], np.array([0.5, -1.0, 0.125])[:, None])  # model voxels: / 4
    assert not pooled[:, labels == 0].any()
    assert np.array_equal(coarse.unpool_mask(labels), mask)
    assert np.array_equal(coarse.unpool_motion(pooled), flow)  # back in benchmark voxels


def test_a_block_belongs_to_an_object_from_three_eighths():
    mask = np.zeros(GRID_SHAPE, np.uint8)
    mask[0:4, 0:4, 0:1] = 1          # 16 of 64: below 3/8
    mask[0:4, 4:8, 0:2] = 2          # 32 of 64
    mask[4:8, 0:4, 0:1] = 3
    mask[4:8, 0:4, 1:2] = 2          # 16 + 16: a tie between 3 and 2, neither reaches 24
    mask[8:12, 0:4, 0:2] = 4
    mask[8:12, 0:2, 2:4] = 1         # 32 of id 4 + 16 of id 1: the most frequent, 4
    labels = coarse.pool_labels(mask)
    assert labels[0, 0, 0] == 0 and labels[0, 1, 0] == 2 and labels[1, 0, 0] == 0 and labels[2, 0, 0] == 4
    assert coarse.MIN_BLOCK_FRACTION * 64 == 24


def test_pool_tsdf_means_blocks_and_is_empty_above_the_volume():
    tsdf = np.ones((2,) + GRID_SHAPE, np.float32)
    tsdf[1, :4, :4, :4] = -1.0
    tsdf[1, 4:8, :4, :2] = 0.0
    pooled = coarse.pool_tsdf(tsdf)
    assert pooled.shape == (2, 32, 32, 16) and pooled.dtype == np.float32
    assert pooled[1, 0, 0, 0] == -1.0 and pooled[1, 1, 0, 0] == 0.5 and (pooled[0] == 1).all()
    assert (pooled[:, :, :, 12:] == 1).all()
    with pytest.raises(ValueError, match="expected"):
        coarse.pool_tsdf(np.ones((64, 64, 24)))


def test_coarse_action_floors_the_pixel():
    assert coarse.coarse_action(np.array([[3, 127, 5], [0, 4, 3]])).tolist() == [[3, 31, 1], [0, 1, 0]]


def test_the_motion_term_is_taken_in_benchmark_voxels():
    from dsr_bench.models.loss import dsr_loss

    g = torch.Generator().manual_seed(0)
    outputs = {"mask_logits": torch.randn(2, 5, 32, 32, 16, generator=g),
               "motion": torch.randn(2, 3, 32, 32, 16, generator=g)}
    gt_mask = torch.randint(0, 3, (2, 32, 32, 16), generator=g)
    gt_flow = torch.randn(2, 3, 32, 32, 16, generator=g)
    _, plain, _ = dsr_loss(outputs, gt_mask, gt_flow)
    _, scaled, _ = dsr_loss(outputs, gt_mask, gt_flow, voxel_factor=4)
    assert torch.allclose(scaled["motion"], 16 * plain["motion"]) and torch.equal(scaled["mask"], plain["mask"])


@pytest.mark.parametrize("name", ["dsr", "gtwarp"])
def test_a_cpu_track_model_predicts_on_the_benchmark_grid(name):
    from dsr_bench.models.data import action_map
    from dsr_bench.models.inference import ModelPredictor
    from dsr_bench.models.labels import slot_labels

    torch.manual_seed(0)
    net = DSRNet(ModelConfig.for_model(name, **CPU)).eval()
    rng = np.random.default_rng(0)
    tsdf = rng.uniform(-1, 1, (2,) + GRID_SHAPE).astype(np.float32)
    actions = np.array([[1, 64, 70], [5, 10, 127]])
    mask = np.stack([_box(), _box(x0=20)])
    flow = np.zeros((2, 3) + GRID_SHAPE, np.float32)
    pred = ModelPredictor(net, torch.device("cpu")).predict_arrays(tsdf, actions, flow, mask)
    assert pred["mask"].shape == (2,) + GRID_SHAPE and pred["motion"].shape == (2, 3) + GRID_SHAPE
    with torch.no_grad():  # step 0 by hand: pooled input, coarse action, outputs brought back
        out = net(torch.from_numpy(coarse.pool_tsdf(tsdf[0]))[None],
                  action_map(coarse.coarse_action(actions[:1]), (32, 32))[:1], net.initial_state(1, "cpu"))
    assert np.array_equal(pred["mask"][0], coarse.unpool_mask(slot_labels(out["mask"])[0].numpy()))
    assert np.allclose(pred["motion"][0], coarse.unpool_motion(out["motion"][0].numpy()), atol=1e-6)


def test_the_pooled_split_is_cached_and_refreshed_when_a_file_changes(tmp_path, monkeypatch):
    from dsr_bench.models.training import cpu_track

    monkeypatch.setenv("DSR_BENCH_CACHE", str(tmp_path / "cache"))
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=2, num_steps=2, split="train")
    first = cpu_track.pooled_split(data, None)
    assert first["tsdf"].shape == (2, 2, 32, 32, 16) and first["flow"].shape == (2, 2, 3, 32, 32, 16)
    assert first["names"].tolist() == ["seq_0000", "seq_0001"] and len(list((tmp_path / "cache").iterdir())) == 1

    def fail(*args, **kwargs):
        raise AssertionError("pooled again")

    monkeypatch.setattr(cpu_track, "_pool_sequence", fail)
    again = cpu_track.pooled_split(data, None)
    assert all(np.array_equal(first[k], again[k]) for k in first)
    (data / "seq_0001.h5").touch()
    with pytest.raises(AssertionError, match="pooled again"):
        cpu_track.pooled_split(data, None)


def test_train_track_cpu_from_the_cli_then_predict_and_evaluate(tmp_path, monkeypatch):
    monkeypatch.setenv("DSR_BENCH_CACHE", str(tmp_path / "cache"))
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=2, num_steps=3, split="train")
    weights = tmp_path / "dsr.pt"
    args = ["train", "--track", "cpu", "--model", "dsr", "--data", str(data), "--out", str(weights),
            "--single-batches", "2", "--multi-batches", "1", "--window", "2", "--batch-size", "2",
            "--bn-recalibration", "1", "--quiet"]
    assert main(args) == 0
    state = torch.load(weights, weights_only=True)
    assert (state["format"], state["model_type"], state["role"]) == ("dsr-bench-weights", "dsr", "weights")
    assert state["model_config"]["voxel_factor"] == 4 and state["model_config"]["width"] == 2
    assert state["model_config"]["grid"] == [32, 32, 16] and state["model_config"]["init"] == "zero-motion"
    assert all(v.dtype == torch.float16 for v in state["model"].values() if v.is_floating_point())
    assert state["recipe"]["single_batches"] == 2 and state["stages"]["multi"]["window"] == 2
    assert state["bn_recalibration_passes"] == 3  # one batch of whole 3-push windows
    assert state["data"]["sequences"] == 2
    counts = {int(v) for k, v in state["model"].items() if k.endswith("num_batches_tracked")}
    assert counts == {3}  # the recalibrated statistics were saved
    preds = tmp_path / "preds"
    assert main(["predict", "--model", "dsr", "--checkpoint", str(weights), "--data", str(data),
                 "--out", str(preds)]) == 0
    meta = json.loads((preds / "meta.json").read_text())
    assert meta["name"] == "dsr-cpu" and meta["parameters"]["grid"] == [32, 32, 16]
    results = tmp_path / "results.json"
    assert main(["evaluate", str(preds), "--data", str(data), "--out", str(results)]) == 0
    scored = json.loads(results.read_text())
    assert scored["meta"]["parameters"]["grid"] == [32, 32, 16] and np.isfinite(scored["metrics"]["motion_full"])
    # each sequence's means, for paired comparisons; with sequences of equal length they average to the headline
    assert sorted(scored["per_sequence"]) == ["seq_0000", "seq_0001"]
    for metric in ("motion_full", "motion_visible", "iou_unordered", "iou_ordered"):
        mean = np.mean([scored["per_sequence"][n][metric] for n in scored["per_sequence"]])
        assert np.isclose(mean, scored["metrics"][metric], rtol=1e-12), metric


@pytest.mark.parametrize("extra, message", [
    (["--stage", "cube-single"], "drop --stage"),
    (["--single-batches", "0"], "at least 1"),
    (["--track", "gpu"], "choose full or cpu"),
    (["--batch-size", "1"], "needs at least 2"),
    (["--bn-recalibration", "-1"], "--bn-recalibration -1: must be >= 0"),
])
def test_train_track_cpu_errors(tmp_path, capsys, extra, message):
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=1, num_steps=2, split="train")
    args = ["train", "--track", "cpu", "--model", "dsr", "--data", str(data), "--out", str(tmp_path / "w.pt"), *extra]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "w.pt").exists()


def test_the_full_track_still_needs_a_stage(tmp_path, capsys):
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=1, num_steps=2, split="train")
    assert main(["train", "--model", "dsr", "--data", str(data), "--out", str(tmp_path / "run")]) == 2
    assert "--stage is needed" in capsys.readouterr().err


def test_the_papers_schedule_is_offered_beside_the_official_tables():
    from dsr_bench.models.training.schedules import stage_for

    scratch = stage_for("dsr", "cube-single", schedule="paper")
    assert [scratch.lr_at(e) for e in (0, 4, 5, 9, 10, 29)] == [1e-3, 1e-3, 5e-4, 5e-4, 2.5e-4, 1e-3 / 32]
    finetune = stage_for("dsr", "cube-multi", schedule="paper")
    assert [finetune.lr_at(e) for e in (0, 2, 3, 6, 19)] == [1e-4, 1e-4, 5e-5, 2.5e-5, 1e-4 / 64]
    assert stage_for("dsr", "cube-single").lr_at(0) == 1e-5  # official: the warm-up epochs
    with pytest.raises(Exception, match="official or paper"):
        stage_for("dsr", "cube-single", schedule="cosine")


def test_the_cpu_splits_are_prefixes_of_the_benchmarks():
    from dsr_bench.dataset.splits import SPLITS, pinned_digests

    for cpu, parent in (("cpu-train", "procedural-train"), ("cpu-train-4k", "procedural-train"),
                        ("cpu-novel-test", "procedural-novel-test"), ("cpu-val", "procedural-test")):
        a, b = SPLITS[cpu], SPLITS[parent]
        assert (a.objects, a.base_seed, a.steps, a.objects_per_scene) == (b.objects, b.base_seed, b.steps,
                                                                         b.objects_per_scene)
        assert a.num_sequences < b.num_sequences
    pins = pinned_digests()
    for cpu, parent in (("cpu-novel-test", "procedural-novel-test"), ("cpu-val", "procedural-test")):
        ours, theirs = pins[cpu]["sequences"], pins[parent]["sequences"]
        assert len(ours) == 100 and all(ours[name] == theirs[name] for name in ours)  # the same files
    # the validation split holds scenes of the training objects, never a training sequence or a novel object
    assert (SPLITS["cpu-val"].role, SPLITS["cpu-val"].objects) == ("val", SPLITS["cpu-train-4k"].objects)
    assert SPLITS["cpu-val"].base_seed not in {s.base_seed for s in SPLITS.values() if s.role == "train"}


def test_stage_one_is_shared_by_the_history_variants_and_init_skips_it(tmp_path, monkeypatch):
    """Stage 1 (single-step windows) is the same computation for dsr, single, nowarp and gtwarp: their
    stage-1 weights are bit-identical, so nowarp may start stage 2 from dsr's (--init)."""
    monkeypatch.setenv("DSR_BENCH_CACHE", str(tmp_path / "cache"))
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=2, num_steps=2, split="train")
    common = ["--data", str(data), "--single-batches", "2", "--multi-batches", "1", "--window", "2",
              "--batch-size", "2", "--bn-recalibration", "1", "--quiet", "--track", "cpu"]
    assert main(["train", "--model", "dsr", "--out", str(tmp_path / "dsr.pt"), *common]) == 0
    assert main(["train", "--model", "single", "--out", str(tmp_path / "single.pt"), *common]) == 0
    a = torch.load(tmp_path / "dsr.stage1.pt", weights_only=True)
    b = torch.load(tmp_path / "single.stage1.pt", weights_only=True)
    assert all(torch.equal(v, b["model"][k]) for k, v in a["model"].items())
    assert main(["train", "--model", "nowarp", "--out", str(tmp_path / "nowarp.pt"), "--init",
                 str(tmp_path / "dsr.stage1.pt"), *common]) == 0
    nowarp = torch.load(tmp_path / "nowarp.pt", weights_only=True)
    assert nowarp["stages"]["single"]["from"] == "dsr.stage1.pt" and nowarp["stages"]["multi"]["batches"] == 1
    assert not (tmp_path / "nowarp.stage1.pt").exists()


def test_a_finished_run_is_continued_in_chunks_from_its_weights_file(tmp_path, monkeypatch):
    """--init with a finished run's weights file continues that run: --multi-batches more of stage 2 from its
    weights, on windows of their own, recorded after its stages with the loss curve; twice in a row, in place."""
    monkeypatch.setenv("DSR_BENCH_CACHE", str(tmp_path / "cache"))
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=2, num_steps=2, split="train")
    common = ["--data", str(data), "--single-batches", "2", "--window", "2", "--batch-size", "2",
              "--bn-recalibration", "1", "--quiet", "--track", "cpu"]
    first = tmp_path / "3dflow.pt"
    assert main(["train", "--model", "3dflow", "--out", str(first), "--multi-batches", "1", *common]) == 0
    before = torch.load(first, weights_only=True)
    more = tmp_path / "3dflow-more.pt"
    assert main(["train", "--model", "3dflow", "--out", str(more), "--init", str(first), "--multi-batches", "2",
                 *common]) == 0
    after = torch.load(more, weights_only=True)
    assert after["stages"]["single"] == before["stages"]["single"] and after["stages"]["multi"] == \
        before["stages"]["multi"]  # the run's own record kept
    (chunk,) = after["stages"]["continued"]
    assert chunk["from"] == "3dflow.pt" and chunk["batches"] == 2 * 2  # no history: x window single-step batches
    assert len(chunk["loss_every_10"]) == 1 and chunk["loss_every_10"][0] > 0
    assert any(not torch.equal(v, after["model"][k]) for k, v in before["model"].items()
               if v.is_floating_point() and "running" not in k)  # trained on, not a copy
    assert not (tmp_path / "3dflow-more.stage1.pt").exists()
    assert chunk["lr"] == 5e-4  # stage 2's rate
    # a second chunk at a rate of its own (a cooling chunk), written in place over the file it continues
    assert main(["train", "--model", "3dflow", "--out", str(more), "--init", str(more), "--multi-batches", "1",
                 "--multi-lr", "1e-4", *common]) == 0
    again = torch.load(more, weights_only=True)
    assert [c["from"] for c in again["stages"]["continued"]] == ["3dflow.pt", "3dflow-more.pt"]
    assert [c["lr"] for c in again["stages"]["continued"]] == [5e-4, 1e-4]
    assert again["recipe"]["init"] == more.name  # a file name, never a path of this machine
    # what each chunk trained on: its sample-steps and its data, so a long run's file says both of every chunk
    assert [c["sample_steps"] for c in again["stages"]["continued"]] == [4 * 2, 2 * 2]  # batches x 1 x batch 2
    assert all(c["data"]["dir"] == "data" and c["data"]["sequences"] == 2 for c in again["stages"]["continued"])
    from dsr_bench.models.training.cpu_track import sample_steps

    # stage 1: 2 single-step batches, stage 2: 1 batch x window 2 (as 2 single-step batches), then 4 and 2 more
    assert sample_steps(again["stages"], batch_size=2) == (2 + 2 + 4 + 2) * 2
    assert sample_steps({"single": {"batches": 3000, "window": 1}, "multi": {"batches": 2000, "window": 1}}) == 40000


@pytest.mark.parametrize("extra, message", [
    (["--init", "missing.stage1.pt"], "not found"),
    (["--init", "dsr.pt"], "holds a 'dsr' model, not 'nowarp'"),  # a finished run continues only its own model
    (["--init", "dsr.stage1.pt", "--lr", "0.01"], "other settings (lr)"),
    (["--init", "dsr.stage1.pt", "--multi-batches", "0"], "give --multi-batches"),
    (["--multi-lr", "0"], "--multi-lr 0.0: a learning rate must be a finite number above 0"),
    (["--multi-lr", "nan"], "--multi-lr nan: a learning rate must be a finite number above 0"),
])
def test_init_errors(tmp_path, monkeypatch, capsys, extra, message):
    monkeypatch.setenv("DSR_BENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=1, num_steps=2, split="train")
    common = ["--data", str(data), "--single-batches", "1", "--window", "2", "--batch-size", "2",
              "--bn-recalibration", "0", "--quiet", "--track", "cpu"]
    assert main(["train", "--model", "dsr", "--out", "dsr.pt", "--multi-batches", "1", *common]) == 0
    capsys.readouterr()
    args = ["train", "--model", "nowarp", "--out", "nowarp.pt", *common, *extra]
    if "--multi-batches" not in extra:
        args += ["--multi-batches", "1"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "nowarp.pt").exists()


def test_docs_say_what_each_shipped_file_trained_on():
    """docs/models.md's table "What each shipped file saw" gives each shipped 3D file's sample-steps as the file's own
    stage records count them, and the training split's checksum prefix of its last chunk."""
    import re
    from pathlib import Path

    from dsr_bench.models.predictors import shipped_weights
    from dsr_bench.models.training.checkpoints import read_weights
    from dsr_bench.models.training.cpu_track import sample_steps

    text = (Path(__file__).resolve().parents[1] / "docs" / "models.md").read_text()
    table = text.split("**What each shipped file saw**", 1)[1].split("\n\n")[1]
    stated, checksums = {}, []
    for row in table.splitlines()[2:]:
        cells = [c.strip() for c in row.strip("|").split("|")]
        checksums = checksums if cells[2] == "the same" else re.findall(r"`([0-9a-f]{8})`", cells[2])
        for name in re.findall(r"`(\w+)\.pt`", cells[0].split("(")[0]):
            stated[name] = (int(cells[1].replace(",", "")), checksums)
    assert set(stated) == {"dsr", "single", "nowarp", "gtwarp", "3dflow"}
    for name, (steps, checksums) in stated.items():
        payload = read_weights(shipped_weights(name)).payload
        assert sample_steps(payload["stages"]) == steps, name
        assert payload["data"]["split_checksum"][:8] == checksums[-1], name


@pytest.mark.parametrize("name", ["dsr", "single", "nowarp", "gtwarp", "3dflow"])
def test_the_shipped_weights_are_small_cpu_track_models_loaded_weights_only(name):
    from dsr_bench.models.inference import load_predictor
    from dsr_bench.models.predictors import shipped_weights

    path = shipped_weights(name)
    assert path is not None and path.stat().st_size < 5_000_000, path
    state = torch.load(path, weights_only=True)
    config = ModelConfig.from_dict(state["model_config"])
    assert (config.name, config.voxel_factor, config.width, config.grid) == (name, 4, 2, (32, 32, 16))
    assert (state["data"]["split"] or state["data"]["dir"]) in ("cpu-train", "cpu-train-4k")  # its training data
    assert "/" not in state["data"]["dir"]  # provenance without a local path
    assert state["bn_recalibration_passes"] > 0  # eval-mode statistics re-estimated on whole sequences
    predictor = load_predictor(name, path)
    assert predictor.name == f"{name}-cpu" and not predictor.model.training


def test_predict_uses_the_shipped_weights_without_a_checkpoint(tmp_path):
    from dsr_bench.dataset.manifest import file_sha256
    from dsr_bench.models.predictors import shipped_weights

    data = write_synthetic_dataset(tmp_path / "data", num_sequences=1, num_steps=2)
    out = tmp_path / "preds"
    assert main(["predict", "--model", "dsr", "--data", str(data), "--out", str(out)]) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["weights"]["source"] == "dsr-bench, shipped CPU-track weights"
    assert meta["weights"]["sha256"] == file_sha256(shipped_weights("dsr")) and meta["name"] == "dsr-cpu"


@pytest.mark.parametrize("model, track, message", [
    ("dsr", "full", "--multi-lr is the CPU track's stage-2 rate (--track cpu); the full track's is --lr"),
    ("se3net", "cpu", "--multi-lr is not an option of the 2D track's models"),
])
def test_multi_lr_belongs_to_the_cpu_tracks_voxel_models(tmp_path, capsys, model, track, message):
    assert main(["train", "--model", model, "--track", track, "--data", str(tmp_path), "--out",
                 str(tmp_path / "w.pt"), "--multi-lr", "1e-4"]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "w.pt").exists()
