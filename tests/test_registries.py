"""The registries (issue 28): models, metrics, cameras and object sets are each one table, and every list of
their names (help texts, error messages, the lists other modules keep) is derived from it; a new entry is
reachable everywhere without another edit."""

from types import MappingProxyType

import pytest

from dsr_bench.cli import main
from dsr_bench.errors import UserError
from dsr_bench.models import registry


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
    from annotator.importer import CAMERA_NAMES
    from dsr_bench.constants import CAMERAS, MODEL_CAMERA
    from generators.capture import CAPTURE_CAMERAS

    assert tuple(CAMERAS) == CAPTURE_CAMERAS == CAMERA_NAMES == ("front", "back") and MODEL_CAMERA == "front"


def test_a_new_camera_is_one_entry(monkeypatch, tmp_path):
    """DATASHEET.md, 'Adding a camera': an entry of constants.CAMERAS is a camera of generate --cameras and of
    make_camera, and the error lists it; the model camera stays required."""
    pytest.importorskip("pybullet")
    from dsr_bench.constants import CAMERAS
    from dsr_bench.geometry import make_camera
    from generators.run import check_plan, plan_from_arguments

    monkeypatch.setitem(CAMERAS, "left", {"eye": (1.2, 0.0, 0.3), "target": (0.5, 0.0, 0.0), "up": (-0.3, 0.0, 0.7)})
    args = {"objects": "cube", "num_sequences": 1, "out": tmp_path / "d"}
    check_plan(plan_from_arguments(**args, cameras="front,left"))
    assert make_camera("left", 24, 32).extrinsics[:3, 3].tolist() == [1.2, 0.0, 0.3]
    with pytest.raises(UserError, match=r"^--cameras 'left': use front or front,back,left$"):
        check_plan(plan_from_arguments(**args, cameras="left"))


def test_object_set_names_are_the_objects_table(capsys, monkeypatch):
    from generators.objects import OBJECT_SET_NAMES, OBJECT_SETS, get_object_set

    assert OBJECT_SET_NAMES == tuple(OBJECT_SETS) == ("cube", "shapenet", "ycb", "procedural", "procedural-novel")
    monkeypatch.setitem(OBJECT_SETS, "boxes", ("generators.objects.builtin:CubeSet", False))
    assert get_object_set("boxes").sample(__import__("numpy").random.default_rng(0), 1)[0].category
    monkeypatch.setenv("COLUMNS", "400")
    for command in ("generate", "generate-captures"):
        assert main([command, "--help"]) == 0
        assert "Object set: cube | shapenet | ycb | procedural | procedural-novel." in capsys.readouterr().out
