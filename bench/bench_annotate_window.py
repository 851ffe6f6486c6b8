"""How well the annotator window keeps up, measured under a virtual display (Xvfb): figures only, never asserted.

    python bench/bench_annotate_window.py [--capture DIR] [--history 425] [--hold 3] [--rate 30] [--json out.json]

Runs itself under `xvfb-run` (or on $DISPLAY) and prints:

- ms per nudge: `Session.nudge` (fit score + save) with a short undo history and with `--history` entries, and
  the fit score alone (the rest is the save);
- ms per redraw after a nudge key (key to frame, less the nudge itself: the key pressed, the frame rendered, and
  a second frame rendered so that a window whose drawing is left to the next frame's event poll counts as drawn),
  to the 3D view's frame and to the panel's, with the cloud in capture colours and in depth-residual colours, and
  the points the 3D view draws of the step's cloud;
- seconds for the next step (key N to frame, a step not visited before: carry forward and snap), for each step
  of the capture in turn (the first is the one compared in docs/annotator.md);
- a held key: xdotool types D at `--rate` keys per second for `--hold` s into the 3D window while the window runs
  its own loop; nudges applied, events the window received, nudges still applied after the last key was sent
  ("queued at release") and the time from the last key to the last motion.

Before vs after: run it with PYTHONPATH pointing at an older copy of the `annotator` package first (the script
uses only what both have: `Session.nudge`, `AnnotatorWindow.press` / `render`), e.g.
`PYTHONPATH=/tmp/old:. python bench/bench_annotate_window.py`. The machine's load shows in every figure.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))
WINDOW_TITLE = "annotator: 3D"


def ensure_capture(path: Path | None, tmp: Path) -> Path:
    """The capture to measure on: `path`, or a simulated one generated under `tmp`."""
    if path is not None:
        return path
    from dsr_bench.cli import main

    if main(["generate-captures", "--out", str(tmp / "caps"), "-n", "1", "--steps", "3"]) != 0:
        raise SystemExit("could not generate a capture")
    return tmp / "caps" / "seq_0000"


def place_at_truth(session) -> None:
    """Every object at its true pose at step 0 (picks of 8 mesh vertices)."""
    from dsr_bench.geometry import pose_to_matrix

    truth = session.capture.truth_poses()[0]
    for obj in range(session.num_objects):
        v, _ = session.capture.mesh(obj)
        m = pose_to_matrix(truth[obj])
        session.init_from_picks(obj, v[:8], v[:8] @ m[:3, :3].T + m[:3, 3])


def ms(seconds: list[float]) -> float:
    """Median of durations, in ms."""
    return 1000.0 * float(np.median(seconds)) if seconds else float("nan")


def time_nudges(session, count: int) -> list[float]:
    """Seconds of `count` nudges of object 1 (alternating +-1 mm along x, so the pose stays put)."""
    out = []
    for k in range(count):
        start = time.perf_counter()
        session.nudge(0, translation=(0.001 if k % 2 == 0 else -0.001, 0.0, 0.0))
        out.append(time.perf_counter() - start)
    return out


def nudge_figures(session, history: int) -> dict:
    """ms per nudge with a short and a long undo history, and ms per fit score."""
    short = time_nudges(session, 20)
    grow = max(0, history - session.undo_depth - 20)
    time_nudges(session, grow)
    long = time_nudges(session, 20)
    scores = []
    for _ in range(20):
        start = time.perf_counter()
        session.score(0)
        scores.append(time.perf_counter() - start)
    return {"nudge_ms_short_history": ms(short), "nudge_ms_long_history": ms(long),
            "history": session.undo_depth, "score_ms": ms(scores)}


class DrawClock:
    """Wraps an open3d visualizer: records when a frame flagged for redrawing (`update_renderer`) has been drawn
    (open3d draws it in `poll_events`)."""

    def __init__(self, vis):
        self.vis, self.flagged, self.drawn = vis, False, None

    def update_renderer(self):
        self.flagged = True
        return self.vis.update_renderer()

    def poll_events(self):
        out = self.vis.poll_events()
        if self.flagged:
            self.flagged, self.drawn = False, time.perf_counter()
        return out

    def __getattr__(self, name):
        return getattr(self.vis, name)


class NudgeTimer:
    """Wraps a session's `nudge` to add up the seconds spent in it."""

    def __init__(self, session):
        self.seconds = self.cpu = 0.0
        self._nudge = session.nudge
        session.nudge = self

    def __call__(self, *args, **kwargs):
        start, cpu = time.perf_counter(), time.process_time()
        try:
            return self._nudge(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - start
            self.cpu += time.process_time() - cpu


def redraw_ms(window, timer: NudgeTimer, count: int = 12) -> tuple[float, float, float]:
    """Median ms from a nudge key to the 3D view's frame and to the panel's, less the time in Session.nudge (keys D
    and A in turn, 1 mm each, 50 ms apart), and the median CPU ms of this process (Mesa's rendering threads
    included, the X server's work not) to both frames, less the nudge's: less sensitive to the machine's load."""
    view, panel = DrawClock(window.vis), DrawClock(window.panel_vis)
    window.vis, window.panel_vis = view, panel
    out_view, out_panel, out_cpu = [], [], []
    try:
        for k in range(count):
            time.sleep(0.05)  # the X server done with the last frame
            timer.seconds, timer.cpu, view.drawn, panel.drawn = 0.0, 0.0, None, None
            start, cpu = time.perf_counter(), time.process_time()
            window.press("D" if k % 2 == 0 else "A")
            window.render()
            window.render()  # draws what the first left flagged for the next frame
            end = time.perf_counter()
            out_cpu.append(time.process_time() - cpu - timer.cpu)
            out_view.append((view.drawn or end) - start - timer.seconds)
            out_panel.append((panel.drawn or end) - start - timer.seconds)
    finally:
        window.vis, window.panel_vis = view.vis, panel.vis
    return ms(out_view), ms(out_panel), ms(out_cpu)


def next_step_seconds(window) -> tuple[float, float]:
    """Seconds from key N (a step not visited before) to its frame, and CPU seconds of this process meanwhile."""
    start, cpu = time.perf_counter(), time.process_time()
    window.press("N")
    window.render()
    window.render()
    return time.perf_counter() - start, time.process_time() - cpu


def type_keys(key: str, count: int, rate: float, done: dict) -> None:
    """Type `key` `count` times at `rate` keys per second into the 3D window (xdotool); records when it ended."""
    found = subprocess.run(["xdotool", "search", "--name", WINDOW_TITLE], check=False, capture_output=True,
                           text=True)
    wid = found.stdout.split()[0] if found.stdout.split() else None
    if wid is None:
        done["error"] = "3D window not found"
        done["end"] = time.perf_counter()
        return
    subprocess.run(["xdotool", "windowfocus", "--sync", wid], check=False, capture_output=True)
    done["start"] = time.perf_counter()
    subprocess.run(["xdotool", "key", "--window", wid, "--delay", str(round(1000 / rate)), "--repeat",
                    str(count), key.lower()], check=False, capture_output=True)
    done["end"] = time.perf_counter()


def held_key(window, hold: float, rate: float, settle: float = 2.0, limit: float = 60.0) -> dict:
    """Type D for `hold` s at `rate` keys/s while the window runs its loop; what moved and when it stopped (still:
    no motion for `settle` s; at most `limit` s after the last key)."""
    session = window.ctl.session
    received: list[float] = []
    on_key = window._on_key

    def counting(key, vis):
        if key == "D":
            received.append(time.perf_counter())
        return on_key(key, vis)

    window._on_key = counting
    from dsr_bench.annotator.keys import glfw_code

    window.vis.register_key_callback(glfw_code("D"), lambda vis: counting("D", vis))
    x0 = float(session.poses()[0][0])
    count = round(hold * rate)
    done: dict = {}
    typist = threading.Thread(target=type_keys, args=("D", count, rate, done), daemon=True)
    motion: list[tuple[float, float]] = []
    last_x = x0
    typist.start()
    while "end" not in done or (time.perf_counter() - max(done["end"], motion[-1][0] if motion else 0.0) < settle
                                and time.perf_counter() - done["end"] < limit):
        window.render()
        x = float(session.poses()[0][0])
        if x != last_x:
            motion.append((time.perf_counter(), x))
            last_x = x
        time.sleep(1 / 60)
    end = done["end"]
    applied = round((last_x - x0) / 0.001)
    after = [m for m in motion if m[0] > end]
    x_at_release = next((x for t, x in reversed(motion) if t <= end), x0)
    return {"keys_sent": count, "rate": rate, "hold_s": hold, "typing_s": end - done.get("start", end),
            "events_received": len(received), "received_after_release": sum(t > end for t in received),
            "nudges_applied": applied, "nudges_applied_at_release": round((x_at_release - x0) / 0.001),
            "queued_at_release": round((last_x - x_at_release) / 0.001),
            "release_to_still_s": (after[-1][0] - end) if after else 0.0, "error": done.get("error")}


def child(args) -> dict:
    """The measurements, in a process with a display."""
    from dsr_bench.annotator import window as win
    from dsr_bench.annotator.session import Session

    with tempfile.TemporaryDirectory(prefix="bench_annotate_window_") as tmp:
        capture = ensure_capture(args.capture, Path(tmp))
        session = Session.open(capture, Path(tmp) / "work")
        place_at_truth(session)
        out = {"capture": str(capture), "annotator": str(Path(win.__file__).parent)}
        out |= nudge_figures(session, args.history)
        window = win.AnnotatorWindow(session, echo=lambda s: None)
        try:
            window.render()
            timer = NudgeTimer(session)
            out["cloud_points"], out["points_drawn"] = len(session.cloud()[0]), len(window.cloud.points)
            out["redraw_ms"], out["redraw_ms_panel"], out["redraw_cpu_ms"] = redraw_ms(window, timer)
            window.press("R")
            window.render()
            out["redraw_ms_residual"], out["redraw_ms_residual_panel"], out["redraw_cpu_ms_residual"] = redraw_ms(
                window, timer)
            window.press("R")
            window.render()
            steps = [next_step_seconds(window) for _ in range(session.num_steps)]
            out["next_steps_s"], out["next_steps_cpu_s"] = [t for t, _ in steps], [c for _, c in steps]
            out["next_step_s"] = out["next_steps_s"][0]
            window.press("P")
            window.render()
            session.nudge = timer._nudge
            if shutil.which("xdotool"):
                out["held"] = held_key(window, args.hold, args.rate)
            else:
                out["held"] = {"error": "xdotool is not installed"}
        finally:
            window.close()
    return out


def report(fig: dict) -> None:
    """Print the figures."""
    print(f"annotator package: {fig['annotator']}; load average (1 min) {fig['load'][0]:.2f} at the start, "
          f"{fig['load'][1]:.2f} at the end, {os.cpu_count()} CPUs")
    print(f"nudge (score + save): {fig['nudge_ms_short_history']:.1f} ms with a short history, "
          f"{fig['nudge_ms_long_history']:.1f} ms at {fig['history']} undo entries; fit score alone "
          f"{fig['score_ms']:.1f} ms")
    print(f"redraw after a nudge key, key to the 3D view's frame | to the panel's: {fig['redraw_ms']:.1f} | "
          f"{fig['redraw_ms_panel']:.1f} ms (capture colours), {fig['redraw_ms_residual']:.1f} | "
          f"{fig['redraw_ms_residual_panel']:.1f} ms (residual colours); the 3D view draws {fig['points_drawn']} of "
          f"the cloud's {fig['cloud_points']} points (key to frame = the nudge above + this); CPU to both frames "
          f"{fig['redraw_cpu_ms']:.1f} ms, {fig['redraw_cpu_ms_residual']:.1f} ms")
    steps = ", ".join(f"{t:.2f}" for t in fig["next_steps_s"])
    cpu = ", ".join(f"{t:.2f}" for t in fig["next_steps_cpu_s"])
    print(f"next step (N, not visited before; steps 1, 2, ... in turn): {steps} s (CPU {cpu} s)")
    h = fig["held"]
    if h.get("error"):
        print(f"held key: not measured ({h['error']})")
        return
    print(f"held key D, {h['keys_sent']} keys at {h['rate']:g}/s ({h['typing_s']:.1f} s of typing): "
          f"{h['events_received']} events received ({h['received_after_release']} after the last key was sent), "
          f"{h['nudges_applied']} nudges applied ({h['nudges_applied_at_release']} by the last key, "
          f"{h['queued_at_release']} still queued then), motion stopped {h['release_to_still_s']:.2f} s after it")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--capture", type=Path, default=None, help="a capture (default: generate a 3-push one)")
    parser.add_argument("--history", type=int, default=425, help="undo entries for the long-history nudge figure")
    parser.add_argument("--hold", type=float, default=3.0, help="seconds the key is held")
    parser.add_argument("--rate", type=float, default=30.0, help="key repeats per second")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures as JSON here")
    parser.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        args.child.write_text(json.dumps(child(args)))
        return
    with tempfile.TemporaryDirectory(prefix="bench_annotate_window_") as tmp:
        out = Path(tmp) / "figures.json"
        prefix = ["xvfb-run", "-a", "-s", "-screen 0 1920x1200x24"] if shutil.which("xvfb-run") else []
        if not prefix and not os.environ.get("DISPLAY"):
            raise SystemExit("no display: install xvfb (scripts/setup.sh) or run where $DISPLAY is set")
        cmd = [*prefix, sys.executable, __file__, "--child", str(out), "--history", str(args.history), "--hold",
               str(args.hold), "--rate", str(args.rate)] + (["--capture", str(args.capture)] if args.capture else [])
        load = os.getloadavg()[0]
        subprocess.run(cmd, check=True)
        fig = json.loads(out.read_text())
        fig["load"] = [load, os.getloadavg()[0]]
    report(fig)
    if args.json:
        args.json.write_text(json.dumps(fig, indent=1))


if __name__ == "__main__":
    main()
