"""Benchmark: seconds to evaluate a test split, and (with --official-repo) the authors' IoU functions
on exactly the same inputs, side by side.

    python bench/bench_evaluate.py --data DIR [--split S] [--num-sequences 8] [--model static] [--repeats 3]
                                   [--official-repo PATH] [--baseline-repo PATH]

Writes predictions with a reference model, then runs, alternated (A, B, C, ... A, B, C, ...):
- reading the arrays evaluate reads, step by step as it reads them, alone (the floor);
- `dsr_bench.scoring.evaluate.evaluate` with all cores, and with one process (every metric);
- only with `--official-repo PATH` (a checkout of columbia-ai-robotics/dsr): the authors'
  `calc_iou_unordered` (per step) and `calc_iou_ordered` (per sequence), loaded from their
  `test.py` alone, in this process (torch on the CPU), timed over their calls only: the inputs
  are built untimed from the same files, logit_pred (1, K, Y, X, Z) the one-hot of our predicted
  slots with the LAST channel empty, mask_gt_argmax (1, Y, X, Z) our ground truth `mask_3d`.
- only with `--baseline-repo PATH` (a checkout of another dsr-bench version, e.g. `git worktree add /tmp/base
  dfc7742`, from before `evaluate` verified the ground truth it scores): `evaluate` of that checkout and of this
  one, each in a fresh process of the same harness (imports untimed, its worker pool timed), on the same
  predictions and data: the cost of a change, such as the scored digests (docs/evaluation.md).
Prints the medians per sequence and the ratios; checks that the authors' values equal our
`iou_unordered_official` / `iou_ordered_official` and prints the largest difference. Without
`--official-repo` no comparison with the authors' code is made (and none is printed).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from official import (add_official_args, alternate, check_official_repo, load_official_functions,  # noqa: E402
                      report, run_main)

READ = "read files only"
OURS = "dsr-bench evaluate, all cores"
OURS_1 = "dsr-bench evaluate, 1 process"
THEIRS = "authors' calc_iou_unordered + calc_iou_ordered"
HERE = "evaluate, this checkout, own process"
BASELINE = "evaluate, --baseline-repo, own process"
#: one `evaluate` in a fresh interpreter whose dsr_bench is the checkout first on sys.path; prints its seconds
_TIMED = """import sys, time
sys.path.insert(0, sys.argv[1])
import dsr_bench
assert dsr_bench.__file__.startswith(sys.argv[1]), dsr_bench.__file__
from dsr_bench.memory import keep_freed_memory
from dsr_bench.scoring.evaluate import evaluate
keep_freed_memory()
t0 = time.perf_counter()
evaluation = evaluate(sys.argv[2], sys.argv[3], "bench", workers=int(sys.argv[4]))
seconds = time.perf_counter() - t0
assert evaluation.results is not None, evaluation.problems[:3]
print(seconds)
"""


def in_own_process(checkout: Path, pred: Path, data: Path, workers: int):
    """A side that runs `evaluate` of `checkout` in a fresh interpreter and returns the seconds it measured."""
    import subprocess

    def run() -> float:
        done = subprocess.run([sys.executable, "-c", _TIMED, str(checkout.resolve()), str(pred), str(data),
                               str(workers)], capture_output=True, text=True, check=False)
        if done.returncode:
            raise RuntimeError(f"evaluate of {checkout} failed: {done.stderr.strip().splitlines()[-1:]}")
        return float(done.stdout.strip().splitlines()[-1])
    return run


def read_only(pred_dir: Path, data_dir: Path, names: list[str]) -> None:
    """Read every step of the arrays `evaluate` reads, the way it reads them (`dsr_bench.dataset.storage`)."""
    import h5py

    from dsr_bench.dataset.storage import read_step

    for name in names:
        with h5py.File(pred_dir / f"{name}.h5", "r") as p, h5py.File(data_dir / f"{name}.h5", "r") as g:
            for ds in (p["mask"], p["motion"], g["mask_3d"], g["scene_flow_3d"], g["tsdf"]):
                for t in range(p["mask"].shape[0]):
                    read_step(ds, t)


def official_inputs(pred_mask: np.ndarray, gt_mask: np.ndarray, num_slots: int):
    """The authors' inputs of one sequence: per step logit_pred (1, K, Y, X, Z) float32, the one-hot
    of the predicted slots 1..S in channels 0..S-1 and empty voxels in the LAST channel (K =
    max(slots, GT objects) + 1, so an unused slot is an empty channel), and mask_gt_argmax
    (1, Y, X, Z) int64, 0 = empty."""
    import torch

    k = max(num_slots, int(gt_mask.max(initial=0))) + 1
    channel = np.where(pred_mask == 0, k - 1, pred_mask.astype(np.int64) - 1)
    logits, gts = [], []
    for t in range(pred_mask.shape[0]):
        onehot = torch.zeros((1, k) + pred_mask.shape[1:], dtype=torch.float32)
        onehot.scatter_(1, torch.from_numpy(channel[t])[None, None], 1.0)
        logits.append(onehot)
        gts.append(torch.from_numpy(gt_mask[t].astype(np.int64))[None])
    return logits, gts


class OfficialSide:
    """One run = the authors' two functions over every sequence; returns the seconds of their
    calls alone and keeps their values for the comparison with ours."""

    def __init__(self, functions: dict, pred_dir: Path, data_dir: Path, names: list[str]):
        self.unordered, self.ordered = functions["calc_iou_unordered"], functions["calc_iou_ordered"]
        self.pred_dir, self.data_dir, self.names = pred_dir, data_dir, names
        self.values: dict[str, dict] = {}
        self.channels: set[int] = set()

    def __call__(self) -> float:
        import time

        import h5py

        from dsr_bench.dataset.sequence import SequenceReader

        seconds = 0.0
        for name in self.names:
            with SequenceReader(self.data_dir / f"{name}.h5") as gt, h5py.File(self.pred_dir / f"{name}.h5", "r") as p:
                steps = gt.num_steps
                gt_mask = gt.read("mask_3d", slice(0, steps))
                pred_mask, num_slots = p["mask"][()], int(p.attrs["num_slots"])
            logits, gts = official_inputs(pred_mask, gt_mask, num_slots)
            self.channels.add(logits[0].shape[1])
            t0 = time.perf_counter()
            unordered = [self.unordered(logit, g) for logit, g in zip(logits, gts)]
            ordered = self.ordered(logits, gts)
            seconds += time.perf_counter() - t0
            self.values[name] = {"unordered": [_first(v) for v in unordered], "ordered": _first(ordered)}
        return seconds


def _first(value) -> float:
    """The one sample's value of a per-sample result (numpy array, tensor, list or scalar)."""
    return float(np.asarray(value, dtype=np.float64).reshape(-1)[0])


