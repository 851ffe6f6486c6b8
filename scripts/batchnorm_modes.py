"""Per-step motion error of a CPU-track model under the three ways BatchNorm can normalise at test time.

    python scripts/batchnorm_modes.py WEIGHTS --data DIR [--split S] [--sequences 100] [--batch-size 8]
        [--as-model dsr] [--train-data DIR --recalibration 16] [--out F.json]

WEIGHTS: a `dsr-bench train --track cpu` file, which keeps the training's moving averages beside the
recalibrated statistics, or a stage-1 file (`.stage1.pt`: weights after single-step windows only, whose
moving averages never saw a state; --as-model dsr runs them as DSR-Net, the state carried, and
--train-data recalibrates them on --recalibration batches of whole training sequences). Each sequence is
run from its first push with the state carried (warped) from step to step, as `dsr-bench predict` runs it,
under:

- eval, moving averages: the running statistics training left (momentum 0.1 over its last batches);
- eval, recalibrated: the statistics `recalibrate_batchnorm` re-estimated on whole sequences (what
  `dsr-bench predict` uses);
- batch statistics: each batch of --batch-size test sequences normalised by its own statistics (the
  official code's evaluation), the running statistics untouched.

Printed per step: the motion MSE on the model's grid over the whole volume, in cm^2 (benchmark
voxels^2 x 0.16), with predicting no motion for scale; and the RMS of the state fed in.
docs/models.md ("BatchNorm") quotes its output.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from dsr_bench.atomic import check_writable, write_text


@torch.no_grad()
def rollout(net, data: dict, batch_size: int, batch_statistics: bool) -> tuple[np.ndarray, np.ndarray]:
    """(per-sequence per-step motion MSE in benchmark voxels^2, per-step state RMS)."""
    from dsr_bench.models.data import action_map
    from dsr_bench.models.dsr_net import batchnorm_statistics

    factor, grid = net.config.voxel_factor, tuple(net.config.grid)
    errors, norms = [], []
    with batchnorm_statistics(net, batch=batch_statistics):
        for first in range(0, len(data["action"]), batch_size):
            sl = slice(first, first + batch_size)
            tsdf = torch.from_numpy(data["tsdf"][sl].astype(np.float32))
            flow = torch.from_numpy(data["flow"][sl].astype(np.float32))
            mask = torch.from_numpy(data["mask"][sl].astype(np.int64))
            maps = torch.stack([action_map(a, grid[:2]) for a in data["action"][sl].astype(np.int64)])
            state = net.initial_state(tsdf.shape[0], "cpu")
            steps, rms = [], []
            for t in range(tsdf.shape[1]):
                out = net(tsdf[:, t], maps[:, t], state)
                steps.append((((out["motion"] - flow[:, t]) * factor) ** 2).mean((1, 2, 3, 4)).numpy())
                rms.append(float(state.pow(2).mean().sqrt()))
                state = net.next_state(out, flow[:, t], mask[:, t])
            errors.append(np.stack(steps, 1))
            norms.append(rms)
    return np.concatenate(errors), np.mean(norms, 0)


def main() -> None:
    from dsr_bench.constants import VOXEL2_TO_CM2
    from dsr_bench.models import DSRNet, ModelConfig, registry
    from dsr_bench.models.training.checkpoints import read_weights
    from dsr_bench.models.training.cpu_track import pooled_split

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("weights", type=Path)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--split")
    parser.add_argument("--sequences", type=int, default=100)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--as-model", help="Run the weights as this model (e.g. a stage-1 file as dsr).")
    parser.add_argument("--train-data", type=Path, help="Training data to recalibrate a stage-1 file on.")
    parser.add_argument("--recalibration", type=int, default=16)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    if args.out:  # before the work: the results can be written
        check_writable(args.out, "--out", directory=False)

    weights = read_weights(args.weights, kind=registry.VOXEL)
    payload, config = dict(weights.payload), weights.config
    if args.as_model:
        config = ModelConfig.for_model(args.as_model, grid=config.grid, width=config.width,
                                       voxel_factor=config.voxel_factor, init=config.init)
    net = DSRNet(config)
    recalibrated = None
    if "bn_moving_averages" not in payload:  # a stage-1 file: its statistics are the moving averages
        payload["bn_moving_averages"] = {k: v for k, v in payload["model"].items() if "running_" in k or "num_b" in k}
        if args.train_data:
            from dsr_bench.models.training.cpu_track import draw_windows
            from dsr_bench.models.training.trainer import recalibrate_batchnorm

            net.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in payload["model"].items()})
            train = pooled_split(args.train_data, None, config.voxel_factor, workers=2)
            windows = draw_windows(train, args.recalibration, train["action"].shape[1], args.batch_size, 2,
                                   tuple(config.grid))
            recalibrate_batchnorm(net, windows, "cpu")
            recalibrated = {k: v.clone() for k, v in net.state_dict().items()}
    data = pooled_split(args.data, args.split, net.config.voxel_factor, workers=2)
    data = {k: v[: args.sequences] for k, v in data.items()}
    static = ((data["flow"].astype(np.float32) * net.config.voxel_factor) ** 2).mean((2, 3, 4, 5))
    modes = {}
    for label, moving, batch in (("eval, moving averages", True, False), ("eval, recalibrated", False, False),
                                 ("batch statistics", False, True)):
        state = dict(payload["model"])
        if not moving and not batch and recalibrated is not None:
            state = recalibrated
        elif not moving and not batch and weights.role == "stage1":
            print(f"{args.weights}: a stage-1 file and no --train-data to recalibrate on; skipping '{label}'")
            continue
        if moving:
            if "bn_moving_averages" not in payload:
                print(f"{args.weights}: no moving averages saved; skipping '{label}'")
                continue
            state.update(payload["bn_moving_averages"])
        net.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()})
        errors, rms = rollout(net, data, args.batch_size, batch)
        modes[label] = {"motion_mse_cm2": (errors.mean(0) * VOXEL2_TO_CM2).round(4).tolist(),
                        "state_rms": np.round(rms, 4).tolist()}
    modes["predicting no motion"] = {"motion_mse_cm2": (static.mean(0) * VOXEL2_TO_CM2).round(4).tolist()}
    steps = len(modes["predicting no motion"]["motion_mse_cm2"])
    print(f"{args.weights.name} on {len(data['action'])} sequences of {args.data}: motion MSE per step (cm^2, "
          "model grid, whole volume)")
    print(f"{'step':>34} " + " ".join(f"{t:>8}" for t in range(steps)))
    for label, row in modes.items():
        print(f"{label:>34} " + " ".join(f"{v:8.4g}" for v in row["motion_mse_cm2"]))
        if "state_rms" in row:
            print(f"{'  state RMS':>34} " + " ".join(f"{v:8.3g}" for v in row["state_rms"]))
    if args.out:
        summary = {"weights": args.weights.name, "sequences": len(data["action"]), "modes": modes}
        write_text(args.out, json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
