"""Copy a dataset keeping only the arrays that training, prediction and scoring read.

    python scripts/slim_dataset.py SRC DST [--level 9]

For shipping a dataset to a remote GPU machine with a small transfer limit: each sequence keeps its
attributes, the arrays training reads (`dsr_bench.models.data.TRAINING_FIELDS`: `tsdf`, `action`,
`mask_3d`, `scene_flow_3d`) and `object_poses` and `visible_fraction` (gzip at --level; byte shuffle
but for the TSDF, where it costs), and drops the camera images. The manifest and split lists are
copied unchanged, so results still name the split checksum of the full data; `dsr-bench validate`
reports the slim files as incomplete, by design. Train, predict and evaluate (3D metrics) work on the copy.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import h5py

from dsr_bench.models.data import TRAINING_FIELDS

#: what training reads, then the object poses and the visible fraction (the occlusion-split scores)
KEEP = TRAINING_FIELDS + ("object_poses", "visible_fraction")


def slim_file(src: Path, dst: Path, level: int) -> None:
    tmp = dst.with_suffix(".tmp")
    with h5py.File(src, "r") as fin, h5py.File(tmp, "w") as fout:
        fout.attrs.update(fin.attrs)
        for name in KEEP:
            if name not in fin:
                continue
            data = fin[name]
            chunks = data.chunks if data.chunks else True
            out = fout.create_dataset(name, data=data[()], chunks=chunks, compression="gzip",
                                      compression_opts=level, shuffle=name != "tsdf")
            out.attrs.update(data.attrs)
    tmp.rename(dst)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("src", type=Path)
    parser.add_argument("dst", type=Path)
    parser.add_argument("--level", type=int, default=9)
    args = parser.parse_args()
    args.dst.mkdir(parents=True, exist_ok=True)
    for path in sorted(args.src.glob("*.h5")):
        slim_file(path, args.dst / path.name, args.level)
    for path in args.src.glob("*.json"):
        shutil.copy2(path, args.dst / path.name)
    if (args.src / "splits").is_dir():
        shutil.copytree(args.src / "splits", args.dst / "splits", dirs_exist_ok=True)
    size = sum(p.stat().st_size for p in args.dst.rglob("*") if p.is_file())
    print(f"{args.dst}: {size / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
