"""Short runs of the full-grid models on a lent GPU: `dsr-bench train --stage curriculum` with a budget, from the
weights committed in the repository (weights/gpu-track/), for two models in one call, with a curve and a held-out score
to keep beside them. The training is that command's, nothing else (`models.training.curriculum.train_curriculum`):
this script adds the compact files a device call can bring back and the install step.

    python scripts/train_gpu.py --data TRAIN_DIR --eval-data HELDOUT_DIR --out OUT [--models dsr single]
        [--minutes 5] [--eval-minutes 1.5] [--eval-sequences N] [--device cuda] [--workers N] [--bf16 | --no-bf16]
    python scripts/train_gpu.py --install OUT    # OUT's weights and curve replace the committed ones
    python scripts/train_gpu.py --runs           # how many runs the committed weights have had

With a GPU of your own and the authors' data sizes, run `dsr-bench train --stage curriculum` itself (docs/models.md,
"Training on one GPU"): no budget, the data on local disk, resumable by running it again.

A run, for each model of --models in turn (the training time, --minutes less --eval-minutes, shared equally):
1. reads the committed weights, weights/gpu-track/<model>.pt (--committed DIR): a weights file of role "checkpoint"
   (format v2, `models.training.checkpoints`) in fp16, with its stage, data position, step, learning-rate
   schedule and RNG states, and `progress` (steps and sample-steps of every run so far, one record per run).
   Adam's moments are not kept (they would triple the file): each run restarts them from zero, bias-corrected.
   None committed: a new run from the first stage.
2. trains with `dsr-bench train --stage curriculum --resume <that file> --max-minutes M` (its stage goes on where it
   stopped: same epoch, batch, step counter and learning rate; a stage whose epochs are done hands its weights to
   the next stage of the curriculum, on --data; the budget ends a stage with a resumable checkpoint and precise
   BatchNorm). bf16 autocast and channels-last on a GPU. An epoch is the paper's, 40,000 sample-steps
   (--epoch-samples), drawn from the few sequences that travel in repeated shuffled passes: the stages and learning
   rates keep the paper's length in sample-steps (about 2.8M in all), whatever data a run carries. Each run should
   carry sequences no earlier run saw (below: a base seed of the run's number).
3. writes OUT/<model>.pt: the last checkpoint, fp16, without Adam's moments, `progress` extended by this run;
   `dsr-bench predict --checkpoint OUT/<model>.pt` reads it like any weights file.
Then OUT/curve.json and OUT/curve.png (per batch: loss, its motion and mask terms, learning rate, the run, the
stage, against the global step and the cumulative sample-steps: the committed curve, docs/evidence/gpu-track/curve.json,
continued), OUT/evaluation.json (each model and the static yardstick predicted on --eval-data's split and scored,
`tracks.evaluate_heldout`, as `dsr-bench predict` and `dsr-bench evaluate` do; --eval-sequences N: its first N,
scored as a partial split) and OUT/summary.json (per model: steps and sample-steps of this run and in total, the
stage reached; the headline metrics, the paired differences to static and DSR-Net - SingleStep; wall time, device,
torch version, the exact command). Work files (the curriculum's run directories with fp32 last.pt, predictions)
go to --work (a temporary directory unless given); OUT holds 4 files + one per model (a device call brings back 8
files at most: with a log beside them, 3 models).

--install OUT checks OUT/<model>.pt (a gpu-track checkpoint of that model, fp16, whose runs continue the committed
file's) and replaces the committed file in place (atomically: one file per model, never a new one), and writes OUT's
curve to docs/evidence/gpu-track/ and its summary as run-NNN.json there. Then commit those paths.

With a lent GPU (a session's device tool: the repository root is the working directory, $OUT comes back).
The data travels with the working tree (64 MiB = 67.1 MB in all, tracked files and committed weights included:
about 32 MB of tree and 11.8 MB per DSR-Net-sized model; a slim full-grid sequence is about 1.9 MB), so
prepare a few slim sequences first, here (.gpu is ignored by git, not by the device tool's carry), and check
that the total stays under the limit:

    R=$(python scripts/train_gpu.py --runs)      # the committed runs: this run's number
    dsr-bench generate --objects procedural --seed $((900000 + R)) -n 3 --out data/gpu-train-$R --workers 2
    dsr-bench generate --objects procedural-novel --seed 50000 -n 1 --out data/gpu-test
    echo /.gpu/ >> .git/info/exclude
    python scripts/slim_dataset.py data/gpu-train-$R .gpu/train
    python scripts/slim_dataset.py data/gpu-test .gpu/test
    du -cb $(git ls-files --cached --others --exclude-standard) .gpu | tail -1

Each run trains on sequences no earlier run saw: the training objects (procedural), base seed 900000 + the
run's number, a seed no split uses (a split's sequences come from its own base seed). The tree with the two
committed models is about 58 MB, which leaves room for the test sequence and about 3 training ones (-n 3; run 0
carried 14 while nothing was committed). The held-out sequence is procedural-novel-test's seq_0000 (base seed 50000,
novel objects).

then one device call, carry [".gpu"], timeout_s 420 (the 5-minute budget of the defaults, its overheads, and
room left in a 15-minute lease to run it again; it trains dsr and single, the defaults):

    PYTHONPATH=. python3 -u scripts/train_gpu.py --data .gpu/train --eval-data .gpu/test --out $OUT 2>&1 | tee $OUT/log

and here `python scripts/train_gpu.py --install FILES_AT` with the folder the files came back to, then
commit weights/gpu-track/ and docs/evidence/gpu-track/. On the CPU, at toy size (what tests/test_gpu_training.py
runs): --device cpu --max-steps 2 --batch-size 1 --workers 0.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shlex
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from anywhere, the toolkit installed or not

from dsr_bench.models.training.schedules import PAPER_EPOCH_SAMPLES  # noqa: E402
#: the weights the lent-GPU runs continue (committed in the repository, not in the package: weights/gpu-track/README.md)
COMMITTED = ROOT / "weights" / "gpu-track"
EVIDENCE = ROOT / "docs" / "evidence" / "gpu-track"
CURVE_FORMAT = "dsr-bench-training-curve"
#: the headline metrics compared (lower is better for the motions, higher for the IoUs)
METRICS = ("motion_visible", "motion_full", "iou_unordered", "iou_ordered")
#: what the curve holds per batch
CURVE_COLUMNS = ("step", "sample_steps", "loss", "motion", "mask", "lr", "run", "stage")


@dataclass
class ModelRun:
    """What training one model did in this run: the file it wrote and this run's part of the curve."""

    model: str
    resumed_from: dict | None
    progress: dict
    run_index: int  # this run's number for the model: the committed file's runs before it
    stages: list[dict] = field(default_factory=list)
    points: list[dict] = field(default_factory=list)
    last: Path | None = None  # the trainer's last checkpoint (fp32, with Adam's moments)
    seconds: float = 0.0
    note: str = ""


