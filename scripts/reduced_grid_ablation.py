"""The paper's history ablation (DSR-Net vs NoWarp vs SingleStep) at a reduced grid, on a CPU.

    python scripts/reduced_grid_ablation.py --train-data DIR --test-data DIR [--test-split S]
        [--train-sequences 240] [--test-sequences 100] [--factor 4 4 3] [--batch-size 8]
        [--steps-single 1500] [--steps-multi 300] [--models dsr nowarp single] [--seed 0]
        [--history-variants] [--bn-recalibration N] [--out OUT.json]

Why: the benchmark's short schedule (scripts/short_schedule.py) needs a GPU and, at the budget
one session has, sees too few 10-step windows for a recurrent state to pay off. The network's
grid is a parameter, so this script trains the same models on sequences downsampled to a coarse
grid (32 x 32 x 16 with the default factor) and held in memory, where a CPU affords tens of
thousands of sample-steps per model.

Downsampling by --factor (y, x, z): the TSDF is averaged over each block; masks and flow are taken
at each block's centre voxel (flow divided by the factor: coarse voxels); the action's pixel is
divided by the factor. Training runs the trainer's pieces: the stages' configurations
(`schedules.stage_for`, with constant learning rates), its optimiser (`setup.make_optimizer`: Adam,
betas (0.9, 0.95)) and its loop unit (`trainer.train_windows`: `train_step` per window, the matched
loss with the matching carried from step to step, the state warped between steps): stage 1 on
single-step windows (--steps-single batches, lr 1e-3), stage 2 on 10-step windows (--steps-multi
batches, lr 5e-4, from stage 1's weights); SingleStep stays single-step and gets 10x the stage-2
batches, i.e. the same sample-steps. Every model starts from the same initial weights and sees
the windows in the same order. Not the trainer's `train`: that reads every non-overlapping window
of a split's files once per epoch and checkpoints to a run directory, while this script draws
windows at random (any start, with replacement) from sequences held in memory on the coarse grid.
Evaluation is the predictor's (`ModelPredictor.predict_arrays`: the state carried over each test
sequence, BatchNorm in eval mode), scored with the benchmark's `metrics.sequence_scores` on the
coarse grid (unordered IoU: matching per step; ordered IoU: one matching per sequence). Printed: the
means, the motion MSE of predicting no motion, and the paired per-sequence differences with
their standard errors. --history-variants
also evaluates each trained history model with its history changed at test time only (zeroed;
for DSR-Net also unwarped): whether the trained network uses what its state carries.

Per step, the motion MSE is printed under both BatchNorm modes: eval mode (the predictor's) and
batch statistics (the official code's evaluation; the test sequences in batches of --batch-size,
since at this grid a single sample leaves one value per channel in the SE(3) head), the model's
running statistics untouched; with, per step and mode, the RMS of the state fed in and the first
BatchNorm's input variance over its running variance. --bn-recalibration N also evaluates each
model after re-estimating its BatchNorm statistics (`trainer.recalibrate_batchnorm`, precise BN)
on N batches of whole training sequences with the state carried. --steps-multi 0 skips stage 2 (a history model whose
statistics never saw a state: docs/models.md, BatchNorm).

Not a leaderboard entry: the benchmark is defined on the 128 x 128 x 48 grid.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from dsr_bench.dataset.manifest import read_split
from dsr_bench.dataset.sequence import SequenceReader
from dsr_bench.models import DSRNet, ModelConfig
from dsr_bench.models.data import action_map
from dsr_bench.models.dsr_net import batchnorm_statistics
from dsr_bench.models.inference import ModelPredictor
from dsr_bench.models.training.schedules import StageConfig, stage_for
from dsr_bench.models.training.setup import make_optimizer
from dsr_bench.models.training.trainer import recalibrate_batchnorm, train_windows, window_record
from dsr_bench.scoring.metrics import sequence_scores

LR_SINGLE, LR_MULTI = 1e-3, 5e-4


def downsample(path: Path, factor: tuple[int, int, int]) -> dict[str, np.ndarray]:
    """One sequence on the coarse grid: tsdf (T, ...) float32, mask (T, ...) uint8 at t, flow (T, 3, ...)
    float32 in coarse voxels, action (T, 3) int64, num_objects."""
    fy, fx, fz = factor
    with SequenceReader(path) as seq:
        steps = seq.num_steps
        tsdf = np.asarray(seq.read("tsdf"), dtype=np.float32)[:steps]
        mask = np.asarray(seq.read("mask_3d"))[:steps]
        flow = np.asarray(seq.read("scene_flow_3d"), dtype=np.float32)[:steps]
        action = np.asarray(seq.read("action"), dtype=np.int64)[:steps]
        num_objects = seq.num_objects
    coarse = F.avg_pool3d(torch.from_numpy(tsdf).unsqueeze(1), factor).squeeze(1).numpy()
    centre = (slice(fy // 2, None, fy), slice(fx // 2, None, fx), slice(fz // 2, None, fz))
    flow = flow[(slice(None), slice(None)) + centre] / np.array(factor, np.float32).reshape(1, 3, 1, 1, 1)
    action = np.stack([action[:, 0], action[:, 1] // fy, action[:, 2] // fx], 1)
    return {"tsdf": coarse, "mask": mask[(slice(None),) + centre].astype(np.uint8), "flow": flow, "action": action,
            "num_objects": num_objects}


def load(data: Path, split: str | None, count: int, factor) -> list[dict]:
    _, names = read_split(data, split)
    names = names[:count]
    out = []
    for i, name in enumerate(names):
        out.append(downsample(data / f"{name}.h5", factor))
        print(f"\rloading {data.name}: {i + 1}/{len(names)}", end="", flush=True)
    print()
    return out


def make_batch(seqs: list[dict], picks: list[tuple[int, int]], window: int, grid) -> dict:
    """A training window batch (B, L, ...) in the data loader's layout from (sequence, start) picks."""
    sl = [(seqs[i], slice(s, s + window)) for i, s in picks]
    return {"tsdf": torch.from_numpy(np.stack([q["tsdf"][s] for q, s in sl])),
            "action": torch.stack([action_map(q["action"][s], grid[:2]) for q, s in sl]),
            "mask_3d": torch.from_numpy(np.stack([q["mask"][s] for q, s in sl])),
            "scene_flow_3d": torch.from_numpy(np.stack([q["flow"][s] for q, s in sl]))}


