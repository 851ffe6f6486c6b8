"""The 2D track's evidence: 2DFlow, SE3-Net, SE3Pose-Net and the 3D models projected onto the image, against
the yardsticks on held-out novel objects.

    python scripts/image_track_evidence.py --data DATA/cpu-novel-test --weights DIR [--work DIR]
        [--models 2dflow se3net se3posenet] [--projected dsr single 3dflow] [--out docs/evidence/2d-track.json]
        [--leaderboard leaderboard]

For the yardsticks (static: no motion; push: every pixel that sees something above the table moved 10 cm
along the push; oracle), each 2D model's weights DIR/<model>.pt and each 3D model of --projected (its
shipped CPU-track weights: `predict` also writes its 3D flow projected onto the front camera's pixels),
runs exactly what a user runs:

    dsr-bench predict --model M [--checkpoint DIR/M.pt] --data DATA --out WORK/M
    dsr-bench evaluate WORK/M --data DATA --out WORK/M.json

then compares `motion_2d` (cm², the object pixels the front camera sees) sequence by sequence: each model's
mean, its paired difference to static and to push with the standard error, and every pair of models.
Predictions already in WORK are reused (delete them to predict again). With --leaderboard, each results
file joins the leaderboard (`dsr-bench leaderboard add`) and the tables are rebuilt.
"""

from __future__ import annotations

import argparse
import itertools
import json
import shlex
import subprocess
import sys
from pathlib import Path

from dsr_bench.atomic import check_writable, write_text

REFERENCES = ("static", "push", "oracle")


def run(*args: str) -> None:
    print("$", " ".join(args), flush=True)
    subprocess.run(args, check=True)


def main() -> None:
    from dsr_bench.scoring.compare import paired_difference

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--weights", type=Path,
                        help="directory of the 2D models' <model>.pt (default: the shipped ones)")
    parser.add_argument("--work", type=Path, default=Path("image-track-evidence"))
    parser.add_argument("--models", nargs="+", default=["2dflow", "se3net", "se3posenet"])
    parser.add_argument("--projected", nargs="*", default=["dsr", "single", "3dflow"])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--leaderboard", type=Path)
    args = parser.parse_args()
    if args.out:  # before the work: the results can be written
        check_writable(args.out, "--out", directory=False)

    cli = [sys.executable, "-m", "dsr_bench"]
    results = {}
    for name in (*REFERENCES, *args.models, *args.projected):
        pred, scored = args.work / name, args.work / f"{name}.json"
        if not scored.is_file():
            extra = ["--checkpoint", str(args.weights / f"{name}.pt")] if args.weights and name in args.models else []
            if not (pred / "meta.json").is_file():
                run(*cli, "predict", "--model", name, *extra, "--data", str(args.data), "--out", str(pred))
            run(*cli, "evaluate", str(pred), "--data", str(args.data), "--out", str(scored))
        results[name] = json.loads(scored.read_text())
        if "motion_2d" not in results[name]["metrics"]:
            sys.exit(f"{scored}: no motion_2d score; the data needs the front camera's images")
        if args.leaderboard:
            run(*cli, "leaderboard", "add", str(scored), "--predictions", str(pred), "--data", str(args.data),
                "--root", str(args.leaderboard))
    if args.leaderboard:
        run(*cli, "leaderboard", "build", "--root", str(args.leaderboard))

    per_seq = {name: r["per_sequence"] for name, r in results.items()}
    learned = [*args.models, *args.projected]
    summary = {"command": shlex.join(["python", "scripts/image_track_evidence.py", *sys.argv[1:]]),
               "data": str(args.data), "split": results["static"]["split"],
               "split_checksum": results["static"]["split_checksum"], "sequences": len(per_seq["static"]),
               "metric": "motion_2d (cm², front-camera object pixels)",
               "means": {name: r["metrics"]["motion_2d"] for name, r in results.items()},
               "per_step": {name: [round(v, 3) for v in r["per_step"]["motion_2d"]] for name, r in results.items()},
               "weights": {name: r["meta"].get("parameters", {}).get("weights") for name, r in results.items()},
               "vs_static": {n: paired_difference(per_seq[n], per_seq["static"], "motion_2d") for n in learned},
               "vs_push": {n: paired_difference(per_seq[n], per_seq["push"], "motion_2d") for n in learned},
               "pairs": {f"{a} - {b}": paired_difference(per_seq[a], per_seq[b], "motion_2d")
                         for a, b in itertools.combinations(learned, 2)}}

    print(f"\n{summary['split']} ({summary['sequences']} sequences), 2D flow MSE (cm²):")
    for name, value in summary["means"].items():
        row = f"{name:>12} {value:9.3f}"
        if name in learned:
            s, p = summary["vs_static"][name], summary["vs_push"][name]
            row += f"   vs static {s['mean']:+8.3f} ± {s['se']:.3f}   vs push {p['mean']:+8.3f} ± {p['se']:.3f}"
        print(row)
    print("\npairs, mean ± standard error:")
    for key, value in summary["pairs"].items():
        print(f"{key:>24} {value['mean']:+8.3f} ± {value['se']:.3f}")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_text(args.out, json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
