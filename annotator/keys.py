"""The annotator's keys: the key map, and the `Controller` that turns keys into `annotator.session.Session` calls.

No window here (testable without a display): the window (`annotator.window`) registers a callback per `KEYMAP`
key that calls `Controller.press`, and redraws what it reports changed. The Controller also holds what the
window shows beyond the Session's own state (`ViewState`: nudge axes and steps, cloud colouring, the message).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

from dsr_bench.annotator.align import FitScore
from dsr_bench.annotator.images import SELECTED_COLOR, muted_colors
from dsr_bench.errors import UserError

#: Nudge sizes: fine / coarse translation (m) and rotation (rad).
TRANSLATION_STEPS: dict[str, float] = {"fine": 0.001, "coarse": 0.01}
ROTATION_STEPS: dict[str, float] = {"fine": float(np.deg2rad(1.0)), "coarse": float(np.deg2rad(5.0))}
#: GLFW key codes of the non-character keys used in KEYMAP.
GLFW_SPECIAL_KEYS: dict[str, int] = {"Space": 32, "Esc": 256, "Enter": 257, "Tab": 258}


@dataclass
class ViewState:
    """What the window shows and how keys act, beyond the Session's own state."""

    frame: str = "table"  # nudge axes: "table" or "object"
    coarse: bool = False  # coarse (1 cm / 5 deg) or fine (1 mm / 1 deg) nudges
    residual: bool = False  # cloud coloured by depth residual instead of the capture colours
    quit: bool = False
    reset_view: bool = False  # set by the key, cleared by the window once it reset the 3D view
    message: str = ""  # what the last key did (or, on opening, what the work is)
    hint: str = ""  # what to do next (`annotator.guide.next_hint`), shown under the message
    warning: str = ""  # the last key's "wrong object?" (`annotator.guide.wrong_object`), else empty
    score_cache: dict = field(default_factory=dict)

    @property
    def translation_step(self) -> float:
        return TRANSLATION_STEPS["coarse" if self.coarse else "fine"]

    @property
    def rotation_step(self) -> float:
        return ROTATION_STEPS["coarse" if self.coarse else "fine"]


def format_score(score: FitScore | None) -> str:
    """One line of a FitScore: inlier RMSE (mm), coverage, fitness, accepted/reason ("fit: -" for None)."""
    if score is None:
        return "fit: -"
    if not np.isfinite(score.rmse):
        return f"fit: - ({score.reason or 'no fit'})"
    line = f"fit: rmse {score.rmse * 1000:.1f} mm, coverage {score.coverage:.2f}, fitness {score.fitness:.2f}"
    if not score.accepted:
        line += f", poor: {score.reason}"
    return line


def object_name(session, obj: int) -> str:
    """The capture's name of object `obj`."""
    return str(session.capture.objects[obj].name)


# --- Key actions: each takes the Controller; a UserError becomes the panel's message ---------------------------------


class Binding(NamedTuple):
    """One key: its label, the Session method its action calls (None: view-only) and the action."""

    label: str
    method: str | None
    action: Callable[..., Any]  # (controller) or, for a nudge, (controller, count=n)
    group: str


def _select(ctl: "Controller", obj: int) -> None:
    from dsr_bench.annotator.guide import describe

    if obj >= ctl.session.num_objects:
        ctl.view.message = f"no object {obj + 1}: this capture has {ctl.session.num_objects}"
        return
    ctl.session.select(obj)
    status = ctl.session.status()[obj]
    ctl.view.message = f"selected {describe(ctl.session, obj)}: " + ("not placed yet" if status == "unset" else status)


def _select_next(ctl: "Controller") -> None:
    _select(ctl, (ctl.session.selected + 1) % max(1, ctl.session.num_objects))


def _translate(axis: int, sign: int, ctl: "Controller", count: int = 1) -> None:
    vec = np.zeros(3)
    vec[axis] = sign * ctl.view.translation_step * count
    ctl.session.nudge(ctl.session.selected, translation=tuple(vec), rotation=(0.0, 0.0, 0.0), frame=ctl.view.frame)
    ctl.view.message = f"moved {'+' if sign > 0 else '-'}{'xyz'[axis]} {vec[axis] * 1000:+g} mm ({ctl.view.frame})"


