"""Benchmark: DSR-Net training and inference throughput, peak memory, and bf16 vs fp32 losses.

    python bench/bench_model.py [--device cuda] [--model dsr] [--batch 12] [--grid 128 128 48]
        [--window 1] [--resident] [--steps 10] [--bf16] [--compile] [--channels-last] [--json OUT.json]
        [--profile]

Training: samples (time steps) per second of `dsr_bench.models.training.trainer.train_step`, the training loop's unit
of work, on a window of `--window` steps in the form `dsr-bench train` hands it over (compact
batches from `collate_compact`, in pinned host memory on a GPU): the mask id check, the copy to the
device and expansion, then per step forward, matched loss, backward, Adam (fused on a GPU) and the
warp of the state between steps; the loss terms are read once per window. The synthetic scenes have
four box objects (3.6% of the full grid's voxels; generated scenes have 1-3%) with random flow on them.
`--resident` keeps dense batches on the device instead (no copy; the id check reads the device copy).
Figures of sessions before 2026-11-23 came from a resident batch, a loss read after every step and
a warp after every step.
Inference: steps per second batched and at batch 1 (BatchNorm in eval mode, state carried, warp
included). Also: the forward warp alone, peak GPU memory, and the relative difference of the loss
under bf16 autocast vs fp32 on one fixed batch (same weights). On a CPU use a small grid (e.g.
--grid 32 32 16); the GPU targets of the benchmark are at the full grid on an H100.
"""

from __future__ import annotations

