"""DSR-Net and baselines on small grids: shapes, conventions, history switches, loss matching,
a few training steps that lower the loss, checkpoints that resume and load safely, prediction."""

import itertools

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dsr_bench.errors import UserError  # noqa: E402
from dsr_bench.models import DSRNet, ModelConfig  # noqa: E402
from dsr_bench.models.loss import best_matching, dsr_loss, matched_target, score_matrix  # noqa: E402
from dsr_bench.models.se3 import blended_motion, euler_to_matrix, soft_centroids  # noqa: E402

GRID = (32, 32, 16)


def test_euler_conventions():
    a = torch.tensor([0.3, 0.0, 0.0])
    standard = euler_to_matrix(a, "standard")
    official = euler_to_matrix(a, "official")
    assert torch.allclose(official, euler_to_matrix(-a, "standard"), atol=1e-6)  # passive = usual R(-theta)
    assert torch.allclose(standard @ torch.tensor([0.0, 1.0, 0.0]), torch.tensor([0.0, np.cos(0.3), np.sin(0.3)], dtype=torch.float32),
                          atol=1e-6)
    z = torch.tensor([0.1, 0.2, 0.3])
    rz = euler_to_matrix(torch.tensor([0, 0, 0.3]), "standard")
    ry = euler_to_matrix(torch.tensor([0, 0.2, 0]), "standard")
    rx = euler_to_matrix(torch.tensor([0.1, 0, 0]), "standard")
    assert torch.allclose(euler_to_matrix(z, "standard"), rz @ ry @ rx, atol=1e-6)


def test_pivots_and_blended_motion():
    mask = torch.zeros(1, 3, 8, 8, 4)
    mask[0, 0, 2:4, 2:4, 0:2] = 1  # object slot 0
    mask[0, 1, 6, 6, 3] = 1  # object slot 1
    mask[0, 2] = 1 - mask[0, 0] - mask[0, 1]  # background last
    pivots = soft_centroids(mask[:, :-1])
    assert torch.allclose(pivots[0, 0], torch.tensor([2.5, 2.5, 0.5]))
    rot = torch.eye(3).repeat(1, 2, 1, 1)
    trans = torch.tensor([[[1.0, 0.0, -1.0], [0.0, 0.0, 0.0]]])
    motion = blended_motion(mask, rot, trans, pivots)
    assert torch.allclose(motion[0, :, 2, 2, 0], torch.tensor([1.0, 0.0, -1.0]))
    assert motion[0, :, 0, 0, 0].abs().sum() == 0  # background does not move
    # a rotation about the pivot leaves the pivot in place
    quarter = euler_to_matrix(torch.tensor([0.0, 0.0, np.pi / 2]), "standard")
    motion = blended_motion(mask, torch.stack([quarter, torch.eye(3)])[None], torch.zeros(1, 2, 3), pivots)
    moved = torch.tensor([2.0, 2.0, 0.0]) + motion[0, :, 2, 2, 0]
    assert torch.allclose(quarter @ (torch.tensor([2.0, 2.0, 0.0]) - pivots[0, 0]) + pivots[0, 0], moved, atol=1e-5)


@pytest.mark.parametrize("name", ["dsr", "single", "nowarp", "gtwarp", "3dflow"])
def test_every_variant_runs_and_carries_history(name):
    torch.manual_seed(0)
    net = DSRNet(ModelConfig.for_model(name, grid=GRID))
    tsdf = torch.rand(2, *GRID) * 2 - 1
    action = torch.zeros(2, 8, *GRID[:2])
    action[:, 3, 10, 12] = 1
    out = net(tsdf, action, net.initial_state(2, "cpu"))
    assert out["mask"].shape == (2, 5) + GRID and torch.allclose(out["mask"].sum(1), torch.ones(2, *GRID), atol=1e-5)
    assert out["motion"].shape == (2, 3) + GRID and out["representation"].shape == (2, 8) + GRID
    gt_flow, gt_mask = torch.randn(2, 3, *GRID), torch.randint(0, 3, (2, *GRID))
    state = net.next_state(out, gt_flow, gt_mask)
    assert state.shape == (2, 8) + GRID and not state.requires_grad
    if name in ("single", "3dflow"):
        assert state.abs().sum() == 0
        other = net(tsdf, action, torch.randn_like(state))  # history is ignored
        assert torch.allclose(other["motion"], out["motion"])
    elif name == "nowarp":
        assert torch.equal(state, out["representation"].detach())
    else:
        assert not torch.equal(state, out["representation"].detach())


def test_se3_head_starts_at_identity():
    net = DSRNet(ModelConfig.for_model("dsr", grid=GRID)).eval()
    out = net(torch.zeros(1, *GRID), torch.zeros(1, 8, *GRID[:2]), net.initial_state(1, "cpu"))
    assert out["motion"].abs().max() < 1e-5  # zero-initialised last layer: identity transforms


