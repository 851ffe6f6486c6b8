"""Benchmark: DSR-Net training and inference throughput, peak memory, and bf16 vs fp32 losses.

    python bench/bench_model.py [--device cuda] [--batch 12] [--grid 128 128 48] [--steps 10] [--bf16] [--compile]

Training: samples per second of one optimisation step (forward, matched loss, backward, Adam) at
the given batch, as the training loop runs it. Inference: steps per second batched and at batch 1
(state carried, warp included). Reports peak GPU memory on CUDA and the relative difference of the
loss in bf16 autocast vs fp32 on a fixed batch. On a CPU use a small grid (e.g. --grid 32 32 16).
"""

from __future__ import annotations

import argparse
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--model", default="dsr")
    parser.add_argument("--batch", type=int, default=12)
    parser.add_argument("--grid", type=int, nargs=3, default=[128, 128, 48])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--bf16", action="store_true")
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--channels-last", action="store_true")
    args = parser.parse_args()

    import torch

    from dsr_bench.models import DSRNet, ModelConfig
    from dsr_bench.models.loss import dsr_loss

    dev = torch.device(args.device if args.device != "cuda" or torch.cuda.is_available() else "cpu")
    if dev.type == "cuda":
        torch.backends.cudnn.benchmark = True
    grid = tuple(args.grid)
    torch.manual_seed(0)
    net = DSRNet(ModelConfig.for_model(args.model, grid=grid)).to(dev)
    if args.channels_last:
        net = net.to(memory_format=torch.channels_last_3d)
    model = torch.compile(net) if args.compile else net
    opt = torch.optim.Adam(net.parameters(), lr=1e-4, betas=(0.9, 0.95))
    b = args.batch
    tsdf = torch.rand(b, *grid, device=dev) * 2 - 1
    action = torch.zeros(b, 8, *grid[:2], device=dev)
    action[:, 0, grid[0] // 2, grid[1] // 2] = 1
    gt_mask = torch.randint(0, 5, (b, *grid), device=dev)
    gt_flow = torch.randn(b, 3, *grid, device=dev)

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize()

    def train_once(bf16):
        opt.zero_grad(set_to_none=True)
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=bf16):
            out = model(tsdf, action, net.initial_state(b, dev))
        loss, _, _ = dsr_loss(out, gt_mask, gt_flow)
        loss.backward()
        opt.step()
        return float(loss.detach())

    for _ in range(2):
        train_once(args.bf16)
    sync()
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    for _ in range(args.steps):
        train_once(args.bf16)
    sync()
    train_rate = b * args.steps / (time.perf_counter() - t0)
    peak = torch.cuda.max_memory_allocated() / 2**30 if dev.type == "cuda" else float("nan")

    net.eval()

    @torch.no_grad()
    def infer(batch, n):
        state = net.initial_state(batch, dev)
        for _ in range(n):
            with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=args.bf16):
                out = model(tsdf[:batch], action[:batch], state)
            state = net.next_state(out)
        sync()

    infer(b, 2)
    t0 = time.perf_counter()
    infer(b, args.steps)
    batched = b * args.steps / (time.perf_counter() - t0)
    infer(1, 2)
    t0 = time.perf_counter()
    infer(1, args.steps)
    single = args.steps / (time.perf_counter() - t0)

    with torch.no_grad():
        out32 = net(tsdf, action, net.initial_state(b, dev))
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=True):
            out16 = net(tsdf, action, net.initial_state(b, dev))
        l32 = float(dsr_loss(out32, gt_mask, gt_flow)[0])
        l16 = float(dsr_loss(out16, gt_mask, gt_flow)[0])
    print(f"device {dev} ({torch.cuda.get_device_name() if dev.type == 'cuda' else 'CPU'}), model {args.model}, "
          f"grid {grid}, batch {b}, bf16 {args.bf16}, compile {args.compile}, channels_last {args.channels_last}")
    print(f"training: {train_rate:.1f} samples/s; peak memory {peak:.2f} GiB")
    print(f"inference: {batched:.1f} steps/s at batch {b}, {single:.1f} steps/s at batch 1")
    print(f"loss fp32 {l32:.5f} vs bf16 autocast {l16:.5f}: relative difference {abs(l16 - l32) / abs(l32) * 100:.3f}%")


if __name__ == "__main__":
    main()
