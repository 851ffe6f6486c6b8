"""Dataset commands: `validate`, `info`, `manifest`, `import-official`, `real-split`."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dsr_bench.atomic import check_writable


def validate(
    data_dir: Path = typer.Argument(..., help="Dataset directory (seq_*.h5, splits/, manifest.json), or one sequence "
                                              "file (.h5: checked alone, without the manifest and split pins)."),
    no_gt: bool = typer.Option(False, "--no-gt", help="Skip the ground-truth consistency checks (faster)."),
    workers: int = typer.Option(1, "--workers", "-w", help="Parallel worker processes."),
) -> None:
    """Check schema, shapes, ranges, checksums and ground-truth consistency; report every problem.

    A valid dataset's splits are named with the pinned split each matches, or none. A single sequence file (an
    annotator's export) is checked alone: what one file can prove (schema, ranges, ground truth, its own digests);
    split pins and a manifest need a dataset directory.
    A progress bar (per sequence) shows on stderr when it is a terminal."""
    from rich.console import Console
    from rich.table import Table

    from dsr_bench.progress import progress_bar  # looked up on each call: tests replace the bar
    from dsr_bench.dataset.validate import summary_line, validate_dataset

    console = Console()
    if data_dir.is_file() or (data_dir.suffix == ".h5" and not data_dir.is_dir()):
        _validate_file(data_dir, no_gt, console)
        return
    with progress_bar("validate") as progress:
        found, count = validate_dataset(data_dir, check_gt=not no_gt, workers=workers, progress=progress)
    problems = [p for p in found if not p.note]
    for note in found:
        if note.note:
            typer.echo(f"{note.where}: {note.message}")
    if not problems:
        console.print(f"[green]valid[/green]: {count} sequences in {data_dir}"
                      f"{' (ground truth not checked)' if no_gt else ', ground truth consistent'}")
        from dsr_bench.dataset.manifest import load_manifest
        from dsr_bench.dataset.pins import pin_matches

        from dsr_bench.dataset.real import pin_lines, read_real_split

        real = read_real_split(data_dir)
        own = set(real["parts"].values()) if real else set()
        for line in pin_matches(load_manifest(data_dir)):  # unwrapped, to copy
            if line.split(":")[0].removeprefix("split ") not in own:  # a real split's part: its own pins say below
                typer.echo(line)
        for line in pin_lines(data_dir):
            typer.echo(line)
        return
    table = Table(title=f"{len(problems)} problems in {data_dir}")
    table.add_column("where")
    table.add_column("problem")
    for p in sorted(problems, key=lambda p: p.where):  # stable: each file's problems in check order
        table.add_row(p.where, p.message)
    console.print(table)
    typer.echo(summary_line(found, count, data_dir))  # unwrapped: the one line that says why it failed
    raise typer.Exit(1)


def _validate_file(path: Path, no_gt: bool, console) -> None:
    """`validate FILE.h5`: one sequence file alone (`dsr_bench.dataset.validate.validate_file`); exit 1 on a
    problem."""
    from rich.table import Table

    from dsr_bench.dataset.validate import SINGLE_FILE_LIMITS, validate_file

    problems, about = validate_file(path, check_gt=not no_gt)
    if problems:
        table = Table(title=f"{len(problems)} problems in {path}")
        table.add_column("problem")
        for message in problems:
            table.add_row(message)
        console.print(table)
        typer.echo(f"{path}: {len(problems)} problem{'s' if len(problems) != 1 else ''} ({problems[0]})")
        raise typer.Exit(1)
    what = (f"a sequence of {about['steps']} pushes and {about['objects']} objects (source {about['source']})"
            if about else "a sequence file")
    checked = "ground truth not checked" if no_gt else "ground truth consistent, digests match its arrays"
    console.print(f"[green]valid[/green]: {path} is {what}: schema and value ranges, {checked}")
    typer.echo(f"note: {SINGLE_FILE_LIMITS}")


def info(
    data_dir: Path = typer.Argument(..., help="Dataset directory."),
    sequences: bool = typer.Option(False, "--sequences", help="Print only the sequence names, one per line."),
) -> None:
    """Summarise a dataset: sequences (their names as ranges), steps, objects, splits and their checksums, size
    on disk; --sequences lists every sequence name."""
    import json
    from collections import Counter

    from rich.console import Console
    from rich.table import Table

    from dsr_bench.dataset.manifest import common_generator_args, completed_entry, load_manifest, name_ranges

    manifest = load_manifest(data_dir)
    if sequences:
        for entry in manifest["sequences"]:
            typer.echo(entry["name"])
        return
    seqs = [completed_entry(data_dir, s) for s in manifest["sequences"]]
    console = Console()
    table = Table(title=f"dsr-bench dataset: {data_dir}", show_header=False)
    table.add_column(style="bold")
    table.add_column(overflow="fold")
    steps = sum(s["num_steps"] for s in seqs)
    paths = [Path(data_dir) / s["file"] for s in seqs]
    size = sum(p.stat().st_size for p in paths if p.is_file())
    missing = sum(not p.is_file() for p in paths)

    def counts(values) -> str:
        return ", ".join(f"{k}: {v}" for k, v in sorted(Counter(values).items(), key=lambda kv: str(kv[0]))) or "-"

    table.add_row("sequences / pushes", f"{len(seqs)} / {steps}" + (f" ({missing} files missing)" if missing else ""))
    table.add_row("sequence names", f"{name_ranges(s['name'] for s in seqs)} (all: --sequences)")
    table.add_row("pushes per sequence", counts(s["num_steps"] for s in seqs))
    table.add_row("objects per scene", counts(s["num_objects"] for s in seqs))
    table.add_row("object sets", counts(s.get("object_set", "") for s in seqs))
    cats = Counter(f"{o.get('set', '?')}/{o.get('category', '?')}" for s in seqs for o in s.get("objects", []))
    table.add_row("objects per set/category", ", ".join(f"{k}: {v}" for k, v in sorted(cats.items())) or "-")
    table.add_row("sources", counts(s.get("source", "?") for s in seqs))
    table.add_row("policies", counts(s.get("policy", "?") for s in seqs))
    table.add_row("size on disk", f"{size / 1e6:.1f} MB, {size / max(steps, 1) / 1e6:.3f} MB "
                                  f"({size / max(steps, 1):,.0f} bytes) per push")
    for name, split in sorted(manifest.get("splits", {}).items()):
        table.add_row(f"split {name}", f"{split['sequences']} sequences: {name_ranges(map(str, split['names']))} "
                                       "(checksum below)")
    common, varying = common_generator_args(seqs)
    table.add_row("generator args",
                  json.dumps(common, sort_keys=True) + (f"; varying: {', '.join(varying)}" if varying else ""))
    table.add_row("toolkit versions", counts(s.get("toolkit_version", "?") for s in seqs)
                  + f" (manifest written by {manifest.get('toolkit_version')})")
    table.add_row("schema version", str(manifest.get("schema_version")))
    from dsr_bench.dataset.real import info_rows, read_real_split

    real = read_real_split(data_dir)
    for label, text in info_rows(real) if real else ():
        table.add_row(label, text)
    console.print(table)
    for name, split in sorted(manifest.get("splits", {}).items()):  # unwrapped, to copy
        typer.echo(f"split {name}: {split['sequences']} sequences, checksum {split['content_sha256']}")
    if manifest.get("splits"):
        typer.echo("(checksums from the files' own digest attributes; `dsr-bench validate` recomputes them)")


def manifest(data_dir: Path = typer.Argument(..., help="Dataset directory.")) -> None:
    """(Re)build manifest.json from the sequence and split files present (after sharded generation)."""
    from dsr_bench.dataset.manifest import build_manifest, missing_dataset, write_manifest

    if not Path(data_dir).is_dir():
        raise missing_dataset(data_dir)
    built = build_manifest(data_dir)
    path = write_manifest(data_dir, built)
    typer.echo(f"wrote {path}: {len(built['sequences'])} sequences, splits: {', '.join(built['splits']) or 'none'}")
    typer.echo(f"its checksums are the files' own digest attributes, not recomputed: `dsr-bench validate {data_dir}` "
               "recomputes them from the arrays, and `dsr-bench evaluate` verifies what it scores against the pins")


def import_official_command(
    src: Path = typer.Argument(..., help="Official release directory (<seq>_<step>.hdf5, train.txt, test.txt)."),
    dst: Path = typer.Argument(..., help="Dataset directory to write in our format (new, or a resumed import)."),
    split: Optional[str] = typer.Option(None, "--split", help="Import only SRC/<split>.txt's sequences (train, test)."),
    workers: int = typer.Option(1, "--workers", "-w", help="Parallel worker processes (about 0.5 GB of memory each)."),
) -> None:
    """Convert the authors' release into our format, losslessly (see docs/format.md)."""
    from rich.progress import Progress

    from dsr_bench.dataset.official import find_official_sequences, import_official, read_official_split

    check_writable(dst, "DST")
    total = len(read_official_split(src, split)) if split else len(find_official_sequences(src))
    with Progress(transient=True) as bar:
        task = bar.add_task("importing", total=total)
        names = import_official(src, dst, split=split, workers=workers, progress=lambda _: bar.advance(task))
    typer.echo(f"imported {len(names)} sequences into {dst}; check them with `dsr-bench validate {dst}`")


