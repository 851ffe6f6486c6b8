"""Benchmark: training samples per second read from disk by the PyTorch dataset, with N workers.

    python bench/bench_loader.py --data DIR [--split S] [--window 10] [--workers 0 1 2] [--batch 4]

Without --data, a small synthetic dataset is written to a temporary directory first.
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
    args = parser.parse_args()

    import torch

    from dsr_bench.torch_data import SequenceWindowDataset

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
    ds = SequenceWindowDataset(data, args.split, window=args.window)
    print(f"dataset {data}: {len(ds)} windows of {args.window} pushes; batch {args.batch}")
    for workers in args.workers:
        loader = torch.utils.data.DataLoader(ds, batch_size=args.batch, shuffle=True, num_workers=workers,
                                             persistent_workers=workers > 0)
        it = iter(loader)
        next(it)  # warm-up: worker start and first file opens
        start, n = time.perf_counter(), 0
        for _ in range(args.batches):
            try:
                batch = next(it)
            except StopIteration:
                it = iter(loader)
                batch = next(it)
            n += len(batch["sequence"]) * args.window
        dt = time.perf_counter() - start
        print(f"workers {workers}: {n / dt:8.1f} sample-steps/s ({dt / args.batches * 1e3:.1f} ms per batch)")


if __name__ == "__main__":
    main()
