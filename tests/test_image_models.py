"""The 2D track's models (2DFlow, SE3-Net, SE3Pose-Net): the rigid-motion algebra on cases with known
answers, shapes and the zero-motion start, losses that fall, the push mapped to the image, and train ->
predict -> evaluate from the CLI on a synthetic dataset (2D-only predictions)."""

import json
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dsr_bench.cli import main  # noqa: E402
from dsr_bench.models import rigid  # noqa: E402
from dsr_bench.models.image_config import IMAGE_MODEL_NAMES, ImageModelConfig  # noqa: E402
from dsr_bench.models.image_nets import ImageNet, flow_at  # noqa: E402
from dsr_bench.models.training.image_track import flow_loss, image_step  # noqa: E402
from dsr_bench.testing import write_synthetic_dataset  # noqa: E402

SMALL = dict(width=4, hidden=16)


def _rot_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def test_pose_matrices_rotate_actively_about_the_world_axes():
    pose = rigid.pose_matrices(torch.tensor([0.1, 0.2, 0.3, 0.0, 0.0, math.pi / 2], dtype=torch.float64))
    assert torch.allclose(pose[:3, :3], _rot_z(math.pi / 2))
    moved = pose[:3, :3] @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64) + pose[:3, 3]
    assert torch.allclose(moved, torch.tensor([0.1, 1.2, 0.3], dtype=torch.float64))  # x -> y, then translated
    assert torch.allclose(rigid.rigid_inverse(pose) @ pose, torch.eye(4, dtype=torch.float64))


def test_flow_from_poses_moves_points_fixed_in_each_object_with_it():
    """Points a_k fixed in object k's frame are seen at P_k a_k and then at P'_k a_k: with one-hot masks the
    flow is exactly P'_k a_k - P_k a_k; the background slot does not move."""
    gen = torch.Generator().manual_seed(0)
    params = torch.randn(1, 2, 6, generator=gen, dtype=torch.float64)
    next_params = params + 0.2 * torch.randn(1, 2, 6, generator=gen, dtype=torch.float64)
    poses, next_poses = rigid.pose_matrices(params), rigid.pose_matrices(next_params)
    local = torch.randn(3, 5, 3, generator=gen, dtype=torch.float64)  # 5 points on each of 2 objects + background

    def seen(transforms):
        return torch.cat([local[k] @ transforms[0, k, :3, :3].T + transforms[0, k, :3, 3] for k in range(2)]
                         + [local[2]])

    points, expected_next = seen(poses), seen(next_poses)
    masks = torch.zeros(1, 3, 15, dtype=torch.float64)
    for k in range(3):
        masks[0, k, 5 * k: 5 * k + 5] = 1
    flow = rigid.flow_from_poses(points[None], masks, poses, next_poses)[0]
    assert torch.allclose(flow[:10], (expected_next - points)[:10], atol=1e-12)
    assert torch.all(flow[10:] == 0)
    # a half-and-half mask blends the two motions linearly
    masks[0, :, 0] = torch.tensor([0.5, 0.5, 0.0], dtype=torch.float64)
    mixed = rigid.flow_from_poses(points[None], masks, poses, next_poses)[0, 0]
    motions = next_poses @ rigid.rigid_inverse(poses)
    one = [motions[0, k, :3, :3] @ points[0] + motions[0, k, :3, 3] - points[0] for k in range(2)]
    assert torch.allclose(mixed, 0.5 * one[0] + 0.5 * one[1], atol=1e-12)


def test_a_quarter_turn_about_a_pivot_keeps_the_pivot_and_turns_the_rest():
    pivot = torch.tensor([[0.5, 0.0, 0.1]], dtype=torch.float64)
    transform = rigid.about_pivots(_rot_z(math.pi / 2)[None], torch.tensor([[0.0, 0.0, 0.02]], dtype=torch.float64),
                                   pivot)
    points = torch.tensor([[[0.5, 0.0, 0.1], [0.6, 0.0, 0.1]]], dtype=torch.float64)
    masks = torch.tensor([[[1.0, 1.0], [0.0, 0.0]]], dtype=torch.float64)
    flow = rigid.blended_flow(points, masks, transform[None])[0]
    assert torch.allclose(flow[0], torch.tensor([0.0, 0.0, 0.02], dtype=torch.float64))  # the pivot only translates
    assert torch.allclose(flow[1], torch.tensor([-0.1, 0.1, 0.02], dtype=torch.float64), atol=1e-12)


