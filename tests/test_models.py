"""DSR-Net and baselines on small grids: official layout and conventions, the SE(3) motion against a
direct formula, history switches, bf16 and channels_last, a few training steps that lower the loss,
checkpoints and the resumable sampler."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from torch import nn  # noqa: E402

from dsr_bench.errors import UserError  # noqa: E402
from dsr_bench.models import DSRNet, ModelConfig  # noqa: E402
from dsr_bench.models.se3 import blended_motion, euler_to_matrix, soft_centroids  # noqa: E402
from dsr_bench.models.warp import forward_warp  # noqa: E402

GRID = (32, 32, 16)
TINY = (16, 16, 16)


def _inputs(grid, batch=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    tsdf = torch.rand(batch, *grid, generator=g) * 2 - 1
    action = torch.zeros(batch, 8, *grid[:2])
    action[:, 3, grid[0] // 3, grid[1] // 2] = 1
    return tsdf, action


def test_euler_conventions():
    a = torch.tensor([0.3, 0.0, 0.0])
    official = euler_to_matrix(a, "official")
    assert torch.allclose(official, euler_to_matrix(-a, "standard"), atol=1e-6)  # passive = usual R(-theta)
    assert torch.allclose(euler_to_matrix(a, "standard") @ torch.tensor([0.0, 1.0, 0.0]),
                          torch.tensor([0.0, np.cos(0.3), np.sin(0.3)], dtype=torch.float32), atol=1e-6)
    angles = torch.tensor([0.1, 0.2, 0.3])
    for conv in ("official", "standard"):
        rz = euler_to_matrix(torch.tensor([0, 0, 0.3]), conv)
        ry = euler_to_matrix(torch.tensor([0, 0.2, 0]), conv)
        rx = euler_to_matrix(torch.tensor([0.1, 0, 0]), conv)
        r = euler_to_matrix(angles, conv)
        assert torch.allclose(r, rz @ ry @ rx, atol=1e-6)  # R = Rz Ry Rx
        assert torch.allclose(r @ r.T, torch.eye(3), atol=1e-6) and torch.det(r) == pytest.approx(1.0, abs=1e-6)
    with pytest.raises(ValueError):
        euler_to_matrix(angles, "xyz")


def test_blended_motion_equals_the_direct_formula():
    g = torch.Generator().manual_seed(0)
    dims = (5, 4, 3)
    mask = torch.softmax(torch.randn(2, 4, *dims, generator=g, dtype=torch.float64) * 3, 1)
    rot = euler_to_matrix(torch.randn(2, 3, 3, generator=g, dtype=torch.float64), "official")
    trans = torch.randn(2, 3, 3, generator=g, dtype=torch.float64)
    pivots = soft_centroids(mask[:, :-1])
    motion = blended_motion(mask, rot, trans, pivots)
    assert motion.dtype == torch.float64
    for b in range(2):
        for idx in np.ndindex(*dims):
            x = torch.tensor(idx, dtype=torch.float64)
            expected = sum(mask[(b, k) + idx] * (rot[b, k] @ (x - pivots[b, k]) + pivots[b, k] + trans[b, k] - x)
                           for k in range(3))
            assert torch.allclose(motion[(b, slice(None)) + idx], expected, atol=1e-10)
        # pivots: probability-weighted mean position of each object channel
        for k in range(3):
            grid = torch.stack(torch.meshgrid(*(torch.arange(d, dtype=torch.float64) for d in dims), indexing="ij"))
            p = (mask[b, k] * grid).sum((1, 2, 3)) / mask[b, k].sum()
            assert torch.allclose(pivots[b, k], p, atol=1e-6)


def test_rotation_about_the_pivot_and_background():
    mask = torch.zeros(1, 3, 8, 8, 4)
    mask[0, 0, 2:4, 2:4, 0:2] = 1
    mask[0, 2] = 1 - mask[0, 0] - mask[0, 1]  # background last
    pivots = soft_centroids(mask[:, :-1])
    assert torch.allclose(pivots[0, 0], torch.tensor([2.5, 2.5, 0.5]))
    quarter = euler_to_matrix(torch.tensor([0.0, 0.0, np.pi / 2]), "standard")
    motion = blended_motion(mask, torch.stack([quarter, torch.eye(3)])[None], torch.zeros(1, 2, 3), pivots)
    moved = torch.tensor([2.0, 2.0, 0.0]) + motion[0, :, 2, 2, 0]
    assert torch.allclose(quarter @ (torch.tensor([2.0, 2.0, 0.0]) - pivots[0, 0]) + pivots[0, 0], moved, atol=1e-5)
    assert motion[0, :, 6, 6, 3].abs().sum() == 0  # background does not move


def test_official_layout_on_the_full_grid():
    net = DSRNet(ModelConfig.for_model("dsr"))
    convs3 = [m for m in net.encoder.modules() if isinstance(m, nn.Conv3d)]
    assert convs3[0].in_channels == 12  # TSDF, 3 coordinates, 8-channel state
    assert [c.stride[0] for c in convs3[:10]] == [2, 2, 1, 1, 1, 2, 1, 1, 1, 2]
    assert net.motion_head.to_vector.kernel_size == (4, 4, 2)
    assert net.mask_head.out_channels == 5 and net.mask_head.kernel_size == (1, 1, 1)
    linears = [m for m in net.motion_head.mlp if isinstance(m, nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(128, 512)] + [(512, 512)] * 3 + [(512, 24)]
    assert {m.negative_slope for m in net.modules() if isinstance(m, nn.LeakyReLU)} == {0.01}
    assert all(isinstance(m, (nn.Conv3d, nn.BatchNorm3d, nn.LeakyReLU)) or not isinstance(m, nn.ReLU)
               for m in net.modules())
    paper = DSRNet(ModelConfig.for_model("dsr", leaky_slope=0.2, grid=GRID))
    assert {m.negative_slope for m in paper.modules() if isinstance(m, nn.LeakyReLU)} == {0.2}
    assert DSRNet(ModelConfig.for_model("dsr", grid=GRID)).motion_head.to_vector.kernel_size == (1, 1, 1)


@pytest.mark.parametrize("name", ["dsr", "single", "nowarp", "gtwarp", "3dflow"])
def test_every_variant_runs_and_carries_history(name):
    torch.manual_seed(0)
    net = DSRNet(ModelConfig.for_model(name, grid=TINY))
    tsdf, action = _inputs(TINY)
    out = net(tsdf, action, net.initial_state(2, "cpu"))
    assert out["mask"].shape == (2, 5) + TINY and torch.allclose(out["mask"].sum(1), torch.ones(2, *TINY), atol=1e-5)
    assert out["motion"].shape == (2, 3) + TINY and out["representation"].shape == (2, 8) + TINY
    assert out["motion"].dtype == torch.float32 and out["motion"].requires_grad
    gt_flow, gt_mask = torch.randn(2, 3, *TINY), torch.randint(0, 3, (2, *TINY))
    state = net.next_state(out, gt_flow, gt_mask)
    assert state.shape == (2, 8) + TINY and not state.requires_grad
    rep, fg = out["representation"].detach(), out["mask"][:, :-1].detach().sum(1)
    if name in ("single", "3dflow"):
        assert state.abs().sum() == 0
        other = net(tsdf, action, torch.randn_like(state))  # history is ignored
        assert torch.allclose(other["motion"], out["motion"])
    elif name == "nowarp":
        assert torch.equal(state, rep)
    elif name == "gtwarp":  # official: ground-truth flow, predicted foreground weights
        assert torch.allclose(state, forward_warp(rep, gt_flow, fg))
    else:
        assert torch.allclose(state, forward_warp(rep, out["motion"].detach(), fg))
    if name not in ("single", "3dflow"):  # the history changes the next prediction
        assert not torch.allclose(net(tsdf, action, state)["mask"], out["mask"])


def test_zero_motion_init_and_input_checks():
    net = DSRNet(ModelConfig.for_model("dsr", grid=TINY, init="zero-motion")).eval()
    tsdf, action = _inputs(TINY, 1)
    assert net(tsdf, action, net.initial_state(1, "cpu"))["motion"].abs().max() < 1e-5
    with pytest.raises(ValueError, match="grid"):
        net(torch.zeros(1, 32, 16, 16), action, net.initial_state(1, "cpu"))
    with pytest.raises(ValueError, match="multiple of 16"):
        ModelConfig.for_model("dsr", grid=(30, 32, 16))
    with pytest.raises(ValueError, match="unknown model"):
        ModelConfig.for_model("transformer")
    with pytest.raises(ValueError, match="euler"):
        ModelConfig.for_model("dsr", euler="zyx")
    with pytest.raises(ValueError, match="unknown model config keys"):
        ModelConfig.from_dict({**ModelConfig().as_dict(), "layers": 3})
    cfg = ModelConfig.for_model("gtwarp", grid=TINY, leaky_slope=0.2)
    assert ModelConfig.from_dict(cfg.as_dict()) == cfg


def test_bf16_autocast_keeps_mask_and_motion_fp32_and_close():
    torch.manual_seed(0)
    net = DSRNet(ModelConfig.for_model("dsr", grid=TINY)).eval()
    tsdf, action = _inputs(TINY)
    with torch.no_grad():
        ref = net(tsdf, action, net.initial_state(2, "cpu"))
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = net(tsdf, action, net.initial_state(2, "cpu"))
    assert low["mask"].dtype == torch.float32 and low["motion"].dtype == torch.float32
    assert (low["mask"] - ref["mask"]).abs().max() < 0.1
    assert (low["motion"] - ref["motion"]).abs().max() < 0.1 * ref["motion"].abs().max() + 0.05


def test_channels_last_gives_the_same_outputs():
    torch.manual_seed(0)
    net = DSRNet(ModelConfig.for_model("dsr", grid=TINY)).eval()
    tsdf, action = _inputs(TINY)
    with torch.no_grad():
        ref = net(tsdf, action, net.initial_state(2, "cpu"))
        out = net.to_channels_last()(tsdf, action, net.initial_state(2, "cpu"))
    assert net.encoder.level0.conv.weight.is_contiguous(memory_format=torch.channels_last_3d)
    assert torch.allclose(out["motion"], ref["motion"], atol=1e-4)
    assert torch.allclose(out["mask"], ref["mask"], atol=1e-5)


def toy_batch(grid=TINY, steps=2, batch=2):
    """A box sliding one voxel per step along +D1, pushed from behind: TSDF, action, mask, flow."""
    tsdf = torch.ones(batch, steps, *grid)
    mask = torch.zeros(batch, steps, *grid, dtype=torch.long)
    flow = torch.zeros(batch, steps, 3, *grid)
    action = torch.zeros(batch, steps, 8, *grid[:2])
    for t in range(steps):
        y0, x0 = 4, 4 + t
        tsdf[:, t, y0:y0 + 5, x0:x0 + 5, :4] = -0.5
        mask[:, t, y0:y0 + 5, x0:x0 + 5, :4] = 1
        flow[:, t, 1][mask[:, t] == 1] = 1.0
        action[:, t, 0, y0 + 2, x0 - 1] = 1
    return {"tsdf": tsdf, "action": action, "mask_3d": mask, "scene_flow_3d": flow}


def test_a_few_training_steps_lower_the_loss():
    from dsr_bench.models.training.trainer import train_step

    torch.manual_seed(0)
    net = DSRNet(ModelConfig.for_model("dsr", grid=TINY))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3, betas=(0.9, 0.95))
    batch = toy_batch()
    terms = [train_step(net, batch, opt, "cpu") for _ in range(10)]
    losses = np.array([[np.mean([t[key] for t in step]) for key in ("total", "motion", "mask")] for step in terms])
    assert np.isfinite(losses).all()
    # the total, the motion MSE and the mask cross-entropy all fall (the first two steps vs the last three)
    assert (losses[-3:].mean(0) < 0.8 * losses[:2].mean(0)).all(), losses


def test_train_step_warps_the_state_between_steps_only():
    """A window of L steps warps the state L - 1 times (the state after the last step is never used),
    and each warp is fed the step's predicted motion and foreground probability."""
    from dsr_bench.models.training.trainer import train_step

    torch.manual_seed(0)
    net = DSRNet(ModelConfig.for_model("dsr", grid=TINY))
    calls = []

    def counting_warp(features, flow, weight, eps, deterministic):
        calls.append((features.shape, flow.shape, float(weight.min()) >= 0 and float(weight.max()) <= 1))
        return forward_warp(features, flow, weight, eps, deterministic)

    net._warp = counting_warp
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    train_step(net, toy_batch(steps=3), opt, "cpu")
    assert calls == [((2, 8, *TINY), (2, 3, *TINY), True)] * 2
    calls.clear()
    train_step(net, toy_batch(steps=1), opt, "cpu")
    assert calls == []  # single-step windows: no warp