def draw_windows(seqs: list[dict], batches: int, window: int, batch_size: int, seed: int):
    """`batches` window batches drawn at random (any start, with replacement) from the in-memory sequences."""
    rng = np.random.default_rng(seed)
    steps = seqs[0]["tsdf"].shape[0]
    grid = seqs[0]["tsdf"].shape[1:]
    for _ in range(batches):
        picks = [(int(rng.integers(len(seqs))), int(rng.integers(steps - window + 1))) for _ in range(batch_size)]
        yield make_batch(seqs, picks, window, grid)


def train_stage(net, seqs, stage: StageConfig, batches: int, seed: int, label: str) -> dict:
    """`batches` windows of the stage's length drawn at random from the in-memory sequences, trained
    with the trainer's optimiser and loop unit."""
    opt = make_optimizer(net, stage, torch.device("cpu"))
    window, batch_size = stage.window, stage.batch_size
    draws = draw_windows(seqs, batches, window, batch_size, seed)
    net.train()
    start, losses = time.perf_counter(), []
    for b, (_, terms, _) in enumerate(train_windows(net, draws, opt, "cpu", mask_reduction=stage.mask_reduction)):
        losses.append(window_record(terms)["loss"])
        if (b + 1) % 50 == 0 or b + 1 == batches:
            print(f"\r{label}: batch {b + 1}/{batches}, loss (last 50) {np.mean(losses[-50:]):.4f}, "
                  f"{time.perf_counter() - start:.0f} s", end="", flush=True)
    print()
    return {"batches": batches, "window": window, "lr": stage.lr, "sample_steps": batches * batch_size * window,
            "seconds": round(time.perf_counter() - start, 1), "loss_first_50": float(np.mean(losses[:50])),
            "loss_last_50": float(np.mean(losses[-50:]))}


