"""Benchmark: do dsr-bench's simulated sequences follow the authors' generator, statistic by statistic?

    python bench/bench_fidelity.py [--ours DIR... | --generate N --objects cube --seed S] [--workers 2]
                                   [--reference H5 | --official-dir DIR] [--paired-with DIR...]
                                   [--bootstrap 2000] [--permutations 10000] [--json OUT]

Our side: directories of dsr-bench sequences (`--ours DIR...`, their seq_*.h5, pooled), or N sequences generated
here into a temporary directory (`dsr-bench generate --objects cube -n N --seed S --workers 2`;
default N = 40, seed 777). The authors' side: the reference file of their generator's cube sequences
(`--reference`, default /work/shared/reference/official-cube-reference.h5), or a directory in the
official release's per-step layout (`--official-dir`, read through `dsr_bench.dataset.official`).

Both sides are reduced to one record per sequence (object positions and (x, y, z, w) quaternions at
t = 0..T, actions [d, row, col], voxels of mask_3d == k at t = 0..T, TSDF band shares at t < T), and
every statistic below is computed from that record alone, identically for both (bench/fidelity_stats.py).
Each statistic is one value per sequence; per side the table shows the mean over sequences and a 95%
percentile interval from 2000 bootstrap resamples of whole sequences, and p is the two-sided
permutation p-value of the difference of the two sides' means (10000 random reassignments of the
pooled sequences to the sides). The resampling uses a fixed numpy seed, so a rerun on the same data
prints the same table. Rows with p <= 0.01 are marked `*`; with 16 rows about 0.16 rows are marked
by chance when both generators are the same.

Definitions (units in the row labels; a push is t -> t+1, t < T; means are over one sequence):
 1. objects moving per push: mean over pushes t of the number of objects whose pose change from t to
    t+1 moves the centre by > 4 mm (3D) or rotates it by > 2 deg (angle 2 acos|w| of q[t+1] * conj(q[t]))
 2. pushes moving >= 2 objects (%): share of pushes in which >= 2 objects move (moving as in 'objects
    moving per push')
 3. first push: cos(dir, to centre): mean over pushes that are the first push of the pushed object in
    the sequence of cos(angle) between the push direction and the xy direction from the object's centre
    before the push to (0.5, 0)
 4. pushed object: translation (cm): mean over pushes of the 3D distance (cm) the pushed object's
    centre moves in its push
    pushed object: rotation (deg): mean over pushes of the rotation angle (deg) of the pushed object in
    its push, 2 acos|w| of q[t+1] * conj(q[t])
 5. moving objects: point displacement (vox): mean over (push, moving object) of the mean |displacement|
    (voxels of 4 mm) of a 5x5x5 lattice at the cell centres of a cube of side s, s^3 =
    voxels_per_object[t] * 0.004^3, centred on the object's origin in its body frame, moved from the
    pose at t to the pose at t+1
 6. distance from centre at t=0 (cm): mean over objects of the xy distance (cm) of the object's centre
    at t = 0 from (0.5, 0)
 7. pushes ending with an object at the edge (%): share of pushes after which some object's centre lies
    within s/2 of the grid's xy bounds (x in [0.244, 0.756], y in [-0.256, 0.256]) or outside them,
    s^3 = voxels_per_object[0] * 0.004^3
 8. voxels per object at t=0: mean over objects of voxels_per_object[0] (voxels of mask_3d == k at t = 0)
 9. TSDF in (-1, 0) (%): mean over steps t < T of the share of TSDF voxels with -1 < v < 0
    TSDF in [0, 1) (%): mean over steps t < T of the share of TSDF voxels with 0 <= v < 1
    TSDF >= 1 (%): mean over steps t < T of the share of TSDF voxels with v >= 1
10. push directions: mean resultant length: length of the mean of the unit push direction vectors
    (cos d pi/4, sin d pi/4) of the sequence's pushes (0: balanced, 1: all one way)
    pushes along the axes (d even) (%): share of pushes with an even direction index d (along +-x or +-y)
11. same object as the previous push (%): share of pushes t >= 1 whose pushed object is the pushed
    object of push t-1
12. start distance to pushed object (cm): mean over pushes of the xy distance (cm) from the push start
    (the action cell's centre) to the pushed object's centre before the push
`--paired-with DIR...`: other directories of ours, one for each --ours directory and with its sequence names
(the same seeds made another way, e.g. with `--sleep-at-rest` against without): each statistic's mean
per-sequence difference (ours - paired) over the sequences both have, its standard error and a sign-flip
permutation p; a far more sensitive test of the change than either side against the authors'.
The pushed object is not recorded in the reference; on both sides it is inferred as follows. pushed
object: the object whose xy centre before the push is nearest to the segment from start + 0.02 m to
start + 0.12 m along the push direction (start = the action cell's centre). On our side, where the
policy records the object it chose, the printout also says how often the inference agrees with it.
A sequence with nothing to average for a statistic (e.g. no moving object) is left out of that row.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import h5py
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fidelity_stats import (
    PUSHED_OBJECT_RULE,
    STATISTICS,
    paired_difference,
    Record,
    bootstrap_interval,
    permutation_pvalue,
    pushed_objects,
    statistics_table,
    tsdf_bands,
    voxel_counts,
)
from official import last_line, run_main

from dsr_bench.errors import UserError

DEFAULT_REFERENCE = Path("/work/shared/reference/official-cube-reference.h5")
#: numpy seed of the bootstrap and the permutations (each row draws from its own stream of it).
RESAMPLE_SEED = 2020
#: p-values at or below this are marked.
ALPHA = 0.01
THEIRS = "authors' generator"
OURS = "dsr-bench"
#: decimals printed per statistic
_DECIMALS = {"moving_per_push": 2, "first_push_cos": 3, "voxels_t0": 0, "direction_resultant": 3,
             "tsdf_negative_pct": 3, "tsdf_near_pct": 3, "tsdf_free_pct": 2}


# --- reading both sides -----------------------------------------------------------------------------


def read_reference(path: str | Path) -> list[Record]:
    """The reference file's sequences (groups seq_*, in name order) as records."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"--reference {path}: file not found; pass the authors' reference .h5 "
                        "(official-cube-reference.h5) or --official-dir DIR")
    records = []
    try:
        with h5py.File(path, "r") as f:
            names = sorted(name for name in f if name.startswith("seq_") and isinstance(f[name], h5py.Group))
            if not names:
                raise UserError(f"--reference {path}: no seq_* groups; is this the authors' reference file?")
            for name in names:
                g = f[name]
                missing = [k for k in ("positions", "orientations", "actions", "voxels_per_object", "tsdf_bands")
                           if k not in g]
                if missing:
                    raise UserError(f"--reference {path}: group {name} lacks {', '.join(missing)}")
                try:
                    records.append(Record(name, g["positions"][()].astype(np.float64),
                                          g["orientations"][()].astype(np.float64), g["actions"][()].astype(np.int64),
                                          g["voxels_per_object"][()].astype(np.int64),
                                          g["tsdf_bands"][()].astype(np.float64)))
                except ValueError as exc:
                    raise UserError(f"--reference {path}: {exc}") from None
    except OSError as exc:
        raise UserError(f"--reference {path}: not a readable HDF5 file ({exc})") from None
    return records


