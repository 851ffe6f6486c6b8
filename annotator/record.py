"""`dsr-bench capture`: record a session of the real rig for `dsr-bench import-capture` (docs/annotator.md,
"Recording a session: dsr-bench capture").

    OUT/front.<db3|bag>, back.<db3|bag>   one recording per camera, written by librealsense (`rs.recorder`; .db3
                                          from librealsense 2.58 on, .bag before): colour and depth at the modes
                                          asked, cameras chosen by serial (`annotator.record_devices`)
    OUT/steps.json                        {"step_times": {"front": [...], "back": [...]}, "board_time": {...}}: per
                                          camera the timestamp (s, the frames' clock) of each step's colour frame
    OUT/pushes.json                       {"pushes": [...]}: the robot's pushes, T for T + 1 steps
    OUT/rig.json                          the rig file given (its meshes copied) or a template, with "capture": the
                                          serials, modes, sync and librealsense release recorded

A step begins when the robot reports a push done: `CaptureSession.step_done(push=...)` from a Python robot script,
or a line `{"event": "step", "push": {...}}` appended to the robot's file (`--robot-file`; `annotator.record_files`).
Step 0 (the scene before the first push) is marked without a push, the board alone on the table by `board()`. A mark
has a time (s): when it was made (the host's clock, `time.time()`) or the time the robot gives; per camera the step's
frame is the first colour frame whose timestamp is at or after mark + settle (and after the previous step's): its
timestamp is the step time. With librealsense's global time (on by default, set on here) frame timestamps are on
the host's clock; a stream on the camera's hardware clock is mapped to it by the largest (timestamp - arrival) seen.
steps.json and pushes.json are rewritten together as steps resolve (a crash leaves a valid prefix).

A stream that stops delivering frames is a dropped stream (`annotator.record_streams`: no frame for `timeout_frames`
frame periods of a connected camera, a frame number jumping by more, or the camera's other stream going on without
it). The session then stops, the recordings are closed (still importable) and the failure is one line, as are a
missing camera and a wrong serial.
"""

from __future__ import annotations

import bisect
import threading
import time as clock_time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dsr_bench.annotator.record_devices import DEFAULT_COLOR, DEFAULT_DEPTH, Camera, Mode, parse_mode
from dsr_bench.annotator.record_files import MarkFiles, RobotFile, check_push, parse_event, rig_content, write_rig
from dsr_bench.annotator.record_streams import Stream, clock_problem, frame_problem
from dsr_bench.errors import UserError

#: How often (s) the session reads the robot's file and checks the streams against the host's clock.
POLL_S = 0.05
#: --timeout-frames: 1 s at 30 fps. A few frames lost to a USB hiccup are counted; a second without frames (or a
#: frame-number jump over it) is a dropped stream.
DEFAULT_TIMEOUT_FRAMES = 30
#: Frame timestamp domains on the host's clock (librealsense's names).
HOST_DOMAINS = ("global_time", "system_time")


@dataclass
class Mark:
    """A mark of the robot: "board" or "step" (with the push that led to it, None for step 0), its time (s, host
    clock or the robot's) and where it came from (for messages)."""

    kind: str
    time: float
    push: dict | None
    where: str


@dataclass
class Summary:
    """What a session recorded: per camera (recording, frames), steps, pushes, notes, and the next command."""

    out: Path
    lines: list[str] = field(default_factory=list)
    steps: int = 0
    importable: bool = False


def parse_recordings(text: str) -> dict[str, Path]:
    """`--from-recordings front=PATH,back=PATH` as {camera: path}; UserError naming the option and the form."""
    from dsr_bench.constants import CAMERAS

    out: dict[str, Path] = {}
    for part in text.split(","):
        camera, sep, path = part.partition("=")
        camera = camera.strip()
        if not sep or not path.strip() or camera not in CAMERAS or camera in out:
            raise UserError(f"--from-recordings {text!r}: give CAMERA=PATH for each camera once, cameras "
                            f"{' and '.join(CAMERAS)}, e.g. --from-recordings front=run/front.db3,back=run/back.db3")
        out[camera] = Path(path.strip())
    if "front" not in out:
        raise UserError(f"--from-recordings {text!r}: the front camera is required (front=PATH)")
    return out


def _mode(value: Mode | str, option: str) -> Mode:
    return value if isinstance(value, Mode) else parse_mode(value, option)


