"""The same weights scored on two splits: does a model fit the scenes it trained on better than new ones?

    python scripts/split_gap.py --seen WORK_A --unseen WORK_B [--models dsr single] [--out gap.json]

WORK_A and WORK_B are `cpu_track_evidence.py` work folders of the same weights on two splits (e.g. the first 100
training sequences and `cpu-val`): each holds the results WORK/<model>.json of `dsr-bench evaluate` (both made with
one weights file, by the SHA-256 their predictions record, or it stops), and may hold WORK/oracle-pooled.json, the
grid's ceiling on that split (`cpu_track_cap.py --work WORK`). For each model and headline metric, prints and
writes the mean over each split's sequences ± its standard error, seen - unseen ± the standard error of a
difference of two independent means (different sequences: nothing to pair), and, where the ceiling is there, each
IoU as a fraction of its split's ceiling. A model that is still fitting its training scenes
scores them no better than new ones; one that has memorised them scores them higher.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np

METRICS = ("motion_visible", "motion_full", "iou_unordered", "iou_ordered")
CEILING = "oracle-pooled"


def sequence_means(results: dict, metric: str) -> np.ndarray:
    """Each sequence's mean of `metric` over its steps, from an `evaluate` results dict's per_sequence."""
    values = [v[metric] for v in results["per_sequence"].values()]
    return np.array([np.mean(v) for v in values], dtype=np.float64)


def mean_and_se(values: np.ndarray) -> tuple[float, float]:
    return float(values.mean()), float(values.std(ddof=1) / np.sqrt(len(values)))


def gap(seen: dict, unseen: dict, seen_cap: dict | None = None, unseen_cap: dict | None = None) -> dict:
    """{metric: {"seen": [mean, se], "unseen": [mean, se], "difference": [mean, se], "of_ceiling": [seen,
    unseen]}} of one model's two results dicts (the ceilings' results optional)."""
    out = {}
    for metric in METRICS:
        (a, sa), (b, sb) = mean_and_se(sequence_means(seen, metric)), mean_and_se(sequence_means(unseen, metric))
        row = {"seen": [a, sa], "unseen": [b, sb], "difference": [a - b, float(np.hypot(sa, sb))]}
        if metric.startswith("iou") and seen_cap and unseen_cap:
            row["of_ceiling"] = [a / seen_cap["metrics"][metric], b / unseen_cap["metrics"][metric]]
        out[metric] = row
    return out


def weights_sha256(results: dict) -> str | None:
    """The SHA-256 of the weights file the results' predictions were made with (meta.json's parameters), or None."""
    weights = ((results.get("meta") or {}).get("parameters") or {}).get("weights") or {}
    return weights.get("sha256") if isinstance(weights, dict) else None


def _read(path: Path) -> dict:
    try:
        results = json.loads(path.read_text())
        if not isinstance(results.get("per_sequence"), dict) or not results["per_sequence"]:
            raise ValueError("no per_sequence")
        return results
    except (OSError, ValueError, AttributeError) as exc:
        raise SystemExit(f"error: {path}: not readable `dsr-bench evaluate` results ({exc}); run "
                         "cpu_track_evidence.py with this --work first") from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seen", type=Path, required=True, help="Work folder of the training split's scores.")
    parser.add_argument("--unseen", type=Path, required=True, help="Work folder of the held-out split's scores.")
    parser.add_argument("--models", nargs="+", default=["dsr", "single"])
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    caps = [args.seen / f"{CEILING}.json", args.unseen / f"{CEILING}.json"]
    seen_cap, unseen_cap = (_read(p) if p.is_file() else None for p in caps)
    summary: dict = {"command": "python " + shlex.join(["scripts/split_gap.py", *(argv or sys.argv[1:])]),
                     "seen": {"split": None, "sequences": None}, "unseen": {"split": None, "sequences": None},
                     "models": {}}
    for model in args.models:
        seen, unseen = _read(args.seen / f"{model}.json"), _read(args.unseen / f"{model}.json")
        sha = {weights_sha256(seen), weights_sha256(unseen)}
        if len(sha) != 1 or None in sha:
            raise SystemExit(f"error: {args.seen / model}.json and {args.unseen / model}.json were not predicted with "
                             "one recorded weights file; score the same weights on both splits")
        summary.setdefault("weights", {})[model] = sha.pop()
        for key, results in (("seen", seen), ("unseen", unseen)):
            summary[key] = {"split": results.get("split"), "sequences": len(results["per_sequence"])}
        summary["models"][model] = gap(seen, unseen, seen_cap, unseen_cap)
        for metric, row in summary["models"][model].items():
            cap = row.get("of_ceiling")
            print(f"{model} {metric}: seen {row['seen'][0]:.4f} ± {row['seen'][1]:.4f}, unseen {row['unseen'][0]:.4f}"
                  f" ± {row['unseen'][1]:.4f}, seen - unseen {row['difference'][0]:+.4f} ± {row['difference'][1]:.4f}"
                  + (f"; of the ceiling {cap[0]:.3f} and {cap[1]:.3f}" if cap else ""))
    if seen_cap and unseen_cap:
        summary["ceiling"] = {"seen": seen_cap["metrics"], "unseen": unseen_cap["metrics"]}
    if args.out:
        from dsr_bench.atomic import write_text

        write_text(args.out, json.dumps(summary, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