def _observation(seq, name: str, t: int) -> np.ndarray:
    """Observation `name` at t = 0..T of an official sequence (t = T: the last step file's `next/` group)."""
    T = seq.num_steps
    return seq.read(T - 1, f"next/{name}") if t == T else seq.read(t, name)


def read_official_dir(path: str | Path) -> list[Record]:
    """The sequences of a directory in the official release's per-step layout, through
    `dsr_bench.dataset.official` (validated shapes and dtypes)."""
    from dsr_bench.dataset.official import find_official_sequences

    path = Path(path)
    if not path.is_dir():
        raise UserError(f"--official-dir {path}: not a directory; pass the official release's data directory "
                        "(<seq>_<step>.hdf5 files)")
    records = []
    for seq_id, seq in find_official_sequences(path).items():
        T = seq.num_steps
        positions = np.stack([_observation(seq, "positions", t) for t in range(T + 1)]).astype(np.float64)
        n = positions.shape[1]
        try:
            records.append(Record(
                f"official_{seq_id}", positions,
                np.stack([_observation(seq, "orientations", t) for t in range(T + 1)]).astype(np.float64),
                np.stack([seq.read(t, "action") for t in range(T)]).astype(np.int64),
                np.stack([voxel_counts(_observation(seq, "mask_3d", t), n) for t in range(T + 1)]),
                np.stack([tsdf_bands(seq.read(t, "tsdf")) for t in range(T)])))
        except ValueError as exc:
            raise UserError(f"--official-dir {path}: sequence {seq_id}: {exc}") from None
    return records