def compare(theirs: dict[str, dict], ours: dict[str, dict]) -> dict[str, float]:
    """Largest |authors' - ours| over (sequence, step) for the unordered IoU and over sequences for
    the ordered IoU (ours: the mean over steps of iou_ordered_official under the sequence's one
    matching, which is what the authors' per-sample ordered IoU is)."""
    du = [abs(a - b) for name in ours for a, b in zip(theirs[name]["unordered"], ours[name]["iou_unordered_official"],
                                                      strict=True)]
    do = [abs(theirs[name]["ordered"] - float(np.mean(ours[name]["iou_ordered_official"]))) for name in ours]
    return {"unordered": max(du), "ordered": max(do),
            "theirs_unordered": float(np.mean([v for n in ours for v in theirs[n]["unordered"]])),
            "ours_unordered": float(np.mean([v for n in ours for v in ours[n]["iou_unordered_official"]])),
            "theirs_ordered": float(np.mean([theirs[n]["ordered"] for n in ours])),
            "ours_ordered": float(np.mean([np.mean(ours[n]["iou_ordered_official"]) for n in ours]))}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--split")
    parser.add_argument("--num-sequences", type=int, default=8)
    parser.add_argument("--model", default="static")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each side, alternated (default 3)")
    parser.add_argument("--baseline-repo", type=Path, metavar="PATH",
                        help="another dsr-bench checkout: time its evaluate beside this one's, each in its own process")
    parser.add_argument("--workers", type=int, default=0, help="evaluate's workers in the --baseline-repo sides")
    add_official_args(parser, needs_env=False)
    args = parser.parse_args(argv)
    if args.baseline_repo is not None and not (args.baseline_repo / "dsr_bench" / "scoring" / "evaluate.py").is_file():
        from dsr_bench.errors import UserError

        raise UserError(f"--baseline-repo {args.baseline_repo}: not a dsr-bench checkout (no "
                        "dsr_bench/scoring/evaluate.py); make one with `git worktree add PATH COMMIT`")

    from dsr_bench.memory import keep_freed_memory
    from dsr_bench.scoring.evaluate import evaluate, score_sequence
    from dsr_bench.dataset.manifest import build_manifest, read_split, write_manifest
    from dsr_bench.models.predictors import load_predictor, predict_split

    keep_freed_memory()  # as `dsr-bench evaluate` does in its own process (its workers do too)
    functions = None
    if args.official_repo is not None:
        functions = load_official_functions(check_official_repo(args.official_repo, ("test.py",)))
    split, names = read_split(args.data, args.split)
    names = names[: args.num_sequences]
    work = Path(tempfile.mkdtemp(prefix="dsr-bench-eval-"))
    try:
        data = work / "data"  # a dataset of just these sequences, so evaluate scores exactly them
        (data / "splits").mkdir(parents=True)
        for name in names:
            os.symlink((args.data / f"{name}.h5").resolve(), data / f"{name}.h5")
        (data / "splits" / "bench.txt").write_text("".join(f"{n}\n" for n in names))
        write_manifest(data, build_manifest(data))
        pred = work / "pred"
        predict_split(load_predictor(args.model), data, names, pred)
        read_only(pred, data, names)  # warm the page cache for every side
        # ours per sequence (untimed; also pays the imports before any side is timed)
        ours = {name: score_sequence((name, str(pred / f"{name}.h5"), str(data / f"{name}.h5")))[2] for name in
                (names if functions else names[:1])}

        results: dict = {}

        def run_ours(workers: int):
            def run() -> None:
                evaluation = evaluate(pred, data, "bench", workers=workers)
                if evaluation.results is None:
                    raise RuntimeError(f"evaluate found problems: {evaluation.problems[:3]}")
                results["ours"] = evaluation.results
            return run

        runs = {READ: lambda: read_only(pred, data, names), OURS: run_ours(0), OURS_1: run_ours(1)}
        side = None
        if functions:
            side = runs[THEIRS] = OfficialSide(functions, pred, data, names)
        if args.baseline_repo is not None:
            runs[HERE] = in_own_process(Path(__file__).resolve().parents[1], pred, data, args.workers)
            runs[BASELINE] = in_own_process(args.baseline_repo, pred, data, args.workers)
        timings = alternate(runs, args.repeats)

        n = len(names)
        print(f"{n} sequences of {split} ({args.model} predictions); {os.cpu_count()} cores; "
              f"{args.repeats} runs of each side, alternated")
        ratios = [(OURS_1, READ)] + ([(HERE, BASELINE)] if args.baseline_repo is not None else [])
        if side:
            ratios = [(THEIRS, OURS), (THEIRS, OURS_1)] + ratios
        figures = report(timings, ratios, per=n, unit="sequence")
        if args.baseline_repo is not None:
            print(f"this checkout's evaluate over the baseline's: {100 * (figures[f'{HERE} / {BASELINE}'] - 1):+.1f}% "
                  f"(medians; runs {', '.join(f'{v:.2f}' for v in timings[HERE])} s vs "
                  f"{', '.join(f'{v:.2f}' for v in timings[BASELINE])} s)")
        print(f"dsr-bench at these medians, 400 sequences: {figures[OURS] * 400:.0f} s (all cores), "
              f"{figures[OURS_1] * 400:.0f} s (1 process)")
        metrics = results["ours"]["metrics"]
        print("dsr-bench metrics: " + ", ".join(f"{k} {metrics[k]:.6f}" for k in
                                                 ("motion_visible", "motion_full", "iou_unordered", "iou_ordered",
                                                  "iou_unordered_official", "iou_ordered_official")))
        if side is None:
            print("no comparison with the authors' code was made: pass --official-repo PATH (a checkout of "
                  "columbia-ai-robotics/dsr) to time their calc_iou_unordered / calc_iou_ordered beside ours")
            return {"timings": timings, "figures": figures}
        import torch

        diff = compare(side.values, ours)
        print(f"authors' functions: torch {torch.__version__} on the CPU, {torch.get_num_threads()} threads, "
              f"K = {', '.join(map(str, sorted(side.channels)))} channels (last empty), batch 1, their calls only "
              "(inputs built untimed)")
        print(f"  mask IoU unordered: authors' {diff['theirs_unordered']:.6f}, dsr-bench iou_unordered_official "
              f"{diff['ours_unordered']:.6f}, max |difference| over (sequence, step) {diff['unordered']:.2e}")
        print(f"  mask IoU ordered:   authors' {diff['theirs_ordered']:.6f}, dsr-bench iou_ordered_official "
              f"{diff['ours_ordered']:.6f}, max |difference| over sequences {diff['ordered']:.2e}")
        if max(diff["unordered"], diff["ordered"]) > 1e-6:
            print("  WARNING: the authors' values differ from ours: the timings compare different computations")
        return {"timings": timings, "figures": figures, "difference": diff}
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    run_main(main)