def test_bad_grid_and_model():
    with pytest.raises(ValueError, match="multiple of 16"):
        ModelConfig.for_model("dsr", grid=(30, 32, 16))
    with pytest.raises(ValueError, match="unknown model"):
        ModelConfig.for_model("transformer")


def test_matching_equals_brute_force_and_targets():
    torch.manual_seed(1)
    logits = torch.randn(3, 5, 6, 6, 4)
    gt = torch.randint(0, 5, (3, 6, 6, 4))
    scores = score_matrix(torch.log_softmax(logits, 1), gt)
    for b, order in enumerate(best_matching(scores)):
        best = max(itertools.permutations(range(4)), key=lambda p: float(sum(scores[b, i, p[i]] for i in range(4))))
        assert float(sum(scores[b, i, best[i]] for i in range(4))) == pytest.approx(
            float(sum(scores[b, i, order[i]] for i in range(4))))
    target = matched_target(gt, [np.array([3, 2, 1, 0])] * 3, 5)
    assert torch.equal(target[gt == 0], torch.full_like(target[gt == 0], 4))  # empty -> background (last)
    assert torch.equal(target[gt == 1], torch.full_like(target[gt == 1], 3))


def test_matching_is_carried_between_steps():
    logits = torch.randn(1, 5, 6, 6, 4)
    gt = torch.randint(0, 3, (1, 6, 6, 4))
    _, _, matching = dsr_loss({"mask_logits": logits, "motion": torch.zeros(1, 3, 6, 6, 4)}, gt, torch.zeros(1, 3, 6, 6, 4))
    fixed = [np.array([3, 2, 1, 0])]
    _, terms_fixed, used = dsr_loss({"mask_logits": logits, "motion": torch.zeros(1, 3, 6, 6, 4)}, gt,
                                    torch.zeros(1, 3, 6, 6, 4), fixed)
    assert used is fixed
    _, terms_best, _ = dsr_loss({"mask_logits": logits, "motion": torch.zeros(1, 3, 6, 6, 4)}, gt,
                                torch.zeros(1, 3, 6, 6, 4), matching)
    assert terms_best["mask"] <= terms_fixed["mask"] + 1e-6


def _toy_batch(steps=3, batch=2):
    """A box sliding one voxel per step in +D1 on a small grid, with its flow and action."""
    tsdf = torch.ones(batch, steps, *GRID)
    mask = torch.zeros(batch, steps, *GRID, dtype=torch.long)
    flow = torch.zeros(batch, steps, 3, *GRID)
    action = torch.zeros(batch, steps, 8, *GRID[:2])
    for t in range(steps):
        y0, x0 = 10, 8 + t
        tsdf[:, t, y0:y0 + 6, x0:x0 + 6, :5] = -0.5
        mask[:, t, y0:y0 + 6, x0:x0 + 6, :5] = 1
        flow[:, t, 1][mask[:, t] == 1] = 1.0
        action[:, t, 0, y0 + 3, x0 - 2] = 1
    return {"tsdf": tsdf, "action": action, "mask_3d": mask, "scene_flow_3d": flow}


def test_a_few_training_steps_lower_the_loss():
    from dsr_bench.train import train_step

    torch.manual_seed(0)
    net = DSRNet(ModelConfig.for_model("dsr", grid=GRID))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3, betas=(0.9, 0.95))
    batch = _toy_batch()
    losses = [np.mean([t["total"] for t in train_step(net, batch, opt, torch.device("cpu"))]) for _ in range(12)]
    assert losses[-1] < 0.6 * losses[0], losses


def test_checkpoint_round_trip_and_resume(tmp_path):
    from dsr_bench.train import STAGES, load_checkpoint, save_checkpoint

    cfg = ModelConfig.for_model("nowarp", grid=GRID)
    net = DSRNet(cfg)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.StepLR(opt, 5, 0.5)
    path = save_checkpoint(tmp_path / "c.pt", net, opt, sched, cfg, STAGES["cube-single"], 2, 7, 40)
    state = load_checkpoint(path)  # weights_only=True inside
    assert state["epoch"] == 2 and state["batch_index"] == 7 and state["step"] == 40
    assert ModelConfig.from_dict(state["model_config"]) == cfg
    again = DSRNet(cfg)
    again.load_state_dict(state["model"])
    for a, b in zip(net.state_dict().values(), again.state_dict().values()):
        assert torch.equal(a, b)
    (tmp_path / "bad.pt").write_bytes(b"junk")
    with pytest.raises(UserError, match="not a loadable"):
        load_checkpoint(tmp_path / "bad.pt")