# --- the committed state ------------------------------------------------------------------------------------------
def empty_progress() -> dict:
    """The progress record of a model never trained: no steps (batches), sample-steps or runs."""
    return {"steps": 0, "sample_steps": 0, "seconds": 0.0, "runs": []}


def read_committed(path: Path, model: str):
    """The committed weights of `model` (a `Weights`: role "checkpoint"), or None where there are none."""
    from dsr_bench.models import registry
    from dsr_bench.models.training.checkpoints import read_weights

    if not path.exists():
        return None
    return read_weights(path, kind=registry.VOXEL, model=model, role="checkpoint")


def compact_checkpoint(last: Path, dest: Path, progress: dict) -> Path:
    """Write the trainer's checkpoint `last` as the committed form at `dest` (atomically): the weights in fp16,
    the optimiser without its moments (its parameter groups only: the learning rate and betas resume), the
    schedule, stage, data position, step, RNG states and data provenance as saved, and `progress`."""
    from dsr_bench.models.training.checkpoints import read_weights, save_weights

    saved = read_weights(last, role="checkpoint")
    payload = saved.payload
    optimizer = {"state": {}, "param_groups": payload["optimizer"]["param_groups"]}
    sections = {key: payload[key] for key in ("scheduler", "stage", "epoch", "batch_index", "step", "rng", "seed",
                                              "world_size") if key in payload}
    return save_weights(dest, saved.config, payload["model"], "checkpoint", fp16=True, data=payload.get("data"),
                        optimizer=optimizer, progress=progress, **sections)


