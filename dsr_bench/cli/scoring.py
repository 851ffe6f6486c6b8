"""Scoring commands: `predict`, `evaluate`, `leaderboard build|add`."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Optional

import typer

from dsr_bench.atomic import check_writable, write_text
from dsr_bench.engine_options import (RayAddress, Slurm, SlurmLocal, SlurmLogs, SlurmPartition, SlurmTasks,
                                         SlurmTime)
from dsr_bench.engines import engine_from_options, slurm_options_given
from dsr_bench.memory import keep_freed_memory
from dsr_bench.models import registry

#: The kernels `dsr-bench predict` runs the shipped CPU-track networks with on a CPU: set in the environment before
#: torch loads (it reads them then), where the user has not set them. MKL's reproducible SSE2 branch for every matrix
#: product, which is what torch's 3D convolutions and linear layers are there (by default MKL picks its kernels by
#: instruction set and by vendor: an Intel Xeon's predictions differed from an AMD EPYC's in every file); oneDNN's
#: AVX2 kernels for the 2D track's convolutions (its SSE4.1, AVX2 and AVX-512 kernels give different bits); ATen's
#: AVX2 kernels (its AVX-512 ones give the same bits today, its default ones do not: no FMA). With
#: `inference.same_bits_on_any_cpu` (one thread) the predictions are the same bytes on every x86-64 CPU with AVX2
#: (docs/models.md, "Predictions across CPUs").
SAME_BITS_ENV = {"MKL_CBWR": "COMPATIBLE", "ONEDNN_MAX_CPU_ISA": "AVX2", "ATEN_CPU_CAPABILITY": "avx2"}

leaderboard_app = typer.Typer(help="Build the leaderboard tables or add a results entry.", no_args_is_help=True)


def predict(
    model: str = typer.Option(..., "--model", help=registry.help_text()),
    data: Path = typer.Option(..., "--data", help="Dataset directory."),
    out: Path = typer.Option(..., "--out", "-o", help="Predictions directory to write."),
    split: Optional[str] = typer.Option(None, "--split", help="Split to predict (default: the only one)."),
    checkpoint: Optional[Path] = typer.Option(None, "--checkpoint", help="Checkpoint of a learned model (default: "
                                              "the CPU-track weights shipped with dsr-bench, docs/models.md)."),
    weights: Optional[Path] = typer.Option(None, "--weights", help="The authors' released weights instead "
                                           "(dsr.pth, dsr_ft.pth, single.pth, nowarp.pth, gtwarp.pth, 3dflow.pth); "
                                           "run as the authors ran them: their warp kernel, BatchNorm over "
                                           "batches of 12 sequences (docs/models.md)."),
    warp: Optional[str] = typer.Option(None, "--warp", help="The history warp's kernel: official (the authors', "
                                       "the default with --weights) or floor (ours, the default otherwise)."),
    bn_batch: Optional[int] = typer.Option(None, "--bn-batch", help="With --weights: sequences run "
                                           "together, BatchNorm normalising over them (default 12, the authors' "
                                           "test protocol; 1: each sequence alone)."),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda (learned models)."),
) -> None:
    """Run a model over a split and write the predictions contract (one .h5 per sequence + meta.json, which
    names the dataset directory and split for `evaluate` and `view`). The shipped weights run on a CPU with fixed
    kernels on one thread: their predictions are the same bytes on every x86-64 CPU with AVX2 (docs/models.md)."""
    from rich.progress import Progress

    from dsr_bench.dataset.manifest import read_split
    from dsr_bench.models.predictors import load_predictor, predict_split
    from dsr_bench.scoring.predictions import record_source

    check_writable(out)  # before the model is loaded and run
    # the shipped CPU-track weights on a CPU: the same kernels on every CPU (SAME_BITS_ENV, before torch loads)
    shipped = (checkpoint is None and weights is None and device.split(":")[0] == "cpu"
               and registry.model_entry(model).kind != registry.REFERENCE)
    if shipped:
        _same_kernels_on_any_cpu()
    predictor = load_predictor(model, checkpoint, device, weights=weights, warp=warp, bn_batch=bn_batch)
    split, names = read_split(data, split)
    with Progress(transient=True) as bar, _same_bits(shipped):
        task = bar.add_task(f"predict {model}", total=len(names))
        predict_split(predictor, data, names, out, progress=lambda: bar.advance(task))
    record_source(out, data, split)  # what `evaluate OUT` and `view --predictions OUT` infer --data and --split from
    typer.echo(f"wrote {len(names)} prediction files for split {split} to {out}")


def same_bits_unset(environ: Mapping[str, str]) -> dict[str, str]:
    """`SAME_BITS_ENV`'s variables that `environ` leaves unset (a variable the user set is kept; ONEDNN_MAX_CPU_ISA
    counts as set where its former name DNNL_MAX_CPU_ISA is)."""
    return {name: value for name, value in SAME_BITS_ENV.items()
            if name not in environ and (name != "ONEDNN_MAX_CPU_ISA" or "DNNL_MAX_CPU_ISA" not in environ)}


def _same_kernels_on_any_cpu() -> None:
    """Set `SAME_BITS_ENV`'s variables that the environment leaves unset, if torch has not loaded yet (a process that
    imported torch before keeps the kernels it chose: its predictions are the same bytes on that machine only)."""
    import os
    import sys

    if "torch" not in sys.modules:
        os.environ.update(same_bits_unset(os.environ))


def _same_bits(shipped: bool):
    """`inference.same_bits_on_any_cpu` for the shipped weights on a CPU, else nothing."""
    import contextlib

    if not shipped:
        return contextlib.nullcontext()
    from dsr_bench.models.inference import same_bits_on_any_cpu

    return same_bits_on_any_cpu()


def _print_results(results: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    from dsr_bench.scoring.metrics import METRICS, TRACKS

    m, b = results["metrics"], results.get("breakdowns") or {}
    table = Table(title=f"{results['method']} on {results['split']} ({results['coverage']['scored']}/"
                        f"{results['coverage']['expected']} sequences{'' if 'motion_visible' in m else ', 2D-only'})")
    table.add_column("metric")
    table.add_column("value", justify="right")
    titled = [metric for metric in METRICS if metric.title]  # the table of metrics' order
    rows = [(metric.title, m[metric.key]) for metric in titled if metric.key in m]
    if b:
        rows += [(f"IoU of mostly occluded objects ({b['occluded_object_steps']})", b["iou_occluded_objects"]),
                 (f"IoU of visible objects ({b['visible_object_steps']})", b["iou_visible_objects"]),
                 ("flow MSE of moved objects (cm²)", b["motion_moved_objects"]),
                 ("flow MSE of static objects (cm²)", b["motion_static_objects"])]
    for name, value in rows:
        table.add_row(name, "-" if value is None or value != value else f"{value:.4f}")
    Console().print(table)
    steps = results["per_step"]
    # per step: each track's metrics, those where higher is better (the IoUs) first
    keys = [metric.key for metric in sorted(titled, key=lambda metric: (TRACKS.index(metric.track),
                                                                        metric.lower_is_better)) if metric.key in steps]
    per = Table(title="per step index")
    per.add_column("step")
    for key in keys:
        per.add_column(key, justify="right")
    for t in range(max(len(steps[k]) for k in keys)):
        per.add_row(str(t), *[f"{steps[k][t]:.4f}" for k in keys])
    Console().print(per)


def _printable(text: str) -> str:
    """`text` on one line: control characters (a newline in a file name) escaped."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def evaluate(
    pred_dir: Path = typer.Argument(..., help="Predictions directory: one SEQUENCE.h5 per sequence of the "
                                     "split and meta.json, nothing else (regular files, no links)."),
    data: Optional[Path] = typer.Option(None, "--data", help="Dataset directory with the ground truth (default: the "
                                        "one PRED_DIR/meta.json names, as `dsr-bench predict` writes it)."),
    split: Optional[str] = typer.Option(None, "--split", help="Split to score (default: the one meta.json names for "
                                        "that dataset, else the dataset's only split)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Write the results JSON here, and its per-step "
                                       "plots beside it (results.json -> results-steps.png)."),
    allow_partial: bool = typer.Option(False, "--allow-partial", help="Score the valid sequences despite problems."),
    workers: int = typer.Option(0, "--workers", "-w", help="Worker processes (0 = all cores; with --ray local the "
                                "CPUs of its Ray, with --slurm the processes of each task, 0 = 1)."),
    ray: RayAddress = None,
    slurm: Slurm = False,
    slurm_partition: SlurmPartition = None,
    slurm_time: SlurmTime = None,
    slurm_tasks: SlurmTasks = None,
    slurm_logs: SlurmLogs = None,
    slurm_local: SlurmLocal = False,
) -> None:
    """Validate a predictions directory strictly, then score it with the benchmark's metrics.

    Here, on a Ray cluster (--ray) or in a SLURM job array (--slurm), with the same numbers whichever.
    Each problem is one line `PRED_DIR/FILE: problem` on stderr; any problem means no score (exit 1).
    A progress bar (per sequence) shows on stderr when it is a terminal."""
    from rich.console import Console

    from dsr_bench.progress import progress_bar  # looked up on each call: tests replace the bar
    from dsr_bench.scoring.evaluate import evaluate as run, require_predictions_dir
    from dsr_bench.scoring.plots import steps_plot_path
    from dsr_bench.scoring.predictions import infer_source

    require_predictions_dir(pred_dir)
    if out is not None:
        check_writable(out, "--out", directory=False)  # before scoring, not after
        check_writable(steps_plot_path(out), "--out", directory=False)
    slurm_given = slurm_options_given(slurm_partition, slurm_time, slurm_tasks, slurm_logs, slurm_local)
    engine = engine_from_options(ray, slurm, workers, slurm_given, "dsr-bench-evaluate", output=pred_dir)
    data, split, note = infer_source(pred_dir, data, split)
    if note:
        typer.echo(_printable(note), err=True)
    if engine is not None:  # remote workers are given absolute paths
        pred_dir, data = pred_dir.absolute(), data.absolute()
    keep_freed_memory()  # this process scores the sequences itself with --workers 1 (dsr_bench/memory.py)
    with progress_bar("evaluate") as progress:
        evaluation = run(pred_dir, data, split, allow_partial=allow_partial, workers=workers, progress=progress,
                         engine=engine)
    console = Console(stderr=True)
    for warning in evaluation.warnings:
        typer.echo(f"warning: {_printable(warning)}", err=True)
    if evaluation.problems:
        typer.echo(f"{len(evaluation.problems)} problems in {pred_dir}:", err=True)
        for where, message in evaluation.problems:
            typer.echo(f"  {_printable(str(pred_dir / where))}: {_printable(message)}", err=True)
    if evaluation.results is None:
        console.print("[red]no score[/red]: " + ("no sequence could be scored; fix the problems above" if allow_partial
                      else "fix the problems above, or score what is valid with --allow-partial"))
        raise typer.Exit(1)
    _print_results(evaluation.results)
    typer.echo(_printable(pins_line(evaluation.results, data)), err=True)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        write_text(out, json.dumps(evaluation.results, indent=1, sort_keys=True) + "\n")
        console.print(f"results written to {out}")
        from dsr_bench.leaderboard.board import no_motion_entry
        from dsr_bench.scoring.plots import steps_plot_path, write_steps_plot

        no_motion, no_motion_note = no_motion_entry(evaluation.results)  # the static row of the same split version
        plot, why = write_steps_plot(evaluation.results, steps_plot_path(out), evaluation.per_sequence_steps,
                                     no_motion, no_motion_note)
        typer.echo(f"per-step plots written to {_printable(str(plot))}" if plot else f"no per-step plots: {why}",
                   err=True)  # unwrapped: a path to copy
    else:
        typer.echo("no results JSON or per-step plots written (no --out): add --out results.json to write both "
                   "(results.json and results-steps.png)", err=True)
    if evaluation.problems:
        console.print(f"[yellow]partial[/yellow]: scored {evaluation.results['coverage']['scored']} of "
                      f"{evaluation.results['coverage']['expected']} sequences")