def read_ours(path: str | Path, flag: str = "--ours") -> tuple[list[Record], list[np.ndarray | None]]:
    """Records of a directory of dsr-bench sequences (its seq_*.h5), and each one's recorded policy choice
    (`policy/chosen_object`, or None where the file has none)."""
    from dsr_bench.dataset.sequence import SequenceReader

    path = Path(path)
    if not path.is_dir():
        raise UserError(f"{flag} {path}: not a directory; pass a dsr-bench dataset directory (seq_*.h5)")
    files = sorted(path.glob("seq_*.h5"))
    if not files:
        raise UserError(f"{flag} {path}: no seq_*.h5 sequence files; generate some with `dsr-bench generate`")
    records, chosen = [], []
    for file in files:
        with SequenceReader(file) as seq:
            T, n = seq.num_steps, seq.num_objects
            poses = seq.read("object_poses").astype(np.float64)
            try:
                records.append(Record(
                    seq.name, poses[..., :3], poses[..., 3:7], seq.read("action").astype(np.int64),
                    np.stack([voxel_counts(seq.read("mask_3d", t), n) for t in range(T + 1)]),
                    np.stack([tsdf_bands(seq.read("tsdf", t)) for t in range(T)])))
            except ValueError as exc:
                raise UserError(f"{flag} {file}: {exc}") from None
            chosen.append(seq.read("policy/chosen_object") if "policy/chosen_object" in seq else None)
    return records, chosen


def read_pooled(paths: list[Path], flag: str) -> tuple[list[Record], list[np.ndarray | None]]:
    """`read_ours` of each directory, pooled; with more than one, each record is named 'k:NAME' (k: the directory's
    place in `paths`), so that the k-th directories of two pools pair by name."""
    records, chosen = [], []
    for k, path in enumerate(paths):
        these, picked = read_ours(path, flag)
        if len(paths) > 1:
            these = [Record(f"{k}:{r.name}", r.positions, r.quaternions, r.actions, r.voxels_per_object,
                            r.tsdf_bands) for r in these]
        records += these
        chosen += picked
    return records, chosen


def dsr_bench_executable() -> Path:
    """The `dsr-bench` command of this environment."""
    exe = Path(sys.executable).with_name("dsr-bench")
    if exe.exists():
        return exe
    found = shutil.which("dsr-bench")
    if found is None:
        raise UserError("dsr-bench: command not found next to this Python or on PATH; install the toolkit "
                        "(pip install -e .[sim]) or pass --ours DIR")
    return Path(found)