def _batch(b=4, h=48, w=64, seed=0):
    gen = torch.Generator().manual_seed(seed)
    v, u = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
    points = torch.stack([0.5 + 0.2 * u, 0.2 * v, torch.zeros_like(u)]).expand(b, 3, h, w).clone()
    mask = torch.zeros(b, h, w, dtype=torch.int64)
    mask[:, 10:30, 20:40] = 1
    points[:, 2][mask > 0] = 0.05
    valid = torch.ones(b, 1, h, w)
    valid[:, :, :2] = 0
    points = points * valid
    flow = torch.zeros(b, 3, h, w)
    flow[:, 0][mask > 0] = 0.03  # the object moves 3 cm along world x
    action = torch.stack([torch.zeros(b, dtype=torch.int64), torch.full((b,), 20),
                          torch.randint(0, w, (b,), generator=gen)], 1)
    return {"points": points, "valid": valid, "next_points": points.clone(), "next_valid": valid.clone(),
            "flow": flow * valid, "mask": mask, "action": action}


@pytest.mark.parametrize("name", IMAGE_MODEL_NAMES)
def test_models_start_still_and_have_the_documented_shapes(name):
    torch.manual_seed(0)
    net = ImageNet(ImageModelConfig(name=name, **SMALL)).eval()
    batch = _batch(b=2)
    with torch.no_grad():
        out = net(batch["points"], batch["valid"], batch["action"])
        small = flow_at(out, batch["points"], batch["valid"])
        full = flow_at(out, torch.nn.functional.interpolate(batch["points"], scale_factor=2),
                       torch.ones(2, 1, 96, 128))
    assert small.shape == (2, 3, 48, 64) and full.shape == (2, 3, 96, 128)
    assert torch.all(small == 0) and torch.all(full.abs() < 1e-6)  # zero-initialised motion outputs
    if name != "2dflow":
        assert out["masks"].shape == (2, 5, 48, 64)
        assert torch.allclose(out["masks"].sum(1), torch.ones(2, 48, 64))
        assert torch.all(out["masks"][:, -1][batch["valid"][:, 0] == 0] == 1)  # no point: background
    if name == "se3posenet":
        assert out["poses"].shape == out["next_poses"].shape == (2, 4, 4, 4)


@pytest.mark.parametrize("name", IMAGE_MODEL_NAMES)
def test_losses_fall_when_fitting_a_push(name):
    torch.manual_seed(0)
    net = ImageNet(ImageModelConfig(name=name, **SMALL))
    optimizer = torch.optim.Adam(net.parameters(), lr=3e-3)
    batch = _batch()
    losses = []
    for _ in range(40):
        (terms,) = image_step(net, batch, optimizer, "cpu")  # the 2D track's step in the one loop
        assert all(isinstance(v, float) for v in terms.values())  # read once, at the step's end
        extra = net.config.pose_consistency * terms["consistency"] if "consistency" in terms else 0.0
        assert terms["total"] == pytest.approx(terms["flow"] + extra, rel=1e-6)
        losses.append(terms["flow"])
    assert losses[0] == pytest.approx(9.0, rel=1e-3)  # 3 cm on every object pixel, none predicted: 9 cm^2
    assert np.mean(losses[-5:]) < 0.5 * losses[0]
    batch["flow"][0, 0, 0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match="loss is nan"):
        image_step(net, batch, optimizer, "cpu")


def test_flow_loss_weighs_object_and_table_pixels_separately():
    target = torch.zeros(1, 3, 2, 2)
    flow = torch.zeros(1, 3, 2, 2)
    flow[0, 0, 0, 0] = 0.01  # 1 cm wrong on the one object pixel
    flow[0, 1, 1, 1] = 0.02  # 2 cm wrong on one of three table pixels
    mask = torch.tensor([[[1, 0], [0, 0]]])
    assert float(flow_loss(flow, target, mask, torch.ones(1, 1, 2, 2))) == pytest.approx(1.0 + 4.0 / 3)


def test_the_action_images_carry_the_direction_everywhere_and_the_start_point():
    from dsr_bench.models.image_nets import action_maps

    maps = action_maps(torch.tensor([[3, 10, 20], [0, 0, 0]]), (24, 32))
    assert maps.shape == (2, 11, 24, 32)
    assert torch.all(maps[0, 3] == 1) and torch.all(maps[0, :3] == 0) and torch.all(maps[1, 0] == 1)
    assert int(maps[0, 8].argmax()) == 10 * 32 + 20 and float(maps[0, 8, 10, 20]) == 1.0  # the bump peaks at (v, u)
    assert float(maps[0, 9, 10, 28]) == pytest.approx(8 / 32) and float(maps[0, 10, 18, 20]) == pytest.approx(8 / 32)