# --- training -----------------------------------------------------------------------------------------------------
def train_model(model: str, args: argparse.Namespace, deadline: float, work: Path, report=print) -> ModelRun:
    """Train `model` until `deadline` (time.monotonic()) or --max-steps batches: `dsr-bench train --stage curriculum`
    from its committed file (`train_curriculum`); returns what was done (the curriculum's last checkpoint in `last`)."""
    from dsr_bench.dataset.manifest import file_sha256
    from dsr_bench.errors import UserError
    from dsr_bench.models.training.config import CURRICULUM, TrainConfig
    from dsr_bench.models.training.curriculum import train_curriculum

    committed = args.committed / f"{model}.pt"
    weights = read_committed(committed, model)
    progress = empty_progress() if weights is None else dict(weights.get("progress") or empty_progress())
    progress["runs"] = list(progress.get("runs", []))
    resumed = None if weights is None else {"file": committed.name, "sha256": file_sha256(committed),
                                            "steps": progress["steps"], "sample_steps": progress["sample_steps"]}
    done = ModelRun(model, resumed, progress, len(progress["runs"]))
    out = work / f"{model}-run{done.run_index}"
    if out.exists():
        raise UserError(f"--work {work}: {out.name} is there from an earlier run; give an empty --work")
    config = TrainConfig(model_name=model, stage_name=CURRICULUM, data=args.data, out=out, split=args.split,
                         resume=None if weights is None else committed, epochs=args.epochs,
                         batch_size=args.batch_size, epoch_samples=args.epoch_samples or None, window=args.window,
                         max_steps=args.max_steps, max_seconds=max(deadline - time.monotonic(), 1e-3),
                         device=args.device, bf16=args.bf16, channels_last=args.channels_last, workers=args.workers,
                         seed=args.seed, bn_recalibration=args.bn_recalibration, progress=False)
    started = time.monotonic()
    curriculum = train_curriculum(config, report, min_stage_seconds=args.min_stage_seconds)
    done.seconds = time.monotonic() - started
    for stage in curriculum.stages:
        for record in stage.batches:
            progress["steps"] += 1
            progress["sample_steps"] += int(record["samples"])
            done.points.append({"step": progress["steps"], "sample_steps": progress["sample_steps"],
                                "loss": record["loss"], "motion": record["motion_loss"], "mask": record["mask_loss"],
                                "lr": record["lr"], "run": done.run_index, "stage": stage.stage})
        done.stages.append(stage.summary())
    done.last = curriculum.last if curriculum.stages else None
    if curriculum.next_stage is None:
        done.note = "the curriculum's last stage is done"
    return done


def device_name(device: str) -> str:
    """The accelerator's name (CUDA), else the processor's and its core count."""
    import torch

    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    return f"{platform.processor() or platform.machine()} CPU, {os.cpu_count()} cores"


# --- the curve ----------------------------------------------------------------------------------------------------
def load_curve(path: Path) -> dict:
    """A curve file (`CURVE_FORMAT`), or an empty curve where there is none."""
    from dsr_bench.errors import UserError

    if not path.is_file():
        return {"format": CURVE_FORMAT, "version": 1, "models": {}}
    try:
        curve = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise UserError(f"--curve {path}: unreadable ({exc}); give the committed curve.json") from None
    if not isinstance(curve, dict) or curve.get("format") != CURVE_FORMAT:
        raise UserError(f"--curve {path}: not a {CURVE_FORMAT} file; give the committed curve.json")
    return curve