def real_split(
    exports: Path = typer.Argument(..., help="Folder of the annotator's exports (`dsr-bench annotate CAPTURE --export "
                                             "FOLDER/NAME.h5`), one .h5 per annotated capture."),
    out: Path = typer.Option(..., "--out", "-o", help="The real split's directory (new): seq_*.h5, splits/, "
                                                      "manifest.json, real_split.json."),
    fine_tune: Optional[int] = typer.Option(None, "--fine-tune", help="Sequences to fine-tune on (default: a third "
                                            "of the exports, the paper's 50 of 150; with --test only: the rest)."),
    test: Optional[int] = typer.Option(None, "--test", help="Sequences held out and scored (default: the rest; the "
                                       "paper's 100)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the draw of the two parts."),
    name: str = typer.Option("real", "--name", help="The split's name: its parts are the splits NAME-finetune and "
                                                    "NAME-test."),
    workers: int = typer.Option(1, "--workers", "-w", help="Parallel worker processes checking the exports."),
) -> None:
    """Make a real split from annotated captures: fine-tune and test parts drawn with --seed, the manifest, and
    real_split.json (the split's own pins, which `validate` and `evaluate` check, and each sequence's provenance).
    An export whose annotation is incomplete or flagged, or that fails `validate`, is refused by name."""
    from rich.progress import Progress

    from dsr_bench.dataset.real_build import build_real_split

    check_writable(out)
    with Progress(transient=True) as bar:
        task = bar.add_task("checking exports", total=None)
        record = build_real_split(exports, out, finetune=fine_tune, test=test, seed=seed, name=name,
                                  workers=max(1, workers), progress=lambda i, n: bar.update(task, completed=i, total=n))
    parts = record["parts"]
    for part, split in parts.items():
        pin = record["pins"][split]
        typer.echo(f"split {split}: {len(pin['sequences'])} sequences ({part}), checksum {pin['checksum']}")
    if record["unused"]:
        typer.echo(f"left out: {len(record['unused'])} exports ({', '.join(u['export'] for u in record['unused'][:4])}"
                   f"{' ...' if len(record['unused']) > 4 else ''})")
    typer.echo(f"wrote {out} (pinned by {out / 'real_split.json'}); next: `dsr-bench validate {out}`, then fine-tune "
               f"with `dsr-bench train --finetune --init WEIGHTS --data {out}` and score on --split {parts['test']}")


def register(app: typer.Typer) -> None:
    app.command("real-split")(real_split)
    app.command("validate")(validate)
    app.command("info")(info)
    app.command("manifest")(manifest)
    app.command("import-official")(import_official_command)
