"""A split's sequences reduced to model-ready arrays once, stacked and cached on disk: what the CPU-sized
tracks train on (`cpu_track.pooled_split`: pooled volumes; `image_track.image_split`: subsampled images)."""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dsr_bench.atomic import atomic_directory
from dsr_bench.errors import UserError
from dsr_bench.parallel import run_in_order


def cache_dir() -> Path:
    """Where reduced splits are cached: $DSR_BENCH_CACHE, else ~/.cache/dsr-bench."""
    return Path(os.environ.get("DSR_BENCH_CACHE") or Path.home() / ".cache" / "dsr-bench")


def cached_split(data_dir: Path, split: str | None, kind: str, version: list, reduce: Callable[[Path], dict],
                 workers: int = 1, progress: Callable[[int, int], None] | None = None) -> dict[str, np.ndarray]:
    """`reduce(path)` of every sequence of DATA_DIR's split, each array stacked on a new first axis (N, ...),
    plus "names" (N,), read-only and memory-mapped. Cached in `cache_dir()` as the folder `<kind>-<key>/` of one
    `.npy` per array, the key a hash of `version` (what defines the reduction) and the files' paths, sizes and
    modification times (a changed or regenerated file is reduced again). All sequences must have the same number
    of pushes."""
    from dsr_bench.dataset.manifest import read_split

    data_dir = Path(data_dir).resolve()
    _, names = read_split(data_dir, split)
    paths = [data_dir / f"{name}.h5" for name in names]
    missing = [p.name for p in paths if not p.is_file()]
    if missing:
        raise UserError(f"{data_dir}: {len(missing)} sequences of the split are missing ({missing[0]}, ...); "
                        "generate them again")
    stamp = [(str(p), p.stat().st_size, p.stat().st_mtime_ns) for p in paths]
    key = hashlib.sha256(json.dumps([*version, stamp]).encode()).hexdigest()[:20]
    cached = cache_dir() / f"{kind}-{key}"
    if not (cached / "names.npy").is_file():
        reduced = run_in_order(reduce, paths, workers, progress)
        lengths = {len(r["action"]) for r in reduced}
        if len(lengths) != 1:
            raise UserError(f"{data_dir}: sequences of {sorted(lengths)} pushes; the CPU-sized tracks need one length")
        out: dict[str, Any] = {k: np.stack([r[k] for r in reduced]) for k in reduced[0]}  # arrays, by name
        out["names"] = np.array(names)
        del reduced
        cached.parent.mkdir(parents=True, exist_ok=True)
        with atomic_directory(cached) as tmp:
            for name, array in out.items():
                np.save(tmp / f"{name}.npy", array)
        del out
    # memory-mapped, read-only: runs training side by side share one copy in the page cache (4,000 pooled
    # sequences are 5.9 GB)
    return {p.stem: np.load(p, mmap_mode="r") for p in sorted(cached.glob("*.npy"))}
