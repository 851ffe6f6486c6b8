"""The files `dsr-bench capture` writes beside the recordings (`annotator.record`; docs/annotator.md, "Recording a
session"): steps.json and pushes.json as the recording goes, rig.json (the given rig file, or a template, with what
was recorded), and the robot's file of events read as it grows.

steps.json and pushes.json must agree (T + 1 step times, T pushes: `import-capture` refuses anything else), and each
is rewritten at every step. Two renames cannot be atomic together, so while recording both are links into one
version directory, `OUT/.steps/<n>/`, and a new step writes version n + 1 and swaps the link `OUT/.steps/current`
(one rename): a crash at any instant leaves two files of one version, a valid prefix of the session. At the end both
become plain files of the last version (each renamed over its link: their contents agree all along) and `.steps/`
goes. Where links cannot be made (a file system without them) both are written in place, pushes first.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

from dsr_bench.annotator.inputs import finite, inside
from dsr_bench.atomic import write_text
from dsr_bench.errors import UserError

STEPS_FILE, PUSHES_FILE, RIG_FILE = "steps.json", "pushes.json", "rig.json"
VERSIONS = ".steps"
#: The rig template's board: docs/annotator.md's example (7 x 5 squares of 6 cm, 4.5 cm 4x4 markers, centred on the
#: workspace).
TEMPLATE_BOARD = {"squares": [7, 5], "square_length": 0.06, "marker_length": 0.045, "dictionary": "DICT_4X4_50",
                  "offset": [0.29, 0.15, 0.0]}
#: The robot file's events (one a line): a bare word or a JSON object {"event": ..., "push": {...}, "time": s}.
EVENTS = ("board", "step", "done")


class MarkFiles:
    """steps.json and pushes.json in OUT, rewritten together (module docstring)."""

    def __init__(self, out: Path) -> None:
        self.out, self.version, self.linked = out, 0, True
        versions = out / VERSIONS
        try:
            versions.mkdir()
            (versions / "current").symlink_to("0")
            for name in (STEPS_FILE, PUSHES_FILE):
                (out / name).symlink_to(Path(VERSIONS, "current", name))
        except OSError:  # no links here: plain files, pushes written first
            shutil.rmtree(versions, ignore_errors=True)
            for name in (STEPS_FILE, PUSHES_FILE):
                (out / name).unlink(missing_ok=True)
            self.linked = False

    def write(self, steps: dict, pushes: dict) -> None:
        """Write one version of both files (steps.json's and pushes.json's content)."""
        texts = {PUSHES_FILE: json.dumps(pushes, indent=1), STEPS_FILE: json.dumps(steps, indent=1)}
        if not self.linked:
            for name, text in texts.items():
                write_text(self.out / name, text)
            return
        versions = self.out / VERSIONS
        folder = versions / str(self.version)
        folder.mkdir(exist_ok=True)
        for name, text in texts.items():
            write_text(folder / name, text)
        swap = versions / f".current.tmp-{os.getpid()}"
        swap.unlink(missing_ok=True)
        swap.symlink_to(str(self.version))
        os.replace(swap, versions / "current")
        if self.version > 0:
            shutil.rmtree(versions / str(self.version - 1), ignore_errors=True)
        self.version += 1

    def finish(self) -> None:
        """Both files as plain files of the last version written, the version directory removed."""
        if not self.linked:
            return
        for name in (PUSHES_FILE, STEPS_FILE):
            write_text(self.out / name, (self.out / name).read_text())  # renamed over the link
        shutil.rmtree(self.out / VERSIONS, ignore_errors=True)


def check_push(push, where: str) -> dict:
    """A push as pushes.json holds it ({"start": [x, y], "direction": [dx, dy]} or "angle_deg", optional "length";
    table frame, m), checked as `import-capture` reads it; UserError naming `where`."""
    example = '{"start": [0.45, -0.03], "direction": [0.7071, 0.7071]}'
    if not isinstance(push, dict) or "start" not in push or ("direction" in push) == ("angle_deg" in push):
        raise UserError(f"{where}: a push is {example} (table frame, m; or \"angle_deg\" instead of \"direction\"), "
                        f"got {json.dumps(push)[:80]}")
    start, direction = push["start"], push.get("direction")
    if not (isinstance(start, list) and len(start) == 2 and all(finite(v) for v in start)):
        raise UserError(f"{where}: push start {json.dumps(start)[:40]} must be [x, y] (m, table frame)")
    if direction is not None:
        if not (isinstance(direction, list) and len(direction) == 2 and all(finite(v) for v in direction)) or \
                abs(math.hypot(*direction) - 1) > 0.01:
            raise UserError(f"{where}: push direction {json.dumps(direction)[:40]} must be a unit vector [dx, dy]")
    elif not finite(push["angle_deg"]):
        raise UserError(f"{where}: push angle_deg {json.dumps(push['angle_deg'])[:40]} must be a number (degrees)")
    if "length" in push and not (finite(push["length"]) and 0 < push["length"] < 1):
        raise UserError(f"{where}: push length {json.dumps(push['length'])[:40]} must be metres in (0, 1)")
    return dict(push)


def parse_event(line: str, where: str) -> tuple[str, dict | None, float | None]:
    """(event, push or None, time s or None) of one line of the robot's file (EVENTS); UserError naming `where`."""
    text = line.strip()
    if text in EVENTS:
        return text, None, None
    try:
        entry = json.loads(text)
    except json.JSONDecodeError:
        entry = None
    if not isinstance(entry, dict) or entry.get("event") not in EVENTS or not set(entry) <= {"event", "push", "time"}:
        raise UserError(f"{where}: {text[:60]!r} is not an event: write one line per event, `board`, `step` (step 0), "
                        '`{"event": "step", "push": {"start": [x, y], "direction": [dx, dy]}}` (a push done: the next '
                        'step), `done`; optionally "time": s on the frames\' clock')
    time = entry.get("time")
    if time is not None and not finite(time):
        raise UserError(f"{where}: time {json.dumps(time)[:40]} must be a number (s, the frames' clock)")
    if entry.get("push") is not None and entry["event"] != "step":
        raise UserError(f"{where}: only a step follows a push; move the push to its step's line")
    push = check_push(entry["push"], where) if entry.get("push") is not None else None
    return entry["event"], push, None if time is None else float(time)