def extend_curve(curve: dict, runs: list[ModelRun]) -> dict:
    """`curve` with each model's points of this run appended, after the committed history alone: points beyond
    the steps the resumed file had (a run that was not installed) are dropped first."""
    models = dict(curve.get("models", {}))
    for done in runs:
        had = 0 if done.resumed_from is None else done.resumed_from["steps"]
        old = models.get(done.model, {c: [] for c in CURVE_COLUMNS})
        keep = sum(1 for s in old["step"] if s <= had)
        columns = {c: list(old.get(c, []))[:keep] for c in CURVE_COLUMNS}
        for point in done.points:
            for c in CURVE_COLUMNS:
                value = point[c]
                columns[c].append(round(value, 6) if isinstance(value, float) else value)
        models[done.model] = columns
    return {"format": CURVE_FORMAT, "version": 1, "models": models}


def plot_curve(curve: dict, path: Path) -> Path:
    """The loss of each model per batch against cumulative sample-steps (log scale), a running mean over 50 batches
    over it, the first batch of each run marked; written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from dsr_bench.atomic import atomic_path

    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=100)
    for i, (model, columns) in enumerate(sorted(curve["models"].items())):
        x, y = np.asarray(columns["sample_steps"], float), np.asarray(columns["loss"], float)
        if not len(x):
            continue
        colour = f"C{i}"
        ax.plot(x, y, color=colour, alpha=0.25, lw=0.8)
        width = min(50, len(y))
        mean = np.convolve(y, np.ones(width) / width, mode="valid")
        ax.plot(x[width - 1:], mean, color=colour, lw=1.8, label=f"{model} ({int(x[-1]):,} sample-steps)")
        runs = np.asarray(columns["run"])
        for start in np.flatnonzero(np.r_[True, runs[1:] != runs[:-1]]):
            ax.axvline(x[start], color=colour, ls=":", lw=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("sample-steps (cumulative over runs)")
    ax.set_ylabel("training loss per batch")
    ax.set_title("full-grid models, GPU runs (dotted: a run's first batch)")
    ax.legend(loc="upper right")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path


# --- evaluation ---------------------------------------------------------------------------------------------------
def _finite(value: Any) -> Any:
    """JSON-safe: NaN and infinities as None, recursively."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def evaluate_models(models: dict[str, Path | None], args: argparse.Namespace, work: Path, report=print) -> dict:
    """Predict --eval-data's split (its first --eval-sequences) with each model (its weights file; None: a reference
    predictor) and score it (`tracks.evaluate_heldout`, partial when a subset); {model: results}."""
    from dsr_bench.models.training.tracks import evaluate_heldout

    results = {}
    for model, checkpoint in models.items():
        started = time.monotonic()
        results[model] = evaluate_heldout(model, checkpoint, args.eval_data, args.eval_split,
                                          work / "predictions" / model, args.device, args.eval_sequences,
                                          args.eval_workers)
        shown = ", ".join(f"{m} {results[model]['metrics'][m]:.4f}" for m in METRICS if m in results[model]["metrics"])
        report(f"evaluated {model} on {results[model]['coverage']['scored']} sequences of {results[model]['split']}: "
               f"{shown} ({time.monotonic() - started:.0f} s)")
    return results


def compare(results: dict) -> dict:
    """Headline metrics of each model, and paired differences per sequence (mean, standard error, n): every
    model - static, and DSR-Net - SingleStep where both ran."""
    from dsr_bench.scoring.compare import paired_difference

    per = {name: r["per_sequence"] for name, r in results.items()}
    out: dict[str, Any] = {"metrics": {name: {m: r["metrics"].get(m) for m in METRICS} for name, r in results.items()},
                           "paired": {}}
    pairs = [(name, "static") for name in results if name != "static"]
    if "dsr" in results and "single" in results:
        pairs.append(("dsr", "single"))
    for a, b in pairs:
        out["paired"][f"{a} - {b}"] = {m: paired_difference(per[a], per[b], m) for m in METRICS}
    return out