def evaluate(net, seqs: list[dict]) -> dict[str, np.ndarray]:
    """Per-sequence mean unordered and ordered IoU and motion MSE (coarse voxels^2), by the predictor
    (BatchNorm in eval mode), and the motion MSE of every step (`motion_mse_steps`, (sequences, T))."""
    predictor = ModelPredictor(net, torch.device("cpu"))  # BatchNorm in eval mode
    slots = net.config.num_slots - 1
    per_seq = {"iou_unordered": [], "iou_ordered": [], "motion_mse": [], "motion_mse_steps": []}
    for i, q in enumerate(seqs):
        pred = predictor.predict_arrays(q["tsdf"], q["action"], q["flow"], q["mask"], source=f"test sequence {i}")
        motion, flow = torch.from_numpy(pred["motion"]), torch.from_numpy(q["flow"])
        errors = [float(((motion[t:t + 1] - flow[t:t + 1]) ** 2).sum(1).mean()) for t in range(len(motion))]
        scores = sequence_scores(pred["mask"], q["mask"], slots, q["num_objects"])
        per_seq["iou_unordered"].append(float(np.mean(scores["iou_unordered"])))
        per_seq["iou_ordered"].append(float(np.mean(scores["iou_ordered"])))
        per_seq["motion_mse"].append(float(np.mean(errors)))
        per_seq["motion_mse_steps"].append(errors)
    return {key: np.array(v) for key, v in per_seq.items()}


@torch.no_grad()
def rollout(net, seqs: list[dict], batch_size: int, batch_statistics: bool) -> dict[str, np.ndarray]:
    """The test sequences `batch_size` at a time, the state carried as the predictor carries it, BatchNorm
    in eval mode or normalising by each batch's statistics (the running statistics untouched).
    Returns per step: the motion MSE (sequences, T), the state's RMS (T) and the mean over channels
    of the first BatchNorm's input variance over its running variance (T): how far the statistics
    eval mode normalises by are from what the layer sees. Needs sequences of equal length."""
    grid = tuple(net.config.grid)
    first_norm = net.encoder.level0.norm
    errors, rms, ratios = [], [], []
    hook = first_norm.register_forward_hook(lambda m, inp, out: ratios[-1].append(
        (inp[0].float().var((0, 2, 3, 4), unbiased=False) / m.running_var).mean().item()))
    try:
        with batchnorm_statistics(net, batch=batch_statistics):
            for first in range(0, len(seqs), batch_size):
                group = seqs[first:first + batch_size]
                tsdf = torch.from_numpy(np.stack([q["tsdf"][:len(q["action"])] for q in group]))
                flow = torch.from_numpy(np.stack([q["flow"] for q in group]))
                maps = torch.stack([action_map(q["action"], grid[:2]) for q in group])
                state = net.initial_state(len(group), torch.device("cpu"))
                steps, norms = [], []
                ratios.append([])
                for t in range(tsdf.shape[1]):
                    out = net(tsdf[:, t], maps[:, t], state)
                    steps.append(((out["motion"] - flow[:, t]) ** 2).sum(1).flatten(1).mean(1).numpy())
                    norms.append(state.pow(2).mean().item() * len(group))
                    if t + 1 < tsdf.shape[1]:
                        mask = torch.from_numpy(np.stack([q["mask"][t] for q in group]))
                        state = net.next_state(out, flow[:, t], mask)
                errors.append(np.stack(steps, 1))
                rms.append(norms)
    finally:
        hook.remove()
    return {"motion_mse": np.concatenate(errors), "state_rms": np.sqrt(np.sum(rms, 0) / len(seqs)),
            "variance_ratio": np.mean(ratios, 0)}