def test_a_training_step_never_makes_the_host_wait():
    """Forward, matched loss (ids checked elsewhere), backward, fused Adam and the warp of the state
    call no operator that reads a tensor's value to the host (.item(), float(), int()), copies Python
    data to the device (torch.tensor) or sizes a result by the data (nonzero, boolean indexing): on a
    GPU each would stall the queue. Recorded on the CPU through torch's dispatcher."""
    from torch.utils._python_dispatch import TorchDispatchMode

    from dsr_bench.models.loss import dsr_loss

    waits = {"aten._local_scalar_dense.default", "aten.lift_fresh.default", "aten.nonzero.default",
             "aten.masked_select.default"}

    class Record(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.found = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            indices = [a for arg in args if isinstance(arg, (list, tuple)) for a in arg]
            if str(func) in waits or (str(func).startswith("aten.index") and any(
                    isinstance(a, torch.Tensor) and a.dtype == torch.bool for a in indices)):
                self.found.append(str(func))
            return func(*args, **(kwargs or {}))

    torch.manual_seed(0)
    net = DSRNet(ModelConfig.for_model("dsr", grid=TINY))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3, fused=True)  # what `dsr-bench train` uses on a GPU
    batch = toy_batch(steps=3)
    state, matching, records = net.initial_state(2, "cpu"), None, []
    for t in range(3):  # step 0 also fills the per-device cache of the permutation table
        with Record() as record:
            opt.zero_grad(set_to_none=True)
            out = net(batch["tsdf"][:, t], batch["action"][:, t], state)
            loss, _, matching = dsr_loss(out, batch["mask_3d"][:, t], batch["scene_flow_3d"][:, t], matching,
                                         check=False)
            loss.backward()
            opt.step()
            state = net.next_state(out, batch["scene_flow_3d"][:, t], batch["mask_3d"][:, t])
        records.append(record.found)
    assert records[1] == records[2] == [], records
    with Record() as record:  # the recorder does see a value read to the host
        float(loss.detach())
    assert record.found == ["aten._local_scalar_dense.default"]


