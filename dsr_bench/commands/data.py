"""Dataset commands: `validate`, `info`, `manifest`, `import-official`."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def validate(
    data_dir: Path = typer.Argument(..., help="Dataset directory (seq_*.h5, splits/, manifest.json)."),
    no_gt: bool = typer.Option(False, "--no-gt", help="Skip the ground-truth consistency checks (faster)."),
    workers: int = typer.Option(1, "--workers", "-w", help="Parallel worker processes."),
) -> None:
    """Check schema, shapes, ranges, checksums and ground-truth consistency; report every problem."""
    from rich.console import Console
    from rich.table import Table

    from dsr_bench.validate import validate_dataset

    console = Console()
    problems, count = validate_dataset(data_dir, check_gt=not no_gt, workers=workers)
    if not problems:
        console.print(f"[green]valid[/green]: {count} sequences in {data_dir}"
                      f"{' (ground truth not checked)' if no_gt else ', ground truth consistent'}")
        return
    table = Table(title=f"{len(problems)} problems in {data_dir}")
    table.add_column("where")
    table.add_column("problem")
    for p in problems:
        table.add_row(p.where, p.message)
    console.print(table)
    raise typer.Exit(1)


def info(data_dir: Path = typer.Argument(..., help="Dataset directory.")) -> None:
    """Summarise a dataset: sequences, steps, objects, splits and their checksums, size on disk."""
    from collections import Counter

    from rich.console import Console
    from rich.table import Table

    from dsr_bench.manifest import load_manifest

    manifest = load_manifest(data_dir)
    seqs = manifest["sequences"]
    console = Console()
    table = Table(title=f"dsr-bench dataset: {data_dir}", show_header=False)
    steps = sum(s["num_steps"] for s in seqs)
    size = sum((Path(data_dir) / s["file"]).stat().st_size for s in seqs if (Path(data_dir) / s["file"]).exists())
    table.add_row("sequences / pushes", f"{len(seqs)} / {steps}")
    table.add_row("objects per scene", ", ".join(f"{k}: {v}" for k, v in sorted(Counter(s["num_objects"] for s in seqs).items())))
    sets = Counter(s.get("object_set", "") for s in seqs)
    table.add_row("object sets", ", ".join(f"{k}: {v}" for k, v in sorted(sets.items())))
    cats = Counter(o.get("category", "?") for s in seqs for o in s.get("objects", []))
    table.add_row("object categories", ", ".join(f"{k}: {v}" for k, v in cats.most_common(12)))
    table.add_row("size on disk", f"{size / 1e6:.1f} MB ({size / max(steps, 1) / 1e6:.2f} MB per push)")
    for name, split in sorted(manifest.get("splits", {}).items()):
        table.add_row(f"split {name}", f"{split['sequences']} sequences, checksum {split['content_sha256'][:16]}...")
    table.add_row("toolkit / schema", f"{manifest.get('toolkit_version')} / {manifest.get('schema_version')}")
    console.print(table)


def manifest(data_dir: Path = typer.Argument(..., help="Dataset directory.")) -> None:
    """(Re)build manifest.json from the sequence and split files present (after sharded generation)."""
    from dsr_bench.errors import UserError
    from dsr_bench.manifest import build_manifest, write_manifest

    if not Path(data_dir).is_dir():
        raise UserError(f"dataset directory not found: {data_dir}")
    built = build_manifest(data_dir)
    path = write_manifest(data_dir, built)
    typer.echo(f"wrote {path}: {len(built['sequences'])} sequences, splits: {', '.join(built['splits']) or 'none'}")


def import_official_command(
    src: Path = typer.Argument(..., help="Official release directory (<seq>_<step>.hdf5, train.txt, test.txt)."),
    dst: Path = typer.Argument(..., help="New dataset directory in the dsr-bench format."),
) -> None:
    """Convert the authors' release into our format, losslessly (see docs/format.md)."""
    from dsr_bench.official import import_official

    names = import_official(src, dst)
    typer.echo(f"imported {len(names)} sequences into {dst}; check them with `dsr-bench validate {dst}`")


def register(app: typer.Typer) -> None:
    app.command("validate")(validate)
    app.command("info")(info)
    app.command("manifest")(manifest)
    app.command("import-official")(import_official_command)
