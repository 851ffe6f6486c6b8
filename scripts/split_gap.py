"""The same weights scored on two splits: does a model fit the scenes it trained on better than new ones?

    python scripts/split_gap.py --seen WORK_A --unseen WORK_B [--models dsr single] [--out gap.json]

WORK_A and WORK_B are `cpu_track_evidence.py` work folders of the same weights on two splits (e.g. the first 100
training sequences and `cpu-val`): each holds the results WORK/<model>.json of `dsr-bench evaluate` (both made with
one weights file, by the SHA-256 their predictions record, or it stops), and may hold WORK/oracle-pooled.json, the
grid's ceiling on that split (`cpu_track_cap.py --work WORK`; its split must be the models'). For each model and
headline metric, prints and writes the mean over each split's sequences ± its standard error, seen - unseen ± the
standard error of a difference of two independent means (different sequences: nothing to pair), and, where both
ceilings are there, each IoU as a fraction of its split's ceiling. A model that is still fitting its training
scenes scores them no better than new ones; one that has memorised them scores them higher. A problem with an
input is one line on stderr and exit 2.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
from pathlib import Path

import numpy as np

METRICS = ("motion_visible", "motion_full", "iou_unordered", "iou_ordered")
CEILING = "oracle-pooled"


class InputError(Exception):
    """A results file that cannot be compared, with the one line that says why."""


def sequence_values(results: dict, metric: str, source: Path) -> np.ndarray:
    """Each sequence's value of `metric` (its mean over the steps, as `evaluate`'s per_sequence holds it)."""
    values = []
    for name, scores in results["per_sequence"].items():
        value = scores.get(metric) if isinstance(scores, dict) else None
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
            raise InputError(f"{source}: per_sequence {name} {metric} is {value!r}, not a number; score the "
                             "predictions again with `dsr-bench evaluate`")
        values.append(float(value))
    return np.array(values, dtype=np.float64)


def mean_and_se(values: np.ndarray) -> tuple[float, float]:
    """(mean, standard error of the mean: sample standard deviation / sqrt(n)) of two or more values."""
    return float(values.mean()), float(values.std(ddof=1) / np.sqrt(len(values)))


def gap(seen: np.ndarray, unseen: np.ndarray, ceilings: tuple[float, float] | None = None) -> dict:
    """{"seen": [mean, se], "unseen": [mean, se], "difference": [seen - unseen, its se][, "of_ceiling": [seen /
    its ceiling, unseen / its ceiling]]} of one metric's per-sequence values on two splits."""
    (a, sa), (b, sb) = mean_and_se(seen), mean_and_se(unseen)
    row: dict = {"seen": [a, sa], "unseen": [b, sb], "difference": [a - b, float(np.hypot(sa, sb))]}
    if ceilings:
        row["of_ceiling"] = [a / ceilings[0], b / ceilings[1]]
    return row


def weights_sha256(results: dict) -> str | None:
    """The SHA-256 of the weights file the results' predictions were made with (meta.json's parameters), or None."""
    weights = ((results.get("meta") or {}).get("parameters") or {}).get("weights") or {}
    return weights.get("sha256") if isinstance(weights, dict) else None


def read_results(path: Path) -> dict:
    """An `evaluate` results dict with two or more scored sequences; InputError otherwise."""
    try:
        results = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not readable ({type(exc).__name__}); run cpu_track_evidence.py (or "
                         "cpu_track_cap.py) with this --work first") from None
    if not isinstance(results, dict) or not isinstance(results.get("per_sequence"), dict) \
            or len(results["per_sequence"]) < 2 or not isinstance(results.get("metrics"), dict):
        raise InputError(f"{path}: not `dsr-bench evaluate` results of two or more sequences; score the split "
                         "with `dsr-bench evaluate`")
    return results


def _split(results: dict) -> tuple:
    return results.get("split"), results.get("split_checksum"), sorted(results["per_sequence"])


def compare(seen_dir: Path, unseen_dir: Path, models: list[str]) -> dict:
    """The summary `main` writes: each model's `gap` for every metric, the splits, the weights and the ceilings."""
    summary: dict = {"models": {}, "weights": {}}
    splits: dict = {}
    pairs: dict[str, dict] = {}
    for model in models:
        pair = {key: read_results(folder / f"{model}.json")
                for key, folder in (("seen", seen_dir), ("unseen", unseen_dir))}
        sha = {weights_sha256(r) for r in pair.values()}
        if len(sha) != 1 or None in sha:
            raise InputError(f"{seen_dir / model}.json and {unseen_dir / model}.json were not predicted with one "
                             "recorded weights file; score the same weights on both splits")
        summary["weights"][model] = sha.pop()
        for key, results in pair.items():
            if splits.setdefault(key, _split(results)) != _split(results):
                raise InputError(f"{(seen_dir if key == 'seen' else unseen_dir) / model}.json scored other sequences"
                                 f" than the other models' in that folder; score every model on one split")
        pairs[model] = pair
    ceilings = {}
    for key, folder in (("seen", seen_dir), ("unseen", unseen_dir)):
        path = folder / f"{CEILING}.json"
        if path.is_file():
            ceiling = read_results(path)
            if _split(ceiling) != splits[key]:
                raise InputError(f"{path} scored another split than {folder}'s models; measure it again with "
                                 f"cpu_track_cap.py --work {folder}")
            ceilings[key] = ceiling["metrics"]
    for model, pair in pairs.items():
        rows = {}
        for metric in METRICS:
            caps = tuple(ceilings[k].get(metric) for k in ("seen", "unseen")) if len(ceilings) == 2 else None
            usable = metric.startswith("iou") and caps and all(isinstance(c, (int, float)) and c > 0 for c in caps)
            rows[metric] = gap(sequence_values(pair["seen"], metric, seen_dir / f"{model}.json"),
                               sequence_values(pair["unseen"], metric, unseen_dir / f"{model}.json"),
                               caps if usable else None)
        summary["models"][model] = rows
    for key in ("seen", "unseen"):
        summary[key] = {"split": splits[key][0], "split_checksum": splits[key][1], "sequences": len(splits[key][2])}
    if len(ceilings) == 2:
        summary["ceiling"] = {k: {m: ceilings[k].get(m) for m in METRICS} for k in ("seen", "unseen")}
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seen", type=Path, required=True, help="Work folder of the training split's scores.")
    parser.add_argument("--unseen", type=Path, required=True, help="Work folder of the held-out split's scores.")
    parser.add_argument("--models", nargs="+", default=["dsr", "single"])
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    try:
        summary = compare(args.seen, args.unseen, args.models)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    summary = {"command": "python " + shlex.join(["scripts/split_gap.py", *(sys.argv[1:] if argv is None else argv)]),
               **summary}
    for model, rows in summary["models"].items():
        for metric, row in rows.items():
            cap = row.get("of_ceiling")
            print(f"{model} {metric}: seen {row['seen'][0]:.4f} ± {row['seen'][1]:.4f}, unseen {row['unseen'][0]:.4f}"
                  f" ± {row['unseen'][1]:.4f}, seen - unseen {row['difference'][0]:+.4f} ± {row['difference'][1]:.4f}"
                  + (f"; of the ceiling {cap[0]:.3f} and {cap[1]:.3f}" if cap else ""))
    if args.out:
        from dsr_bench.atomic import write_text

        write_text(args.out, json.dumps(summary, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
