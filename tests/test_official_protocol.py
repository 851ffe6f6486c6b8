"""Running the authors' weights as they ran them (docs/models.md): the history warp's kernel is chosen on the
network (ours for our models, the authors' for theirs), and their test protocol, BatchNorm with statistics
over a batch of independent sequences, makes one sequence's predictions depend on the others in its batch;
`predict_split` groups consecutive sequences of the split, the last group holding the rest. Our models'
path (running statistics, one sequence at a time, our kernel) is unchanged."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dsr_bench.models import DSRNet, ModelConfig  # noqa: E402
from dsr_bench.models.dsr_net import batchnorm_statistics  # noqa: E402
from dsr_bench.models.labels import slot_labels  # noqa: E402
from dsr_bench.models.warp import FLOOR, OFFICIAL, forward_warp  # noqa: E402

SMALL = (48, 48, 16)  # a single sample leaves > 1 value per channel in the SE(3) head: batch 1 works


def _network(seed: int = 0, **overrides) -> DSRNet:
    """A DSR-Net with random weights and running statistics that are not the initial ones."""
    torch.manual_seed(seed)
    net = DSRNet(ModelConfig.for_model("dsr", grid=SMALL, **overrides))
    with torch.no_grad():
        for layer in net.modules():
            if isinstance(layer, torch.nn.modules.batchnorm._BatchNorm):
                layer.running_mean.normal_(0, 0.1)
                layer.running_var.uniform_(0.5, 1.5)
    return net.eval()


def _sequence(seed: int, steps: int = 3, grid=SMALL) -> tuple[np.ndarray, np.ndarray]:
    """(tsdf (T, *grid), actions (T, 3)): a random box pushed along +D1, one voxel a step."""
    g = np.random.default_rng(seed)
    tsdf = np.ones((steps,) + grid, np.float32)
    y0, x0, size, height = (int(g.integers(4, grid[0] - 12)), int(g.integers(2, 8)), int(g.integers(4, 9)),
                            int(g.integers(3, 10)))
    for t in range(steps):
        tsdf[t, y0:y0 + size, x0 + t:x0 + t + size, :height] = -0.5
    actions = np.array([[0, y0 + size // 2, max(x0 + t - 1, 0)] for t in range(steps)])
    return tsdf, actions


def _by_hand(net: DSRNet, sequences: list, batch_statistics: bool, kernel: str = FLOOR) -> list[dict]:
    """The sequences (all of one length) run together step by step: the network, its masks and motion, and
    the history warped by `forward_warp` with `kernel`."""
    from dsr_bench.models.data import action_map

    tsdf = torch.from_numpy(np.stack([s[0] for s in sequences]))
    maps = torch.stack([action_map(s[1], SMALL[:2]) for s in sequences], 1)  # (T, B, 8, Y, X)
    state = net.initial_state(len(sequences), "cpu")
    masks, motions = [], []
    with torch.no_grad(), batchnorm_statistics(net, batch=batch_statistics):
        for t in range(tsdf.shape[1]):
            out = net(tsdf[:, t], maps[t], state)
            masks.append(slot_labels(out["mask"]).numpy())
            motions.append(out["motion"].numpy())
            state = forward_warp(out["representation"], out["motion"], out["mask"][:, :-1].sum(1), kernel=kernel)
    return [{"mask": np.stack(masks)[:, b], "motion": np.stack(motions)[:, b]} for b in range(len(sequences))]


def _same(a: dict, b: dict) -> bool:
    return all(np.array_equal(a[k], b[k]) for k in ("mask", "motion"))


def test_our_models_keep_our_kernel_running_statistics_and_one_sequence_at_a_time(tmp_path):
    """`dsr-bench predict --checkpoint` (predictors.load_predictor): FLOOR, eval mode, batch 1; predictions
    equal, bit for bit, the network run by hand with `forward_warp`'s defaults."""
    from dsr_bench.models.predictors import load_predictor
    from dsr_bench.models.training.checkpoints import save_checkpoint
    from dsr_bench.models.training.schedules import STAGES

    net = _network(1)
    opt = torch.optim.Adam(net.parameters())
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda e: 1.0)
    ckpt = save_checkpoint(tmp_path / "d.pt", net, opt, sched, net.config, STAGES["cube-multi"], 0, 0, 0)
    predictor = load_predictor("dsr", ckpt)
    assert predictor.model.warp_kernel == FLOOR and predictor.bn_batch == 1 and not predictor.official_bn
    assert predictor.weights["warp"].startswith("floor")
    assert predictor.weights["batchnorm"] == "running statistics (eval)"
    seq = _sequence(3)
    assert _same(predictor.predict_arrays(*seq), _by_hand(net, [seq], batch_statistics=False)[0])
    # in eval mode a sequence's predictions do not depend on what it is batched with
    together = predictor.predict_arrays_batch([seq, _sequence(4)])[0]
    assert np.array_equal(together["mask"], predictor.predict_arrays(*seq)["mask"])
    assert np.allclose(together["motion"], predictor.predict_arrays(*seq)["motion"], atol=1e-5)