def _rotate(axis: int, sign: int, ctl: "Controller", count: int = 1) -> None:
    vec = np.zeros(3)
    vec[axis] = sign * ctl.view.rotation_step * count
    ctl.session.nudge(ctl.session.selected, translation=(0.0, 0.0, 0.0), rotation=tuple(vec), frame=ctl.view.frame)
    name = ("roll", "pitch", "yaw")[axis]
    ctl.view.message = f"rotated {name} {np.rad2deg(vec[axis]):+g} deg ({ctl.view.frame})"


def _toggle_frame(ctl: "Controller") -> None:
    ctl.view.frame = "object" if ctl.view.frame == "table" else "table"
    ctl.view.message = f"nudges in {ctl.view.frame} axes"


def _toggle_coarse(ctl: "Controller") -> None:
    ctl.view.coarse = not ctl.view.coarse
    ctl.view.message = f"{'coarse' if ctl.view.coarse else 'fine'} steps"


def _snap(ctl: "Controller") -> None:
    score = ctl.session.snap(ctl.session.selected)
    if not score.kept:  # nothing changed
        ctl.view.message = f"snap rejected, pose unchanged: {score.reason}"
    else:
        verdict = "snapped" if score.accepted else "snap kept (better than before), fit still poor"
        ctl.view.message = f"{verdict}: {format_score(score)[5:]}"
    _warn_wrong_object(ctl, other_shapes=True)


def _warn_wrong_object(ctl: "Controller", other_shapes: bool) -> None:
    """Append "wrong object? ..." to the message when the selected object's pose lies on another object's points
    (`annotator.guide.wrong_object`; `other_shapes`: also try the unplaced objects' meshes on a poor fit)."""
    from dsr_bench.annotator.guide import wrong_object

    found = wrong_object(ctl.session, ctl.session.selected, other_shapes=other_shapes)
    if found:
        ctl.view.message += f" | {found}"
        ctl.view.warning = found


def _confirm(ctl: "Controller") -> None:
    ctl.session.confirm(ctl.session.selected)
    ctl.view.message = f"confirmed {object_name(ctl.session, ctl.session.selected)}"


def _go(delta: int, ctl: "Controller") -> None:
    target = ctl.session.step + delta
    last = ctl.session.num_steps  # steps are 0..T
    if not 0 <= target <= last:
        ctl.view.message = f"no step {target}: steps are 0..{last}"
        return
    snapped = ctl.session.go_to(target)
    ctl.view.message = f"step {target}" + (f", snapped objects {[i + 1 for i in snapped]}" if snapped else "")


def _undo(ctl: "Controller") -> None:
    what = ctl.session.describe_undo()
    ctl.view.message = f"undone: {what}; now at step {ctl.session.step}" if ctl.session.undo() else "nothing to undo"


def _redo(ctl: "Controller") -> None:
    what = ctl.session.describe_redo()
    ctl.view.message = f"redone: {what}; now at step {ctl.session.step}" if ctl.session.redo() else "nothing to redo"


def _from_previous(ctl: "Controller") -> None:
    ctl.session.init_from_previous(ctl.session.selected)
    ctl.view.message = "pose taken from the previous step"


def _recarry(ctl: "Controller") -> None:
    obj = ctl.session.selected
    steps = ctl.session.recarry(obj)
    if steps:
        ctl.view.message = f"re-carried object {obj + 1} to steps {', '.join(map(str, steps))}"
    else:
        ctl.view.message = (f"nothing to re-carry: no later step holds object {obj + 1} carried from a pose that has "
                            "changed since")


def _next_to_check(ctl: "Controller") -> None:
    found = ctl.session.next_to_check()
    if found is None:
        ctl.view.message = "every object at every visited step is checked and fits well (N goes on)"
        return
    step, obj, why = found
    ctl.session.go_to(step)  # a visited step: only the cursor moves
    ctl.session.select(obj)
    ctl.view.message = f"step {step}, object {obj + 1} ({object_name(ctl.session, obj)}): {why}"


def _pick(ctl: "Controller") -> None:
    ctl.pick()


def _toggle_residual(ctl: "Controller") -> None:
    ctl.view.residual = not ctl.view.residual
    if ctl.view.residual:
        ctl.session.residual_colors(index=ctl.session.shown())  # fail here (message) rather than while drawing
    ctl.view.message = f"cloud coloured by {'depth residual' if ctl.view.residual else 'capture colours'}"


def _progress(ctl: "Controller") -> None:
    ctl.echo(ctl.session.progress_table())
    ctl.view.message = "progress table printed to the terminal"


def _reset_view(ctl: "Controller") -> None:
    ctl.view.reset_view = True
    ctl.view.message = "view reset"


