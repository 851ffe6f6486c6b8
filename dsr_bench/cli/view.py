"""`dsr-bench view`: a sequence (and predictions) in the rerun viewer."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dsr_bench.errors import UserError


def view(
    sequence: str = typer.Argument(..., help="A sequence name within --data (seq_0042; seq_42 or 42 mean it "
                                   "too) or a path to a .h5 file (a sequence, or a plan file of `dsr-bench plan`)."),
    data: Optional[Path] = typer.Option(None, "--data", help="Dataset directory holding the sequence (with "
                                        "--predictions, default: the one their meta.json names)."),
    predictions: Optional[Path] = typer.Option(
        None, "--predictions", help="Predictions directory (PRED_DIR/<sequence>.h5) to show beside the ground truth."),
    save: Optional[Path] = typer.Option(None, "--save", help="Write a .rrd recording instead of opening a viewer."),
    web: bool = typer.Option(False, "--web", help="Serve the web viewer instead of spawning the native one."),
    web_port: Optional[int] = typer.Option(None, "--web-port", help="Port of the web viewer's page (default 9090)."),
    grpc_port: Optional[int] = typer.Option(None, "--grpc-port", help="Port the web viewer streams the data from "
                                            "(rerun's gRPC server, default 9876)."),
) -> None:
    """Open a sequence in the rerun viewer: cameras, TSDF, amodal voxels, meshes, push, flow, predictions.
    With --predictions and no --data, the dataset is the one the predictions' meta.json names."""
    from dsr_bench.display import no_display  # looked up on each call: tests stand in for a display
    from dsr_bench.dataset.manifest import resolve_sequence

    if save is not None and web:
        raise UserError("--save and --web exclude each other: choose one")
    if save is not None and save.suffix != ".rrd":
        raise UserError(f"--save {save}: the recording file must end in .rrd")
    if grpc_port is not None and not web:
        raise UserError("--grpc-port is a port of the web viewer: add --web, or drop it")
    from dsr_bench.viewer import import_rerun

    import_rerun()  # before any work: without the viewer extra, one line naming it
    if sequence.endswith(".h5") and Path(sequence).is_file() and predictions is None and data is None:
        from dsr_bench.viewer.plan import is_plan_file

        if is_plan_file(sequence):  # a plan file of `dsr-bench plan` (docs/planning.md)
            if save is None and not web and no_display():
                raise UserError("no display to open the viewer on: write a recording with --save out.rrd, "
                                "or serve it with --web")
            from dsr_bench.viewer.plan import view_plan

            _report(view_plan(sequence, save=save, web=web, web_port=web_port, grpc_port=grpc_port), save, web)
            return
    if data is None and predictions is not None and not (sequence.endswith(".h5") and Path(sequence).is_file()):
        data = _data_of(predictions)
    path = resolve_sequence(data, sequence)
    if save is None and not web and no_display():
        raise UserError("no display to open the viewer on: write a recording with --save out.rrd, "
                        "or serve it with --web")
    from dsr_bench.viewer import view as run

    out = run(path, predictions=predictions, save=save, web=web, web_port=web_port, grpc_port=grpc_port)
    _report(out, save, web)


def _report(out, save: Optional[Path], web: bool) -> None:
    """Say where the recording went (--save), or serve until interrupted (--web)."""
    if save is not None:
        typer.echo(f"wrote {out} (open it with: rerun {out})")
    elif web:
        typer.echo(web_message(out))
        import time

        while True:
            time.sleep(3600)


def _data_of(predictions: Path) -> Path:
    """The dataset directory that PREDICTIONS/meta.json names, said on stderr (a UserError naming the fix if none)."""
    from dsr_bench.scoring.predictions import META_NAME, meta_source

    from dsr_bench.scoring.evaluate import require_predictions_dir

    require_predictions_dir(predictions)
    data, _ = meta_source(predictions)
    typer.echo(f"data: {data} (from {predictions / META_NAME})", err=True)
    return data


def web_message(url: str) -> str:
    """The one line `view --web` prints: the URL and both ports the browser needs (page and data)."""
    from dsr_bench.viewer import web_ports

    page, data = web_ports(url)
    return (f"serving the web viewer at {url} : the browser loads the page from port {page} and the data from "
            f"port {data} (rerun's gRPC server), so from another machine forward both, e.g. "
            f"ssh -L {page}:localhost:{page} -L {data}:localhost:{data} HOST ; press Ctrl-C to stop")


def register(app: typer.Typer) -> None:
    app.command("view")(view)
