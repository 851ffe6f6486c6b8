"""The authors' released checkpoints: names mapped by the table, shapes checked, every tensor used,
the same network after a round trip through the official names, one-line errors, and
`dsr-bench predict --weights` end to end. The official key lists (both motion layouts) are in
tests/data/official_checkpoint_keys.txt, measured from the authors' model.py."""

import hashlib
import json
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from dsr_bench.errors import UserError
from dsr_bench.models import DSRNet, ModelConfig
from dsr_bench.models.official_weights import (
    FILLED_MASK_BIAS,
    LAYOUT,
    convert_official_state,
    is_official_state,
    key_table,
)

KEYS_FILE = Path(__file__).parent / "data" / "official_checkpoint_keys.txt"
VARIANTS = ("dsr", "single", "nowarp", "gtwarp", "3dflow")
SMALL = (32, 32, 16)


def _official_keys() -> dict[str, dict[str, tuple]]:
    """{"se3"|"conv": {key: shape}} in the file's order."""
    out, current = {}, None
    for line in KEYS_FILE.read_text().splitlines():
        if line.startswith("# ModelDSR("):
            current = out.setdefault("se3" if "motion_type='se3'" in line else "conv", {})
        elif line.strip() and not line.startswith("#"):
            key, shape = line.split(" ", 1)
            out_shape = shape.strip("()").replace(" ", "")
            current[key] = tuple(int(n) for n in out_shape.split(",") if n)
    return out


OFFICIAL = _official_keys()


def _random(key: str, shape: tuple, gen: torch.Generator) -> torch.Tensor:
    """A plausible tensor for `key`: scaled weights, BatchNorm affine near (1, 0), positive variances."""
    if key.endswith("num_batches_tracked"):
        return torch.randint(1, 10_000, (), generator=gen)
    if key.endswith("running_var"):
        return torch.rand(shape, generator=gen) + 0.5
    values = torch.randn(shape, generator=gen)
    if len(shape) >= 2:  # conv / linear weight: fan-in scaling keeps activations finite
        fan_in = 1
        for n in shape[1:]:
            fan_in *= n
        return values * (1.0 / fan_in) ** 0.5
    if ".norm.weight" in key or ".bn1.weight" in key or ".bn2.weight" in key:
        return 1 + 0.1 * values
    return 0.1 * values


