"""The one weights format (`dsr_bench.models.training.checkpoints`): what every training path writes, the
model type resolving the network, the files of version 1 (the shipped weights among them) still read exactly,
forged files refused in one line."""

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dsr_bench.cli import main  # noqa: E402
from dsr_bench.errors import UserError  # noqa: E402
from dsr_bench.models import DSRNet, ModelConfig, registry  # noqa: E402
from dsr_bench.models.image_config import ImageModelConfig  # noqa: E402
from dsr_bench.models.training.checkpoints import (  # noqa: E402
    WEIGHTS_FORMAT, WEIGHTS_VERSION, half, read_weights, save_weights,
)

TINY = dict(grid=(16, 16, 16))
ROOT = Path(__file__).resolve().parents[1]


def _voxel(name="dsr", seed=0):
    torch.manual_seed(seed)
    net = DSRNet(ModelConfig.for_model(name, **TINY))
    with torch.no_grad():  # running statistics that are not the defaults, so that loading them is seen
        for key, value in net.state_dict().items():
            if "running_" in key:
                value.uniform_(0.5, 1.5)
    return net.eval()


def _image(name="se3net", seed=0):
    from dsr_bench.models.image_nets import ImageNet

    torch.manual_seed(seed)
    return ImageNet(ImageModelConfig(name=name, width=4, hidden=16)).eval()


def _voxel_output(net):
    g = torch.Generator().manual_seed(1)
    tsdf = torch.rand(1, *TINY["grid"], generator=g) * 2 - 1
    action = torch.zeros(1, 8, *TINY["grid"][:2])
    action[0, 2, 5, 7] = 1
    with torch.no_grad():
        out = net(tsdf, action, net.initial_state(1, "cpu"))
    return out["mask"], out["motion"]


@pytest.mark.parametrize("name", registry.names(registry.VOXEL, registry.IMAGE))
def test_the_model_type_saved_with_the_weights_resolves_the_network(tmp_path, name):
    net = _image(name) if registry.MODELS[name].kind == registry.IMAGE else _voxel(name)
    path = save_weights(tmp_path / "w.pt", net.config, net.state_dict(), "weights", fp16=True,
                        data={"dir": "d", "split": None, "sequences": 1, "split_checksum": ""})
    raw = torch.load(path, weights_only=True)
    assert (raw["format"], raw["version"], raw["model_type"], raw["role"]) == (WEIGHTS_FORMAT, WEIGHTS_VERSION, name,
                                                                             "weights")
    weights = read_weights(path)
    again = weights.network()
    assert type(again) is type(net) and again.config == net.config and not again.training
    assert (weights.model_type, weights.kind, weights.version) == (name, registry.MODELS[name].kind, 2)
    for key, value in half(net.state_dict()).items():  # fp16 in the file, widened exactly
        assert torch.equal(again.state_dict()[key], value.float() if value.is_floating_point() else value), key


def _legacy_files(tmp_path, net, image=None) -> dict:
    """The files each training path wrote before the one format (version 1), as they wrote them."""
    config = net.config.as_dict()
    files = {"dsr-bench-checkpoint": {"format": "dsr-bench-checkpoint", "model": net.state_dict(),
                                      "optimizer": {}, "scheduler": {}, "model_config": config, "stage": {},
                                      "epoch": 1, "batch_index": 0, "step": 3, "rng": {}, "git": "x",
                                      "torch_version": "x", "data": "/a/local/path", "split": "train"},
             "dsr-bench-cpu-weights": {"format": "dsr-bench-cpu-weights", "model_config": config,
                                       "model": half(net.state_dict()), "recipe": {}, "stages": {},
                                       "data": {"dir": "d"}, "git": "x", "torch_version": "x"},
             "dsr-bench-cpu-weights-stage1": {"format": "dsr-bench-cpu-weights-stage1", "model_config": config,
                                              "model": net.state_dict(), "recipe": {}, "stages": {}},
             "no format (the first last.pt files)": {"model": net.state_dict(), "model_config": config}}
    if image is not None:
        files["dsr-bench-image-weights"] = {"format": "dsr-bench-image-weights", "model_config": image.config.as_dict(),
                                            "model": half(image.state_dict()), "recipe": {}, "training": {}}
    paths = {}
    for i, (label, payload) in enumerate(files.items()):
        paths[label] = tmp_path / f"legacy{i}.pt"
        torch.save(payload, paths[label])
    return paths