def test_the_push_start_is_projected_with_the_sequences_camera(tmp_path):
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.geometry import pixel_to_world
    from dsr_bench.constants import PUSH_HEIGHT
    from dsr_bench.models.image_data import action_pixels

    data = write_synthetic_dataset(tmp_path / "data", num_sequences=1, num_steps=3)
    with SequenceReader(data / "seq_0000.h5") as seq:
        actions, camera = np.asarray(seq.read("action")), seq.camera("front")
    pixels = action_pixels(actions, camera, (120, 160))
    assert pixels.dtype == np.int64 and np.array_equal(pixels[:, 0], actions[:, 0])
    world = np.concatenate([pixel_to_world(actions[:, 1:]), np.full((len(actions), 1), PUSH_HEIGHT)], 1)
    uv, _ = camera.project(world)  # at 240 x 320: half-size pixels are half the coordinates
    assert np.abs(pixels[:, 2] - uv[:, 0] / 2).max() <= 0.5 + 1e-9
    assert np.abs(pixels[:, 1] - uv[:, 1] / 2).max() <= 0.5 + 1e-9


@pytest.mark.parametrize("name", IMAGE_MODEL_NAMES)
def test_train_predict_evaluate_from_the_cli(name, tmp_path, capsys):
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=2, num_steps=2)
    weights = tmp_path / f"{name}.pt"
    assert main(["train", "--model", name, "--track", "cpu", "--data", str(data), "--out", str(weights),
                 "--single-batches", "2", "--batch-size", "2", "--quiet"]) == 0
    state = torch.load(weights, weights_only=True)
    assert state["model_config"]["name"] == name and state["model_config"]["image_factor"] == 2
    assert state["data"]["sequences"] == 2 and all(v.dtype != torch.float32 for v in state["model"].values())
    pred = tmp_path / "pred"
    assert main(["predict", "--model", name, "--checkpoint", str(weights), "--data", str(data),
                 "--out", str(pred)]) == 0
    import h5py

    with h5py.File(pred / "seq_0000.h5", "r") as f:
        assert set(f) == {"motion_2d"} and f["motion_2d"].shape == (2, 240, 320, 3)
    meta = json.loads((pred / "meta.json").read_text())
    assert meta["name"] == f"{name}-cpu" and meta["parameters"]["image"] == [120, 160]
    assert ("num_slots" in meta["parameters"]) == (name != "2dflow")  # 2DFlow has no masks
    results = tmp_path / "results.json"
    assert main(["evaluate", str(pred), "--data", str(data), "--out", str(results)]) == 0
    metrics = json.loads(results.read_text())["metrics"]
    assert set(metrics) == {"motion_2d"} and math.isfinite(metrics["motion_2d"])
    # the wrong model for the weights, and a 3D-track option, are one-line errors
    other = "se3net" if name == "2dflow" else "2dflow"
    assert main(["predict", "--model", other, "--checkpoint", str(weights), "--data", str(data),
                 "--out", str(tmp_path / "p2")]) == 2
    assert f"holds a '{name}' model" in capsys.readouterr().err
    assert main(["train", "--model", "2dflow", "--stage", "cube-single", "--data", str(data), "--out",
                 str(tmp_path / "x.pt")]) == 2
    assert "--stage is not an option of the 2D track" in capsys.readouterr().err


@pytest.mark.parametrize("name", IMAGE_MODEL_NAMES)
def test_the_shipped_2d_weights_are_small_cpu_track_models(name, tmp_path):
    from dsr_bench.models.predictors import load_predictor, shipped_weights

    path = shipped_weights(name)
    assert path is not None and path.stat().st_size < 4_000_000, path
    state = torch.load(path, weights_only=True)
    assert ImageModelConfig.from_dict(state["model_config"]) == ImageModelConfig(name=name, image_factor=2)
    assert state["data"]["dir"] == "cpu-train" and state["data"]["split_checksum"]
    first, last = state["training"]["loss_first_tenth"]["flow"], state["training"]["loss_last_tenth"]["flow"]
    assert last < 0.8 * first  # it learned
    predictor = load_predictor(name)  # no --checkpoint: the shipped file
    assert predictor.name == f"{name}-cpu" and predictor.weights["source"] == "dsr-bench, shipped CPU-track weights"
    assert not predictor.net.training


def test_a_file_that_is_not_2d_weights_is_a_one_line_error(tmp_path, capsys):
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=1, num_steps=2)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a torch file")
    three_d = tmp_path / "dsr.pt"
    torch.save({"format": "dsr-bench-cpu-weights", "model": {}, "model_config": {}}, three_d)
    for path, message in ((junk, "junk.pt: not a loadable dsr-bench checkpoint"),
                          (three_d, "dsr.pt: not a 2D-track weights file"),
                          (tmp_path / "missing.pt", "checkpoint not found")):
        assert main(["predict", "--model", "se3net", "--checkpoint", str(path), "--data", str(data),
                     "--out", str(tmp_path / "p")]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "p").exists()
