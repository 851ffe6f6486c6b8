"""The registries (issue 28): models, metrics, cameras and object sets are each one table, and every list of
their names (help texts, error messages, the lists other modules keep) is derived from it; a new entry is
reachable everywhere without another edit."""

import re
import sys
import textwrap
from dataclasses import asdict, dataclass
from pathlib import Path
from types import MappingProxyType

import numpy as np
import pytest

from dsr_bench.cli import main
from dsr_bench.errors import UserError
from dsr_bench.models import registry


ROOT = Path(__file__).resolve().parents[1]


def _doc_blocks(path: str, heading: str) -> list[str]:
    """The python code blocks of a docs section, dedented (an entry is shown at its indentation in the table)."""
    section = (ROOT / path).read_text().split(f"\n## {heading}\n", 1)[1].split("\n## ", 1)[0]
    return [textwrap.dedent(b) for b in re.findall(r"^```python\n(.*?)^```", section, re.M | re.S)]


def _with_models(monkeypatch, *entries):
    """The model table with `entries` appended, as a new entry in registry.py would be."""
    monkeypatch.setattr(registry, "MODELS", MappingProxyType({**registry.MODELS, **{e.name: e for e in entries}}))


def test_model_names_in_the_table_order():
    """The lists every caller used to keep by hand are the table's, in the order help and errors showed them."""
    from dsr_bench.models.config import MODEL_NAMES as VOXEL_NAMES
    from dsr_bench.models.image_config import IMAGE_MODEL_DESCRIPTIONS, IMAGE_MODEL_NAMES
    from dsr_bench.models.predictors import IMAGE_MODELS, LEARNED_MODELS, MODEL_NAMES, REFERENCE_MODELS

    assert registry.names() == MODEL_NAMES == ("oracle", "static", "push", "dsr", "single", "nowarp", "gtwarp",
                                               "3dflow", "2dflow", "se3net", "se3posenet")
    assert REFERENCE_MODELS == ("oracle", "static", "push")
    assert LEARNED_MODELS == VOXEL_NAMES == ("dsr", "single", "nowarp", "gtwarp", "3dflow")
    assert IMAGE_MODELS == IMAGE_MODEL_NAMES == ("2dflow", "se3net", "se3posenet")
    assert IMAGE_MODEL_DESCRIPTIONS["se3net"].startswith("SE3-Net: K masks")
    assert registry.help_text() == " | ".join(MODEL_NAMES)


def test_each_entry_builds_its_model():
    """A reference entry makes its predictor; a voxel entry's switches are its ModelConfig; an image entry is a
    valid ImageModelConfig."""
    from dsr_bench.models.config import ModelConfig
    from dsr_bench.models.image_config import ImageModelConfig
    from dsr_bench.models.predictors import load_predictor

    for name in registry.names(registry.REFERENCE):
        assert load_predictor(name).name == name
    assert ModelConfig.for_model("3dflow").motion == "flow" and ModelConfig.for_model("3dflow").history == "none"
    assert ModelConfig.for_model("nowarp").history == "nowarp" and ModelConfig.for_model("nowarp").motion == "se3"
    for name in registry.names(registry.IMAGE):
        assert ImageModelConfig(name=name).name == name
    with pytest.raises(ValueError, match="unknown model 'static'"):
        ModelConfig.for_model("static")  # a reference model has no network


def test_entries_are_checked():
    with pytest.raises(ValueError, match="kind 'conv'"):
        registry.ModelEntry("x", "conv")
    with pytest.raises(ValueError, match="names its predictor class"):
        registry.ModelEntry("x", registry.REFERENCE)
    with pytest.raises(ValueError, match="only a voxel model"):
        registry.ModelEntry("x", registry.IMAGE, variant={"history": "none"})


def test_a_new_model_is_one_entry(monkeypatch):
    """docs/models.md, 'Adding a model': an entry of the table is a model of predict, of ModelConfig and of
    train's choices, with no other edit."""
    from dsr_bench.models.config import ModelConfig
    from dsr_bench.models.predictors import StaticPredictor, load_predictor

    _with_models(monkeypatch, registry.ModelEntry("warpflow", registry.VOXEL, "WarpFlow: warped history, conv flow",
                                                  {"history": "warp", "motion": "flow"}),
                 registry.ModelEntry("still", registry.REFERENCE,
                                     predictor="dsr_bench.models.predictors:StaticPredictor"))
    config = ModelConfig.for_model("warpflow")
    assert (config.name, config.history, config.motion) == ("warpflow", "warp", "flow")
    assert isinstance(load_predictor("still"), StaticPredictor)
    with pytest.raises(UserError, match="--model warpflow needs --checkpoint CKPT"):  # no shipped weights for it
        load_predictor("warpflow")
    with pytest.raises(UserError, match=r"choose one of oracle, .*, se3posenet, warpflow, still$"):
        load_predictor("nope")


