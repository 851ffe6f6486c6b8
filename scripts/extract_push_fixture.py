"""Write tests/data/official_push_paths.npz: the no-object pushes of run A of the authors' recorded push
(`official-push-trajectories.h5` of the shared reference data, made from their unmodified simulator), as the
arm-path test reads them.

    python scripts/extract_push_fixture.py [--reference H5] [--out tests/data/official_push_paths.npz]

Per push (88): the commanded start (x, y) and angle, the arm's joint angles when the push began (`q_home`),
the recorded length of each of the 5 moves in physics steps (`move_steps`) and which rows of the samples are
its own (`offset`, `count`). Per sample (the recording's, thinned by Douglas-Peucker to 0.01 mm in the push
phase): the physics step since the push began, the tool tip and the stick's lower end (float32, metres, world).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import h5py
import numpy as np

REFERENCE = Path("/work/shared/reference/official-push-trajectories.h5")
OUT = Path(__file__).resolve().parent.parent / "tests" / "data" / "official_push_paths.npz"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", type=Path, default=REFERENCE)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    with h5py.File(args.reference, "r") as f:
        pushes, samples = f["pushes"], f["samples"]
        chosen = np.flatnonzero(pushes["run"][:] == 0)  # run A: no objects, the grid and 16 random starts
        offsets, counts = pushes["sample_offset"][:][chosen], pushes["sample_count"][:][chosen]
        rows = np.concatenate([np.arange(o, o + n) for o, n in zip(offsets, counts)])
        arrays = {
            "start": pushes["cmd_start"][:][chosen, :2],
            "angle": pushes["cmd_angle"][:][chosen],
            "q_home": pushes["q_at_cmd"][:][chosen, 0],
            "move_steps": pushes["phase_steps"][:][chosen].astype(np.int32),
            "offset": (np.cumsum(counts) - counts).astype(np.int64),
            "count": counts.astype(np.int64),
            "step": samples["step"][:][rows].astype(np.uint16),
            "tip": samples["tip_pos"][:][rows],
            "stick_end": samples["stick_end_pos"][:][rows],
            "source": np.array(f"{args.reference.name}, run A "
                               f"({f.attrs['source_repo']} at {f.attrs['source_commit']})"),
        }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    partial = args.out.with_suffix(".partial.npz")
    np.savez_compressed(partial, **arrays)
    partial.replace(args.out)
    print(f"wrote {args.out}: {len(chosen)} pushes, {len(rows)} samples, {args.out.stat().st_size / 1e3:.0f} kB")


if __name__ == "__main__":
    main()