def test_train_step_reports_the_first_non_finite_step():
    """The window's terms are read once at its end; a non-finite loss names its step."""
    from dsr_bench.models.training.trainer import train_step

    torch.manual_seed(0)
    net = DSRNet(ModelConfig.for_model("dsr", grid=TINY))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    batch = toy_batch(steps=3)
    terms = train_step(net, batch, opt, "cpu")
    assert len(terms) == 3 and all(isinstance(t[k], float) for t in terms for k in ("total", "motion", "mask"))
    assert all(t["total"] == pytest.approx(t["motion"] + 5 * t["mask"], rel=1e-6) for t in terms)
    batch["tsdf"][:, 1, 0, 0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match="loss is nan at window step 1; lower the learning rate"):
        train_step(net, batch, opt, "cpu")


def test_slot_labels_put_the_background_slot_at_zero():
    from dsr_bench.models.labels import slot_labels

    probs = torch.zeros(2, 5, 3)  # (B, K, voxels): K - 1 = 4 object slots, background last
    probs[0, 4, 0] = probs[0, 0, 1] = probs[0, 3, 2] = 1
    probs[1, 2, :] = 1
    labels = slot_labels(probs)
    assert labels.dtype == torch.uint8 and labels.tolist() == [[0, 1, 4], [3, 3, 3]]


