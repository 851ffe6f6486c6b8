"""Copy the CPU track's trained weights into the package (what `dsr-bench predict --model M` uses by default).

    python scripts/ship_cpu_weights.py RUNS_DIR [--data DATA/cpu-train] [--models dsr single nowarp gtwarp 3dflow
        2dflow se3net se3posenet]

RUNS_DIR/<model>.pt are `dsr-bench train --track cpu` files. Each is checked (it reads as a weights file,
`models.training.checkpoints.read_weights`: weights_only=True, role "weights", a CPU-track model of that
name (for the 2D track's 2dflow, se3net, se3posenet: one on 120 x 160 images), its weights are fp16), its
provenance is kept (recipe, stage losses, git hash, the data it saw by directory name and split checksum, the
--init it started from by file name: never a local path; --data fills in the training split's checksum where a
file lacks it) and it is written to dsr_bench/models/weights/cpu-track/<model>.pt; the stage-1 files stay out.
Prints each file's size and SHA-256 for docs/models.md.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import torch


def main() -> None:
    from dsr_bench.atomic import atomic_path
    from dsr_bench.dataset.manifest import file_sha256
    from dsr_bench.errors import UserError
    from dsr_bench.models import registry
    from dsr_bench.models.predictors import SHIPPED_WEIGHTS
    from dsr_bench.models.training.checkpoints import read_weights, trained_split_checksum

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", type=Path)
    parser.add_argument("--models", nargs="+", default=["dsr", "single", "nowarp", "gtwarp", "3dflow"])
    parser.add_argument("--data", type=Path, help="The training data, to record its split checksum if missing.")
    args = parser.parse_args()

    SHIPPED_WEIGHTS.mkdir(parents=True, exist_ok=True)
    for model in args.models:
        try:
            weights = read_weights(args.runs / f"{model}.pt", model=model, role="weights")
        except UserError as exc:
            raise SystemExit(str(exc)) from None
        payload, config = weights.payload, weights.config
        cpu_sized = config.image_factor == 2 if weights.kind == registry.IMAGE else config.voxel_factor != 1
        if not cpu_sized:
            raise SystemExit(f"{args.runs / f'{model}.pt'}: not the CPU-track weights of {model}")
        if any(v.is_floating_point() and v.dtype != torch.float16 for v in payload["model"].values()):
            raise SystemExit(f"{model}: weights are not fp16")
        data = payload.get("data", {})
        data["dir"] = Path(str(data.get("dir", ""))).name  # a directory name, not a path of this machine
        if not data.get("split_checksum") and args.data:
            data["split_checksum"] = trained_split_checksum(args.data, data.get("split"))
        payload["data"] = data
        recipe = payload.get("recipe")
        if isinstance(recipe, dict) and recipe.get("init"):
            recipe["init"] = Path(str(recipe["init"])).name  # a file name, not a path of this machine
        buffer = io.BytesIO()
        torch.save(payload, buffer)
        target = SHIPPED_WEIGHTS / f"{model}.pt"
        with atomic_path(target) as tmp:
            tmp.write_bytes(buffer.getvalue())
        print(f"{target}: {target.stat().st_size / 1e6:.2f} MB, sha256 {file_sha256(target)}")


if __name__ == "__main__":
    main()