def _quit(ctl: "Controller") -> None:
    ctl.view.quit = True
    ctl.view.message = "bye"


def _build_keymap() -> dict[str, Binding]:
    km: dict[str, Binding] = {}
    for i in range(5):
        km[str(i + 1)] = Binding(f"select object {i + 1}", "select", partial(_select, obj=i), "select object / next")
    km["Tab"] = Binding("select the next object", "select", _select_next, "select object / next")
    for key, axis, sign in (("D", 0, 1), ("A", 0, -1), ("W", 1, 1), ("S", 1, -1), ("E", 2, 1), ("Q", 2, -1)):
        km[key] = Binding(f"move {'+-'[sign < 0]}{'xyz'[axis]}", "nudge", partial(_translate, axis, sign),
                          "move +x -x +y -y +z -z")
    for key, axis, sign in (("L", 0, 1), ("J", 0, -1), ("I", 1, 1), ("K", 1, -1), ("O", 2, 1), ("U", 2, -1)):
        km[key] = Binding(f"rotate {'+-'[sign < 0]}{('roll', 'pitch', 'yaw')[axis]}", "nudge",
                          partial(_rotate, axis, sign), "rotate +-roll +-pitch +-yaw")
    km["T"] = Binding("table / object axes", None, _toggle_frame, "table / object axes")
    km["G"] = Binding("fine / coarse steps", None, _toggle_coarse, "fine / coarse steps")
    km["Space"] = Binding("snap (ICP)", "snap", _snap, "snap (ICP)")
    km["Enter"] = Binding("confirm", "confirm", _confirm, "confirm")
    km["N"] = Binding("next step", "go_to", partial(_go, 1), "next / previous step")
    km["P"] = Binding("previous step", "go_to", partial(_go, -1), "next / previous step")
    km["Z"] = Binding("undo", "undo", _undo, "undo / redo")
    km["Y"] = Binding("redo", "redo", _redo, "undo / redo")
    km["C"] = Binding("pose from the previous step", "init_from_previous", _from_previous,
                      "pose from the previous step")
    km["X"] = Binding("re-carry to later steps", "recarry", _recarry, "re-carry to later steps")
    km["B"] = Binding("next object to check", "next_to_check", _next_to_check, "next object to check")
    km["M"] = Binding("pick >= 3 point pairs", "init_from_picks", _pick, "pick >= 3 pairs cloud <-> mesh")
    km["R"] = Binding("depth-residual colours", "residual_colors", _toggle_residual, "depth-residual colours")
    km["F"] = Binding("progress table (terminal)", "progress_table", _progress, "progress table (terminal)")
    km["V"] = Binding("reset the 3D view", None, _reset_view, "reset the 3D view")
    km["Esc"] = Binding("quit", None, _quit, "quit (all saved)")
    return km


#: Key name -> Binding. Letters are case-insensitive; see `glfw_code` for the key codes.
KEYMAP: dict[str, Binding] = _build_keymap()


def glfw_code(key: str) -> int:
    """GLFW key code of a KEYMAP key name (upper-case letters and digits are their ASCII codes)."""
    if key in GLFW_SPECIAL_KEYS:
        return GLFW_SPECIAL_KEYS[key]
    if len(key) == 1 and (key.isdigit() or "A" <= key <= "Z"):
        return ord(key)
    raise ValueError(f"no GLFW code for key {key!r}")


def key_help_lines(keymap: dict[str, Binding] | None = None) -> list[str]:
    """One line per key group: the group's keys, a tab, its label ("D A W S E Q\tmove +x -x ...")."""
    groups: dict[str, list[str]] = {}
    for key, binding in (keymap or KEYMAP).items():
        groups.setdefault(binding.group, []).append(key)
    return [f"{' '.join(keys)}\t{group}" for group, keys in groups.items()]


# --- Key coalescing: what a held key does -------------------------------------------------------------------------


#: A nudge key repeated within one frame moves at most this many steps (the rest of its repeats are dropped).
MAX_REPEAT = 5
#: Key events older than this (s) when the window gets to them are dropped if they are nudges (never other keys).
MAX_LAG = 0.5


@dataclass(frozen=True)
class KeyAction:
    """What the window does with pending keys: press `key` standing for `count` presses (> 1: a merged nudge)."""

    key: str
    count: int = 1


def is_nudge(key: str) -> bool:
    """Whether a key (KEYMAP name, letters case-insensitive) nudges the selected object."""
    binding = KEYMAP.get(key.upper() if len(key) == 1 else key)
    return binding is not None and binding.method == "nudge"


