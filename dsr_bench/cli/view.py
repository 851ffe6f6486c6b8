"""`dsr-bench view`: a sequence (and predictions) in the rerun viewer."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def view(
    sequence: str = typer.Argument(..., help="A sequence name within --data (seq_0042) or a path to a .h5 file."),
    data: Optional[Path] = typer.Option(None, "--data", help="Dataset directory holding the sequence."),
    predictions: Optional[Path] = typer.Option(
        None, "--predictions", help="Predictions directory (PRED_DIR/<sequence>.h5) to show beside the ground truth."),
    save: Optional[Path] = typer.Option(None, "--save", help="Write a .rrd recording instead of opening a viewer."),
    web: bool = typer.Option(False, "--web", help="Serve the web viewer instead of spawning the native one."),
    web_port: Optional[int] = typer.Option(None, "--web-port", help="Port of the web viewer (default 9090)."),
) -> None:
    """Open a sequence in the rerun viewer: cameras, TSDF, amodal voxels, meshes, push, flow, predictions."""
    from dsr_bench.display import no_display
    from dsr_bench.errors import UserError
    from dsr_bench.dataset.manifest import resolve_sequence

    if save is not None and web:
        raise UserError("--save and --web exclude each other: choose one")
    if save is not None and save.suffix != ".rrd":
        raise UserError(f"--save {save}: the recording file must end in .rrd")
    path = resolve_sequence(data, sequence)
    if save is None and not web and no_display():
        raise UserError("no display to open the viewer on: write a recording with --save out.rrd, "
                        "or serve it with --web")
    from dsr_bench.viewer import view as run

    out = run(path, predictions=predictions, save=save, web=web, web_port=web_port)
    if save is not None:
        typer.echo(f"wrote {out} (open it with: rerun {out})")
    elif web:
        typer.echo(f"serving the web viewer at {out} ; press Ctrl-C to stop")
        import time

        while True:
            time.sleep(3600)


def register(app: typer.Typer) -> None:
    app.command("view")(view)