def generate_ours(out: Path, num: int, objects: str, seed: int, workers: int) -> Path:
    """Run `dsr-bench generate` into `out`; its output goes to stderr, a failure is a one-line UserError."""
    cmd = [str(dsr_bench_executable()), "generate", "--objects", objects, "-n", str(num), "--seed", str(seed),
           "--workers", str(workers), "--out", str(out)]
    print(f"generating: {' '.join(cmd)}", file=sys.stderr, flush=True)
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, check=False)
    sys.stderr.write(proc.stdout)
    if proc.returncode != 0:
        raise UserError(f"dsr-bench generate exited {proc.returncode}: {last_line(proc.stdout)}")
    return out


# --- comparison and printout ------------------------------------------------------------------------


def compare(theirs: list[Record], ours: list[Record], n_boot: int, n_perm: int,
            seed: int = RESAMPLE_SEED) -> list[dict]:
    """One row per statistic: each side's mean, 95% bootstrap interval and n, and the permutation p."""
    a, b = statistics_table(theirs), statistics_table(ours)
    rows = []
    for i, (key, (label, definition)) in enumerate(STATISTICS.items()):
        rng = np.random.default_rng([seed, i])
        sides = {}
        for side, values in (("authors", a[key]), ("ours", b[key])):
            mean, low, high = bootstrap_interval(values, n_boot, rng)
            sides[side] = {"mean": mean, "low": low, "high": high, "n": int(np.isfinite(values).sum())}
        p = permutation_pvalue(a[key], b[key], n_perm, rng)
        rows.append({"key": key, "label": label, "definition": definition, **sides, "p": p,
                     "marked": bool(np.isfinite(p) and p <= ALPHA)})
    return rows


def compare_paired(ours: list[Record], other: list[Record], n_perm: int, seed: int = RESAMPLE_SEED) -> list[dict]:
    """One row per statistic: the paired difference ours - other over the sequences of the same name
    (`fidelity_stats.paired_difference`)."""
    names = sorted({r.name for r in ours} & {r.name for r in other})
    if not names:
        raise UserError("--paired-with: no sequence name in common with ours; pair the same seeds made two ways")
    by_name = ({r.name: r for r in ours}, {r.name: r for r in other})
    a, b = (statistics_table([side[n] for n in names]) for side in by_name)
    rows = []
    for i, (key, (label, _)) in enumerate(STATISTICS.items()):
        rng = np.random.default_rng([seed, 1000 + i])
        diff = paired_difference(a[key], b[key], n_perm, rng)
        rows.append({"key": key, "label": label, **diff, "marked": bool(np.isfinite(diff["p"]) and diff["p"] <= ALPHA)})
    return rows