def official_state(layout: str, seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return {k: _random(k, shape, gen) for k, shape in OFFICIAL[layout].items()}


def test_the_fixture_holds_both_official_layouts():
    assert len(OFFICIAL["se3"]) == 254 and len(OFFICIAL["conv"]) == 230
    counts = {layout: sum(torch.Size(s).numel() for k, s in keys.items() if not k.endswith("num_batches_tracked"))
              for layout, keys in OFFICIAL.items()}
    params = {layout: sum(torch.Size(s).numel() for k, s in keys.items()
                          if not k.endswith(("running_mean", "running_var", "num_batches_tracked")))
              for layout, keys in OFFICIAL.items()}
    assert params == {"se3": 5855205, "conv": 3709227} and counts["se3"] > params["se3"]  # the file's header
    assert [k for k, _ in key_table("se3")] == list(OFFICIAL["se3"])  # the table names every key, in order
    assert [k for k, _ in key_table("conv")] == list(OFFICIAL["conv"])


@pytest.mark.parametrize("name", VARIANTS)
def test_every_official_tensor_is_used_and_loads(name):
    layout = LAYOUT[name]
    state = official_state(layout)
    assert is_official_state({"state_dict": state}) and is_official_state(state)
    converted = convert_official_state({"state_dict": state}, name)
    net = DSRNet(ModelConfig.for_model(name))
    assert list(converted) == list(net.state_dict())  # exactly our keys
    net.load_state_dict(converted)  # strict
    ours = net.state_dict()
    for theirs, mine in key_table(layout):  # every official tensor, unchanged, under its name
        assert torch.equal(ours[mine], state[theirs]), (theirs, mine)
        assert ours[mine].dtype == state[theirs].dtype
    if layout == "conv":  # the official 3DFlow has no mask head: ours predicts background everywhere
        assert not ours["mask_head.weight"].any()
        assert ours["mask_head.bias"].tolist() == [0.0, 0.0, 0.0, 0.0, FILLED_MASK_BIAS]


def _randomise(net: DSRNet, seed: int) -> None:
    """Random parameters and BatchNorm running statistics, so that every tensor matters in eval mode."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for key, value in net.state_dict().items():
            value.copy_(_random(key, tuple(value.shape), gen))


@pytest.mark.parametrize("name", VARIANTS)
def test_a_round_trip_through_the_official_names_gives_the_same_network(name):
    """Our random state -> official names (the inverse table) -> converted back: identical tensors and
    identical outputs, in eval mode (running statistics) and with batch statistics."""
    cfg = ModelConfig.for_model(name, grid=SMALL)
    net = DSRNet(cfg)
    _randomise(net, 1)
    inverse = {mine: theirs for theirs, mine in key_table(LAYOUT[name])}
    official = {inverse[k]: v.clone() for k, v in net.state_dict().items() if k in inverse}
    assert set(official) == set(OFFICIAL[LAYOUT[name]])  # the official names, all of them
    other = DSRNet(cfg)
    other.load_state_dict(convert_official_state({"state_dict": official}, name, grid=SMALL))
    if LAYOUT[name] == "conv":  # the filled mask head is the only difference
        other.mask_head.load_state_dict(net.mask_head.state_dict())
    for key, value in net.state_dict().items():
        assert torch.equal(value, other.state_dict()[key]), key
    gen = torch.Generator().manual_seed(2)
    tsdf = torch.rand((2,) + SMALL, generator=gen) * 2 - 1  # batch 2: batch statistics of a 1 x 1 x 1 volume
    action = torch.zeros(2, 8, *SMALL[:2])
    action[0, 3, 10, 12] = action[1, 6, 20, 5] = 1
    state = torch.randn((2, cfg.state_channels) + SMALL, generator=gen)
    with torch.no_grad():
        for train in (False, True):
            net.train(train)
            other.train(train)
            a, b = net(tsdf, action, state), other(tsdf, action, state)
            for key in ("mask_logits", "mask", "motion", "representation"):
                assert torch.equal(a[key], b[key]), (key, train)
            if cfg.history == "warp":
                assert torch.equal(net.next_state(a), other.next_state(b))


def _message(exc_info) -> str:
    text = str(exc_info.value)
    assert "\n" not in text
    return text


def test_a_bad_official_file_fails_in_one_line():
    state = official_state("se3")
    extra = dict(state, **{"transform_decoder.conv3d99.conv.weight": torch.zeros(1)})
    with pytest.raises(UserError) as exc:
        convert_official_state({"state_dict": extra}, "dsr", source="dsr.pth")
    assert _message(exc).startswith("dsr.pth: unknown key 'transform_decoder.conv3d99.conv.weight'")
    missing = {k: v for k, v in state.items() if k != "volume_encoder.resn32.bn2.running_var"}
    with pytest.raises(UserError) as exc:
        convert_official_state({"state_dict": missing}, "dsr", source="dsr.pth")
    assert _message(exc).startswith("dsr.pth: key 'volume_encoder.resn32.bn2.running_var' is missing")
    wrong = dict(state, **{"transform_decoder.mlp._layers.4.weight": torch.zeros(30, 512)})
    with pytest.raises(UserError) as exc:
        convert_official_state({"state_dict": wrong}, "single", source="single.pth")
    assert _message(exc).startswith("single.pth: transform_decoder.mlp._layers.4.weight has shape (30, 512), "
                                    "our motion_head.mlp.8.weight needs (24, 512)")
    with pytest.raises(UserError) as exc:  # the authors' networks need the full grid
        convert_official_state(state, "dsr", grid=SMALL, source="dsr.pth")
    assert "transform_decoder.conv3d50.weight" in _message(exc) and "128 x 128 x 48 grid" in _message(exc)
    with pytest.raises(UserError) as exc:
        convert_official_state({"state_dict": official_state("conv")}, "dsr", source="3dflow.pth")
    assert _message(exc) == ("3dflow.pth holds a conv-motion (3DFlow) network, not what --model dsr needs; "
                             "use --model 3dflow")
    with pytest.raises(UserError) as exc:
        convert_official_state({"state_dict": state}, "3dflow", source="dsr.pth")
    assert "holds an SE(3)-motion network" in _message(exc) and "use --model dsr" in _message(exc)
    with pytest.raises(UserError) as exc:
        convert_official_state({"state_dict": {"encoder.level0.conv.weight": torch.zeros(1)}}, "dsr", source="x.pth")
    assert "not the authors' DSR weights" in _message(exc)
    assert not is_official_state({"model": {}, "model_config": {}}) and not is_official_state([1])


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from dsr_bench.testing import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("official") / "data", num_sequences=1, num_steps=1)


def test_predict_with_the_authors_weights(data, tmp_path, capsys):
    """`dsr-bench predict --model dsr --weights dsr.pth` on the full grid (one sequence of one push): run as
    the authors ran them (their warp kernel, BatchNorm over batches of 12); meta.json and the results record
    the file, its sha256, the BatchNorm mode and the warp kernel, and the predictions score. --warp floor
    --bn-batch 1 depart from it, and say so."""
    from dsr_bench.cli import main

    weights = tmp_path / "dsr.pth"
    torch.save({"state_dict": official_state("se3")}, weights)
    pred = tmp_path / "pred"
    assert main(["predict", "--model", "dsr", "--weights", str(weights), "--data", str(data), "--out", str(pred)]) == 0
    meta = json.loads((pred / "meta.json").read_text())
    expected = {"source": "official", "file": "dsr.pth", "sha256": hashlib.sha256(weights.read_bytes()).hexdigest(),
                "batchnorm": "batch statistics over 12 consecutive sequences of the split (the authors' test "
                             "protocol); the last batch holds the rest",
                "warp": "official: the authors' kernel (base corner int(p), truncated toward zero)"}
    assert meta["name"] == "dsr" and meta["weights"] == expected and meta["parameters"]["weights"] == expected
    assert "run as the authors ran them: warp kernel official" in meta["description"]
    assert main(["evaluate", str(pred), "--data", str(data), "--out", str(tmp_path / "r.json")]) == 0
    results = json.loads((tmp_path / "r.json").read_text())
    assert results["meta"]["parameters"]["weights"]["source"] == "official"
    assert results["meta"]["parameters"]["weights"]["warp"].startswith("official")
    assert main(["predict", "--model", "dsr", "--weights", str(weights), "--warp", "floor", "--bn-batch", "1",
                 "--data", str(data), "--out", str(tmp_path / "floor")]) == 0
    meta = json.loads((tmp_path / "floor" / "meta.json").read_text())
    assert meta["weights"]["warp"].startswith("floor") and meta["weights"]["batchnorm"] == "batch statistics (official)"
    assert "departing from the authors' way: warp kernel floor" in meta["description"]
    capsys.readouterr()

    def one_line_error(*argv) -> str:
        assert main(["predict", *argv, "--data", str(data), "--out", str(tmp_path / "p")]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1
        return err

    flow = tmp_path / "3dflow.pth"
    torch.save({"state_dict": official_state("conv")}, flow)
    assert one_line_error("--model", "dsr", "--weights", str(flow)).endswith(
        "holds a conv-motion (3DFlow) network, not what --model dsr needs; use --model 3dflow")
    assert "use --model dsr" in one_line_error("--model", "single", "--weights", str(weights))  # dsr.pth is DSR-Net
    assert "not both" in one_line_error("--model", "dsr", "--weights", str(weights), "--checkpoint", str(weights))
    assert "not --model static" in one_line_error("--model", "static", "--weights", str(weights))
    assert "weights not found" in one_line_error("--model", "dsr", "--weights", str(tmp_path / "none.pth"))
    assert "--bn-batch is for the authors' weights" in one_line_error("--model", "dsr", "--bn-batch", "12")
    assert "sequences per batch must be at least 1" in one_line_error("--model", "dsr", "--weights", str(weights),
                                                                     "--bn-batch", "0")
    assert "--warp 'round': choose one of floor, official" in one_line_error("--model", "dsr", "--warp", "round")
    assert "not --model static" in one_line_error("--model", "static", "--warp", "official")
    ours = tmp_path / "ours.pt"
    torch.save({"format": "dsr-bench-checkpoint", "model": {}, "model_config": {}}, ours)
    assert "pass it with --checkpoint" in one_line_error("--model", "dsr", "--weights", str(ours))