def test_version_1_files_read_as_before_and_predict_the_same_as_version_2(tmp_path):
    net, image = _voxel("gtwarp"), _image("se3posenet")
    roles = {"dsr-bench-checkpoint": "checkpoint", "dsr-bench-cpu-weights": "weights",
             "dsr-bench-cpu-weights-stage1": "stage1", "no format (the first last.pt files)": "weights",
             "dsr-bench-image-weights": "weights"}
    for label, path in _legacy_files(tmp_path, net, image).items():
        weights = read_weights(path)
        assert (weights.version, weights.role) == (1, roles[label]), label
        again = weights.network()
        fp16 = label in ("dsr-bench-cpu-weights", "dsr-bench-image-weights")
        source = image if label == "dsr-bench-image-weights" else net
        rewritten = read_weights(save_weights(tmp_path / f"v2-{path.name}", source.config, source.state_dict(),
                                              "weights", fp16=fp16)).network()
        for a, b in zip(again.state_dict().values(), rewritten.state_dict().values()):
            assert torch.equal(a, b), label
        if source is net:  # the same network, hence the same predictions, bit for bit
            assert all(torch.equal(a, b) for a, b in zip(_voxel_output(again), _voxel_output(rewritten))), label
    with pytest.raises(UserError, match="not a 2D-track weights file"):
        read_weights(tmp_path / "legacy1.pt", kind=registry.IMAGE)


def test_the_shipped_weights_are_the_files_the_leaderboard_scored():
    """Their SHA-256 is in the leaderboard's entries and docs/models.md: they are read as they are (a version-1
    file is never rewritten into the new format), as weights of the model they are named after."""
    from dsr_bench.dataset.manifest import file_sha256
    from dsr_bench.models.predictors import SHIPPED_WEIGHTS

    recorded = {}
    for entry in sorted((ROOT / "leaderboard" / "entries").glob("*.json")):
        weights = json.loads(entry.read_text()).get("meta", {}).get("parameters", {}).get("weights", {})
        if weights.get("source") == "dsr-bench, shipped CPU-track weights":
            recorded[weights["file"]] = weights["sha256"]
    assert len(recorded) >= 5
    for name, sha in recorded.items():
        path = SHIPPED_WEIGHTS / name
        assert file_sha256(path) == sha, name
        weights = read_weights(path)
        assert weights.version in (1, WEIGHTS_VERSION), name
        assert (weights.role, weights.model_type) == ("weights", path.stem), name


def _forge(tmp_path, name, **changes):
    net = _voxel("single")
    payload = {"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, "model_type": "single", "role": "weights",
               "model_config": net.config.as_dict(), "model": net.state_dict()}
    payload.update(changes)
    path = tmp_path / name
    torch.save(payload, path)
    return path