def format_paired(rows: list[dict], n_perm: int) -> str:
    """The paired table: one statistic per row, mean difference +- standard error, n and p."""
    body = []
    for row in rows:
        d = _DECIMALS.get(row["key"], 1 if row["key"].endswith("_pct") else 2) + 1
        cell = "n/a" if not np.isfinite(row["mean"]) else f"{row['mean']:+.{d}f} ± {row['se']:.{d}f}"
        p = "n/a" if not np.isfinite(row["p"]) else f"{row['p']:.4f}"
        body.append((row["label"], cell, str(row["n"]), p + (" *" if row["marked"] else "")))
    head = ("statistic", "ours - paired (mean ± SE)", "n", "p")
    widths = [max(len(r[i]) for r in body + [head]) for i in range(4)]
    lines = ["| " + " | ".join(h.ljust(w) for h, w in zip(head, widths)) + " |",
             "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    lines += ["| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |" for r in body]
    lines.append(f"Per-sequence differences over the sequences both sides have; p: two-sided sign-flip permutation "
                 f"test ({n_perm} permutations); * p <= {ALPHA}.")
    return "\n".join(lines)


def inference_agreement(records: list[Record], chosen: list[np.ndarray | None]) -> float | None:
    """Share of pushes whose inferred pushed object is the policy's recorded choice (None: nothing recorded)."""
    pairs = [(pushed_objects(r), c) for r, c in zip(records, chosen) if c is not None and len(c) == r.num_pushes]
    if not pairs:
        return None
    return float(np.mean(np.concatenate([p == c for p, c in pairs])))


def _cell(side: dict, decimals: int) -> str:
    if not np.isfinite(side["mean"]):
        return "n/a"
    return f"{side['mean']:.{decimals}f} [{side['low']:.{decimals}f}, {side['high']:.{decimals}f}]"


def format_table(rows: list[dict], n_theirs: int, n_ours: int, n_boot: int, n_perm: int) -> str:
    """The table, one statistic per row, and its footnote (the definitions)."""
    body = []
    for row in rows:
        d = _DECIMALS.get(row["key"], 1 if row["key"].endswith("_pct") else 2)
        label = row["label"]
        counts = [row[s]["n"] for s in ("authors", "ours")]
        if counts != [n_theirs, n_ours]:
            label += f" (n = {counts[0]} / {counts[1]})"
        p = "n/a" if not np.isfinite(row["p"]) else f"{row['p']:.4f}"
        body.append((label, _cell(row["authors"], d), _cell(row["ours"], d), p + (" *" if row["marked"] else "")))
    head = ("statistic", f"{THEIRS} (n = {n_theirs}) [95%]", f"{OURS} (n = {n_ours}) [95%]", "p")
    widths = [max(len(r[i]) for r in body + [head]) for i in range(4)]
    lines = ["| " + " | ".join(h.ljust(w) for h, w in zip(head, widths)) + " |",
             "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    lines += ["| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |" for r in body]
    lines.append("")
    lines.append(f"Per-sequence values; mean over sequences [95% percentile interval, {n_boot} bootstrap resamples "
                 f"of sequences]; p: two-sided permutation test of the difference of means ({n_perm} "
                 f"permutations of sequences); numpy seed {RESAMPLE_SEED}; * p <= {ALPHA}. (n = a / b): sequences "
                 "with a value, where some have nothing to average.")
    for i, row in enumerate(rows, 1):
        lines.append(f"{i:2d}. {row['label']}: {row['definition']}")
    lines.append(f"    {PUSHED_OBJECT_RULE}.")
    return "\n".join(lines)


def write_json(path: Path, payload: dict) -> None:
    """Write `payload` to `path` through a temporary name (NaN as null)."""
    def clean(v):
        if isinstance(v, float) and not np.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list):
            return [clean(x) for x in v]
        return v

    path = Path(path)
    if not path.parent.is_dir():
        raise UserError(f"--json {path}: directory {path.parent} does not exist")
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(clean(payload), indent=2) + "\n")
    os.replace(tmp, path)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ours_arg = parser.add_mutually_exclusive_group()
    ours_arg.add_argument("--ours", type=Path, metavar="DIR", nargs="+",
                          help="directories of dsr-bench sequences (seq_*.h5), pooled")
    ours_arg.add_argument("--generate", type=int, metavar="N",
                          help="generate N sequences into a temporary directory (the default, N = 40)")
    parser.add_argument("--objects", default="cube", help="object set of --generate (default cube, as the reference)")
    parser.add_argument("--seed", type=int, default=777, help="base seed of --generate (default 777)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes of --generate (default 2)")
    theirs_arg = parser.add_mutually_exclusive_group()
    theirs_arg.add_argument("--reference", type=Path, metavar="H5", default=None,
                            help=f"the authors' reference file (default {DEFAULT_REFERENCE})")
    theirs_arg.add_argument("--official-dir", type=Path, metavar="DIR",
                            help="a directory in the official per-step layout (<seq>_<step>.hdf5), e.g. made by "
                                 "the authors' data_generation.py")
    parser.add_argument("--paired-with", type=Path, metavar="DIR", nargs="+",
                        help="as many directories as --ours, the k-th with the same sequence names as --ours' k-th: "
                             "paired differences too")
    parser.add_argument("--bootstrap", type=int, default=2000, help="bootstrap resamples (default 2000)")
    parser.add_argument("--permutations", type=int, default=10000, help="permutations (default 10000)")
    parser.add_argument("--json", type=Path, metavar="OUT", help="also write the numbers to OUT (JSON)")
    args = parser.parse_args(argv)

    for name in ("bootstrap", "permutations", "workers"):
        if getattr(args, name) < 1:
            raise UserError(f"--{name} {getattr(args, name)}: must be at least 1")
    if args.generate is not None and args.generate < 1:
        raise UserError(f"--generate {args.generate}: must be at least 1")
    if args.json is not None and not args.json.parent.is_dir():
        raise UserError(f"--json {args.json}: directory {args.json.parent} does not exist")
    for flag, dirs in (("--ours", args.ours), ("--paired-with", args.paired_with)):  # checked before anything is read
        for path in dirs or []:
            if not path.is_dir():
                raise UserError(f"{flag} {path}: not a directory; pass a dsr-bench dataset directory (seq_*.h5)")
    if args.paired_with is not None and (args.ours is None or len(args.paired_with) != len(args.ours)):
        raise UserError(f"--paired-with: {len(args.paired_with)} directories for "
                        f"{0 if args.ours is None else len(args.ours)} of --ours; give one for each --ours directory, "
                        "with its sequence names")

    # the authors' side first: a bad path fails before minutes of generation
    if args.official_dir is not None:
        theirs, theirs_source = read_official_dir(args.official_dir), f"official-layout directory {args.official_dir}"
    else:
        reference = args.reference or DEFAULT_REFERENCE
        theirs, theirs_source = read_reference(reference), f"reference file {reference}"

    scratch = None
    try:
        if args.ours is not None:
            ours, chosen = read_pooled(args.ours, "--ours")
            ours_source = f"director{'y' if len(args.ours) == 1 else 'ies'} {' '.join(map(str, args.ours))}"
        else:
            num = 40 if args.generate is None else args.generate
            scratch = Path(tempfile.mkdtemp(prefix="dsr-bench-fidelity-"))
            ours_dir = generate_ours(scratch / "data", num, args.objects, args.seed, args.workers)
            ours_source = f"dsr-bench generate --objects {args.objects} -n {num} --seed {args.seed}"
            ours, chosen = read_ours(ours_dir)
    finally:
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)

    rows = compare(theirs, ours, args.bootstrap, args.permutations)
    agreement = inference_agreement(ours, chosen)
    print(f"{THEIRS}: {len(theirs)} sequences ({theirs_source})")
    print(f"{OURS}: {len(ours)} sequences ({ours_source})")
    if agreement is not None:
        print(f"pushed-object inference agrees with dsr-bench's recorded policy choice in {100 * agreement:.1f}% "
              "of its pushes")
    print()
    print(format_table(rows, len(theirs), len(ours), args.bootstrap, args.permutations))
    paired = None
    if args.paired_with is not None:
        other, _ = read_pooled(args.paired_with, "--paired-with")
        paired = compare_paired(ours, other, args.permutations)
        print()
        print(f"paired with {' '.join(map(str, args.paired_with))} ({len(other)} sequences):")
        print(format_paired(paired, args.permutations))
    payload = {"authors": {"source": theirs_source, "sequences": len(theirs)},
               "ours": {"source": ours_source, "sequences": len(ours)},
               "bootstrap": args.bootstrap, "permutations": args.permutations, "seed": RESAMPLE_SEED,
               "alpha": ALPHA, "pushed_object_rule": PUSHED_OBJECT_RULE, "inference_agreement_ours": agreement,
               "statistics": rows}
    if paired is not None:
        payload["paired"] = {"source": [str(p) for p in args.paired_with], "statistics": paired}
    if args.json is not None:
        write_json(args.json, payload)
    return payload


if __name__ == "__main__":
    run_main(main)
