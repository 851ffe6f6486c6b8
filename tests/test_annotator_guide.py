"""A newcomer's first annotation (issue 42 part 4): from an empty capture to a validated export, the window saying
what to do at each step (`annotator.guide`: the opening message, the "next:" line, "wrong object?"), the objects'
previews, the residual colours of a misplaced object, the pick window's muted colours, the 3D view opening on the
whole workspace, a private XDG_RUNTIME_DIR, and every fit verdict with a reason.

Fixture: the small ideal-sensor capture of conftest.py (box_0, can_1, box_2; 3 pushes, 240 x 320 images).
"""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("open3d")
pytest.importorskip("PIL")

from dsr_bench.annotator import guide, images, keys, panel  # noqa: E402
from dsr_bench.annotator.session import Session  # noqa: E402
from dsr_bench.geometry import pose_to_matrix  # noqa: E402
from helpers import virtual_display  # noqa: E402


def _pairs(session, truth, obj: int, onto: int, step: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(mesh points of object `obj`, the cloud points a person clicks for them): on its own blob, where they lie at
    its true pose; on object `onto`'s blob (the wrong one), where they would lie were the object standing turned as
    it truly is, centred on the other object's true centre."""
    v, _ = session.capture.mesh(obj)
    m = pose_to_matrix(truth[step, obj])
    pick = v[np.unique([np.argmin(v[:, 0]), np.argmax(v[:, 0]), np.argmin(v[:, 1]), np.argmax(v[:, 1]),
                        np.argmax(v[:, 2])])]
    cloud = pick @ m[:3, :3].T + m[:3, 3]
    if onto != obj:
        w, _ = session.capture.mesh(onto)
        n = pose_to_matrix(truth[step, onto])
        own = m[:3, :3] @ (0.5 * (v.min(0) + v.max(0))) + m[:3, 3]
        other = n[:3, :3] @ (0.5 * (w.min(0) + w.max(0))) + n[:3, 3]
        cloud = cloud + (other - own)
    return pick, cloud


class ScriptedPicker:
    """The person's clicks in the two pick windows: the shown points nearest the wanted cloud points, then the mesh
    samples nearest the wanted mesh points; records the colours each window was given."""

    def __init__(self):
        self.pairs: tuple[np.ndarray, np.ndarray] | None = None
        self.colours: list[np.ndarray | None] = []

    def __call__(self, points, colors, title, mesh):
        from scipy.spatial import cKDTree

        assert self.pairs is not None
        self.colours.append(None if colors is None else np.asarray(colors))
        wanted = self.pairs[1] if mesh is None else self.pairs[0]
        return cKDTree(points).query(wanted)[1]


def _place(ctl: keys.Controller, picker: ScriptedPicker, truth, obj: int, onto: int | None = None) -> None:
    """Select object `obj` (key obj + 1), pick it onto object `onto`'s points (M), snap (Space)."""
    ctl.press(str(obj + 1))
    picker.pairs = _pairs(ctl.session, truth, obj, obj if onto is None else onto, ctl.session.step)
    ctl.press("M")
    ctl.press("Space")


def test_a_first_annotation_from_an_empty_capture_to_a_validated_export(capture_dir, truth, tmp_path, capsys,
                                                                       monkeypatch):
    from dsr_bench.cli import main

    session = Session.open(capture_dir, tmp_path / "work")
    picker = ScriptedPicker()
    ctl = keys.Controller(session, picker=picker, echo=lambda text: None)
    names = [o.name for o in session.capture.objects]
    # a fresh capture: the message says what the work is, the next line what to do first
    assert ctl.view.message == "new: place the 3 objects at step 0, then N carries them to steps 1..3"
    assert ctl.view.hint.startswith(f"next: find object 1, {names[0]} (a ") and "M, shift+click 3+ points" in \
        ctl.view.hint
    # object selected
    ctl.press("2")
    assert ctl.view.message.startswith(f"selected object 2, {names[1]} (a ") and "not placed yet" in ctl.view.message
    assert ctl.view.hint.startswith(f"next: find object 2, {names[1]}")
    # picked on the wrong blob (box_2's points for the can): the picks and the snap say so, the next line says undo
    picker.pairs = _pairs(session, truth, 1, 2)
    ctl.press("M")
    assert ctl.view.message.startswith("pose initialised from") and "wrong object?" in ctl.view.message
    assert f"object 3, {names[2]}" in ctl.view.message and ctl.view.hint.startswith("next: Z undoes")
    ctl.press("Space")
    assert "wrong object?" in ctl.view.message and ctl.view.hint.startswith("next: Z undoes")
    while session.status()[1] != "unset":
        ctl.press("Z")
    assert ctl.view.message.startswith("undone:") and ctl.view.hint.startswith(f"next: find object 2, {names[1]}")
    # the right blob: a fit; then the next object to place, until step 0 is done
    picker.pairs = _pairs(session, truth, 1, 1)
    ctl.press("M")
    assert ctl.view.message.startswith("pose initialised from") and "wrong object" not in ctl.view.message
    assert ctl.view.hint.startswith(f"next: Space snaps {names[1]}")
    ctl.press("Space")
    assert ctl.view.message.startswith("snapped: rmse") and "wrong object" not in ctl.view.message
    assert ctl.view.hint.startswith("next: press 3 to select object 3")
    for obj in (2, 0):
        _place(ctl, picker, truth, obj)
        assert ctl.view.message.startswith("snapped: rmse"), ctl.view.message
    assert ctl.view.hint.startswith("next: step 0 is done: N goes to step 1")
    # the pick windows showed the cloud muted, as the 3D view does
    cloud_colours = [c for c in picker.colours if c is not None and c.shape[1] == 3][0]
    hi, lo = cloud_colours.max(1), cloud_colours.min(1)
    assert np.all(hi - lo <= images.MUTED_SATURATION * hi + 1e-9)
    # the steps: N carries them forward
    for step in range(1, session.num_steps + 1):
        ctl.press("N")
        assert ctl.view.message.startswith(f"step {step}"), ctl.view.message
        for obj in [i for i, status in enumerate(session.status()) if status not in ("snapped", "confirmed")]:
            ctl.press(str(obj + 1))  # a carried pose left unchecked: snap it, as the next line says
            assert ctl.view.hint.startswith(f"next: Space snaps {names[obj]}")
            ctl.press("Space")
    # every step done: the next line says how to export and validate
    out = f"{session.capture.name}.h5"
    assert ctl.view.hint.startswith(f"next: all {session.num_steps + 1} steps are done: Esc quits")
    assert f"--export {out}, then dsr-bench validate {out}" in ctl.view.hint
    session.close()
    # export (what the line says, with this test's --work) and validate the file alone
    monkeypatch.chdir(tmp_path)
    assert main(["annotate", str(capture_dir), "--work", str(tmp_path / "work"), "--export", out]) == 0
    capsys.readouterr()
    assert main(["validate", out]) == 0
    said = " ".join(capsys.readouterr().out.split())
    assert said.startswith(f"valid: {out} is a sequence of 3 pushes and 3 objects (source annotated)")
    assert "split pins" in said and "need a dataset directory" in said


def test_the_objects_row_shows_each_objects_preview_framed_in_its_colour(capture_dir, tmp_path):
    session = Session.open(capture_dir, tmp_path / "work")
    view = keys.ViewState()
    pan = panel.Panel(session, view, text_width=300, image_width=320, font_size=12)
    row = pan.objects_row()
    assert row.shape[1] == 300
    frames = np.round(images.object_colors(session.status(), session.selected) * 255).astype(np.uint8)
    for rgb in np.unique(frames, axis=0):  # the selected object's frame and the unset ones'
        assert np.all(row == rgb, axis=-1).sum() >= 4 * panel.PREVIEW_SIZE
    # each preview shows the mesh in its own colour, muted as the views show it
    for obj in range(session.num_objects):
        preview = pan._preview(obj, 40)
        drawn = np.any(preview != panel.PREVIEW_BACKGROUND, axis=-1)
        assert 0.05 < drawn.mean() < 0.9
        colour = images.muted_colors(np.asarray(session.capture.objects[obj].identity["color"]))
        mean = preview[drawn].mean(0) / 255
        assert np.abs(mean / mean.sum() - colour / colour.sum()).sum() < 0.05  # its hue, shaded
    # the panel holds the row: under the camera images when they leave room, else above the keys
    image = pan.image()
    assert np.all(image == frames[0], axis=-1).sum() >= 4 * panel.PREVIEW_SIZE
    # each placed object's number beside its outline, in the outline's colour (the images stay muted otherwise)
    session.init_from_picks(0, *_pairs(session, session.capture.truth_poses(), 0, 0))
    name = next(iter(session.capture.cameras))
    small = images.scaled_camera(session.capture.cameras[name].camera, 320)
    base = np.full((small.height, small.width, 3), 90, np.uint8)
    colours = images.object_colors(session.status(), session.selected)
    outlined = pan.overlay(name, small, base, session.poses(), colours, session.selected)
    labelled = pan.label(name, small, outlined, session.poses(), colours, session.selected)
    sel = np.round(np.array(images.SELECTED_COLOR) * 255).astype(np.uint8)
    assert np.all(labelled == sel, axis=-1).sum() > np.all(outlined == sel, axis=-1).sum() + 10
    changed = np.any(labelled != outlined, axis=-1)
    assert np.all((np.all(labelled == sel, axis=-1) | (np.ptp(labelled.astype(int), axis=-1) <= 2))[changed])
    session.close()


def test_a_box_preview_is_its_silhouette_at_the_given_scale():
    trimesh = pytest.importorskip("trimesh")
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    small = images.mesh_preview(np.asarray(box.vertices), np.asarray(box.faces), 64, 0.4, (1.0, 0.0, 0.0))
    large = images.mesh_preview(np.asarray(box.vertices), np.asarray(box.faces), 64, 0.2, (1.0, 0.0, 0.0))
    area = [np.any(p != (44, 44, 50), axis=-1).sum() for p in (small, large)]
    assert 3.0 < area[1] / area[0] < 5.0  # half the extent: four times the area
    assert np.all(small[np.any(small != (44, 44, 50), axis=-1)][:, 1:] == 0)  # shaded red, nothing else
    lit = np.unique(large[np.any(large != (44, 44, 50), axis=-1)][:, 0])
    assert len(lit) >= 3  # its three visible faces shaded apart


def test_wrong_object_by_shape_when_the_capture_gives_no_colours(capture_dir, truth, tmp_path):
    session = Session.open(capture_dir, tmp_path / "work")
    for item in session.capture.objects:  # a real capture's objects: names and meshes, no colours
        item.identity.pop("color", None)
    session.init_from_picks(1, *_pairs(session, truth, 1, 2))  # the can on the box's points
    session.snap(1)
    said = guide.wrong_object(session, 1)
    assert said is not None and said.startswith(f"wrong object? its points fit object 3, "
                                                f"{session.capture.objects[2].name}")
    assert guide.wrong_object(session, 1, other_shapes=False) is None  # after the picks alone: not tried
    session.undo()
    session.undo()
    session.init_from_picks(1, *_pairs(session, truth, 1, 1))
    session.snap(1)
    assert guide.wrong_object(session, 1) is None  # its own points
    session.close()


def test_wrong_object_on_a_placed_objects_points(capture_dir, truth, tmp_path):
    session = Session.open(capture_dir, tmp_path / "work")
    session.init_from_picks(2, *_pairs(session, truth, 2, 2))
    session.snap(2)
    session.place(0, pose_to_matrix(truth[0, 2]))  # box_0 right where box_2 is
    said = guide.wrong_object(session, 0, other_shapes=False)
    assert said is not None and f"of its points are those of object 3, {session.capture.objects[2].name}" in said
    assert guide.wrong_object(session, 2, other_shapes=False) is not None  # and box_2 on box_0's: both said
    session.place(0, pose_to_matrix(truth[0, 0]))
    assert guide.wrong_object(session, 0) is None and guide.wrong_object(session, 2) is None
    session.close()


def test_residual_colours_are_red_where_a_misplaced_object_really_is(capture_dir, truth, tmp_path):
    from scipy.spatial import cKDTree

    from dsr_bench.annotator import align
    from dsr_bench.annotator.thresholds import THRESHOLDS

    session = Session.open(capture_dir, tmp_path / "work")
    for obj in range(session.num_objects):
        session.place(obj, pose_to_matrix(truth[0, obj]))
    wrong = truth[0, 1].copy()
    wrong[0] += 0.05  # the can placed 5 cm off its points
    session.place(1, pose_to_matrix(wrong))
    points = session.cloud()[0]
    colours = session.residual_colors()
    true_surface = align.posed_samples(session.samples(1), pose_to_matrix(truth[0, 1]))[0]
    on_it = (cKDTree(true_surface).query(points)[0] < 0.002) & (points[:, 2] > 0.01)
    assert on_it.sum() > 50
    posed = np.vstack([align.posed_samples(session.samples(k), pose_to_matrix(session.poses()[k]))[0]
                       for k in range(session.num_objects)])
    far = on_it & (cKDTree(posed).query(points)[0] >= images.RESIDUAL_SCALE)  # 1 cm and more from every mesh
    assert far.sum() > 0.5 * on_it.sum()
    red = images.residual_ramp(np.ones(1))[0]
    assert np.all(np.isclose(colours[far], red))  # red, also beyond 2 cm (where they were grey)
    # the other objects' surfaces are near their meshes (blue), the table stays grey
    other = (cKDTree(align.posed_samples(session.samples(2), pose_to_matrix(truth[0, 2]))[0]).query(points)[0]
             < 0.001) & (points[:, 2] > 0.01)
    assert np.mean(colours[other][:, 2] > 0.5) > 0.9
    near_mesh = cKDTree(posed).query(points)[0] < 2 * images.RESIDUAL_SCALE
    table = (points[:, 2] <= THRESHOLDS.table_margin) | ((points[:, 2] <= images.RESIDUAL_FLOOR) & ~near_mesh)
    assert table.sum() > 1000 and np.all(np.ptp(colours[table], axis=1) < 1e-9)
    session.close()


def test_every_fit_verdict_has_a_reason(capture_dir, tmp_path):
    """The annotation-error benchmark's verdicts, flagged or not, all say why (a miss names what let it
    through) and carry their named checks: flagged exactly when a check failed, each check with its reason, and an
    accepted true pose checked all the way to the refinement; a FitScore given no reason gets one."""
    sys.path.insert(0, str(Path(__file__).parents[1] / "bench"))
    import bench_annotate_errors as bench

    from dsr_bench.annotator.align import FitScore
    from dsr_bench.annotator.checks import CHECKS

    wrong, right = bench.run_capture(Path(capture_dir), tmp_path / "work", np.random.default_rng(0), steps=[1])
    assert len(wrong) > 30 and len(right) == 3
    for verdict in wrong + right:
        assert verdict["reason"].strip(), verdict
        assert verdict["reason"].startswith("accepted: ") != verdict["flagged"], verdict
        checks = verdict["checks"]
        assert checks and all(c["name"] in CHECKS and c["reason"].strip() for c in checks), verdict
        assert verdict["flagged"] == (not all(c["passed"] for c in checks)), verdict
    for verdict in right:
        if not verdict["flagged"]:
            names = [c["name"] for c in verdict["checks"]]
            assert {"coverage", "rmse", "sinks", "unexplained", "snap_move", "snap_turn"} <= set(names), names
    assert any(not v["flagged"] for v in right)
    assert FitScore(0.001, 0.9, 0.5, True, "").reason and FitScore(0.001, 0.9, 0.5, False, " ").reason


def test_a_private_runtime_dir_where_the_environment_has_none(monkeypatch, tmp_path):
    from dsr_bench.annotator import opening as win

    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    made = win.ensure_runtime_dir()
    assert made is not None and os.environ["XDG_RUNTIME_DIR"] == made and os.path.isabs(made)
    info = os.stat(made)
    assert stat.S_ISDIR(info.st_mode) and info.st_uid == os.getuid() and stat.S_IMODE(info.st_mode) == 0o700
    assert win.ensure_runtime_dir() is None  # a valid one is kept
    monkeypatch.setenv("XDG_RUNTIME_DIR", "relative/dir")
    assert win.ensure_runtime_dir() not in (None, "relative/dir")
    shared = tmp_path / "shared"
    shared.mkdir(mode=0o755)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(shared))  # others may enter it: not a runtime dir
    assert win.ensure_runtime_dir() != str(shared)