def evaluate_both(net, seqs: list[dict], batch_size: int, label: str) -> tuple[dict[str, np.ndarray], dict]:
    """`evaluate` (eval mode, the predictor) and the per-step motion MSE with batch statistics; prints
    both per step, and the state's RMS and the first BatchNorm's variance ratio under each mode
    (returned as the second item)."""
    per_seq = evaluate(net, seqs)
    eval_mode = rollout(net, seqs, batch_size, batch_statistics=False)
    batch_mode = rollout(net, seqs, batch_size, batch_statistics=True)
    per_seq["motion_mse_steps_batch_statistics"] = batch_mode["motion_mse"]
    diagnostics = {f"{key}_{mode}": run[key] for mode, run in (("eval", eval_mode), ("batch_statistics", batch_mode))
                   for key in ("state_rms", "variance_ratio")}
    for key, mode in (("motion_mse_steps", "eval mode"), ("motion_mse_steps_batch_statistics", "batch statistics")):
        print(f"{label}: motion MSE per step, BatchNorm {mode}: "
              + " ".join(f"{e:.3g}" for e in per_seq[key].mean(0)), flush=True)
    for key, values in diagnostics.items():
        print(f"{label}: {key}: " + " ".join(f"{e:.3g}" for e in values), flush=True)
    return per_seq, {key: np.round(v, 6).tolist() for key, v in diagnostics.items()}


