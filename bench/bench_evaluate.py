"""Benchmark: seconds to evaluate a test split, ours vs the official evaluation code's approach.

    python bench/bench_evaluate.py --data DIR [--split S] [--num-sequences 8] [--model static]

Writes predictions with a reference model, then times (1) `dsr_bench.evaluate.evaluate` with all
cores, (2) the same metrics computed the way the official evaluation does it: per step a Python
loop over every permutation of the object slots with one full-volume tensor reduction per
(slot, object) pair, and (3) reading the same files alone (the floor). Both evaluators' numbers are
printed so they can be compared; times are extrapolated linearly to 400 sequences.
"""

from __future__ import annotations

import argparse
import itertools
import tempfile
import time
from pathlib import Path

import numpy as np


def official_style(pred_dir: Path, data_dir: Path, names: list[str], slots: int = 4) -> dict[str, float]:
    """Official-style evaluation: permutation loops with per-pair reductions (torch on the CPU)."""
    import h5py
    import torch

    per_step: dict[str, list[list[float]]] = {"iou_unordered": [], "motion_visible": [], "motion_full": []}
    for name in names:
        with h5py.File(pred_dir / f"{name}.h5", "r") as p, h5py.File(data_dir / f"{name}.h5", "r") as g:
            steps = int(g.attrs["num_steps"])
            for t in range(steps):
                pm = torch.from_numpy(p["mask"][t].astype(np.int64))
                gm = torch.from_numpy(g["mask_3d"][t].astype(np.int64))
                best = -1.0
                for perm in itertools.permutations(range(1, slots + 1)):
                    total = 0.0
                    for i in range(slots):
                        a, b = pm == perm[i], gm == i + 1
                        inter = (a & b).sum().item()
                        union = (a | b).sum().item()
                        total += inter / max(union, 1)
                    best = max(best, total / slots)
                motion = torch.from_numpy(p["motion"][t].astype(np.float32))
                gt = torch.from_numpy(g["scene_flow_3d"][t])
                tsdf = torch.from_numpy(g["tsdf"][t])
                sq = ((motion - gt) ** 2).sum(0)
                sel = (tsdf > -0.99) & (tsdf < 0) & (gm > 0)
                sel[..., 0] = False
                vis = (sq[sel].mean().item() * 0.16) if sel.any() else float("nan")
                full = ((motion - gt) ** 2).mean().item() * 0.16
                for key, value in (("iou_unordered", best), ("motion_visible", vis), ("motion_full", full)):
                    while len(per_step[key]) <= t:
                        per_step[key].append([])
                    per_step[key][t].append(value)
    return {k: float(np.nanmean([np.nanmean(v) for v in steps])) for k, steps in per_step.items()}


def read_only(pred_dir: Path, data_dir: Path, names: list[str]) -> None:
    import h5py

    for name in names:
        with h5py.File(pred_dir / f"{name}.h5", "r") as p, h5py.File(data_dir / f"{name}.h5", "r") as g:
            p["mask"][()], p["motion"][()]
            g["mask_3d"][()], g["scene_flow_3d"][()], g["tsdf"][()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--split")
    parser.add_argument("--num-sequences", type=int, default=8)
    parser.add_argument("--model", default="static")
    args = parser.parse_args()

    import os
    import shutil

    from dsr_bench.evaluate import evaluate
    from dsr_bench.manifest import read_split
    from dsr_bench.predictors import load_predictor, predict_split

    split, names = read_split(args.data, args.split)
    names = names[: args.num_sequences]
    work = Path(tempfile.mkdtemp(prefix="dsr-bench-eval-"))
    data = work / "data"  # a dataset of just these sequences, so evaluate scores exactly them
    (data / "splits").mkdir(parents=True)
    for name in names:
        os.symlink((args.data / f"{name}.h5").resolve(), data / f"{name}.h5")
    (data / "splits" / "bench.txt").write_text("".join(f"{n}\n" for n in names))
    from dsr_bench.manifest import build_manifest, write_manifest

    write_manifest(data, build_manifest(data))
    pred = work / "pred"
    predict_split(load_predictor(args.model), data, names, pred)
    read_only(pred, data, names)  # warm the page cache for everyone

    t0 = time.perf_counter()
    read_only(pred, data, names)
    t_read = time.perf_counter() - t0
    t0 = time.perf_counter()
    ours = evaluate(pred, data, "bench").results
    t_ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    ours_1 = evaluate(pred, data, "bench", workers=1).results
    t_ours_1 = time.perf_counter() - t0
    t0 = time.perf_counter()
    theirs = official_style(pred, data, names)
    t_official = time.perf_counter() - t0

    n = len(names)
    print(f"{n} sequences of {split} ({args.model} predictions); {os.cpu_count()} cores")
    print(f"{'':28s}{'seconds':>10s}{'s/sequence':>12s}{'400 seq (extrapolated)':>26s}")
    for label, t in (("read files only", t_read), ("dsr-bench, all cores", t_ours), ("dsr-bench, 1 process", t_ours_1),
                     ("official approach", t_official)):
        print(f"{label:28s}{t:10.2f}{t / n:12.3f}{t / n * 400:20.0f} s")
    print(f"speed-up vs official approach: {t_official / t_ours:.1f}x (all cores), {t_official / t_ours_1:.1f}x (1 process)")
    print(f"dsr-bench time / read-only time: {t_ours_1 / t_read:.2f} (1 process)")
    for key, mine in (("iou_unordered", "iou_unordered_official"), ("motion_visible", "motion_visible"),
                      ("motion_full", "motion_full")):
        print(f"  {key:16s} dsr-bench ({mine}) {ours['metrics'][mine]:.6f}   official approach {theirs[key]:.6f}")
    print(f"  (dsr-bench's headline iou_unordered, empty-empty pairs left out: {ours['metrics']['iou_unordered']:.6f})")
    del ours_1
    shutil.rmtree(work)


if __name__ == "__main__":
    main()