def pins_line(results: dict, data: Path) -> str:
    """What the scored ground truth was verified against: the toolkit's pins of a named split, a real split's own
    pins (`dsr-bench real-split`), or nothing (an unpinned dataset: its results cannot join the leaderboard)."""
    real, split = results.get("real_split"), results["split"]
    if real is not None:
        where = Path(data) / real["pins"]
        if results["pinned"]:
            return (f"pinned to its own real-split pins ({where}: the real split {real['name']!r}, "
                    f"{real['part']} part, checksum {str(real['checksum'])[:12]}...), not the toolkit's "
                    "split_pins.json")
        return f"not pinned: {split} differs from its own real-split pins ({where}; see the warnings above)"
    if results["pinned"]:
        return f"pinned to the toolkit's pins of {split} (split_pins.json), its ground truth verified while scoring"
    return (f"not pinned: {split} is neither one of the toolkit's pinned splits as pinned nor a real split "
            "(`dsr-bench real-split`); its results cannot join the leaderboard")


@leaderboard_app.command("build")
def leaderboard_build(root: Path = typer.Option(Path("leaderboard"), "--root", help="Leaderboard directory.")) -> None:
    """Write leaderboard/README.md and leaderboard/index.html from entries/, planning/ and paper.json. Every entry
    file is validated first (schema, ranges, coverage, metrics against their per-step values, split pin); one that
    fails is skipped with one warning line naming it and its problem, and the rest are built."""
    from dsr_bench.leaderboard.board import build

    md, page = build(root, warn=lambda line: typer.echo(f"warning: {_printable(line)}", err=True))
    typer.echo(f"wrote {md} and {page}")