# --- the run ------------------------------------------------------------------------------------------------------
def run(args: argparse.Namespace, command: str, report=print) -> dict:
    """Train, write OUT's weights, curve, evaluation and summary; returns the summary."""
    import torch

    from dsr_bench.atomic import write_text
    from dsr_bench.dataset.manifest import file_sha256
    from dsr_bench.models.training.checkpoints import git_hash

    started = time.monotonic()
    args.out.mkdir(parents=True, exist_ok=True)
    train_until = started + 60 * (args.minutes - args.eval_minutes)
    date = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    device, torch_version, git = device_name(args.device), str(torch.__version__), git_hash()
    runs: list[ModelRun] = []
    with tempfile.TemporaryDirectory(prefix="train-gpu-") as scratch:
        work = args.work or Path(scratch)
        for i, model in enumerate(args.models):
            deadline = time.monotonic() + (train_until - time.monotonic()) / (len(args.models) - i)
            done = train_model(model, args, deadline, work, report)
            runs.append(done)
            if done.last is None:
                report(f"{model}: nothing trained ({done.note or 'no time left'})")
                continue
            done.progress["seconds"] = round(float(done.progress.get("seconds", 0.0)) + done.seconds, 1)
            done.progress["runs"].append({
                "run": done.run_index, "date": date, "device": device, "torch": torch_version, "git": git,
                "command": command, "data": Path(args.data).resolve().name, "stages": done.stages,
                "steps": len(done.points), "sample_steps": sum(s["sample_steps"] for s in done.stages),
                "seconds": round(done.seconds, 1)})
            compact_checkpoint(done.last, args.out / f"{model}.pt", done.progress)
            if args.device.startswith("cuda"):
                torch.cuda.empty_cache()
        curve = extend_curve(load_curve(args.curve), runs)
        write_text(args.out / "curve.json", json.dumps(curve, separators=(",", ":")) + "\n")
        plot_curve(curve, args.out / "curve.png")
        trained = {r.model: args.out / f"{r.model}.pt" for r in runs if r.last is not None}
        results = evaluate_models({"static": None, **trained}, args, work, report)
    write_text(args.out / "evaluation.json", json.dumps(_finite(results), indent=1) + "\n")
    models = {}
    for done in runs:
        path = args.out / f"{done.model}.pt"
        entry = {"resumed_from": done.resumed_from, "stages": done.stages, "note": done.note,
                 "steps_run": len(done.points), "sample_steps_run": sum(s["sample_steps"] for s in done.stages),
                 "steps_total": done.progress["steps"], "sample_steps_total": done.progress["sample_steps"],
                 "train_seconds": round(done.seconds, 1)}
        if path.is_file() and done.last is not None:
            entry["weights"] = {"file": path.name, "sha256": file_sha256(path), "bytes": path.stat().st_size}
        models[done.model] = entry
    eval_split = next(iter(results.values()))
    summary = {"command": command, "date": date, "device": device, "torch": torch_version, "git": git,
               "minutes": args.minutes, "wall_seconds": round(time.monotonic() - started, 1),
               "data": Path(args.data).resolve().name, "models": models,
               "evaluation": {"data": Path(args.eval_data).resolve().name, "split": eval_split["split"],
                              "sequences": eval_split["coverage"]["scored"], **compare(results)}}
    write_text(args.out / "summary.json", json.dumps(_finite(summary), indent=1) + "\n")
    report(f"wrote {', '.join(sorted(p.name for p in args.out.iterdir()))} to {args.out} "
           f"in {summary['wall_seconds']:.0f} s on {device}")
    return summary


def _committed_runs(path: Path, model: str) -> list:
    weights = read_committed(path, model)
    return [] if weights is None else list((weights.get("progress") or {}).get("runs", []))


def committed_runs(committed_dir: Path, models: list[str]) -> int:
    """Runs made so far by the committed weights of `models` (the most of any): the next run's number."""
    return max((len(_committed_runs(committed_dir / f"{model}.pt", model)) for model in models), default=0)