def summary_of(per_seq: dict[str, np.ndarray]) -> dict:
    """Means over the sequences (per step for the per-step errors)."""
    return {key: (v.mean(0).round(6).tolist() if v.ndim == 2 else float(v.mean())) for key, v in per_seq.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--train-data", type=Path, required=True)
    parser.add_argument("--train-split")
    parser.add_argument("--test-data", type=Path, required=True)
    parser.add_argument("--test-split")
    parser.add_argument("--train-sequences", type=int, default=240)
    parser.add_argument("--test-sequences", type=int, default=100)
    parser.add_argument("--factor", type=int, nargs=3, default=[4, 4, 3])
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--steps-single", type=int, default=1500)
    parser.add_argument("--steps-multi", type=int, default=300)
    parser.add_argument("--models", nargs="+", default=["dsr", "nowarp", "single"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--history-variants", action="store_true",
                        help="Also evaluate history models with the history zeroed (and DSR-Net unwarped) at test time.")
    parser.add_argument("--bn-recalibration", type=int, default=0, metavar="N",
                        help="Also evaluate each model after re-estimating its BatchNorm statistics on N batches of "
                             "10-step training windows, the state carried (precise BN).")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    factor = tuple(args.factor)
    train = load(args.train_data, args.train_split, args.train_sequences, factor)
    test = load(args.test_data, args.test_split, args.test_sequences, factor)
    grid = tuple(train[0]["tsdf"].shape[1:])
    if any(g % 16 for g in grid):
        sys.exit(f"error: --factor {' '.join(map(str, factor))} gives the grid {grid}; "
                 "every side must be a multiple of 16")
    print(f"grid {grid}; {len(train)} training and {len(test)} test sequences; torch threads {torch.get_num_threads()}")
    zero_motion_mse = float(np.mean([((q["flow"]) ** 2).sum(1).mean() for q in test]))
    print(f"motion MSE of predicting no motion: {zero_motion_mse:.3f}")
    results, per_seq = {}, {}
    for name in args.models:
        torch.manual_seed(args.seed)
        net = DSRNet(ModelConfig.for_model(name, grid=grid))
        history = net.config.history != "none"
        single = stage_for(name, "cube-single", lr=LR_SINGLE, batch_size=args.batch_size)
        stage1 = train_stage(net, train, single, args.steps_single, args.seed, f"{name} stage 1")
        multi = stage_for(name, "cube-multi", lr=LR_MULTI, batch_size=args.batch_size)  # windows of 1 without history
        batches = args.steps_multi if history else 10 * args.steps_multi
        stage2 = train_stage(net, train, multi, batches, args.seed + 1, f"{name} stage 2") if batches else None
        per_seq[name], diagnostics = evaluate_both(net, test, args.batch_size, name)
        results[name] = {"stage_single": stage1, "stage_multi": stage2, **summary_of(per_seq[name]), **diagnostics}
        variants = [] if not (args.history_variants and history) else \
            ["none"] + (["nowarp"] if net.config.history == "warp" else [])
        trained, labels = net.config, [name]
        for variant in variants:  # the same weights, the history changed at test time only
            net.config = dataclasses.replace(trained, history=variant)
            labels.append(f"{name}/test-history-{variant}")
            per_seq[labels[-1]], diagnostics = evaluate_both(net, test, args.batch_size, labels[-1])
            results[labels[-1]] = {**summary_of(per_seq[labels[-1]]), **diagnostics}
        net.config = trained
        if args.bn_recalibration:  # the same weights, BatchNorm's statistics re-estimated on whole sequences
            windows = draw_windows(train, args.bn_recalibration, len(train[0]["action"]), args.batch_size,
                                   args.seed + 2)
            passes = recalibrate_batchnorm(net, windows, "cpu")
            labels.append(f"{name}/bn-recalibrated")
            per_seq[labels[-1]], diagnostics = evaluate_both(net, test, args.batch_size, labels[-1])
            results[labels[-1]] = {"forward_passes": passes, **summary_of(per_seq[labels[-1]]), **diagnostics}
        for label in labels:
            r = results[label]
            print(f"{label}: ordered IoU {r['iou_ordered']:.4f}, unordered {r['iou_unordered']:.4f}, "
                  f"motion MSE {r['motion_mse']:.3f}", flush=True)
    print(f"\n{'model':26s} {'ordered IoU':>12s} {'unordered IoU':>14s} {'motion MSE':>11s}")
    for name, r in results.items():
        print(f"{name:26s} {r['iou_ordered']:12.4f} {r['iou_unordered']:14.4f} {r['motion_mse']:11.3f}")
    pairs = {}
    comparisons = [("dsr", "nowarp"), ("nowarp", "single"), ("dsr", "single")]
    comparisons += [(name, label) for label in per_seq if "/" in label for name in [label.split("/")[0]]]
    for a, b in comparisons:
        if a in per_seq and b in per_seq:
            d = per_seq[a]["iou_ordered"] - per_seq[b]["iou_ordered"]
            se = float(d.std(ddof=1) / np.sqrt(len(d)))
            pairs[f"{a}-{b}"] = {"mean": float(d.mean()), "standard_error": se, "sequences_better": int((d > 0).sum()),
                                 "sequences": len(d)}
            print(f"ordered IoU {a} - {b}: {d.mean():+.4f} +- {se:.4f} (standard error over {len(d)} sequences; "
                  f"{a} better on {(d > 0).sum()})")
    ordering = None
    if {"dsr", "nowarp", "single"} <= set(results):
        ordering = results["dsr"]["iou_ordered"] > results["nowarp"]["iou_ordered"] > results["single"]["iou_ordered"]
        print("paper's ordering DSR-Net > NoWarp > SingleStep on ordered IoU: "
              f"{'holds' if ordering else 'does not hold'}")
    if args.out:
        summary = {"command": "python " + " ".join(shlex.quote(a) for a in sys.argv), "grid": list(grid),
                   "factor": list(factor), "train_data": str(args.train_data), "test_data": str(args.test_data),
                   "train_sequences": len(train), "test_sequences": len(test), "batch_size": args.batch_size,
                   "seed": args.seed, "torch": torch.__version__, "machine": platform.processor() or platform.machine(),
                   "threads": torch.get_num_threads(), "zero_motion_mse": zero_motion_mse, "models": results,
                   "paired_ordered_iou": pairs,
                   "ordering_holds": ordering}
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_name(f".{args.out.name}.tmp")
        tmp.write_text(json.dumps(summary, indent=1) + "\n")
        tmp.replace(args.out)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