def window_child(capture_dir: str, work_dir: str, out: str) -> None:
    """Run under Xvfb at 1366 x 768: open the window on a fresh capture, place the objects through its keys (a
    scripted picker), save the messages, the panel and the 3D view's projection of the workspace to `out`."""
    from dsr_bench.annotator import window as win
    from dsr_bench.constants import GRID_BOUNDS

    session = Session.open(Path(capture_dir), Path(work_dir))
    truth = session.capture.truth_poses()
    picker = ScriptedPicker()
    window = win.AnnotatorWindow(session, screen=(1366, 768), picker=picker, echo=lambda text: None)
    window.render()
    said = [(window.ctl.view.message, window.ctl.view.hint)]
    fresh = window.panel_screenshot()
    params = window.vis.get_view_control().convert_to_pinhole_camera_parameters()
    from dsr_bench.annotator.picking import project

    corners = np.array([[x, y, z] for x in GRID_BOUNDS[0] for y in GRID_BOUNDS[1] for z in GRID_BOUNDS[2]])
    uv, depth = project(corners, params.intrinsic.intrinsic_matrix, params.extrinsic)
    for obj, onto in ((0, 2), (0, 0), (1, 1), (2, 2)):
        window.press(str(obj + 1))
        if onto != obj:  # the wrong blob first, then undone
            picker.pairs = _pairs(session, truth, obj, onto)
            window.press("M")
            window.render()
            said.append((window.ctl.view.message, window.ctl.view.hint))
            while session.status()[obj] != "unset":
                window.press("Z")
            continue
        picker.pairs = _pairs(session, truth, obj, obj)
        window.press("M")
        window.press("Space")
        window.render()
        said.append((window.ctl.view.message, window.ctl.view.hint))
    placed = window.panel_screenshot()
    expected = window.panel.image()
    window.close()
    np.savez(out, said=np.array(said), fresh=fresh, placed=placed, expected=expected, uv=uv, depth=depth,
             size=[params.intrinsic.width, params.intrinsic.height])