@pytest.mark.parametrize("changes, message", [
    ({"model_type": "gpt"}, "model type 'gpt' is not one of"),
    ({"model_type": "oracle"}, "model type 'oracle' is not one of"),  # a reference model has no weights
    ({"model_type": "dsr"}, "model type 'dsr' but a model_config of 'single'"),
    ({"version": 3}, "version 3, newer than this dsr-bench reads"),
    ({"version": "2"}, "version '2' of dsr-bench-weights is not one"),
    ({"version": True}, "version True of dsr-bench-weights is not one"),
    ({"role": "everything"}, "role 'everything' is not one of"),
    ({"format": "other-tool"}, "format 'other-tool' is not a dsr-bench weights file"),
    ({"model": {"encoder.level0.conv.weight": "rm -rf /"}}, "its model is not a state dict of tensors"),
    ({"model": [1, 2]}, "model_config and model must be dicts"),
    ({"model_config": {"name": "single", "grid": [16, 16, 16], "exploit": 1}}, "unusable model_config"),
])
def test_a_forged_weights_file_is_refused_in_one_line(tmp_path, changes, message):
    path = _forge(tmp_path, "forged.pt", **changes)
    with pytest.raises(UserError, match=message) as info:
        read_weights(path).network()
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_non_finite_or_misfitting_weights_are_one_line_from_predict(tmp_path, capsys):
    from dsr_bench.testing import write_synthetic_dataset

    data = write_synthetic_dataset(tmp_path / "data", num_sequences=1, num_steps=1)
    state = _voxel("single").state_dict()
    state["encoder.level0.conv.weight"][0, 0, 0, 0, 0] = float("nan")
    shapes = _voxel("single").state_dict()
    shapes["encoder.level0.conv.weight"] = shapes["encoder.level0.conv.weight"][:1]
    for name, model, message in (("nan.pt", state, "NaN or infinite"), ("shape.pt", shapes, "weights do not fit")):
        path = _forge(tmp_path, name, model=model)
        assert main(["predict", "--model", "single", "--checkpoint", str(path), "--data", str(data),
                     "--out", str(tmp_path / "p")]) == 2
        err = capsys.readouterr().err
        assert message in err and name in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "p").exists()


def test_resume_reads_only_a_whole_checkpoint(tmp_path):
    net = _voxel("dsr")
    weights = save_weights(tmp_path / "w.pt", net.config, net.state_dict(), "weights")
    with pytest.raises(UserError, match="finished weights, not a run's checkpoint .* start from them with --init"):
        read_weights(weights, role="checkpoint")
    torn = save_weights(tmp_path / "c.pt", net.config, net.state_dict(), "checkpoint", optimizer={}, step=1)
    with pytest.raises(UserError, match="a checkpoint without scheduler, stage, epoch, batch_index, rng"):
        read_weights(torn, role="checkpoint")
    assert read_weights(torn).role == "checkpoint"  # its weights still serve --init and predict
    with pytest.raises(UserError, match="not the stage-1 weights of a CPU-track run"):
        read_weights(weights, role="stage1")


def test_the_recipes_write_the_one_format_with_their_provenance(tmp_path, monkeypatch):
    """A CPU-track run's weights and stage-1 files and a 2D-track run's weights: the one format, the model
    type, their role, the data by directory name (no local path)."""
    from dsr_bench.testing import write_synthetic_dataset

    monkeypatch.setenv("DSR_BENCH_CACHE", str(tmp_path / "cache"))
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=2, num_steps=2, split="train")
    common = ["--data", str(data), "--batch-size", "2", "--single-batches", "1", "--quiet", "--track", "cpu"]
    assert main(["train", "--model", "3dflow", "--out", str(tmp_path / "3dflow.pt"), "--multi-batches", "1",
                 "--window", "1", "--bn-recalibration", "0", *common]) == 0
    assert main(["train", "--model", "2dflow", "--out", str(tmp_path / "2dflow.pt"), *common]) == 0
    for name, role in (("3dflow.pt", "weights"), ("3dflow.stage1.pt", "stage1"), ("2dflow.pt", "weights")):
        weights = read_weights(tmp_path / name)
        assert (weights["format"], weights.version, weights.role) == (WEIGHTS_FORMAT, 2, role), name
        assert weights.model_type == name.split(".")[0] and weights["recipe"]["model_name"] == weights.model_type
        assert weights["data"]["dir"] == "data" and weights["data"]["sequences"] == 2 and weights["git"]
    record = read_weights(tmp_path / "3dflow.pt")["stages"]["single"]
    assert set(record["loss_first_tenth"]) == {"total", "motion", "mask"} and record["window"] == 1
    assert np.isfinite(list(read_weights(tmp_path / "2dflow.pt")["training"]["loss_last_tenth"].values())).all()
