"""The CPU track's learning curve: each model's held-out scores against the sample-steps its weights trained on.

    python scripts/cpu_track_curve.py SUMMARY [SUMMARY ...] --out docs/evidence/CURVE.json [--plot CURVE.png]
        [--cap 0.642] [--mark STEPS:LABEL ...]

Each SUMMARY is what `scripts/cpu_track_evidence.py --out` wrote for one set of weights (its `--against`
namesakes count as points too). Every summary must have scored the same split (by its checksum). A point is one
weights file (by SHA-256; the same file in two summaries is one point): its model, its sample-steps (counted from
the training stages the file records, `cpu_track.sample_steps`), the means of the four metrics and, where the
summary has them, the paired differences to the static yardstick. --cap draws the grid's ceiling (ordered IoU of
the pooled ground truth brought back; docs/models.md) on the plot. Prints the table; the JSON records the command.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from dsr_bench.atomic import check_writable, write_text

METRICS = ("iou_ordered", "iou_unordered", "motion_visible", "motion_full")
RESCORE_TOLERANCE = 1e-3  # one file scored twice: predictions made with other kernels move a mean by ~1e-5


def curve_points(summaries: list[dict]) -> dict[str, list[dict]]:
    """Per model, its points sorted by sample-steps: {"sample_steps", "sha256", "means", "vs_static"}, and
    "rescored_within" (the largest difference of a mean) where two summaries scored the same file: the first
    summary's scores are kept. Predictions of the same weights made with other kernels (another CPU, or `--checkpoint`
    against the shipped path's fixed kernels, docs/models.md "Predictions across CPUs") differ in their last bits.

    Raises ValueError when the summaries scored different splits, or one file's means differ by more than
    `RESCORE_TOLERANCE`."""
    from dsr_bench.models.training.cpu_track import sample_steps

    checksums = {s["split_checksum"] for s in summaries}
    if len(checksums) != 1:
        raise ValueError(f"the summaries scored different splits (checksums {sorted(checksums)}); "
                         "give summaries of one split")
    points: dict[str, dict[str, dict]] = {}
    for summary in summaries:
        scored = [(name, record, summary["means"][name], summary.get("vs_static", {}).get(name))
                  for name, record in summary["weights"].items()]
        scored += [(name, record, summary["against_means"][name], None)
                   for name, record in summary.get("against", {}).items() if name in summary.get("against_means", {})]
        for name, record, means, vs_static in scored:
            point = {"sha256": record["sha256"], "sample_steps": sample_steps(record["stages"]),
                     "means": {m: means[m] for m in METRICS}}
            known = points.setdefault(name, {}).get(record["sha256"])
            if known is None:
                point["vs_static"] = vs_static
                points[name][record["sha256"]] = point
                continue
            apart = max(abs(known["means"][m] - point["means"][m]) for m in METRICS)
            if apart > RESCORE_TOLERANCE:
                raise ValueError(f"{name} {record['sha256'][:12]}: two summaries give it scores {apart:.3g} apart "
                                 f"(more than rounding, {RESCORE_TOLERANCE}); were they of the same data?")
            known["rescored_within"] = max(apart, known.get("rescored_within", 0.0))
            if vs_static and not known.get("vs_static"):
                known["vs_static"] = vs_static
    return {name: sorted(by_sha.values(), key=lambda p: p["sample_steps"]) for name, by_sha in sorted(points.items())}


def plot(curve: dict[str, list[dict]], cap: float | None, path: Path, marks: list[tuple[int, str]],
         split: str) -> None:
    """Ordered (solid) and unordered (dashed) IoU on `split` against sample-steps, one colour a model, the cap dotted,
    and a vertical line at each of `marks` (sample-steps, label)."""
    from matplotlib.figure import Figure

    from dsr_bench.scoring.plots import save_figure

    fig = Figure(figsize=(9, 4.2), layout="constrained")
    ax = fig.subplots()
    for i, (name, points) in enumerate(curve.items()):
        steps = [p["sample_steps"] / 1000 for p in points]
        colour = f"C{i}"
        ax.plot(steps, [p["means"]["iou_ordered"] for p in points], "o-", color=colour, label=f"{name}, ordered")
        ax.plot(steps, [p["means"]["iou_unordered"] for p in points], "s--", color=colour,
                label=f"{name}, unordered")
    if cap is not None:
        ax.axhline(cap, color="grey", linestyle=":", label=f"the grid's cap ({cap})")
    for steps, label in marks:
        ax.axvline(steps / 1000, color="black", linestyle="-.", linewidth=0.8)
        ax.annotate(label, (steps / 1000, 0.02), xytext=(4, 0), textcoords="offset points", fontsize=8)
    ax.set_xlabel("sample-steps (thousands)")
    ax.set_ylabel(f"IoU on {split}")
    ax.set_ylim(0, 1 if cap is None else max(0.7, cap + 0.05))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.01, 0.5))
    save_figure(fig, path)  # atomic, and the same figure gives the same bytes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("summaries", type=Path, nargs="+")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--plot", type=Path)
    parser.add_argument("--cap", type=float, help="The grid's ceiling of ordered IoU, drawn on the plot.")
    parser.add_argument("--mark", action="append", default=[], metavar="STEPS:LABEL",
                        help="A labelled vertical line on the plot at STEPS sample-steps (where the data changed).")
    args = parser.parse_args()
    marks = []
    for mark in args.mark:
        steps, _, label = mark.partition(":")
        if not steps.isdigit():
            raise SystemExit(f"--mark {mark!r}: give STEPS:LABEL, STEPS a whole number of sample-steps")
        marks.append((int(steps), label))
    check_writable(args.out, "--out", directory=False)
    if args.plot:
        check_writable(args.plot, "--plot", directory=False)
    summaries = []
    for path in args.summaries:
        try:
            summaries.append(json.loads(path.read_text()))
        except (OSError, ValueError) as exc:
            raise SystemExit(f"{path}: not a readable cpu_track_evidence summary ({exc}); give its --out") from None
        if not isinstance(summaries[-1], dict) or "weights" not in summaries[-1] or "means" not in summaries[-1]:
            raise SystemExit(f"{path}: not a cpu_track_evidence summary (no 'weights' and 'means'); give its --out")
    try:
        curve = curve_points(summaries)
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    first = summaries[0]
    record = {"command": shlex.join(["python", "scripts/cpu_track_curve.py", *sys.argv[1:]]),
              "split": first["split"], "split_checksum": first["split_checksum"], "sequences": first["sequences"],
              "cap_iou_ordered": args.cap, "marks": [{"sample_steps": m, "label": t} for m, t in marks],
              "models": curve}
    print(f"{first['split']} ({first['sequences']} sequences)")
    print(f"{'model':>8} {'sample-steps':>12} {'sha256':>12} " + " ".join(f"{m:>15}" for m in METRICS))
    for name, points in curve.items():
        for p in points:
            print(f"{name:>8} {p['sample_steps']:>12,} {p['sha256'][:12]:>12} "
                  + " ".join(f"{p['means'][m]:15.4f}" for m in METRICS))
    write_text(args.out, json.dumps(record, indent=1) + "\n")
    if args.plot:
        plot(curve, args.cap, args.plot, marks, split=first["split"])


if __name__ == "__main__":
    main()