def test_checkpoint_round_trip(tmp_path):
    from dsr_bench.models.training.checkpoints import WEIGHTS_FORMAT, read_weights, save_checkpoint
    from dsr_bench.models.training.schedules import STAGES

    cfg = ModelConfig.for_model("nowarp", grid=TINY)
    net = DSRNet(cfg)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda e: 0.5 ** e)
    path = save_checkpoint(tmp_path / "c.pt", net, opt, sched, cfg, STAGES["cube-single"], 2, 7, 40)
    assert not list(tmp_path.glob(".*tmp*"))  # no temporary file left behind
    state = read_weights(path, role="checkpoint")  # weights_only=True inside
    assert state["epoch"] == 2 and state["batch_index"] == 7 and state["step"] == 40 and state["git"]
    assert (state["format"], state.version, state.model_type, state.role) == (WEIGHTS_FORMAT, 2, "nowarp", "checkpoint")
    assert state.config == cfg and ModelConfig.from_dict(state["model_config"]) == cfg
    again = DSRNet(cfg)
    again.load_state_dict(state["model"])
    for a, b in zip(net.state_dict().values(), again.state_dict().values()):
        assert torch.equal(a, b)
    (tmp_path / "bad.pt").write_bytes(b"junk")
    with pytest.raises(UserError, match="not a loadable"):
        read_weights(tmp_path / "bad.pt")
    torch.save({"weights": torch.zeros(1)}, tmp_path / "other.pt")
    with pytest.raises(UserError, match="not a dsr-bench checkpoint"):
        read_weights(tmp_path / "other.pt")


