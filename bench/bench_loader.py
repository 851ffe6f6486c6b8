"""Benchmark: training samples per second read from disk by the PyTorch dataset, with N workers.

    python bench/bench_loader.py --data DIR [--split S] [--window 10] [--workers 0 1 2] [--batch 4]
        [--collate default compact] [--device cuda] [--target 136]

Windows are the training's (non-overlapping: stride = window). With no worker the rate is also given per second of
the process's CPU time, which other jobs on the machine do not lower: what one core delivers. With --target R (the
sample-steps per second the GPU trains at: 128-144 on an H100 for the full-grid models, docs/models.md), each line
also says how many loading processes at that rate would feed it (without a worker: at the per-CPU-second rate):
whether `dsr-bench train --workers N` keeps the GPU busy.

Without --data, a small synthetic dataset is written to a temporary directory first. `--collate`
compares batching by torch's default_collate with `collate_compact` (what `dsr-bench train` uses:
flow as its non-zero voxels, actions as indices), reporting the bytes each batch carries. With
`--device cuda`, batches are pinned and every batch is also copied to the GPU and made dense
(`batch_to_device`), as in training.
"""

from __future__ import annotations

import argparse
import tempfile
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data")
    parser.add_argument("--split")
    parser.add_argument("--window", type=int, default=1)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--workers", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--batches", type=int, default=20)
    parser.add_argument("--collate", nargs="+", default=["default", "compact"], choices=["default", "compact"])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--target", type=float, help="Sample-steps/s to feed: the workers it takes at each rate.")
    args = parser.parse_args()

    import torch

    from dsr_bench.models.data import SequenceWindowDataset

    data, tmp = args.data, None
    if data is None:
        from dsr_bench.testing import write_synthetic_dataset

        tmp = tempfile.TemporaryDirectory(prefix="dsr-loader-")
        data = write_synthetic_dataset(tmp.name, num_sequences=4, num_steps=10)
    try:
        run(data, args, torch, SequenceWindowDataset)
    finally:
        if tmp is not None:
            tmp.cleanup()


def run(data, args, torch, SequenceWindowDataset) -> None:
    from dsr_bench.models.data import batch_to_device, collate_compact

    import math

    ds = SequenceWindowDataset(data, args.split, window=args.window, stride=args.window)
    device = torch.device(args.device)
    print(f"dataset {data}: {len(ds)} windows of {args.window} pushes; batch {args.batch}; device {device}")
    for collate in args.collate:
        for workers in args.workers:
            loader = torch.utils.data.DataLoader(
                ds, batch_size=args.batch, shuffle=True, num_workers=workers, persistent_workers=workers > 0,
                collate_fn=collate_compact if collate == "compact" else None, pin_memory=device.type == "cuda")
            it = iter(loader)
            next(it)  # warm-up: worker start and first file opens
            start, cpu, n, sent = time.perf_counter(), time.process_time(), 0, 0
            for _ in range(args.batches):
                try:
                    batch = next(it)
                except StopIteration:
                    it = iter(loader)
                    batch = next(it)
                n += len(batch["sequence"]) * args.window
                sent += sum(v.numel() * v.element_size() for v in batch.values() if isinstance(v, torch.Tensor))
                if device.type == "cuda":
                    batch_to_device(batch, device)
            if device.type == "cuda":
                torch.cuda.synchronize()
            dt, cpu = time.perf_counter() - start, time.process_time() - cpu
            rate = n / dt
            # sample-steps/s of one loading process; with no worker, per second of its CPU time too, which other
            # processes on the machine do not lower: what one core of a quiet machine delivers
            each = rate / max(workers, 1) if workers else n / cpu
            need = ("" if args.target is None
                    else f"; {math.ceil(args.target / each)} such processes feed {args.target:g}/s")
            per_core = f", {n / cpu:.1f} per CPU-second" if not workers else ""
            print(f"collate {collate:8s} workers {workers}: {rate:8.1f} sample-steps/s{per_core} ("
                  f"{dt / args.batches * 1e3:.1f} ms per batch, {sent / args.batches / 2**20:.1f} MiB per batch{need})")


if __name__ == "__main__":
    main()