class KeyCoalescer:
    """The key events a window received since its last frame -> the actions to apply before drawing the next.

    The window's key callback only `push`es (key, time); once per frame the window `drain`s: a run of the same
    nudge key becomes one nudge of the summed size, at most `max_repeat` steps (the repeats beyond are dropped),
    nudges waiting longer than `max_lag` s are dropped, and every other key is kept, once, in order. A held key so
    moves at most `max_repeat` steps per frame, however fast it repeats or however slow the frame, and nothing is
    left queued between frames: releasing it stops the motion at the next frame. No window here: pure.
    """

    def __init__(self, max_repeat: int = MAX_REPEAT, max_lag: float = MAX_LAG):
        self.max_repeat = int(max_repeat)
        self.max_lag = float(max_lag)
        self._pending: list[tuple[str, float]] = []
        self.received = 0
        self.dropped = 0

    def push(self, key: str, t: float) -> None:
        """A key event received at time `t` (s, any monotonic clock)."""
        self._pending.append((key.upper() if len(key) == 1 else key, float(t)))
        self.received += 1

    @property
    def pending(self) -> int:
        """Key events not yet drained."""
        return len(self._pending)

    def drain(self, now: float) -> list[KeyAction]:
        """The actions for the events pushed since the last drain (see the class docstring); empties the queue."""
        out: list[KeyAction] = []
        for key, t in self._pending:
            if not is_nudge(key):
                out.append(KeyAction(key))
            elif now - t > self.max_lag:
                self.dropped += 1
            elif out and out[-1].key == key and is_nudge(key):
                if out[-1].count < self.max_repeat:
                    out[-1] = KeyAction(key, out[-1].count + 1)
                else:
                    self.dropped += 1
            else:
                out.append(KeyAction(key))
        self._pending.clear()
        return out


def coalesce(events: Sequence[tuple[str, float]], frames: Sequence[float], max_repeat: int = MAX_REPEAT,
             max_lag: float = MAX_LAG) -> list[tuple[float, KeyAction]]:
    """What a window does with key events: (key, time) events and the times its frames start (both ascending) ->
    (frame time, action) in order; each frame drains the events received before it (`KeyCoalescer`)."""
    keys, k = KeyCoalescer(max_repeat, max_lag), 0
    out: list[tuple[float, KeyAction]] = []
    for frame in frames:
        while k < len(events) and events[k][1] <= frame:
            keys.push(*events[k])
            k += 1
        out.extend((frame, action) for action in keys.drain(frame))
    return out


# --- The controller ---------------------------------------------------------------------------------------------------