def test_the_window_tells_a_newcomer_each_step_under_xvfb(capture_dir, tmp_path):
    out = tmp_path / "window.npz"
    code = (f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); import test_annotator_guide as t; "
            f"t.window_child({str(capture_dir)!r}, {str(tmp_path / 'work')!r}, {str(out)!r})")
    with virtual_display("1366x768x24") as display_env:
        env = {k: v for k, v in display_env.items() if k != "XDG_RUNTIME_DIR"}
        env["PYTHONPATH"] = str(Path(__file__).parents[1])
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                              cwd=str(Path(__file__).parents[1]))
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    assert "XDG_RUNTIME_DIR" not in proc.stderr  # libwayland's complaint: the window gave itself a runtime dir
    shots = np.load(out)
    said = [tuple(map(str, pair)) for pair in shots["said"]]
    assert said[0][0].startswith("new: place the 3 objects") and said[0][1].startswith("next: find object 1")
    assert "wrong object?" in said[1][0] and said[1][1].startswith("next: Z undoes")
    assert all(message.startswith("snapped") for message, _ in said[2:]), said
    assert said[-1][1].startswith("next: step 0 is done: N goes to step 1")
    # the first 3D view shows the whole workspace: every corner of the grid inside it
    width, height = (int(v) for v in shots["size"])
    uv = shots["uv"]
    assert np.all(shots["depth"] > 0)
    assert np.all((uv >= 0) & (uv <= [width, height]))
    # the panel window shows what the panel draws (its "next:" line in its colour, the objects' previews)
    fresh, placed = shots["fresh"], shots["placed"]
    assert np.array_equal(placed, shots["expected"])
    hint = np.array(panel.HINT_COLOR, np.uint8)
    assert np.all(np.abs(fresh.astype(int) - hint) <= 2, axis=-1).sum() > 50
    assert fresh.shape[:2] == (768 - 90, placed.shape[1])  # the panel window of the 1366 x 768 layout
