"""The CPU track's evidence: every reference model against the yardsticks on held-out novel objects.

    python scripts/cpu_track_evidence.py --data DATA/cpu-novel-test --weights DIR [--work DIR]
        [--models dsr nowarp single gtwarp 3dflow] [--out docs/evidence/cpu-track.json] [--leaderboard leaderboard]
        [--history-variants] [--controls single-same-windows]

For the yardsticks (static: no motion; push: every object voxel moved 10 cm along the push; oracle) and for
each model's weights DIR/<model>.pt, runs exactly what a user runs:

    dsr-bench predict --model M [--checkpoint DIR/M.pt] --data DATA --out WORK/M
    dsr-bench evaluate WORK/M --data DATA --out WORK/M.json

then compares the models sequence by sequence (`per_sequence` of the results): the mean of each metric, and
for each model the paired difference to static and to push with its standard error (the standard
deviation of the per-sequence differences / sqrt(n)); and DSR-Net vs NoWarp vs SingleStep on IoU. With
--leaderboard, each results file joins the leaderboard (`dsr-bench leaderboard add`) and the tables are
rebuilt. Predictions already in WORK are reused (delete them to predict again), once checked: a model's reused
predictions or results must record the SHA-256 of the weights file they stand for, or the script stops.

--history-variants also scores DSR-Net and NoWarp with their history zeroed at test time (the same
weights; `dsr-history-none`), and DSR-Net with its state not warped (`dsr-history-nowarp`): whether the
trained networks use what their state carries. --controls NAME... scores further weights files
DIR/NAME.pt (e.g. single-same-windows: SingleStep trained with `--same-windows`), never on the leaderboard.
--against DIR2 scores each model's namesake DIR2/<model>.pt too (WORK/against-<model>) and gives the paired
differences model - namesake (`vs_against`; the namesakes' means in `against_means`): e.g. weights continued
from DIR2's (`--track cpu --init`) against them.
The summary records its own command and each weights file's SHA-256 and training stages. A --checkpoint is
predicted with the shipped weights' fixed kernels on one thread (`same_bits_env`), so a file scores the same bytes
as a weights folder or as the shipped files, on any CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
from collections.abc import Callable
from functools import partial
from pathlib import Path


from dsr_bench.atomic import check_writable, write_text

METRICS = ("motion_visible", "motion_full", "iou_unordered", "iou_ordered")
REFERENCES = ("static", "push", "oracle")
PAIRS = (("dsr", "nowarp"), ("dsr", "single"), ("nowarp", "single"), ("gtwarp", "dsr"))


def run(*args: str, env: dict | None = None) -> None:
    print("$", " ".join(args), flush=True)
    subprocess.run(args, check=True, env=env)


def same_bits_env() -> dict:
    """The environment in which `predict --checkpoint` makes the bytes the shipped weights' path makes on any x86-64
    CPU with AVX2 (the kernels `predict` fixes for them, `cli.scoring.same_bits_unset`, on `SAME_BITS_THREADS`;
    docs/models.md "Predictions across CPUs"): a variable the user set is kept."""
    from dsr_bench.cli.scoring import same_bits_unset
    from dsr_bench.models.inference import SAME_BITS_THREADS

    return {"OMP_NUM_THREADS": str(SAME_BITS_THREADS), **os.environ, **same_bits_unset(os.environ)}


def paired(a: dict, b: dict, metric: str) -> dict:
    """Mean of a - b over the sequences both scored, its standard error and n."""
    from dsr_bench.scoring.compare import paired_difference

    return paired_difference(a, b, metric)


def torch_config(path: Path) -> dict:
    """The model_config of a weights file."""
    from dsr_bench.models.training.checkpoints import read_weights

    return read_weights(path)["model_config"]


def weights_record(path: Path) -> dict:
    """A weights file's SHA-256 and its training stages as recorded in it (CPU-track files: stage records, the
    continued chunks without their curves)."""
    from dsr_bench.dataset.manifest import file_sha256
    from dsr_bench.models.training.checkpoints import read_weights

    stages = read_weights(path).get("stages") or {}
    shown = {k: v for k, v in stages.items() if k != "continued"}
    if "continued" in stages:
        shown["continued"] = [{k: v for k, v in c.items() if k != "loss_every_10"} for c in stages["continued"]]
    return {"file": path.name, "sha256": file_sha256(path), "stages": shown}


def recorded_weights_sha256(meta: object) -> str | None:
    """The SHA-256 of the weights file a prediction's meta (predictions' meta.json, or a results file's "meta")
    records, or None where it records none (the yardsticks)."""
    if not isinstance(meta, dict):
        return None
    weights = meta.get("weights") or (meta.get("parameters") or {}).get("weights")
    return weights.get("sha256") if isinstance(weights, dict) else None


def check_reused(path: Path, meta: object, weights: Path | None) -> None:
    """Stop unless the reused predictions or results at `path` were made from `weights` (None: from no weights)."""
    from dsr_bench.dataset.manifest import file_sha256

    recorded, expected = recorded_weights_sha256(meta), weights and file_sha256(weights)
    if recorded != expected:
        made = f"weights {recorded[:12]}" if recorded else "no weights file"
        wanted = f"{weights} ({expected[:12]})" if expected else "no weights file"
        sys.exit(f"{path}: reused work made from {made}, not {wanted}; delete it to predict again")


def predict_with_history(weights: Path, model: str, history: str, data: Path, out: Path) -> None:
    """Predict the split with `model`'s weights, its history replaced at test time by `history`."""
    import dataclasses

    from dsr_bench.dataset.manifest import read_split
    from dsr_bench.models.predictors import load_predictor, predict_split

    print(f"# {model} with its history '{history}' at test time: {weights}", flush=True)
    predictor = load_predictor(model, weights)
    predictor.model.config = dataclasses.replace(predictor.model.config, history=history)
    predictor.name = f"{predictor.name}-history-{history}"
    _, names = read_split(data, None)
    predict_split(predictor, data, names, out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--weights", type=Path, required=True)
    parser.add_argument("--work", type=Path, default=Path("cpu-track-evidence"))
    parser.add_argument("--models", nargs="+", default=["dsr", "nowarp", "single", "gtwarp", "3dflow"])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--leaderboard", type=Path)
    parser.add_argument("--history-variants", action="store_true")
    parser.add_argument("--controls", nargs="*", default=[])
    parser.add_argument("--against", type=Path, help="Another weights folder: each model against its namesake there.")
    args = parser.parse_args()
    if args.out:  # before the work: the results can be written
        check_writable(args.out, "--out", directory=False)

    cli = [sys.executable, "-m", "dsr_bench"]

    def scored(label: str, predict: Callable[[Path], None], weights: Path | None = None) -> dict:
        """WORK/<label>.json, the results of `predict(WORK/<label>)` evaluated; either one reused when there (made
        from `weights`, checked by the SHA-256 they record)."""
        pred, results_file = args.work / label, args.work / f"{label}.json"
        if results_file.is_file():
            results = json.loads(results_file.read_text())
            check_reused(results_file, results.get("meta"), weights)
            return results
        if (pred / "meta.json").is_file():
            check_reused(pred / "meta.json", json.loads((pred / "meta.json").read_text()), weights)
        else:
            predict(pred)
        run(*cli, "evaluate", str(pred), "--data", str(args.data), "--out", str(results_file))
        return json.loads(results_file.read_text())

    def predict_cli(model: str, checkpoint: Path | None) -> Callable[[Path], None]:
        extra = [] if checkpoint is None else ["--checkpoint", str(checkpoint)]
        env = None if checkpoint is None else same_bits_env()  # a file's scores the same bytes whichever way it ran
        return lambda pred: run(*cli, "predict", "--model", model, *extra, "--data", str(args.data), "--out",
                                str(pred), env=env)

    from dsr_bench.models.predictors import SHIPPED_WEIGHTS

    shipped = args.weights.resolve() == SHIPPED_WEIGHTS.resolve()  # predicted as users do: no --checkpoint
    results = {}
    for name in (*REFERENCES, *args.models):
        checkpoint = None if name in REFERENCES or shipped else args.weights / f"{name}.pt"
        results[name] = scored(name, predict_cli(name, checkpoint),
                               None if name in REFERENCES else args.weights / f"{name}.pt")
        if args.leaderboard:
            run(*cli, "leaderboard", "add", str(args.work / f"{name}.json"), "--predictions", str(args.work / name),
                "--data", str(args.data), "--root", str(args.leaderboard))
    if args.leaderboard:
        run(*cli, "leaderboard", "build", "--root", str(args.leaderboard))

    variants = [("dsr", "none"), ("dsr", "nowarp"), ("nowarp", "none")] if args.history_variants else []
    for name, history in variants:
        results[f"{name}-history-{history}"] = scored(
            f"{name}-history-{history}",
            partial(predict_with_history, args.weights / f"{name}.pt", name, history, args.data),
            args.weights / f"{name}.pt")
    for label in args.controls:
        weights = args.weights / f"{label}.pt"
        results[label] = scored(label, lambda pred, w=weights: predict_cli(torch_config(w)["name"], w)(pred), weights)

    against = {name: scored(f"against-{name}", predict_cli(name, args.against / f"{name}.pt"),
                            args.against / f"{name}.pt")
               for name in (args.models if args.against else ())}

    per_seq = {name: r["per_sequence"] for name, r in results.items()}
    summary = {"command": shlex.join(["python", "scripts/cpu_track_evidence.py", *sys.argv[1:]]),
               "weights": {name: weights_record(args.weights / f"{name}.pt") for name in (*args.models,
                                                                                         *args.controls)},
               "data": str(args.data), "split": results["static"]["split"],
               "split_checksum": results["static"]["split_checksum"], "sequences": len(per_seq["static"]),
               "means": {name: {m: r["metrics"][m] for m in METRICS} for name, r in results.items()},
               "grid": {name: r["meta"].get("parameters", {}).get("grid") for name, r in results.items()},
               "per_step": {name: {m: [round(v, 4) for v in r["per_step"][m]] for m in ("iou_ordered", "motion_full")}
                            for name, r in results.items()},
               "breakdowns": {name: r["breakdowns"] for name, r in results.items()},
               "vs_static": {}, "vs_push": {}, "pairs": {}}
    for name in args.models:
        summary["vs_static"][name] = {m: paired(per_seq[name], per_seq["static"], m) for m in METRICS}
        summary["vs_push"][name] = {m: paired(per_seq[name], per_seq["push"], m) for m in METRICS[:2]}
    if against:
        summary["against"] = {name: weights_record(args.against / f"{name}.pt") for name in against}
        summary["against_means"] = {name: {m: r["metrics"][m] for m in METRICS} for name, r in against.items()}
        summary["vs_against"] = {name: {m: paired(per_seq[name], r["per_sequence"], m) for m in METRICS}
                                 for name, r in against.items()}
    pairs = list(PAIRS) + [(f"{n}-history-{h}", n) for n, h in variants] + \
        [(c, "single") for c in args.controls] + [("dsr", c) for c in args.controls]
    for a, b in pairs:
        if a in per_seq and b in per_seq:
            summary["pairs"][f"{a} - {b}"] = {m: paired(per_seq[a], per_seq[b], m) for m in METRICS}

    print(f"\n{summary['split']} ({summary['sequences']} sequences), means:")
    print(f"{'':>8} " + " ".join(f"{m:>15}" for m in METRICS))
    for name, row in summary["means"].items():
        print(f"{name:>8} " + " ".join(f"{row[m]:15.4f}" for m in METRICS))
    print("\nordered IoU per step, and IoU of mostly occluded / visible objects:")
    for name in summary["per_step"]:
        b = summary["breakdowns"][name]
        print(f"{name:>8} " + " ".join(f"{v:.3f}" for v in summary["per_step"][name]["iou_ordered"])
              + f" | occluded {b['iou_occluded_objects'] or 0:.3f} ({b['occluded_object_steps']}), "
              f"visible {b['iou_visible_objects'] or 0:.3f}")
    for key in ("vs_static", "vs_push", "pairs", *(("vs_against",) if against else ())):
        print(f"\npaired differences ({key}), mean +- standard error:")
        for name, row in summary[key].items():
            print(f"{name:>16} " + " ".join(f"{m} {v['mean']:+.4f} +- {v['se']:.4f}" for m, v in row.items()))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_text(args.out, json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
