"""Copy a dataset keeping only the arrays that training, prediction and scoring read.

    python scripts/slim_dataset.py SRC DST [--level 9]

For shipping a dataset to a remote GPU machine with a small transfer limit: each sequence keeps its
attributes, the arrays training reads (`dsr_bench.models.data.TRAINING_FIELDS`: `tsdf`, `action`,
`mask_3d`, `scene_flow_3d`) and `object_poses` and `visible_fraction`, and drops the cameras' arrays (and
so the list of arrays derived from them). Each sequence is read through the toolkit's reader (format,
schema version and chunks checked) and written in the format's storage layout
(`dsr_bench.dataset.storage.write_array`: one chunk per step, all-zero flow tiles left out; deflate at
--level), atomically (`dsr_bench.atomic`). The manifest and split lists are copied unchanged, so results
still name the split checksum of the full data; `dsr-bench validate` reports the slim files as incomplete,
by design. Train, predict and evaluate (3D metrics) work on the copy.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import h5py
import numpy as np

from dsr_bench.atomic import atomic_path, check_writable, write_bytes
from dsr_bench.dataset.derived import DERIVED_FROM_ATTR
from dsr_bench.dataset.sequence import DERIVED_ATTR, SequenceReader
from dsr_bench.dataset.storage import write_array
from dsr_bench.models.data import TRAINING_FIELDS

#: what training reads, then the object poses and the visible fraction (the occlusion-split scores)
KEEP = TRAINING_FIELDS + ("object_poses", "visible_fraction")


def slim_file(src: Path, dst: Path, level: int = 9) -> None:
    """Write `dst`: `src`'s attributes (but the derived arrays' lists: no camera and no official/ array is kept)
    and its arrays in KEEP."""
    with SequenceReader(src) as seq:
        arrays = {name: (np.ascontiguousarray(seq.read(name)), dict(seq.dataset(name).attrs))
                  for name in KEEP if name in seq}
    with h5py.File(src, "r") as f:  # the attributes as stored (JSON strings stay the same strings)
        attrs = {key: value for key, value in f.attrs.items() if key not in (DERIVED_ATTR, DERIVED_FROM_ATTR)}
    with atomic_path(dst) as tmp, h5py.File(tmp, "w", track_order=True) as f:
        f.attrs.update(attrs)
        for name, (array, array_attrs) in arrays.items():
            write_array(f, name, array, level).attrs.update(array_attrs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("src", type=Path)
    parser.add_argument("dst", type=Path)
    parser.add_argument("--level", type=int, default=9, choices=range(1, 10), metavar="1..9")
    args = parser.parse_args()
    check_writable(args.dst, "DST")
    args.dst.mkdir(parents=True, exist_ok=True)
    for path in sorted(args.src.glob("*.h5")):
        slim_file(path, args.dst / path.name, args.level)
    for path in sorted(args.src.glob("*.json")):
        write_bytes(args.dst / path.name, path.read_bytes())
    if (args.src / "splits").is_dir():
        (args.dst / "splits").mkdir(exist_ok=True)
        for path in sorted((args.src / "splits").iterdir()):
            if path.is_file():
                write_bytes(args.dst / "splits" / path.name, path.read_bytes())
    size = sum(p.stat().st_size for p in args.dst.rglob("*") if p.is_file())
    print(f"{args.dst}: {size / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