def mesh_samples(vertices: np.ndarray, faces: np.ndarray, count: int = 6000, seed: int = 0) -> np.ndarray:
    """Points (M, 3) on a mesh surface (object frame, m) for picking: its vertices plus uniform samples."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
                                     o3d.utility.Vector3iVector(np.asarray(faces, np.int32)))
    o3d.utility.random.seed(seed)
    samples = np.asarray(mesh.sample_points_uniformly(count).points) if len(faces) else np.zeros((0, 3))
    return np.vstack([np.asarray(vertices, np.float64), samples])


def rich_echo(text: str) -> None:
    """Print to the terminal with rich (no markup, no highlighting)."""
    try:
        from rich.console import Console

        Console(highlight=False, soft_wrap=True).print(text, markup=False)
    except ImportError:  # pragma: no cover - rich is a core dependency
        print(text)


class Controller:
    """Keys -> Session calls and the view state; no window (testable without a display).

    session: an `annotator.session.Session`; picker(points (M,3), colors (M,3) or None, title, mesh) -> picked
    indices, mesh: None for the cloud, the object's (vertices, faces) for its samples (the window passes its
    `ClickPicker`; without one, pick mode says so); echo(text): terminal output (default: rich).
    """

    def __init__(self, session, picker: Callable[..., np.ndarray] | None = None,
                 echo: Callable[[str], None] | None = None):
        from dsr_bench.annotator.guide import next_hint, opening_message

        self.session = session
        self.view = ViewState(message=opening_message(session), hint=next_hint(session))
        self.picker = picker
        self.echo = echo or rich_echo

    def press(self, key: str, count: int = 1) -> set[str]:
        """Act on one key (a KEYMAP name, letters case-insensitive); returns what changed: a subset of
        {"cloud", "meshes", "panel"}. A UserError from the session becomes the panel's message. `count`: for a
        nudge key, how many presses it stands for (one nudge of `count` steps, see `KeyCoalescer`)."""
        name = key.upper() if len(key) == 1 else key
        binding = KEYMAP.get(name)
        if binding is None:
            self.view.message = f"key {key!r} does nothing; see the keys listed below"
            return {"panel"}
        before = self._snapshot()
        self.view.warning = ""
        try:
            if binding.method == "nudge":
                binding.action(self, count=max(1, int(count)))
            else:
                binding.action(self)
        except UserError as exc:
            self.view.message = f"{binding.label}: {exc}"
            self.echo(f"[{binding.label}] {exc}")
        if binding.method not in (None, "recarry"):
            self._offer_recarry()
        self._update_hint()
        after = self._snapshot()
        changed = {"panel"}
        if before[:2] != after[:2]:
            changed.add("cloud")
        if before[2:] != after[2:]:
            changed.add("meshes")
            if self.view.residual and before[2] != after[2]:  # the residual colours follow the poses only
                changed.add("cloud")
        return changed

    def _offer_recarry(self) -> None:
        """After a change: when later steps hold the selected object carried from a pose that has changed since,
        say so in the message and name the key that re-carries them."""
        s = self.session
        try:
            stale = s.stale_steps(s.selected)
        except UserError:
            return
        if stale:
            self.view.message += (f" | steps {', '.join(map(str, stale))} hold object {s.selected + 1} carried from "
                                  "its old pose: X re-carries them")

    def _update_hint(self) -> None:
        """The "next:" line after a key (`annotator.guide.next_hint`: statuses only, no fit)."""
        from dsr_bench.annotator.guide import next_hint, undo_hint

        try:
            self.view.hint = (undo_hint(self.session, self.session.selected) if self.view.warning
                              else next_hint(self.session))
        except UserError as exc:
            self.view.hint = f"next: - ({exc})"

    def _snapshot(self) -> tuple:
        s = self.session
        return (s.step, self.view.residual, s.poses().tobytes(), tuple(s.status()), s.selected, self.view.frame)

    def cloud(self) -> tuple[np.ndarray, np.ndarray]:
        """Points (K,3) world m and colours (K,3) 0..1 of what the window draws of the current step's fused cloud:
        its subset `Session.shown` (chosen once per step; fitting uses the whole cloud); the colours are the depth
        residual's in residual mode, computed for these points only."""
        points, colors, _ = self.session.cloud()
        index = self.session.shown()
        points, colors = points[index], colors[index]
        if self.view.residual:
            try:
                colors = self.session.residual_colors(index=index)
            except UserError as exc:
                self.view.message = f"residual colours: {exc}"
        return points, colors

    def pick(self) -> None:
        """Pick mode: >= 3 cloud points, then as many mesh points (same order) -> session.init_from_picks."""
        if self.picker is None:
            raise UserError("pick mode needs the annotator window (no picker)")
        s, obj = self.session, self.session.selected
        points, colors = self.cloud()
        if not self.view.residual:  # muted as the 3D view's: no object's own colour reads as a status colour
            colors = muted_colors(colors)
        self.view.message = "pick mode: shift + click 3 or more points on the cloud, then Q"
        cloud_idx = self.picker(points, colors, "pick >= 3 cloud points (shift+click), then close with Q", None)
        if len(cloud_idx) < 3:
            self.view.message = f"pick: {len(cloud_idx)} cloud points picked; need 3 or more (shift+click)"
            return
        vertices, faces = s.capture.mesh(obj)
        samples = mesh_samples(vertices, faces)
        shade = np.tile(np.asarray(SELECTED_COLOR), (len(samples), 1))
        self.view.message = (f"pick mode: shift + click the same {len(cloud_idx)} points on the mesh in the same "
                             "order, then Q")
        mesh_idx = self.picker(samples, shade, f"pick the same {len(cloud_idx)} points on the mesh, in order, "
                                               "then close with Q", (vertices, faces))
        if len(mesh_idx) != len(cloud_idx):
            self.view.message = (f"pick: {len(mesh_idx)} mesh points for {len(cloud_idx)} cloud points; "
                                 "pick the same number in the same order (M to retry)")
            return
        s.init_from_picks(obj, samples[np.asarray(mesh_idx)], points[np.asarray(cloud_idx)])
        self.view.message = f"pose initialised from {len(cloud_idx)} picked pairs"
        _warn_wrong_object(self, other_shapes=False)

    def meshes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(vertices, faces) of every object's mesh, object frame."""
        return [self.session.capture.mesh(i) for i in range(self.session.num_objects)]