import argparse
import json
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--model", default="dsr")
    parser.add_argument("--batch", type=int, default=12)
    parser.add_argument("--grid", type=int, nargs=3, default=[128, 128, 48])
    parser.add_argument("--window", type=int, default=1, help="Time steps per training window (1: single-step stage).")
    parser.add_argument("--resident", action="store_true", help="Keep the training batch on the device (no copy).")
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--bf16", action="store_true")
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--channels-last", action="store_true")
    parser.add_argument("--json", help="Also write the figures to this JSON file.")
    parser.add_argument("--profile", action="store_true",
                        help="Also print the top operators of two training and two inference steps (torch.profiler).")
    args = parser.parse_args()

    import torch

    from dsr_bench.models import DSRNet, ModelConfig
    from dsr_bench.models.loss import dsr_loss
    from dsr_bench.models.warp import forward_warp
    from dsr_bench.models.data import collate_compact
    from dsr_bench.models.training.trainer import train_step

    dev = torch.device(args.device if args.device != "cuda" or torch.cuda.is_available() else "cpu")
    if dev.type == "cuda":
        torch.backends.cudnn.benchmark = True
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    if args.compile and dev.type != "cuda":
        raise SystemExit("error: --compile needs a GPU (torch.compile's CPU backend fails on DSR-Net's backward pass)")
    grid = tuple(args.grid)
    torch.manual_seed(0)
    net = DSRNet(ModelConfig.for_model(args.model, grid=grid)).to(dev)
    if args.channels_last:
        net.to_channels_last()
    model = torch.compile(net) if args.compile else net
    if args.compile:
        net.compile_warp()
    opt = torch.optim.Adam(net.parameters(), lr=1e-5, betas=(0.9, 0.95), fused=True if dev.type == "cuda" else None)
    b = args.batch
    g = torch.Generator().manual_seed(1)
    tsdf = (torch.rand(b, *grid, generator=g) * 2 - 1).to(dev)
    action = torch.zeros(b, 8, *grid[:2], device=dev)
    action[:, 0, grid[0] // 2, grid[1] // 2] = 1
    gt_mask = torch.zeros(b, *grid, dtype=torch.long)
    box = (max(grid[0] // 6, 1), max(grid[1] // 6, 1), max(grid[2] // 3, 1))
    for i in range(b):  # four box objects per scene
        for obj in range(1, 5):
            y = int(torch.randint(0, grid[0] - box[0] + 1, (1,), generator=g))
            x = int(torch.randint(0, grid[1] - box[1] + 1, (1,), generator=g))
            gt_mask[i, y:y + box[0], x:x + box[1], :box[2]] = obj
    gt_flow = (torch.randn(b, 3, *grid, generator=g) * (gt_mask > 0).unsqueeze(1)).to(dev)
    gt_mask = gt_mask.to(dev)
    dense = {"tsdf": tsdf, "action": action, "mask_3d": gt_mask.to(torch.uint8), "scene_flow_3d": gt_flow}
    dense = {k: v.unsqueeze(1).expand(-1, args.window, *v.shape[1:]).contiguous() for k, v in dense.items()}
    if args.resident:
        window = dense
    else:  # as the training DataLoader hands it over: compact, in host memory, pinned for a GPU
        window = collate_compact([{k: v[i].cpu() for k, v in dense.items()} for i in range(b)])
        if dev.type == "cuda":
            window = {k: v.pin_memory() if isinstance(v, torch.Tensor) else v for k, v in window.items()}

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize()

    def train_once(bf16: bool) -> list[dict]:
        return train_step(model, window, opt, dev, bf16)

    net.train()
    for _ in range(args.warmup):
        train_once(args.bf16)
    sync()
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    for _ in range(args.steps):
        train_once(args.bf16)
    sync()
    train_rate = b * args.window * args.steps / (time.perf_counter() - t0)
    peak_train = torch.cuda.max_memory_allocated() / 2**30 if dev.type == "cuda" else float("nan")

    net.eval()

    @torch.no_grad()
    def infer(batch: int, n: int) -> None:
        state = net.initial_state(batch, dev)
        for _ in range(n):
            with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=args.bf16):
                out = model(tsdf[:batch], action[:batch], state)
            state = net.next_state(out, gt_flow[:batch], gt_mask[:batch])
        sync()

    rates = {}
    for batch in (b, 1):
        infer(batch, args.warmup)
        if dev.type == "cuda":
            torch.cuda.reset_peak_memory_stats()
        t0 = time.perf_counter()
        infer(batch, args.steps)
        rates[batch] = batch * args.steps / (time.perf_counter() - t0)
    peak_infer = torch.cuda.max_memory_allocated() / 2**30 if dev.type == "cuda" else float("nan")

    with torch.no_grad():
        feats = torch.randn(b, 8, *grid, device=dev)
        weight = torch.rand(b, *grid, device=dev)

        def warp_time_ms(warp) -> float:
            warp(feats, gt_flow, weight)
            sync()
            t0 = time.perf_counter()
            for _ in range(args.steps):
                warp(feats, gt_flow, weight)
            sync()
            return (time.perf_counter() - t0) / args.steps * 1000

        warp_ms = warp_time_ms(forward_warp)
        warp_compiled_ms = warp_diff = float("nan")
        if args.compile and dev.type == "cuda":
            compiled = net._warp  # the compiled warp the network runs (set by compile_warp), not a second one
            warp_diff = float((compiled(feats, gt_flow, weight) - forward_warp(feats, gt_flow, weight)).abs().max())
            warp_compiled_ms = warp_time_ms(compiled)
        out32 = net(tsdf, action, net.initial_state(b, dev))
        with torch.autocast(dev.type, dtype=torch.bfloat16):
            out16 = net(tsdf, action, net.initial_state(b, dev))
        l32 = float(dsr_loss(out32, gt_mask, gt_flow)[0])
        l16 = float(dsr_loss(out16, gt_mask, gt_flow)[0])
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
        sort = "cuda_time_total" if dev.type == "cuda" else "cpu_time_total"
        for label, work in (("training", lambda: [train_once(args.bf16) for _ in range(2)]),
                            ("inference", lambda: infer(b, 2))):
            (net.train if label == "training" else net.eval)()
            with profile(activities=activities) as prof:
                work()
                sync()
            print(f"--- profile: two {label} steps at batch {b}")
            print(prof.key_averages().table(sort_by=sort, row_limit=14, max_name_column_width=60))
        net.eval()
    name = torch.cuda.get_device_name() if dev.type == "cuda" else f"CPU ({torch.get_num_threads()} threads)"
    figures = {"device": name, "model": args.model, "grid": list(grid), "batch": b, "window": args.window,
               "resident": args.resident, "bf16": args.bf16,
               "compile": args.compile, "channels_last": args.channels_last, "train_samples_per_s": train_rate,
               "infer_steps_per_s_batched": rates[b], "infer_steps_per_s_batch1": rates[1], "warp_ms": warp_ms,
               "warp_compiled_ms": warp_compiled_ms,
               "warp_compiled_max_abs_diff": warp_diff, "peak_train_gib": peak_train, "peak_infer_gib": peak_infer,
               "loss_fp32": l32, "loss_bf16": l16,
               "loss_rel_diff_pct": abs(l16 - l32) / abs(l32) * 100, "torch": torch.__version__}
    print(f"device {name}, model {args.model}, grid {grid}, batch {b}, window {args.window}, "
          f"resident {args.resident}, bf16 {args.bf16}, compile {args.compile}, channels_last {args.channels_last}")
    print(f"training: {train_rate:.1f} samples/s ({train_rate / b:.2f} steps/s); peak memory {peak_train:.2f} GiB")
    print(f"inference: {rates[b]:.1f} steps/s at batch {b}, {rates[1]:.1f} steps/s at batch 1; "
          f"peak memory {peak_infer:.2f} GiB")
    print(f"forward warp alone: {warp_ms:.2f} ms at batch {b}; compiled {warp_compiled_ms:.2f} ms "
          f"(max abs difference {warp_diff:.2e})")
    print(f"loss fp32 {l32:.5f} vs bf16 autocast {l16:.5f}: relative difference {figures['loss_rel_diff_pct']:.3f}%")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(figures, f, indent=1)


if __name__ == "__main__":
    main()