def test_window_sampler_resumes_and_splits_ranks():
    from dsr_bench.models.training.loaders import WindowSampler

    full = WindowSampler(23, batch_size=4, seed=3)
    full.set_epoch(5)
    order = list(full)
    assert len(order) == 20 and len(set(order)) == 20  # whole batches only
    resumed = WindowSampler(23, batch_size=4, seed=3)
    resumed.set_epoch(5, start_batch=2)
    assert list(resumed) == order[8:] and len(resumed) == 12
    other = WindowSampler(23, batch_size=4, seed=3)
    other.set_epoch(6)
    assert list(other) != order  # reshuffled every epoch
    ranks = [WindowSampler(23, batch_size=4, seed=3, rank=r, world=2) for r in range(2)]
    for s in ranks:
        s.set_epoch(5)
    a, b = list(ranks[0]), list(ranks[1])
    assert len(a) == len(b) == 8 and not set(a) & set(b)


def test_an_epoch_longer_than_the_data_repeats_shuffled_passes():
    from dsr_bench.models.training.loaders import WindowSampler
    from dsr_bench.models.training.schedules import stage_for

    one_pass = WindowSampler(5, batch_size=2, seed=3)
    one_pass.set_epoch(4)
    longer = WindowSampler(5, batch_size=2, seed=3, length=13)  # 2 passes and 3 windows of a third, 6 batches
    longer.set_epoch(4)
    order = list(longer)
    assert len(order) == len(longer) == 12 and longer.batches == 6
    assert order[:4] == list(one_pass)  # the first pass is the one-pass epoch's order
    assert sorted(order[:5]) == sorted(order[5:10]) == [0, 1, 2, 3, 4]  # every window once per pass
    assert order[5:10] != order[:5]  # each pass shuffled anew
    again = WindowSampler(5, batch_size=2, seed=3, length=13)
    again.set_epoch(4, start_batch=3)
    assert list(again) == order[6:]  # a resumed run goes on at the same window
    # the stage's epoch in sample-steps: windows of 10 pushes make a tenth as many windows
    assert stage_for("dsr", "cube-multi", epoch_samples=40_000).epoch_windows(37) == 4000
    assert stage_for("single", "cube-multi", epoch_samples=40_000).epoch_windows(370) == 40_000
    assert stage_for("dsr", "cube-single").epoch_windows(37) == 37  # none set: one pass
    with pytest.raises(UserError, match="--epoch-samples 0"):
        stage_for("dsr", "cube-single", epoch_samples=0)


def test_stage_configs_follow_the_official_schedule():
    from dsr_bench.models.training.schedules import stage_for

    first = stage_for("dsr", "cube-single")
    assert (first.window, first.epochs, first.batch_size, first.betas) == (1, 30, 12, (0.9, 0.95))
    assert [first.lr_at(e) for e in (0, 1, 2, 4, 5, 9, 10, 19, 20, 24, 25, 29)] == \
        [1e-5, 1e-5, 1e-3, 1e-3, 5e-4, 5e-4, 2e-4, 2e-4, 5e-5, 5e-5, 1e-5, 1e-5]
    multi = stage_for("dsr", "shapenet-multi")
    assert (multi.window, multi.epochs) == (10, 20)
    assert [multi.lr_at(e) for e in (0, 4, 5, 10, 15, 19)] == [5e-4, 5e-4, 2e-4, 5e-5, 1e-5, 1e-5]
    assert stage_for("single", "cube-multi").window == 1 and stage_for("3dflow", "shapenet-multi").window == 1
    assert stage_for("dsr", "cube-multi", lr=3e-4).lr_at(7) == 3e-4
    with pytest.raises(UserError, match="--stage"):
        stage_for("dsr", "warmup")
    with pytest.raises(UserError, match="windows of 1"):
        stage_for("single", "cube-single", window=3)
