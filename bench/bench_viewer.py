"""Benchmark: seconds to load (log) a 10-step sequence into a rerun recording.

    python bench/bench_viewer.py --data DIR [--sequence seq_0000] [--predictions PRED_DIR]

Times `dsr_bench.viewer.view(..., save=...)` after the imports are paid (rerun, h5py), i.e. what a
user waits for between the command and a complete recording. Target: under 2 s on 2 cores.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--sequence", default="seq_0000")
    parser.add_argument("--predictions", type=Path)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    import rerun  # noqa: F401  (import cost excluded)

    from dsr_bench.sequence import SequenceReader
    from dsr_bench.viewer import view

    path = args.data / f"{args.sequence}.h5"
    with SequenceReader(path) as seq:
        steps = seq.num_steps
    out = Path(tempfile.mkdtemp()) / "bench.rrd"
    times = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        view(path, predictions=args.predictions, save=out)
        times.append(time.perf_counter() - start)
    print(f"{args.sequence}: {steps} pushes, predictions: {'yes' if args.predictions else 'no'}")
    print(f"load time: best {min(times):.2f} s, mean {sum(times) / len(times):.2f} s over {args.repeats} runs; "
          f"recording {out.stat().st_size / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
