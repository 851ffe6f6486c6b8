"""Benchmark: seconds per 10-step sequence per CPU core, and where the time goes.

    python bench/bench_generate.py [--objects procedural] [--sequences 5] [--steps 10]

Runs the generator in one process after a warm-up sequence that pays the imports. pybullet and
our numpy code are single-threaded; open3d's ray casting may use a second core, so process CPU
seconds are printed next to wall seconds (CPU seconds per sequence is the per-core cost, and the
figure to compare on a shared machine, where wall time also counts other jobs). Prints per-phase
CPU and wall seconds (physics, rendering + ground truth, HDF5 writing) and bytes per step.
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", default="procedural")
    parser.add_argument("--sequences", type=int, default=5)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--cameras", default="front")
    args = parser.parse_args()

    from dsr_bench.dataset.digests import digest_attrs
    from dsr_bench.dataset.sequence import write_sequence
    from dsr_bench.dataset.storage import _DEFLATE
    from dsr_bench.dataset.splits import sequence_seed
    from dsr_bench.generators.episode import EpisodeConfig, generate_episode
    from dsr_bench.generators.objects import get_object_set

    object_set = get_object_set(args.objects)
    config = EpisodeConfig(objects=args.objects, steps=args.steps, cameras=tuple(args.cameras.split(",")))
    out = Path(tempfile.mkdtemp(prefix="dsr-bench-bench-"))
    generate_episode(config, object_set, sequence_seed(999, 0), "warmup")
    rows = []
    usage0 = resource.getrusage(resource.RUSAGE_SELF)
    cpu0 = time.process_time()
    wall0 = time.perf_counter()
    for i in range(args.sequences):
        t0, c0 = time.perf_counter(), time.process_time()
        ep = generate_episode(config, object_set, sequence_seed(1234, i), f"seq_{i:04d}")
        t1, c1 = time.perf_counter(), time.process_time()
        ep.attrs.update(digest_attrs(ep.arrays, ep.attrs["objects"]))
        t2, c2 = time.perf_counter(), time.process_time()
        path = write_sequence(out / f"seq_{i:04d}.h5", ep.arrays, ep.attrs, ep.meshes)
        t3, c3 = time.perf_counter(), time.process_time()
        rows.append({"total": t3 - t0, "simulate+observe": t1 - t0, "digest": t2 - t1, "write": t3 - t2,
                     "total_cpu": c3 - c0, "simulate+observe_cpu": c1 - c0, "digest_cpu": c2 - c1,
                     "write_cpu": c3 - c2, "scene_attempts": ep.scene_attempts, "bytes": path.stat().st_size,
                     **ep.timings})
    wall = time.perf_counter() - wall0
    cpu = time.process_time() - cpu0
    usage = resource.getrusage(resource.RUSAGE_SELF)
    user, system = usage.ru_utime - usage0.ru_utime, usage.ru_stime - usage0.ru_stime
    mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    print(f"machine: {os.cpu_count()} cores; object set {args.objects}; {args.steps} pushes; cameras {args.cameras}; "
          f"fast deflate (isal): {'yes' if _DEFLATE is not None else 'no'}")
    print(f"sequences: {args.sequences}; wall {wall:.1f} s; process CPU {cpu:.1f} s "
          f"(CPU/wall {cpu / wall:.2f}: >1 means library threads used a second core, <1 that the machine is busy)")
    print(f"seconds per sequence (wall, one process): {mean['total']:.2f}")
    print(f"CPU seconds per sequence: {cpu / args.sequences:.2f} "
          f"(user {user / args.sequences:.2f}, system {system / args.sequences:.2f})")
    print("where the time goes (per sequence):          CPU s           wall s")
    other = mean["simulate+observe"] - mean["physics"] - mean["render"] - mean["policy"]
    other_cpu = mean["simulate+observe_cpu"] - mean["physics_cpu"] - mean["render_cpu"] - mean["policy_cpu"]
    for key, phase in [("physics (pybullet)", "physics"), ("render + TSDF + amodal voxels", "render"),
                       ("push policy", "policy"), ("scene flow, assembly, setup", None),
                       ("content digest", "digest"), ("HDF5 write (gzip)", "write")]:
        value = other_cpu if phase is None else mean[f"{phase}_cpu"]
        value_wall = other if phase is None else mean[phase]
        print(f"  {key:32s} {value:6.3f} ({value / mean['total_cpu'] * 100:4.1f}%)   {value_wall:6.3f}")
    print(f"scene attempts per sequence: {mean['scene_attempts']:.2f}")
    print(f"bytes per step on disk: {mean['bytes'] / args.steps / 1e6:.3f} MB (official release: ~1 MB)")


if __name__ == "__main__":
    main()
