"""Benchmark: seconds to load (log) a sequence into a rerun recording, as `dsr-bench view --save` does.

    python bench/bench_viewer.py                                   # a 10-step synthetic sequence
    python bench/bench_viewer.py --data DIR [--sequence seq_0000] [--predictions PRED_DIR]

Times `dsr_bench.viewer.view(..., save=...)` after the imports are paid (rerun, h5py), i.e. what a
user waits for between the command and a complete recording. Target: a 10-step sequence in under
2 s on 2 cores.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, help="dataset directory (default: a synthetic 10-step sequence)")
    parser.add_argument("--sequence", default="seq_0000")
    parser.add_argument("--predictions", type=Path)
    parser.add_argument("--steps", type=int, default=10, help="pushes of the synthetic sequence")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    import rerun  # noqa: F401  (import cost excluded)

    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.viewer import view

    work = Path(tempfile.mkdtemp(prefix="bench_viewer_"))
    if args.data is None:
        from dsr_bench.testing import write_synthetic_sequence

        path = write_synthetic_sequence(work / f"{args.sequence}.h5", args.steps, 3, seed=0)
    else:
        path = args.data / f"{args.sequence}.h5"
    with SequenceReader(path) as seq:
        steps, objects = seq.num_steps, seq.num_objects
    out = work / "bench.rrd"
    times = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        view(path, predictions=args.predictions, save=out)
        times.append(time.perf_counter() - start)
    size = out.stat().st_size / 1e6
    shutil.rmtree(work)
    print(f"{path}: {steps} pushes, {objects} objects, predictions: {'yes' if args.predictions else 'no'}")
    print(f"load time: best {min(times):.2f} s, mean {sum(times) / len(times):.2f} s over {args.repeats} runs; "
          f"recording {size:.1f} MB")


if __name__ == "__main__":
    main()
