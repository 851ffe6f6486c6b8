"""The CPU track's ceiling on a split: the ground truth pooled to the model grid and brought back, scored.

    python scripts/cpu_track_cap.py --data DATA/cpu-novel-test --work WORK [--split NAME] [--out results.json]
        [--factor 4]

A CPU-track model sees and predicts 16 mm voxels (`models/coarse.py`), so even a perfect one scores what the
ground truth scores after the same round trip: each step's amodal mask pooled (`pool_labels`) and its flow pooled
(`pool_flow`, the mean over each coarse voxel's object), then brought back to the benchmark's 128 x 128 x 48 grid
(`unpool_mask`, `unpool_motion`). These are written as predictions (WORK/oracle-pooled, one file a sequence, as
`dsr-bench predict` writes them) and scored by `dsr-bench evaluate` like any model's, so the ceiling and the
models' scores come from one evaluation. Prints the means of the four headline metrics (flow MSE in cm^2, IoU);
the results (per sequence, per step) go to --out (default WORK/oracle-pooled.json). This is the grid's cap that
`cpu_track_curve.py --cap` draws (ordered IoU 0.645 on cpu-novel-test). The command is recorded in the
predictions' meta.json parameters (`command`), which the results carry.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np

METRICS = ("motion_visible", "motion_full", "iou_unordered", "iou_ordered")


class PooledOracle:
    """The ground truth pooled to the CPU track's grid and brought back (its ceiling)."""

    name = "oracle-pooled"

    def __init__(self, factor: int) -> None:
        from dsr_bench.constants import MAX_OBJECTS_PER_SCENE, VOXEL_SIZE
        from dsr_bench.models.coarse import coarse_grid

        self.factor, self.grid, self.num_slots = factor, coarse_grid(factor), MAX_OBJECTS_PER_SCENE
        self.millimetres = round(factor * VOXEL_SIZE * 1000)
        self.description = (f"the ground truth pooled to {self.millimetres} mm voxels and brought back "
                            "(the grid's ceiling)")

    def predict_sequence(self, seq) -> dict[str, np.ndarray]:
        """{"mask": (T, Y, X, Z) uint8, "motion": (T, 3, Y, X, Z) float32 in benchmark voxels} of one sequence."""
        from dsr_bench.models.coarse import pool_flow, pool_labels, unpool_mask, unpool_motion

        mask = seq.read("mask_3d", slice(0, seq.num_steps))
        flow = seq.read("scene_flow_3d")
        return {"mask": unpool_mask(pool_labels(mask, self.factor), self.factor).astype(np.uint8),
                "motion": unpool_motion(pool_flow(flow, mask, self.factor), self.factor)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="A dataset directory.")
    parser.add_argument("--split", help="Its split to score (default: its only one).")
    parser.add_argument("--work", type=Path, required=True, help="Where the predictions are written.")
    parser.add_argument("--out", type=Path, help="The results JSON (default WORK/oracle-pooled.json).")
    parser.add_argument("--factor", type=int, default=4, help="Benchmark voxels per model voxel (the CPU track: 4).")
    args = parser.parse_args(argv)

    from dsr_bench.atomic import write_text
    from dsr_bench.dataset.manifest import read_split
    from dsr_bench.errors import UserError
    from dsr_bench.models.predictors import predict_split

    try:
        split, names = read_split(args.data, args.split)
        oracle = PooledOracle(args.factor)
    except (UserError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    pred, out = args.work / PooledOracle.name, args.out or args.work / f"{PooledOracle.name}.json"
    predict_split(oracle, args.data, names, pred)
    command = "python " + shlex.join(["scripts/cpu_track_cap.py", *(sys.argv[1:] if argv is None else argv)])
    meta = json.loads((pred / "meta.json").read_text())
    meta["parameters"]["command"] = command  # parameters travel into the results (meta.parameters)
    write_text(pred / "meta.json", json.dumps(meta, indent=1) + "\n")
    # the toolkit's own scoring, as for every model: evaluate validates the predictions and checks the pins
    scored = subprocess.run([sys.executable, "-m", "dsr_bench", "evaluate", str(pred), "--data", str(args.data),
                             "--split", split, "--out", str(out)])
    if scored.returncode:
        return scored.returncode  # evaluate said why, in one line
    means = json.loads(out.read_text())["metrics"]
    print(f"{split} ({len(names)} sequences), the {oracle.millimetres} mm grid's ceiling: "
          + ", ".join(f"{m} {means[m]:.4f}" for m in METRICS))
    print(f"command: {command}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