class RobotFile:
    """The robot's file of events, read as it grows: complete lines only (a line being written waits for its
    newline). It must be empty or absent when the session starts: the session reads it from its start."""

    def __init__(self, path: Path) -> None:
        if path.is_dir() or path.is_file() and path.stat().st_size > 0:
            raise UserError(f"--robot-file {path}: {'is a directory' if path.is_dir() else 'is not empty'}; give a "
                            "new (or empty) file for this session: the command reads every line of it as an event")
        self.path, self.offset, self.lines, self._partial = path, 0, 0, b""

    def read(self) -> list[tuple[str, str]]:
        """(line, where) of each complete line appended since the last read."""
        try:
            with self.path.open("rb") as handle:
                handle.seek(self.offset)
                data = handle.read()
        except FileNotFoundError:
            return []
        self.offset += len(data)
        data = self._partial + data
        *complete, self._partial = data.split(b"\n")
        out = []
        for raw in complete:
            self.lines += 1
            if raw.strip():
                out.append((raw.decode("utf-8", "replace"), f"--robot-file {self.path} line {self.lines}"))
        return out


def rig_content(rig: Path | None, out: Path, capture: dict) -> tuple[dict, list[tuple[Path, Path]], bool]:
    """(rig.json's content, (mesh source, destination) pairs to copy, whether it is a template): the given rig file
    with "capture" (what was recorded: serials, modes, sync) added, its meshes copied beside it; or, without one, a
    template to complete (the board of TEMPLATE_BOARD, no objects). UserError naming the rig file."""
    if rig is None:
        return {"board": TEMPLATE_BOARD, "objects": [], "capture": capture,
                "todo": "a template: give the board you used and the objects (meshes in metres, relative to this "
                        "folder) before `dsr-bench import-capture`"}, [], True
    from dsr_bench.annotator.rig import load_rig

    rig_path, spec = load_rig(rig.parent, rig)
    copies = []
    for i, entry in enumerate(spec.get("objects") or []):
        if isinstance(entry, dict) and isinstance(entry.get("mesh"), str):
            source = inside(rig_path.parent, entry["mesh"], f"object {i + 1} mesh", rig_path)
            if not source.is_file():
                raise UserError(f"{rig_path}: object {i + 1} mesh {entry['mesh']!r} not found under "
                                f"{rig_path.parent}; fix the rig file before recording")
            copies.append((source, out / entry["mesh"]))
    return {**spec, "capture": capture}, copies, False


def write_rig(out: Path, content: dict, copies: list[tuple[Path, Path]]) -> None:
    """OUT/rig.json and the meshes it names."""
    for source, target in copies:
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, target)
    write_text(out / RIG_FILE, json.dumps(content, indent=1))
