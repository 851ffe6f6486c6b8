"""`dsr-bench train` under torchrun: two CPU processes (gloo) train one model with DDP. The first
optimiser step must use the average of the two ranks' gradients, from rank 0's initial weights, on
the disjoint windows the sampler gives each rank."""

import json
import os
import subprocess
import sys

import pytest

torch = pytest.importorskip("torch")

from dsr_bench.models import DSRNet, ModelConfig  # noqa: E402
from dsr_bench.models.data import SequenceWindowDataset, collate_compact  # noqa: E402
from dsr_bench.models.loss import dsr_loss  # noqa: E402
from dsr_bench.models.training.loaders import WindowSampler  # noqa: E402
from dsr_bench.models.training.trainer import _to  # noqa: E402
from dsr_bench.testing import write_synthetic_dataset  # noqa: E402


def test_torchrun_two_processes_average_the_gradients(tmp_path):
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=2, num_steps=2, split="train")
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "dsr_bench.cli", "train", "--model", "dsr", "--stage", "cube-single", "--data", str(data),
           "--out", str(run), "--batch-size", "1", "--workers", "0", "--quiet", "--max-steps", "1",
           "--bn-recalibration", "0"]  # the gradient average is the subject: no recalibration pass after it
    # gloo on loopback: it otherwise resolves the machine's hostname for its interface, which a container may lack
    env = {**os.environ, "OMP_NUM_THREADS": "1", "GLOO_SOCKET_IFNAME": "lo"}
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.count("checkpoint:") == 1  # rank 0 reports and writes
    ckpt = torch.load(run / "last.pt", weights_only=True)
    assert ckpt["world_size"] == 2 and ckpt["step"] == 1
    assert json.loads((run / "config.json").read_text())["world_size"] == 2
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert len(records) == 1 and records[0]["step"] == 1

    # the reference: rank 0's initialisation (seed 0), each rank's first window, gradients averaged
    dataset = SequenceWindowDataset(data, "train", window=1, stride=1)
    firsts = [next(iter(WindowSampler(len(dataset), 1, seed=0, rank=r, world=2))) for r in (0, 1)]
    assert firsts[0] != firsts[1]
    torch.manual_seed(0)
    net = DSRNet(ModelConfig.for_model("dsr", grid=(128, 128, 48)))
    grads = []
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as each rank (OMP_NUM_THREADS=1): at initialisation, with BatchNorm over one
    try:  # sample, the gradients move by ~0.1% with the convolutions' summation order
        for index in firsts:
            net.zero_grad()
            tsdf, action, mask, flow = _to(collate_compact([dataset[index]]), torch.device("cpu"), 5)
            out = net(tsdf[:, 0], action[:, 0], net.initial_state(1, "cpu"))
            dsr_loss(out, mask[:, 0], flow[:, 0])[0].backward()
            grads.append([p.grad.clone() for p in net.parameters()])
    finally:
        torch.set_num_threads(threads)
    state = ckpt["optimizer"]["state"]
    assert len(state) == len(grads[0])
    beta1 = ckpt["stage"]["betas"][0]
    rank0_only = 0
    for i, (g0, g1) in enumerate(zip(*grads)):
        first_moment = state[i]["exp_avg"]  # (1 - beta1) x the gradient the step used
        expected = (1 - beta1) * (g0 + g1) / 2
        scale = float(expected.abs().max()) + 1e-12
        assert torch.allclose(first_moment, expected, rtol=1e-4, atol=1e-5 * scale), i
        rank0_only += not torch.allclose(first_moment, (1 - beta1) * g0, rtol=1e-4, atol=1e-5 * scale)
    assert rank0_only > len(grads[0]) // 2  # the check tells an average from one rank's gradient