@pytest.mark.parametrize("argv, message", [
    (["predict", "--model", "nope", "--data", ".", "--out", "x"], "error: --model 'nope': choose one of oracle, "
     "static, push, dsr, single, nowarp, gtwarp, 3dflow, 2dflow, se3net, se3posenet"),
    (["predict", "--model", "push", "--weights", "w", "--data", ".", "--out", "x"], "error: --weights is for the "
     "authors' released models (dsr, single, nowarp, gtwarp, 3dflow), not --model push"),
    (["train", "--model", "oracle", "--data", ".", "--out", "x"], "error: --model 'oracle': choose one of dsr, single, "
     "nowarp, gtwarp, 3dflow, 2dflow, se3net, se3posenet"),
])
def test_model_errors_name_the_table(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert capsys.readouterr().err.strip() == message


def test_model_help_is_the_table(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "400")  # one help line per option
    assert main(["predict", "--help"]) == 0
    assert "oracle | static | push | dsr | single | nowarp | gtwarp | 3dflow | 2dflow | se3net | se3posenet" in \
        capsys.readouterr().out
    assert main(["train", "--help"]) == 0
    assert ("dsr | single | nowarp | gtwarp | 3dflow (the 3D track) or 2dflow | se3net | se3posenet (the 2D track: "
            "front-camera images)") in capsys.readouterr().out


def test_camera_names_are_the_constants_table():
    """Generate, simulated captures and a real rig's cameras take their names from dsr_bench.constants.CAMERAS."""
    pytest.importorskip("pybullet")  # generators.episode: the simulator
    from dsr_bench.annotator.importer import CAMERA_NAMES
    from dsr_bench.constants import CAMERAS, MODEL_CAMERA
    from dsr_bench.generators.capture import CAPTURE_CAMERAS

    assert tuple(CAMERAS) == CAPTURE_CAMERAS == CAMERA_NAMES == ("front", "back") and MODEL_CAMERA == "front"


def test_docs_adding_a_camera_works_as_written(monkeypatch, tmp_path):
    """docs/format.md, 'Adding a camera': its entry of constants.CAMERAS is a camera of generate --cameras (written,
    validated, read back), of make_camera and of the error's choices; the model camera stays required."""
    pytest.importorskip("pybullet")
    from dsr_bench.constants import CAMERAS
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.geometry import make_camera
    from dsr_bench.generators.run import check_plan, plan_from_arguments

    [block] = _doc_blocks("docs/format.md", "Adding a camera")
    [(name, spec)] = eval("{" + block.strip() + "}").items()
    monkeypatch.setitem(CAMERAS, name, spec)
    assert make_camera(name, 24, 32).extrinsics[:3, 3].tolist() == list(spec["eye"])
    with pytest.raises(UserError, match=rf"^--cameras '{name}': use front or front,back,{name}$"):
        check_plan(plan_from_arguments(objects="cube", num_sequences=1, out=tmp_path / "d", cameras=name))
    out = tmp_path / "data"
    assert main(["generate", "--objects", "cube", "-n", "1", "--steps", "1", "--cameras", f"front,{name}",
                 "--out", str(out)]) == 0
    assert main(["validate", str(out)]) == 0
    with SequenceReader(out / "seq_0000.h5") as seq:
        assert seq.camera(name).extrinsics[:3, 3].tolist() == list(spec["eye"])
        mask = seq.read(f"cameras/{name}/mask", 0)
        assert mask.shape == (240, 320) and set(range(1, 5)) <= set(mask.reshape(-1).tolist())  # it sees the cubes


def test_object_set_names_are_the_objects_table(capsys, monkeypatch):
    from dsr_bench.generators.objects import OBJECT_SET_NAMES, OBJECT_SETS, get_object_set

    assert OBJECT_SET_NAMES == tuple(OBJECT_SETS) == ("cube", "shapenet", "ycb", "procedural", "procedural-novel")
    monkeypatch.setitem(OBJECT_SETS, "boxes", ("dsr_bench.generators.objects.builtin:CubeSet", False))
    assert get_object_set("boxes").sample(np.random.default_rng(0), 1)[0].category
    monkeypatch.setenv("COLUMNS", "400")
    for command in ("generate", "generate-captures"):
        assert main([command, "--help"]) == 0
        assert "Object set: cube | shapenet | ycb | procedural | procedural-novel." in capsys.readouterr().out


def test_docs_adding_a_model_works_as_written(monkeypatch):
    """docs/models.md, 'Adding a model': its entry is a model of ModelConfig whose network runs a step and warps its
    history, load_predictor asks for its checkpoint, and --weights refuses it (no released weights); the kind it
    shows is the 2D track's, as registry.py writes it."""
    torch = pytest.importorskip("torch")
    from dsr_bench.models.config import ModelConfig
    from dsr_bench.models.dsr_net import DSRNet
    from dsr_bench.models.predictors import load_predictor

    block, kind = _doc_blocks("docs/models.md", "Adding a model")
    assert eval(kind.strip().rstrip(","), vars(registry)) == registry.KINDS[registry.IMAGE]
    entry = eval(block.strip().rstrip(","), vars(registry))
    _with_models(monkeypatch, entry)
    config = ModelConfig.for_model(entry.name, grid=(32, 32, 16), voxel_factor=4, width=4)
    assert (config.history, config.motion) == ("warp", "flow")
    net = DSRNet(config).eval()
    with torch.no_grad():
        tsdf, action = torch.zeros(1, 32, 32, 16), torch.zeros(1, 8, 32, 32)
        action[0, 2, 16, 16] = 1
        out = net(tsdf, action, net.initial_state(1, "cpu"))
        assert out["motion"].shape == (1, 3, 32, 32, 16) and net.next_state(out).shape[1] == config.state_channels
    with pytest.raises(UserError, match=f"^--model {entry.name} needs --checkpoint CKPT"):
        load_predictor(entry.name)
    released = r"\(dsr, single, nowarp, gtwarp, 3dflow\)"
    with pytest.raises(UserError, match=rf"^--weights is for the authors' released models {released}, not --model "
                                        rf"{entry.name}$"):
        load_predictor(entry.name, weights=Path("3dflow.pth"))


@dataclass(frozen=True)
class ToyConfig:
    """A kind of model of its own for the test below: a configuration class as a kind needs one."""

    name: str = "toy"
    value: float = 0.5

    @classmethod
    def for_model(cls, name: str, **fields) -> "ToyConfig":
        return cls(name=name, **fields)

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "ToyConfig":
        return cls(**data)


def toy_network(config: ToyConfig):
    """Its network: one weight."""
    import torch

    net = torch.nn.Linear(1, 1, bias=False)
    torch.nn.init.constant_(net.weight, config.value)
    return net


class ToyPredictor:
    """Predicts nothing: enough to be loaded."""

    def __init__(self, name: str, net):
        self.name, self.net, self.num_slots = name, net, None


def toy_loader(entry: registry.ModelEntry, *, checkpoint=None, device="cpu", **options) -> ToyPredictor:
    """Its loader: the weights file read through the one weights format, the network from the type saved in it."""
    from dsr_bench.models.training.checkpoints import read_weights

    return ToyPredictor(entry.name, read_weights(checkpoint, kind="toy", model=entry.name).network(device))


def toy_train(model: str, options: dict, report) -> Path:
    """Its one recipe: the network at the --lr given, written in the one weights format."""
    from dsr_bench.models.training.checkpoints import save_weights

    config = ToyConfig.for_model(model, value=options["lr"])
    return save_weights(options["out"], config, toy_network(config).state_dict(), "weights")


def test_a_new_kind_is_one_object(monkeypatch, tmp_path, capsys):
    """docs/models.md, 'Adding a model': a kind of model is one ModelKind of registry.KINDS, owning its config,
    network, loader and training recipes. With it and an entry of that kind (and no other edit), `dsr-bench train`
    runs its recipe and refuses what the recipe does not read, the type saved with the weights resolves its config
    and network, and load_predictor runs its loader."""
    torch = pytest.importorskip("torch")
    from dsr_bench.models.predictors import load_predictor
    from dsr_bench.models.training.checkpoints import model_types, read_weights
    from dsr_bench.models.training.tracks import Track

    here = __name__
    monkeypatch.setattr(registry, "KINDS", MappingProxyType({**registry.KINDS, "toy": registry.ModelKind(
        "toy", loader=f"{here}:toy_loader", config=f"{here}:ToyConfig", network=f"{here}:toy_network", files="toy",
        tracks={"cpu": f"{here}:TOY_TRACK"})}))
    monkeypatch.setattr(sys.modules[here], "TOY_TRACK", Track("cpu", "the toy track", (), f"{here}:toy_train"),
                        raising=False)
    _with_models(monkeypatch, registry.ModelEntry("toy1", "toy", "Toy: one weight"))
    assert "toy1" in model_types() and registry.trainable() == ("voxel", "image", "toy")
    out = tmp_path / "toy1.pt"
    assert main(["train", "--model", "toy1", "--track", "cpu", "--data", str(tmp_path), "--out", str(out),
                 "--lr", "0.25"]) == 0
    assert capsys.readouterr().out.strip() == f"weights: {out}"
    weights = read_weights(out)
    assert (weights.kind, weights.config) == ("toy", ToyConfig("toy1", 0.25))
    assert torch.equal(weights.network().weight, torch.full((1, 1), 0.25))
    predictor = load_predictor("toy1", out)
    assert isinstance(predictor, ToyPredictor) and predictor.net.weight.item() == 0.25
    for extra, message in ((["--track", "full"], "--track 'full': choose cpu"),
                           (["--track", "cpu", "--bf16"], "--bf16 is not an option of the toy track; drop it")):
        assert main(["train", "--model", "toy1", "--data", ".", "--out", "x.pt", *extra]) == 2
        assert capsys.readouterr().err.strip() == f"error: {message}"
    with pytest.raises(UserError, match="not a toy weights file; train one with `dsr-bench train --model toy1`"):
        read_weights(ROOT / "dsr_bench/models/weights/cpu-track/dsr.pt", kind="toy")


def _epe_by_hand(data: Path, names) -> float:
    """The docs' example metric of a zero-motion prediction, computed here without the metric's code: the ground
    truth's flow length (cm) over the visible surface's object voxels, averaged per step index, then over steps."""
    from dsr_bench.constants import TSDF_SURFACE_LOW
    from dsr_bench.dataset.sequence import SequenceReader

    table = []
    for name in names:
        with SequenceReader(data / f"{name}.h5") as seq:
            row = []
            for t in range(seq.num_steps):
                flow, tsdf, mask = seq.read("scene_flow_3d", t), seq.read("tsdf", t), seq.read("mask_3d", t)
                band = (mask > 0) & (tsdf > TSDF_SURFACE_LOW) & (tsdf < 0)
                band[..., 0] = False
                row.append(np.linalg.norm(flow[:, band].astype(np.float64), axis=0).mean() * 0.4 if band.any()
                           else np.nan)
            table.append(row)
    return float(np.mean(np.nanmean(np.array(table), axis=0)))


def test_docs_adding_a_metric_works_as_written(monkeypatch, tmp_path, capsys):
    """docs/evaluation.md, 'Adding a metric': its function and entry give a headline metric that evaluate scores
    (metrics, per_step, per_sequence, the table's row) with the value computed by hand, every other number the same."""
    from dsr_bench.models.predictors import load_predictor, predict_split
    from dsr_bench.scoring import evaluate as evaluation, metrics
    from dsr_bench.testing import write_synthetic_dataset

    function, entry = _doc_blocks("docs/evaluation.md", "Adding a metric")
    scope = dict(vars(metrics))
    exec(function, scope)
    metric = eval(entry.strip().rstrip(","), scope)
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=2, num_steps=3)
    names = ["seq_0000", "seq_0001"]
    predict_split(load_predictor("static"), data, names, tmp_path / "pred")
    before = evaluation.evaluate(tmp_path / "pred", data, workers=1).results
    monkeypatch.setattr(metrics, "METRICS", metrics.METRICS + (metric,))
    monkeypatch.setattr(evaluation, "METRICS", metrics.METRICS)
    after = evaluation.evaluate(tmp_path / "pred", data, workers=1).results
    key = metric.key
    assert after["metrics"][key] == pytest.approx(_epe_by_hand(data, names), rel=1e-6)
    assert after["metrics"][key] > 0 and len(after["per_step"][key]) == 3
    assert set(after["per_sequence"]["seq_0001"]) == set(before["per_sequence"]["seq_0001"]) | {key}

    def drop(d):
        return {k: v for k, v in d.items() if k != key}

    for part in ("metrics", "per_step", "per_sequence", "breakdowns"):
        cut = {n: drop(v) for n, v in after[part].items()} if part == "per_sequence" else drop(after[part])
        assert cut == before[part], part
    monkeypatch.setenv("COLUMNS", "200")
    assert main(["evaluate", str(tmp_path / "pred"), "--data", str(data), "--workers", "1"]) == 0
    assert metric.title in capsys.readouterr().out