class CaptureSession:
    """A recording session: the cameras recording into OUT, the robot's marks turned into steps.json and
    pushes.json. Open it with `CaptureSession.open`; mark with `board()`, `step_done(push=...)`, end with `done()`
    (or `stop()`, or the `steps` count), then `wait()`. As a context manager it says `done()` at the end of the block
    (`stop()` if the block raised) and waits."""

    def __init__(self, out: Path, cameras: dict[str, Camera], live: bool, *, steps: int | None, settle_s: float,
                 timeout_frames: int, robot_file: RobotFile | None, clock: Callable[[], float],
                 on_event: Callable[[str], None] | None) -> None:
        self.out, self.cameras, self.live = out, cameras, live
        self.steps_limit, self.settle_s, self.timeout_frames = steps, settle_s, timeout_frames
        self.robot_file, self.clock, self.on_event = robot_file, clock, on_event
        self._cond = threading.Condition(threading.RLock())  # _fail runs under it too
        self._pending: list[Mark] = []
        self._marked = 0  # steps marked (step_done calls and robot file step lines)
        self._streams = {n: {k: Stream(c.fps[k]) for k in ("color", "depth")} for n, c in cameras.items()}
        self._stamps: dict[str, list[float]] = {n: [] for n in cameras}
        self._numbers: dict[str, list[int]] = {n: [] for n in cameras}
        self._offset: dict[str, float | None] = {n: None for n in cameras}
        self._domain: dict[str, str] = {}
        self._ended: set[str] = set()
        self.step_times: dict[str, list[float]] = {n: [] for n in cameras}
        self.step_frames: dict[str, list[int]] = {n: [] for n in cameras}
        self.board_time: dict[str, tuple[float, int]] | None = None
        self.pushes: list[dict] = []
        self.marks: list[dict] = []
        self.notes: list[str] = []
        self._events: list[str] = []
        self._changed = True
        self._failure: str | None = None
        self._stopping: str | None = None
        self._done = False
        self._closing = False
        self._closed = threading.Event()
        self.files = MarkFiles(out)
        self.provider: Any = None  # set by open: where the devices came from (removal notices)
        self.suffix, self.compress = ".db3", True
        self._started = clock()
        self._thread = threading.Thread(target=self._run, name="capture-session", daemon=True)

    # --- opening ----------------------------------------------------------------------------------------------------

    @classmethod
    def open(cls, out: str | Path, *, front: str | None = None, back: str | None = None,
             color: Mode | str = DEFAULT_COLOR, depth: Mode | str = DEFAULT_DEPTH, sync: bool = True,
             rig: str | Path | None = None, from_recordings: dict[str, Path] | None = None, steps: int | None = None,
             settle_ms: float = 0.0, timeout_frames: int = DEFAULT_TIMEOUT_FRAMES, compress: bool = True,
             robot_file: str | Path | None = None, clock: Callable[[], float] = clock_time.time,
             on_event: Callable[[str], None] | None = None, start: bool = True) -> CaptureSession:
        """Open the cameras (`front`, `back`: serial numbers; `from_recordings`: {camera: recording} standing in for
        them, the serials then optional and checked) at the `color` and `depth` modes, sync them, write OUT/rig.json
        and start recording (unless `start` is False: then `start()`). Everything is checked before OUT is made:
        UserError (one line) for a bad option, a missing camera, a wrong serial (the serials present listed), a mode
        a camera lacks, an OUT that exists. `clock` gives the marks' default time (s); `on_event(line)` hears each
        step as it resolves (the session's thread)."""
        from dsr_bench.atomic import check_writable

        out = Path(out)
        color, depth = _mode(color, "--color"), _mode(depth, "--depth")
        if out.name in ("", ".", "..") or out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise UserError(f"--out {out}: {'exists and is not empty' if out.exists() else 'names no folder'}; give a "
                            "new folder for this session's recordings")
        check_writable(out, "--out")
        if steps is not None and steps < 1:
            raise UserError(f"--steps {steps}: give the number of pushes to record (1 or more), or leave it out")
        if not settle_ms >= 0:
            raise UserError(f"--settle-ms {settle_ms}: give a delay of 0 ms or more")
        if timeout_frames < 2:
            raise UserError(f"--timeout-frames {timeout_frames}: give 2 frames or more (default "
                            f"{DEFAULT_TIMEOUT_FRAMES}: 1 s at 30 fps)")
        watcher = RobotFile(Path(robot_file)) if robot_file is not None else None
        try:
            import pyrealsense2  # noqa: F401 - the realsense extra
        except ImportError:
            raise UserError("recording RealSense cameras needs pyrealsense2: pip install -e '.[realsense]' "
                            "(librealsense's Python wheel)") from None
        from dsr_bench.annotator.record_devices import (LiveProvider, PlaybackProvider, librealsense_release,
                                                        prepare_camera, recording_suffix, set_sync)

        provider = PlaybackProvider(from_recordings) if from_recordings else LiveProvider()
        present = provider.present()
        wanted = {"front": front, "back": back}
        names = ["front"] + (["back"] if back or from_recordings and "back" in from_recordings else [])
        devices = {n: provider.choose(n, wanted[n], present) for n in names}
        if len(names) == 2 and provider.live and devices["front"].serial == devices["back"].serial:
            raise UserError(f"--front and --back are both {front}: give the two cameras' serials")
        holder: list[CaptureSession] = []

        def ended(camera: str) -> None:
            if holder:
                holder[0]._input_ended(camera)

        cameras = {n: prepare_camera(provider, n, devices[n], color, depth, ended) for n in names}
        sync_note = set_sync(list(cameras.values()), sync)
        release = librealsense_release()
        suffix = recording_suffix(release)
        capture = {"librealsense": release, "sync": sync_note, "settle_ms": settle_ms, "cameras": {
            n: {"serial": c.device.serial, "device": c.device.name, "firmware": c.device.firmware,
                "connection": c.device.connection, "recording": f"{n}{suffix}", "color": c.modes["color"],
                "depth": c.modes["depth"], "sync": c.sync,
                **({"stood_in_by": str(c.device.recording)} if c.device.recording else {})}
            for n, c in cameras.items()}}
        content, copies, template = rig_content(Path(rig) if rig is not None else None, out, capture)
        out.mkdir(parents=True, exist_ok=True)
        write_rig(out, content, copies)
        session = cls(out, cameras, provider.live, steps=steps, settle_s=settle_ms / 1000.0,
                      timeout_frames=timeout_frames, robot_file=watcher, clock=clock, on_event=on_event)
        holder.append(session)
        session.notes.append(f"sync: {sync_note}")
        if template:
            session.notes.append(f"{out / 'rig.json'} is a template: give the board and the objects (meshes) in it "
                                 "before importing")
        session._write()
        session.provider, session.suffix, session.compress = provider, suffix, compress
        if start:
            session.start()
        return session

    def start(self) -> None:
        """Start recording (`open` does unless told not to: marks made before are resolved by the first frames).
        UserError when librealsense cannot start a camera: then OUT is removed, nothing was recorded."""
        import shutil

        try:
            for name, camera in self.cameras.items():
                camera.start(self.out / f"{name}{self.suffix}", self.compress, self._frame)
        except RuntimeError as exc:
            self._close_cameras()
            shutil.rmtree(self.out, ignore_errors=True)
            raise UserError(f"librealsense could not start recording ({exc}); another program (realsense-viewer?) "
                            "may hold the cameras, or they need a USB 3 port: close it and rerun") from None
        serials = {c.device.serial: n for n, c in self.cameras.items()}
        self.provider.watch_removal([c.device for c in self.cameras.values()], lambda serial: self._fail(
            f"the {serials[serial]} camera (serial {serial}) was disconnected"))
        self._started = self.clock()
        self._thread.start()

    # --- the robot's marks ------------------------------------------------------------------------------------------

    def board(self, time: float | None = None) -> None:
        """Mark now (or at `time`, s on the frames' clock) as when the board lies alone on the table."""
        self._mark(Mark("board", self.clock() if time is None else float(time), None, "board()"))

    def step_done(self, push: dict | None = None, time: float | None = None) -> int:
        """Mark the start of the next step: step 0 (no push: the scene before the first push), then one per push
        done (`push`: {"start": [x, y], "direction": [dx, dy]} or "angle_deg", optional "length"; table frame, m).
        Returns the step's number. UserError for a push missing or given where it should not be, or a session that
        has stopped."""
        return self._step(push, self.clock() if time is None else float(time), "step_done()")

    def done(self) -> None:
        """The robot is done: the session ends once the steps marked have their frames."""
        with self._cond:
            self._done = True
            self._cond.notify_all()

    def stop(self, reason: str = "stopped") -> None:
        """End now (Ctrl-C, SIGTERM): steps still waiting for their frames are dropped."""
        with self._cond:
            self._stopping = self._stopping or reason
            self._cond.notify_all()

    def wait(self) -> Summary:
        """Block until the session has ended and its files are complete; the Summary, or UserError (one line) when
        it failed (a dropped stream, a camera unplugged, a bad line of the robot's file): what was recorded until
        then is kept, and the line says so."""
        if self._thread.ident is None:
            raise RuntimeError("the session was opened with start=False: start() it before waiting for it")
        while not self._closed.wait(0.1):  # short waits: a signal handler runs between them
            pass
        summary = self.summary()
        if self._failure:
            kept = (f"importable: dsr-bench import-capture {self.out} --out captures/{self.out.name}"
                    if summary.importable else "not importable: the import needs 2 steps or more")
            raise UserError(f"{self._failure}; what was recorded until then is kept, closed cleanly, in {self.out} "
                            f"({summary.steps} steps; {kept})")
        return summary

    def __enter__(self) -> CaptureSession:
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is not None:
            self.stop("the robot's script raised")
            self._closed.wait()
            return
        self.done()
        self.wait()

    def _step(self, push, time: float, where: str) -> int:
        with self._cond:
            if self._closing or self._failure or self._stopping:
                raise UserError(f"{where}: the session has ended ({self._failure or self._stopping or 'done'})")
            number = self._marked
            if number == 0 and push is not None:
                raise UserError(f"{where}: step 0 is the scene before the first push: mark it without a push, then "
                                "one step per push done")
            if number > 0 and push is None:
                raise UserError(f'{where}: step {number} follows a push: give the push done, {{"start": [x, y], '
                                '"direction": [dx, dy]}} (table frame, m)')
            push = check_push(push, where) if push is not None else None
            self._marked += 1
            self._pending.append(Mark("step", time, push, where))
            self._resolve()
            return number

    def _mark(self, mark: Mark) -> None:
        with self._cond:
            if self._closing or self._failure or self._stopping:
                raise UserError(f"{mark.where}: the session has ended ({self._failure or self._stopping or 'done'})")
            self._pending.append(mark)
            self._resolve()

    def _read_robot_file(self) -> None:
        if self.robot_file is None:
            return
        for line, where in self.robot_file.read():
            try:
                event, push, time = parse_event(line, where)
                if event == "done":
                    self.done()
                elif event == "board":
                    self._mark(Mark("board", self.clock() if time is None else time, None, where))
                else:
                    self._step(push, self.clock() if time is None else time, where)
            except UserError as exc:
                self._fail(str(exc))
                return

    # --- frames -----------------------------------------------------------------------------------------------------

    def _frame(self, camera: str, kind: str, number: int, stamp: float, domain: str) -> None:
        """A frame recorded (librealsense's thread): the stream checks, and the marks it resolves."""
        arrival = self.clock()
        with self._cond:
            if self._closing or self._failure:
                return
            if kind == "error":
                self._fail(f"the {camera} camera's frame callback failed ({domain})")
                return
            problem = frame_problem(camera, self._streams[camera], kind, number, stamp, arrival, self.timeout_frames)
            if problem:
                self._fail(problem)
                return
            if kind == "color":
                self._stamps[camera].append(stamp)
                self._numbers[camera].append(number)
                self._domain.setdefault(camera, domain)
                if domain not in HOST_DOMAINS:
                    offset = stamp - arrival
                    current = self._offset[camera]
                    self._offset[camera] = offset if current is None else max(current, offset)
                else:
                    self._offset[camera] = 0.0
                self._resolve()

    def _input_ended(self, camera: str) -> None:
        """A recording standing in for `camera` was played to its end: no more frames will come."""
        with self._cond:
            self._ended.add(camera)
            self._resolve()
            self._cond.notify_all()

    def _resolve(self) -> None:
        """Resolve the pending marks, in order, whose frames have arrived on every camera (under the lock)."""
        while self._pending and not self._failure:
            mark, picks = self._pending[0], {}
            for name in self.cameras:
                stamps, offset = self._stamps[name], self._offset[name]
                if offset is None:
                    return
                target = mark.time + offset + self.settle_s
                index = bisect.bisect_left(stamps, target)
                if mark.kind == "step" and self.step_times[name]:
                    index = max(index, bisect.bisect_right(stamps, self.step_times[name][-1]))
                if index >= len(stamps):
                    if name in self._ended:
                        end = f"{stamps[-1]:.3f} s" if stamps else "its start"
                        self._fail(f"{mark.where}: no {name} colour frame at or after {target:.3f} s (the frames' "
                                   f"clock): the recording standing in for it ended at {end}; give times on its clock")
                    return
                picks[name] = (stamps[index], self._numbers[name][index])
            self._pending.pop(0)
            self.marks.append({"event": mark.kind, "time": mark.time, "from": mark.where})
            if mark.kind == "board":
                self.board_time = picks
                self._events.append(f"board: {self._picked(picks)}")
            else:
                for name, (stamp, number) in picks.items():
                    self.step_times[name].append(stamp)
                    self.step_frames[name].append(number)
                if mark.push is not None:
                    self.pushes.append(mark.push)
                self._events.append(f"step {len(self.pushes)}: {self._picked(picks)}")
            self._changed = True
            self._cond.notify_all()

    @staticmethod
    def _picked(picks: dict[str, tuple[float, int]]) -> str:
        return ", ".join(f"{n} colour frame {number} at {stamp:.3f} s" for n, (stamp, number) in picks.items())

    def _fail(self, message: str) -> None:
        with self._cond:
            if message and not self._failure and not self._closing:
                self._failure = message
                self._cond.notify_all()

    # --- the session's thread ---------------------------------------------------------------------------------------

    def _ending(self) -> bool:
        """Whether the session ends now: on a failure or a stop at once; when the robot is done (every mark
        resolved) or the steps counted are in, once the last step's depth frames are recorded too (a depth frame at
        or after its colour frame on every camera), and with recordings standing in once they are played whole."""
        if self._failure or self._stopping:
            return True
        counted = self.steps_limit is not None and len(self.pushes) >= self.steps_limit
        if not (counted or self._done and not self._pending):
            return False
        if not self.live:
            return self._ended >= set(self.cameras)
        return all(not times or (self._streams[n]["depth"].last_stamp or 0.0) >= times[-1]
                   for n, times in self.step_times.items())

    def _run(self) -> None:
        """Read the robot's file, check the streams, write the files as steps resolve; at the end close the cameras
        (never in librealsense's threads) and complete the files."""
        try:
            while True:
                self._read_robot_file()
                with self._cond:
                    if self.live:
                        self._fail(clock_problem(self._streams, self.clock(), self._started, self.timeout_frames) or "")
                    ending, events, self._events = self._ending(), self._events, []
                self._write()  # then say the steps: what is said is in the files
                for line in events:
                    self._say(line)
                if ending:
                    break
                with self._cond:
                    if not self._ending() and not self._events:
                        self._cond.wait(POLL_S)
        except Exception as exc:  # noqa: BLE001 - whatever happens here, the cameras are closed and said why
            self._fail(f"the session failed ({type(exc).__name__}: {exc})")
        with self._cond:
            self._closing = True
            dropped = [m.where for m in self._pending]
            if self._stopping:
                self.notes.append(f"ended by {self._stopping}")
        if dropped:
            self.notes.append(f"{len(dropped)} mark(s) had no frames yet when the session ended and were dropped "
                              f"({', '.join(dropped)})")
        self._close_cameras()
        self._write()
        self.files.finish()
        self._closed.set()

    def _say(self, line: str) -> None:
        if self.on_event is not None:
            self.on_event(line)

    def _close_cameras(self) -> None:
        for camera in self.cameras.values():
            camera.stop()

    def _write(self) -> None:
        with self._cond:
            if not self._changed:
                return
            self._changed = False
            steps: dict = {"step_times": {n: list(t) for n, t in self.step_times.items()}}
            if self.board_time is not None:
                steps["board_time"] = {n: stamp for n, (stamp, _) in self.board_time.items()}
            steps["frames"] = {"steps": {n: list(f) for n, f in self.step_frames.items()},
                               **({"board": {n: number for n, (_, number) in self.board_time.items()}}
                                  if self.board_time is not None else {})}
            steps["clock"] = ("frame timestamps (s), librealsense's frame clock: " +
                              ", ".join(f"{n} {d}" for n, d in self._domain.items()))
            steps["marks"] = list(self.marks)
            pushes = {"pushes": list(self.pushes)}
        self.files.write(steps, pushes)

    def summary(self) -> Summary:
        """What was recorded (per camera: the recording, its frames and frames lost; steps, pushes, notes)."""
        with self._cond:
            steps = len(self.step_times["front"])
            out = Summary(self.out, steps=steps, importable=steps >= 2)
            for name, camera in self.cameras.items():
                size = camera.path.stat().st_size / 1e6 if camera.path and camera.path.is_file() else 0.0
                counts = "; ".join(
                    f"{'colour' if k == 'color' else 'depth'} {s.count} frames"
                    + (f" ({s.lost} lost in {s.gaps} gaps)" if s.lost else "") for k, s in self._streams[name].items())
                where = camera.path.name if camera.path else "(not started)"
                out.lines.append(f"{name}: {where} ({size:.1f} MB), {camera.device.describe()}, {counts}")
            board = " and the board" if self.board_time is not None else ""
            pushes = f"{len(self.pushes)} push{'es' if len(self.pushes) != 1 else ''}"
            out.lines.append(f"steps: {steps} ({pushes}){board} in steps.json and pushes.json")
            out.lines += [f"note: {n}" for n in self.notes]
            return out