# --- installing a run's results -----------------------------------------------------------------------------------
def install(src: Path, committed_dir: Path, evidence: Path, report=print) -> list[Path]:
    """Replace the committed weights of each model in `src` with its file there (checked: a gpu-track checkpoint of
    that model in fp16 whose runs extend the committed file's), and put `src`'s curve and summary in `evidence`.
    Returns the paths written."""
    import torch

    from dsr_bench.atomic import write_bytes
    from dsr_bench.errors import UserError

    if not (src / "summary.json").is_file():
        raise UserError(f"--install {src}: no summary.json; give the folder a run of this script wrote")
    summary = json.loads((src / "summary.json").read_text())
    checked: list[tuple[str, Path]] = []
    runs: list[int] = []
    for model in summary["models"]:  # every file checked before any is written
        new_path = src / f"{model}.pt"
        if not new_path.is_file():
            continue
        new = read_committed(new_path, model)
        assert new is not None
        if any(v.is_floating_point() and v.dtype != torch.float16 for v in new["model"].values()):
            raise UserError(f"{new_path}: weights are not fp16; install files this script wrote")
        new_runs = list((new.get("progress") or {}).get("runs", []))
        old_runs = _committed_runs(committed_dir / f"{model}.pt", model)
        if not new_runs or new_runs[: len(old_runs)] != old_runs or len(new_runs) != len(old_runs) + 1:
            raise UserError(f"{new_path} does not continue the committed {model}.pt (its runs: {len(new_runs)}, "
                            f"committed: {len(old_runs)}); train again from the committed weights")
        checked.append((model, new_path))
        runs.append(new_runs[-1]["run"])
    committed_dir.mkdir(parents=True, exist_ok=True)
    evidence.mkdir(parents=True, exist_ok=True)
    written = [write_bytes(committed_dir / f"{model}.pt", path.read_bytes()) for model, path in checked]
    for name in ("curve.json", "curve.png"):
        written.append(write_bytes(evidence / name, (src / name).read_bytes()))
    written.append(write_bytes(evidence / f"run-{max(runs, default=0):03d}.json", (src / "summary.json").read_bytes()))
    for path in written:
        report(f"wrote {path}")
    return written