@leaderboard_app.command("add")
def leaderboard_add(
    results: Path = typer.Argument(..., help="Results JSON from `dsr-bench evaluate --out` (or `dsr-bench plan`)."),
    predictions: Optional[Path] = typer.Option(None, "--predictions", help="The predictions directory the results "
                                               "scored: every number is recomputed from it."),
    data: Optional[Path] = typer.Option(None, "--data", help="Dataset directory with the ground truth (default: the "
                                        "one PRED_DIR/meta.json names, as for `dsr-bench evaluate`)."),
    plans: Optional[Path] = typer.Option(None, "--plans", help="Planning results: the --out directory of "
                                         "`dsr-bench plan`, its plan files rescored."),
    tasks: Optional[str] = typer.Option(None, "--tasks", help="Planning results: the task directory or task set's "
                                        "name (default: the set the results name, as data/<name>)."),
    root: Path = typer.Option(Path("leaderboard"), "--root", help="Leaderboard directory."),
    label: Optional[str] = typer.Option(None, "--label", help="Note shown with the row (e.g. 'short schedule')."),
) -> None:
    """Recompute a results file and add it, then rebuild the tables. The leaderboard never reads a number from the
    file: it scores --predictions again (`dsr-bench evaluate` on the results' split; planning results: rescores
    --plans against the verified tasks) and refuses (one line, exit 2, nothing written) unless the recomputed
    results are pinned, complete, a valid entry and equal to the file in every field but date; what it writes is
    the recomputed results. An entry of the same method, split and predictions is replaced; any other gets its
    own file."""
    from dsr_bench.leaderboard.board import add_entry, build

    target, replaced = add_entry(results, root, label, predictions=predictions, data=data, plans=plans, tasks=tasks)
    build(root, warn=lambda line: typer.echo(f"warning: {_printable(line)}", err=True))
    typer.echo(f"replaced {target} (the same method, split and predictions); tables rebuilt" if replaced else
               f"added {target}; tables rebuilt")


def register(app: typer.Typer) -> None:
    app.command("predict")(predict)
    app.command("evaluate")(evaluate)
    app.add_typer(leaderboard_app, name="leaderboard")