def test_batch_statistics_normalise_over_the_sequences_of_the_batch():
    from dsr_bench.models.inference import ModelPredictor

    net = _network(2)
    predictor = ModelPredictor(net, torch.device("cpu"), official_bn=True, bn_batch=2)
    a, b, c = _sequence(5), _sequence(6), _sequence(7)
    with_b, with_c = predictor.predict_arrays_batch([a, b])[0], predictor.predict_arrays_batch([a, c])[0]
    # the statistics are the batch's: the same network run by hand on the batch (train-mode BatchNorm)
    assert _same(with_b, _by_hand(net, [a, b], batch_statistics=True)[0])
    # so a's predictions depend on the other sequence of its batch, from the first step on
    assert not np.allclose(with_b["motion"][0], with_c["motion"][0], atol=1e-3)
    alone = predictor.predict_arrays(*a)
    assert not np.allclose(with_b["motion"][0], alone["motion"][0], atol=1e-3)
    assert _same(alone, _by_hand(net, [a], batch_statistics=True)[0])
    # a shorter sequence leaves the batch after its last step; the steps before are those of the full batch
    short_b = (b[0][:2], b[1][:2])
    ragged = predictor.predict_arrays_batch([a, short_b])
    assert ragged[0]["motion"].shape[0] == 3 and ragged[1]["motion"].shape[0] == 2
    even = predictor.predict_arrays_batch([(a[0][:2], a[1][:2]), short_b])
    assert _same({k: v[:2] for k, v in ragged[0].items()}, even[0]) and _same(ragged[1], even[1])


def test_the_kernel_is_chosen_on_the_network_and_used_for_the_history():
    net = _network(3)
    gen = torch.Generator().manual_seed(0)
    rep = torch.randn(1, 8, *SMALL, generator=gen)
    mask = torch.softmax(torch.randn(1, 5, *SMALL, generator=gen), 1)
    motion = torch.rand(1, 3, *SMALL, generator=gen) * 6 - 3  # targets below 0 at the low faces
    outputs = {"representation": rep, "mask": mask, "motion": motion}
    fg = mask[:, :-1].sum(1)
    assert net.warp_kernel == FLOOR and torch.equal(net.next_state(outputs), forward_warp(rep, motion, fg))
    assert net.set_warp_kernel(OFFICIAL) is net and net.warp_kernel == OFFICIAL
    official = net.next_state(outputs)
    assert torch.equal(official, forward_warp(rep, motion, fg, kernel=OFFICIAL))
    assert not torch.allclose(official, forward_warp(rep, motion, fg))
    with pytest.raises(ValueError, match="choose one of floor, official"):
        net.set_warp_kernel("nearest")
    # a predictor runs the network's kernel: the authors' one gives other predictions over a sequence
    from dsr_bench.models.inference import ModelPredictor

    seq = _sequence(8)
    theirs = ModelPredictor(net, torch.device("cpu"), official_bn=True).predict_arrays(*seq)
    assert _same(theirs, _by_hand(net, [seq], batch_statistics=True, kernel=OFFICIAL)[0])


def test_predict_split_runs_consecutive_groups_and_a_last_partial_one(tmp_path):
    """Five sequences at bn_batch 3: groups (0, 1, 2) and (3, 4), each file what its group predicts."""
    import h5py

    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.models.coarse import coarse_grid
    from dsr_bench.models.inference import ModelPredictor
    from dsr_bench.models.predictors import predict_split
    from dsr_bench.testing import write_synthetic_dataset

    data = write_synthetic_dataset(tmp_path / "data", num_sequences=5, num_steps=2)
    torch.manual_seed(4)
    net = DSRNet(ModelConfig.for_model("dsr", grid=coarse_grid(4), voxel_factor=4, width=2)).eval()
    predictor = ModelPredictor(net, torch.device("cpu"), official_bn=True, bn_batch=3)
    names = [f"seq_{i:04d}" for i in range(5)]
    predict_split(predictor, data, names, tmp_path / "pred")
    for group in (names[:3], names[3:]):
        readers = [SequenceReader(data / f"{n}.h5") for n in group]
        try:
            expected = predictor.predict_sequences(readers)
        finally:
            for r in readers:
                r.close()
        for name, want in zip(group, expected):
            with h5py.File(tmp_path / "pred" / f"{name}.h5", "r") as got:
                assert np.array_equal(got["mask"][()], want["mask"])
                assert np.allclose(got["motion"][()], want["motion"], atol=1e-2)  # stored as float16
    with SequenceReader(data / "seq_0003.h5") as seq, SequenceReader(data / "seq_0000.h5") as other:
        alone = predictor.predict_sequences([seq, other])[0]  # in another group, another prediction
    with h5py.File(tmp_path / "pred" / "seq_0003.h5", "r") as got:
        assert not np.allclose(got["motion"][()], alone["motion"], atol=1e-2)