# --- the command line ---------------------------------------------------------------------------------------------
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, help="Training dataset directory (full 128 x 128 x 48 grid).")
    parser.add_argument("--split", help="Training split (default: the dataset's only split).")
    parser.add_argument("--eval-data", type=Path, help="Held-out dataset directory to score the new weights on.")
    parser.add_argument("--eval-split", help="Held-out split (default: the dataset's only split).")
    parser.add_argument("--eval-sequences", type=int, default=0, help="Score the first N sequences (0: all).")
    parser.add_argument("--out", type=Path, help="Output folder: <model>.pt, curve.json/png, evaluation.json, "
                        "summary.json.")
    parser.add_argument("--models", nargs="+", default=["dsr", "single"], help="Models to train, in turn.")
    parser.add_argument("--minutes", type=float, default=5.0, help="The whole run's budget in minutes (default 5).")
    parser.add_argument("--eval-minutes", type=float, default=1.5, help="Of --minutes, kept for evaluation and "
                        "the overheads (startup, BatchNorm recalibration, saving); default 1.5.")
    parser.add_argument("--max-steps", type=int, help="At most N batches per model in this run (toy runs).")
    parser.add_argument("--min-stage-seconds", type=float, default=20.0, help="Start a further stage only with "
                        "this much of a model's time left (default 20).")
    parser.add_argument("--epochs", type=int, help="Epochs of each stage, a resumed one too (default: the "
                        "curriculum's: 30, 20, 20).")
    parser.add_argument("--epoch-samples", type=int, default=PAPER_EPOCH_SAMPLES, help="Sample-steps per epoch of a "
                        "stage started here, drawn from --data in repeated shuffled passes, so that the stages and "
                        f"learning rates keep the paper's length whatever data travelled (default {PAPER_EPOCH_SAMPLES}"
                        ": 4000 sequences of 10 pushes; 0: one pass over --data).")
    parser.add_argument("--batch-size", type=int, help="Windows per batch of a stage started here (default 12).")
    parser.add_argument("--window", type=int, help="Pushes per window of a multi-step stage started here (default: "
                        "the stage's, 10; toy runs on short sequences).")
    parser.add_argument("--device", default="cuda" if _cuda() else "cpu", help="cuda (default where one is) or cpu.")
    parser.add_argument("--bf16", action=argparse.BooleanOptionalAction, default=None,
                        help="bf16 autocast (default: on with CUDA).")
    parser.add_argument("--channels-last", action=argparse.BooleanOptionalAction, default=None,
                        help="channels_last_3d memory format (default: on with CUDA).")
    parser.add_argument("--workers", type=int, help="DataLoader workers (default: 0 on the CPU, up to 12 with CUDA).")
    parser.add_argument("--eval-workers", type=int, default=0, help="Scoring processes (0: all cores).")
    parser.add_argument("--bn-recalibration", type=int, default=16, help="Batches of whole sequences for precise "
                        "BatchNorm when a stage ends (default 16).")
    parser.add_argument("--seed", type=int, default=0, help="Seed of a stage started here.")
    parser.add_argument("--committed", type=Path, default=COMMITTED, help="The committed weights' folder.")
    parser.add_argument("--curve", type=Path, default=EVIDENCE / "curve.json", help="The committed curve.")
    parser.add_argument("--evidence", type=Path, default=EVIDENCE, help="Where --install puts the curve and summary.")
    parser.add_argument("--work", type=Path, help="Work folder (trainer runs, predictions; default: a temporary one).")
    parser.add_argument("--install", type=Path, metavar="OUT", help="Replace the committed weights and curve with "
                        "OUT's (a folder this script wrote) and stop.")
    parser.add_argument("--runs", action="store_true", help="Print how many runs the committed weights of --models "
                        "have had (the next run's number: its training sequences' base seed is 900000 + it) and stop.")
    return parser.parse_args(argv)


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def check_args(args: argparse.Namespace) -> None:
    """One-line UserErrors for bad input, before any work."""
    from dsr_bench.atomic import check_writable
    from dsr_bench.dataset.manifest import read_split
    from dsr_bench.errors import UserError
    from dsr_bench.models import registry
    from dsr_bench.models.training.checkpoints import torch_device

    for option, value in (("--data", args.data), ("--eval-data", args.eval_data), ("--out", args.out)):
        if value is None:
            raise UserError(f"{option} is needed (or --install OUT)")
    for model in args.models:
        registry.model_entry(model, registry.VOXEL)
    if len(set(args.models)) != len(args.models):
        raise UserError(f"--models {' '.join(args.models)}: name each model once")
    if not 0 <= args.eval_minutes < args.minutes:
        raise UserError(f"--minutes {args.minutes} --eval-minutes {args.eval_minutes}: the evaluation's share must be "
                        "at least 0 and below the whole budget")
    if args.max_steps is not None and args.max_steps < 1:
        raise UserError(f"--max-steps {args.max_steps}: must be at least 1")
    if args.eval_sequences < 0:
        raise UserError(f"--eval-sequences {args.eval_sequences}: must be >= 0 (0: all)")
    torch_device(args.device)
    read_split(args.data, args.split)
    read_split(args.eval_data, args.eval_split)
    check_writable(args.out)
    if args.bf16 is None:
        args.bf16 = args.device.startswith("cuda")
    if args.channels_last is None:
        args.channels_last = args.device.startswith("cuda")
    if args.workers is None:
        args.workers = min(12, max(0, (os.cpu_count() or 1) - 2)) if args.device.startswith("cuda") else 0
    if args.epoch_samples < 0:
        raise UserError(f"--epoch-samples {args.epoch_samples}: must be >= 0 (0: one pass over --data)")


def main(argv: list[str] | None = None) -> int:
    from dsr_bench.errors import UserError

    args = parse_args(argv)
    command = shlex.join([Path(sys.executable).name, "scripts/train_gpu.py", *(sys.argv[1:] if argv is None else argv)])
    try:
        if args.install is not None:
            install(args.install, args.committed, args.evidence)
            return 0
        if args.runs:
            print(committed_runs(args.committed, args.models))
            return 0
        check_args(args)
        run(args, command)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
