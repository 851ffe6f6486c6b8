"""Benchmark: bytes on disk per step, array by array, and seconds to read a step, for a dataset's files as
they are and re-stored in this toolkit's current layout (`dsr_bench.dataset.storage`).

    python bench/bench_storage.py DATA_DIR [--num-sequences 8] [--repeats 3] [--official-dir SRC]

For each of the first N sequences: every dataset's stored bytes (what `h5py` reports for its chunks) per
step, then the file re-written with `write_sequence` (today's layout: tiled grids, a camera's points derived
from its depth on reading) into a scratch directory, checked bit for bit against the original (every array as
read, NaN payloads included, and the meshes), and the same figures for it. Reading
is timed on each side with `storage.read_step` for the arrays `dsr-bench evaluate` reads (the 3D flow,
the TSDF and the amodal mask), alternated, medians. The table says where the bytes go; the side-by-side
figure against the authors' generator is `bench/bench_generate_official.py --official-repo PATH`, which
measures both generators' files in one run.

For sequences imported from the official release (`dsr-bench import-official SRC DATA_DIR`), `--official-dir SRC`
also sums the release's own step files of the same sequences (each file's `official_files`): the same content in
their layout and in ours, bytes per step.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from dsr_bench.dataset.storage import read_step

EVALUATED = ("scene_flow_3d", "tsdf", "mask_3d")


def stored_bytes(path: Path) -> dict[str, int]:
    """Stored bytes of every dataset of an HDF5 file, by dataset path."""
    sizes: dict[str, int] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: sizes.__setitem__(name, obj.id.get_storage_size())
                     if isinstance(obj, h5py.Dataset) else None)
    return sizes


def restore(src: Path, dst: Path) -> None:
    """Re-write a sequence file through `write_sequence` (today's layout), from its arrays as read: the stored ones
    and those the file leaves out and derives on reading (a schema-3 file's camera points, from its depth)."""
    from dsr_bench.dataset.sequence import SequenceReader, write_sequence

    with SequenceReader(src) as seq, h5py.File(src, "r") as f:
        arrays, extras = {}, {}

        def collect(name: str, obj) -> None:
            if isinstance(obj, h5py.Dataset) and not name.startswith("meshes/"):
                (extras if name.startswith("official/") else arrays)[name] = obj[()]
        f.visititems(collect)
        for name in sorted(seq.derived):  # write_sequence needs every array; it leaves these out again
            arrays[name] = seq.read(name)
        meshes = {i: seq.mesh(i) for i in range(seq.num_objects) if seq.mesh(i) is not None}
        attrs = {k: v for k, v in seq.attrs.items() if k not in ("format", "schema_version")}
    write_sequence(dst, arrays, attrs, meshes, extras)


def official_bytes(src: Path, paths: list[Path]) -> int:
    """Bytes of the release's step files (in `src`) that sequences imported from it (`paths`) were made from."""
    import json

    total = 0
    for path in paths:
        with h5py.File(path, "r") as f:
            files = f.attrs.get("official_files")
        if files is None:
            sys.exit(f"error: {path.name} was not imported from the official release (no official_files); drop "
                     "--official-dir")
        for name in json.loads(files) if isinstance(files, str) else list(files):
            if not (src / name).is_file():
                sys.exit(f"error: --official-dir {src}: {name} (of {path.name}) not found")
            total += (src / name).stat().st_size
    return total


def same_bits(a: Path, b: Path) -> list[str]:
    """Arrays (stored or derived, and the meshes) whose bytes differ between two sequence files (empty: identical)."""
    from dsr_bench.dataset.sequence import SequenceReader

    with SequenceReader(a) as x, SequenceReader(b) as y:
        names = x.array_names()
        differ = sorted(set(names) ^ set(y.array_names()))
        for name in names:
            if name in y:
                p, q = np.asarray(x.read(name)), np.asarray(y.read(name))
                if p.dtype != q.dtype or p.shape != q.shape or p.tobytes() != q.tobytes():
                    differ.append(name)
        for i in range(x.num_objects):
            p, q = x.mesh(i), y.mesh(i)
            if (p is None) != (q is None) or (p is not None and any(u.tobytes() != v.tobytes() for u, v in zip(p, q))):
                differ.append(f"meshes/{i}")
    return differ


def read_seconds(paths: list[Path]) -> float:
    """Seconds per step to read the evaluated arrays of every step of `paths` with `read_step`."""
    steps = 0
    t0 = time.perf_counter()
    for path in paths:
        with h5py.File(path, "r") as f:
            for name in EVALUATED:
                ds = f[name]
                for t in range(ds.shape[0]):
                    read_step(ds, t)
            steps += int(f.attrs["num_steps"])
    return (time.perf_counter() - t0) / max(steps, 1)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data", type=Path, help="a dataset directory (seq_*.h5)")
    parser.add_argument("--num-sequences", type=int, default=8, help="sequences measured (default 8)")
    parser.add_argument("--repeats", type=int, default=3, help="read timings per side, alternated (default 3)")
    parser.add_argument("--official-dir", type=Path, metavar="SRC",
                        help="the release directory DATA_DIR was imported from: compare with its own files")
    args = parser.parse_args(argv)
    paths = sorted(args.data.glob("seq_*.h5"))[: args.num_sequences]
    if not paths:
        sys.exit(f"error: no seq_*.h5 in {args.data}; give a dataset directory (`dsr-bench generate ...`)")
    scratch = Path(tempfile.mkdtemp(prefix="dsr-bench-storage-"))
    try:
        restored = []
        for path in paths:
            restore(path, scratch / path.name)
            differ = same_bits(path, scratch / path.name)  # every array, the meshes included
            if differ:
                sys.exit(f"error: {path.name}: re-stored arrays differ ({', '.join(differ)})")
            restored.append(scratch / path.name)
        steps = 0

        for path in paths:
            with h5py.File(path, "r") as f:
                steps += int(f.attrs["num_steps"])
        before: dict[str, int] = {}
        after: dict[str, int] = {}
        for a, b in zip(paths, restored):
            for name, size in stored_bytes(a).items():
                before[name] = before.get(name, 0) + size
            for name, size in stored_bytes(b).items():
                after[name] = after.get(name, 0) + size
        print(f"{len(paths)} sequences of {args.data}, {steps} steps; arrays re-stored bit for bit")
        print(f"{'array':32s} {'as stored kB/step':>18s} {'current layout kB/step':>23s}")
        for name in sorted(before, key=lambda n: -before[n]):
            if before[name] / steps >= 500:  # 0.5 kB a step and more
                print(f"{name:32s} {before[name] / steps / 1e3:18.1f} {after.get(name, 0) / steps / 1e3:23.1f}"
                      + ("  (derived on reading)" if name not in after else ""))
        files_before = sum(p.stat().st_size for p in paths) / steps / 1e6
        files_after = sum(p.stat().st_size for p in restored) / steps / 1e6
        print(f"{'whole files, MB/step':32s} {files_before:18.3f} {files_after:23.3f}")
        official = None
        if args.official_dir is not None:
            official = official_bytes(args.official_dir, paths) / steps / 1e6
            print(f"the release's own files of these sequences: {official:.3f} MB/step; ours / theirs: "
                  f"{files_before / official:.2f} as stored, {files_after / official:.2f} in the current layout")
        timings: dict[str, list[float]] = {"as stored": [], "current layout": []}
        for _ in range(args.repeats):
            timings["as stored"].append(read_seconds(paths))
            timings["current layout"].append(read_seconds(restored))
        for side, values in timings.items():
            print(f"read {'+'.join(EVALUATED)}, {side}: {statistics.median(values) * 1e3:.1f} ms per step")
        return {"mb_per_step": {"as stored": files_before, "current layout": files_after, "official": official},
                "bytes": {"as stored": before, "current layout": after},
                "read_seconds_per_step": {k: statistics.median(v) for k, v in timings.items()}}
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
