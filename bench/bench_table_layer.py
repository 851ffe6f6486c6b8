"""Benchmark (a fidelity figure, not a speed): what the TSDF's bottom layer (z = 0, the table's plane) reads, in the
authors' step-0 volumes and in ours, at the voxels no object occupies.

    python bench/bench_table_layer.py DATA_DIR [--reference PATH] [--num-sequences 4]

DATA_DIR: a dataset of ours (e.g. `dsr-bench generate --split cube-test`); the reference: the authors' generator's
four step-0 volumes (`tsdf_step0`, `mask_3d_step0` of /work/shared/reference/official-cube-reference.h5). Prints,
per side, the median of the layer's values (TSDF units: 1 = the truncation distance or more in front of a surface)
per scene and pooled, and the share of those voxels in (-1, 0) (behind the surface). The DATASHEET's row on the
table's depth quotes it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import h5py
import numpy as np

DEFAULT_REFERENCE = Path("/work/shared/reference/official-cube-reference.h5")


def table_layer(tsdf: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The z = 0 layer's TSDF values (volumes indexed (y, x, z)) at the voxels whose mask is 0 (no object)."""
    return np.asarray(tsdf)[:, :, 0][np.asarray(mask)[:, :, 0] == 0].astype(np.float64)


def summary(layers: list[np.ndarray]) -> dict:
    """Median per scene and pooled, and the pooled share of values in (-1, 0)."""
    pooled = np.concatenate(layers)
    return {"median_per_scene": [float(np.median(x)) for x in layers], "median": float(np.median(pooled)),
            "negative_share": float(np.mean((pooled > -1) & (pooled < 0)))}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data", type=Path, help="a dataset directory of ours (seq_*.h5)")
    parser.add_argument("--reference", type=Path, default=DEFAULT_REFERENCE, help="the authors' reference file")
    parser.add_argument("--num-sequences", type=int, default=4, help="our sequences measured (default 4)")
    args = parser.parse_args(argv)
    from dsr_bench.dataset.sequence import SequenceReader

    paths = sorted(args.data.glob("seq_*.h5"))[: args.num_sequences]
    if not paths:
        sys.exit(f"error: no seq_*.h5 in {args.data}; give a dataset directory (`dsr-bench generate ...`)")
    if not args.reference.is_file():
        sys.exit(f"error: --reference {args.reference}: no such file; give the authors' official-cube-reference.h5")
    ours = []
    for path in paths:
        with SequenceReader(path) as seq:
            ours.append(table_layer(seq.read("tsdf", 0), seq.read("mask_3d", 0)))
    theirs = []
    with h5py.File(args.reference, "r") as f:
        for name in sorted(f):
            if "tsdf_step0" in f[name]:
                theirs.append(table_layer(f[name]["tsdf_step0"][()], f[name]["mask_3d_step0"][()]))
    out = {"ours": summary(ours), "theirs": summary(theirs)}
    for side, s in out.items():
        scenes = ", ".join(f"{m:+.4f}" for m in s["median_per_scene"])
        print(f"{side:6s} z = 0 layer, free voxels: median {s['median']:+.4f} (per scene {scenes}); "
              f"in (-1, 0): {100 * s['negative_share']:.1f}%")
    return out


if __name__ == "__main__":
    main()
