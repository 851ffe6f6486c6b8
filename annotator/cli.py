"""`dsr-bench annotate`: annotate object poses in a capture (window), or report, auto-carry and export."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def resolve_capture(capture: str, captures: Path) -> Path:
    """A capture directory from a name under `captures` (`seq_0042`, or its number however padded: `seq_42`,
    `42`) or a path (`captures/seq_042` the same way). Not found or ambiguous: a UserError naming what exists."""
    from dsr_bench.dataset.manifest import match_sequence_name, name_ranges
    from dsr_bench.errors import UserError

    by_name = Path(captures) / capture
    if by_name.is_dir():
        return by_name
    if Path(capture).is_dir():
        return Path(capture)
    typed = Path(capture)
    folder = typed.parent if typed.parent != Path(".") else Path(captures)
    held = sorted(d.name for d in folder.iterdir() if d.is_dir()) if folder.is_dir() else []
    found = match_sequence_name(typed.name, held, "capture")
    if found is not None:
        return folder / found
    make = f"make simulated ones with `dsr-bench generate-captures --out {folder} -n 5`"
    if not folder.is_dir():
        raise UserError(f"capture {capture!r} not found: no directory {folder}; give a capture name under --captures "
                        f"or a path ({make})")
    holds = f"it holds {name_ranges(held)}" if held else "it holds no captures"
    raise UserError(f"capture {capture!r} not found in {folder}: {holds}; give one of them or a path ({make})")


def annotate(
    capture: str = typer.Argument(..., help="A capture name under --captures (seq_0042; seq_42 or 42 "
                                 "mean it too) or a capture directory."),
    captures: Path = typer.Option(Path("captures"), "--captures", help="Directory holding the captures."),
    work: Optional[Path] = typer.Option(None, "--work", help="Annotation state directory (default CAPTURE/annotation)"),
    status: bool = typer.Option(False, "--status", help="Print the progress table and exit."),
    auto: bool = typer.Option(False, "--auto", help="Carry poses forward over every unvisited step, snapping what "
                                                    "moved (step 0 must be placed)."),
    export: Optional[Path] = typer.Option(None, "--export", help="Write the annotated sequence file (OUT.h5)."),
    allow_unchecked: bool = typer.Option(False, "--allow-unchecked",
                                         help="Export even poses that are not snapped or confirmed."),
    place: Optional[Path] = typer.Option(None, "--place", help="Place step 0 without the window from a JSON file of "
                                         "poses or picks (docs/annotator.md), then snap; runs before --auto/--export."),
    bop: Optional[Path] = typer.Option(None, "--bop", help="Also (or only) export as a BOP dataset to this directory "
                                       "(camera.json, models/ with models_info.json, test/<scene per camera>/ with "
                                       "scene_gt, scene_camera, scene_gt_info, rgb, depth, mask, mask_visib)."),
    window_size: Optional[str] = typer.Option(None, "--window-size", help="Screen size WxH (px) to lay the windows "
                                              "out in, e.g. 1600x1000 (default: the display's)."),
) -> None:
    """Annotate object poses in a two-camera capture; without flags, open the annotation window."""
    from dsr_bench.annotator.session import Session
    from dsr_bench.errors import UserError

    screen = None
    if window_size is not None:  # checked before any work
        from dsr_bench.annotator.layout import MIN_SCREEN, parse_window_size

        screen = parse_window_size(window_size)
        if screen[0] < MIN_SCREEN[0] or screen[1] < MIN_SCREEN[1]:
            raise UserError(f"--window-size {window_size} is smaller than {MIN_SCREEN[0]}x{MIN_SCREEN[1]}; "
                            "give a larger screen size")
    if allow_unchecked and export is None and bop is None:
        raise UserError("--allow-unchecked only applies to --export OUT.h5 or --bop DIR")
    from dsr_bench.atomic import check_writable

    if export is not None:  # before any work: the outputs can be written
        check_writable(export, "--export", directory=False)
    if bop is not None:
        check_writable(bop, "--bop")
    changes = place is not None or auto or not (status or export is not None or bop is not None)  # else only reads
    session = Session.open(resolve_capture(capture, captures), work, read_only=not changes)
    for note in session.notes:  # e.g. a journal record a crash cut short, resumed without it
        typer.echo(f"annotate: {note}", err=True)
    if place is not None:
        from dsr_bench.annotator.placement import place_step0

        lines = place_step0(session, place)
        typer.echo(f"placed {len(lines)} objects at step 0 from {place}:")
        for line in lines:
            typer.echo(f"  {line}")
    if auto:
        import time

        started = time.perf_counter()

        def visited(step: int, last: int, objects: list[int]) -> None:  # each step as it is done: it takes seconds
            plural = "s" if len(objects) != 1 else ""
            typer.echo(f"auto: step {step}/{last}: snapped {len(objects)} moved object{plural} "
                       f"({time.perf_counter() - started:.1f} s)", err=True)

        snapped = session.auto(progress=visited)
        moved = sum(len(v) for v in snapped.values())
        typer.echo(f"auto: visited {len(snapped)} steps, snapped {moved} moved objects")
    if status or auto or place is not None:
        typer.echo(session.progress_table())
    if export is not None:
        path = session.export(export, allow_unchecked=allow_unchecked)
        typer.echo(f"wrote {path}")
    if bop is not None:
        from dsr_bench.annotator.bop import export_bop

        path = export_bop(session, bop, allow_unchecked=allow_unchecked)
        typer.echo(f"wrote the BOP scenes to {path}")
    if status or auto or export is not None or place is not None or bop is not None:
        return
    from dsr_bench.display import no_display

    if no_display():
        raise UserError(NO_DISPLAY)
    try:
        from dsr_bench.annotator import window
    except ImportError as exc:
        raise UserError(f"the annotation window is unavailable ({exc}); use --status, --auto or --export") from None
    try:
        window.run(session, screen=screen)
    except UserError:
        raise
    except Exception as exc:  # noqa: BLE001 - GL/display failures surface as various errors
        if _display_error(exc):
            raise UserError(f"cannot open a display ({NO_DISPLAY.split(': ', 1)[1]})") from None
        raise


#: The one line shown when no window can be opened: the headless way, then the virtual display.
NO_DISPLAY = ("no display for the annotation window: place step 0 without it with --place POSES.json (poses or picks, "
              "docs/annotator.md), then --auto and --export; or run under `xvfb-run -a dsr-bench annotate ...`")


def _display_error(exc: Exception) -> bool:
    text = f"{type(exc).__name__}: {exc}".lower()
    return any(w in text for w in ("display", "glfw", "opengl", "x11", "window", "glx"))


def import_capture(
    src: Path = typer.Argument(..., help="Folder of <camera>_color_<N>.png / <camera>_depth_<N>.png (cameras front, "
                                         "back) with rig.json, or of RealSense recordings front / back (.bag: "
                                         "librealsense up to 2.57; .db3: 2.58 on; or a ROS2 bag directory) with "
                                         "rig.json and steps.json (docs/annotator.md, 'Real captures in')."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Capture directory to write (e.g. "
                                       "captures/seq_0000); required unless --inspect."),
    rig: Optional[Path] = typer.Option(None, "--rig", help="The rig file: intrinsics, distortion, depth scale, "
                                       "extrinsics or ChArUco board, objects (default SRC/rig.json)."),
    pushes: Optional[Path] = typer.Option(None, "--pushes", help="The robot's push log, start [x, y] m and direction "
                                          "per push, table frame (default SRC/pushes.json)."),
    steps: Optional[Path] = typer.Option(None, "--steps", help="Recordings only: the time (s, the frames' timestamps, "
                                         "librealsense's frame clock) of every step, JSON \"step_times\": one time "
                                         "per step (default SRC/steps.json)."),
    max_gap_ms: Optional[float] = typer.Option(None, "--max-gap-ms", help="Recordings only: largest gap (ms) from a "
                                               "step time to its colour frame and from it to its depth frame (default "
                                               "50)."),
    name: Optional[str] = typer.Option(None, "--name", help="Capture name (default the rig file's, else OUT's name)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace OUT if it exists."),
    inspect: bool = typer.Option(False, "--inspect", help="Only report what the recording holds (format and "
                                 "writer, streams, frame counts and gaps, intrinsics, distortion, depth units, board "
                                 "detections per camera, step times, pushes) and what the import would refuse; convert "
                                 "and write nothing."),
) -> None:
    """Import a real rig's colour and depth (PNGs, or RealSense .bag / .db3 recordings: depth registered to colour)
    as a capture: undistort, calibrate to the table (ChArUco board or given extrinsics), map the logged pushes to
    benchmark actions."""
    from dsr_bench.annotator.importer import import_capture as run_import
    from dsr_bench.errors import UserError

    if inspect:
        from dsr_bench.annotator.inspect import inspect_source

        if out is not None or name is not None or overwrite:
            raise UserError("--inspect converts nothing: drop --out, --name and --overwrite (or drop --inspect to "
                            "import)")
        found = inspect_source(src, rig=rig, pushes=pushes, steps=steps, max_gap_ms=max_gap_ms)
        for line in found.lines:
            typer.echo(line)
        if found.problems:
            raise UserError(f"{src}: {len(found.problems)} problem(s) the import would refuse (marked PROBLEM above); "
                            f"the first: {found.problems[0]}")
        typer.echo(f"{src}: nothing the import would refuse was found")
        return
    if out is None:
        raise UserError("import-capture needs --out CAPTURE (the capture directory to write), or --inspect to only "
                        "report what SRC holds")
    path, report = run_import(src, out, rig=rig, pushes=pushes, steps=steps, max_gap_ms=max_gap_ms, name=name,
                              overwrite=overwrite)
    for cam, how in report["extrinsics"].items():
        r = report.get("cameras", {}).get(cam)
        detail = "" if r is None else (f": {r['corners']} corners, reprojection {r['reprojection_px']:.2f} px, "
                                       f"{r['board_mm']:.2f} mm on the board"
                                       + ("" if r["depth_mm"] is None else f", depth {r['depth_mm']:+.1f} mm"))
        typer.echo(f"{cam}: extrinsics from the {how}{detail}")
    if report.get("between_cameras_mm") is not None:
        typer.echo(f"between the cameras: {report['between_cameras_mm']:.2f} mm on the board "
                   f"({report['shared_corners']} shared corners)")
    typer.echo(f"wrote {path}")


def capture(
    out: Path = typer.Option(..., "--out", "-o", help="New folder for the session: front.<db3|bag>, back.<db3|bag> "
                             "(librealsense's recordings), steps.json, pushes.json, rig.json; import it with "
                             "`dsr-bench import-capture OUT --out captures/NAME`."),
    front: Optional[str] = typer.Option(None, "--front", help="Serial number of the front camera (the view models "
                                        "see; `rs-enumerate-devices -s` lists them)."),
    back: Optional[str] = typer.Option(None, "--back", help="Serial number of the back camera (optional)."),
    color: str = typer.Option("1280x720@30", "--color", help="Colour mode WIDTHxHEIGHT@FPS (default 1280x720@30: the "
                              "D415 modes of the paper's rig)."),
    depth: str = typer.Option("1280x720@30", "--depth", help="Depth mode WIDTHxHEIGHT@FPS (default 1280x720@30, the "
                              "D415's full depth resolution)."),
    sync: bool = typer.Option(True, "--sync/--no-sync", help="Hardware-sync the cameras (front master, back slave; "
                              "the sync cable) where both support it; skipped with a note where not."),
    robot_file: Optional[Path] = typer.Option(None, "--robot-file", help="A new or empty file the robot's script "
                                              "appends one event a line to: board, step (step 0), {\"event\": "
                                              "\"step\", \"push\": {...}} (a push done), done."),
    steps: Optional[int] = typer.Option(None, "--steps", help="End after this many pushes (N + 1 steps)."),
    rig: Optional[Path] = typer.Option(None, "--rig", help="The rig file (board, objects) to copy into OUT with its "
                                       "meshes (default: a template to complete before importing)."),
    settle_ms: float = typer.Option(0.0, "--settle-ms", help="A step's frame is the first colour frame at least this "
                                    "many ms after its mark (default 0)."),
    timeout_frames: int = typer.Option(30, "--timeout-frames", help="A stream is dropped after this many frame "
                                       "periods without a frame, or a frame-number jump of more (default 30: 1 s at "
                                       "30 fps)."),
    uncompressed: bool = typer.Option(False, "--uncompressed", help="Record without librealsense's compression."),
    from_recordings: Optional[str] = typer.Option(None, "--from-recordings", help="front=PATH[,back=PATH]: "
                                                  "librealsense recordings, played back, stand in for the cameras "
                                                  "(tests, dry runs); --front/--back then optional, checked against "
                                                  "their serials."),
) -> None:
    """Record a session of the real rig for import-capture: two RealSense cameras by serial number, colour and depth
    recorded by librealsense, hardware-synced where they can be, and the robot's step marks and pushes (steps.json,
    pushes.json, written as the recording goes). Ends on Ctrl-C / SIGTERM, after --steps pushes, or when the robot
    writes done."""
    import signal

    from dsr_bench.annotator.record import CaptureSession, parse_recordings
    from dsr_bench.errors import UserError

    session = CaptureSession.open(out, front=front, back=back, color=color, depth=depth, sync=sync, rig=rig,
                                  from_recordings=parse_recordings(from_recordings) if from_recordings else None,
                                  steps=steps, settle_ms=settle_ms, timeout_frames=timeout_frames,
                                  compress=not uncompressed, robot_file=robot_file, on_event=typer.echo)
    previous = {}
    for number in (signal.SIGINT, signal.SIGTERM):
        try:
            previous[number] = signal.signal(number, lambda n, _: session.stop(f"{signal.Signals(n).name}"))
        except ValueError:  # not the main thread: the caller stops the session
            pass
    cams = ", ".join(f"{n} ({c.device.describe()}: colour {c.modes['color']}, depth {c.modes['depth']})"
                     for n, c in session.cameras.items())
    ends = " or ".join(["Ctrl-C"] + ([f"{steps} pushes"] if steps else []) + (["`done` in the robot file"]
                                                                             if robot_file else []))
    typer.echo(f"recording {cams} into {out}; {session.notes[0]}; ends on {ends}", err=False)
    try:
        summary = session.wait()
    except UserError:
        for line in session.summary().lines:
            typer.echo(line)
        raise
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
    for line in summary.lines:
        typer.echo(line)
    if summary.importable:
        typer.echo(f"next: dsr-bench import-capture {out} --out captures/{out.name}")
    else:
        typer.echo(f"{out} holds {summary.steps} step(s): not importable (import-capture needs 2 steps or more)")


def register(app: typer.Typer) -> None:
    """Add `annotate`, `capture` and `import-capture` to the `dsr-bench` CLI (the `dsr_bench.commands` entry
    point)."""
    app.command("annotate")(annotate)
    app.command("capture")(capture)
    app.command("import-capture")(import_capture)
