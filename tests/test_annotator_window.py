"""The annotator window: its pure parts (silhouettes and outlines, key table, help text, panel, controller) on a
real Session without a display, and the real open3d window driven under a virtual display (Xvfb) with screenshot
checks."""

from __future__ import annotations

import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("open3d")
pytest.importorskip("PIL")

from dsr_bench.annotator import images, keys, panel  # noqa: E402
from dsr_bench.annotator import window as win  # noqa: E402
from dsr_bench.annotator.session import Session  # noqa: E402
from dsr_bench.errors import UserError  # noqa: E402
from dsr_bench.geometry import make_camera, pose_to_matrix  # noqa: E402
from helpers import virtual_display  # noqa: E402

#: The Session methods the window calls (annotator/session.py, see the annotator docs) ...
SESSION_METHODS = {"poses", "status", "cloud", "go_to", "select", "init_from_picks", "init_from_previous", "nudge",
                   "snap", "confirm", "undo", "redo", "score", "stored_score", "residual_colors", "progress_table",
                   "recarry", "next_to_check"}
#: ... and the properties it reads.
SESSION_PROPERTIES = {"step", "selected", "num_steps", "num_objects", "undo_depth", "redo_depth"}
#: The calls that change the annotation.
MUTATING = {"go_to", "init_from_picks", "init_from_previous", "nudge", "snap", "confirm", "undo", "redo", "recarry"}


# --- a tiny capture and sessions on it ----------------------------------------------------------------


def _box(extents) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    mesh = trimesh.creation.box(extents=extents)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def _yaw(deg: float) -> np.ndarray:
    a = np.deg2rad(deg) / 2
    return np.array([0.0, 0.0, np.sin(a), np.cos(a)])


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    """A simulated 2-push capture of 2 objects at 120x160 (generators/capture.py), or a hand-made one."""
    out = tmp_path_factory.mktemp("capture") / "seq"
    return _make_capture(out)


def _make_capture(out: Path) -> Path:
    try:
        from dsr_bench.generators.capture import generate_capture
    except ImportError:
        generate_capture = None
    if generate_capture is not None:
        return generate_capture(out, name="seq", seed=1, steps=2, objects_per_scene=2, image_shape=(120, 160))
    from dsr_bench.dataset.capture import CaptureCamera, write_capture

    cams = {n: make_camera(n, 120, 160) for n in ("front", "back")}
    cameras = {n: CaptureCamera(n, c.height, c.width, c.intrinsics, c.extrinsics, 0.001) for n, c in cams.items()}
    meshes = [_box((0.06, 0.04, 0.05)), _box((0.05, 0.05, 0.04))]
    poses = np.array([[[0.45, 0.0, 0.025, *_yaw(10)], [0.58, 0.05, 0.02, *_yaw(-20)]]] * 3)
    depth = {n: np.full((120, 160), 0.6) for n in cams}
    color = {n: np.full((120, 160, 3), 128, np.uint8) for n in cams}
    return write_capture(out, name="seq", cameras=cameras, colors=[color] * 3, depths=[depth] * 3,
                         actions=np.zeros((2, 3), int), pushes_world=np.zeros((2, 2, 3)),
                         objects=[(f"box{i}", v, f, {}) for i, (v, f) in enumerate(meshes)], truth_poses=poses)


def _place_at_truth(session: Session) -> None:
    """Every object at its true pose at the current step, through the pick API (8 mesh vertices as picks)."""
    truth = session.capture.truth_poses()[session.step]
    for obj in range(session.num_objects):
        v, _ = session.capture.mesh(obj)
        m = pose_to_matrix(truth[obj])
        session.init_from_picks(obj, v[:8], v[:8] @ m[:3, :3].T + m[:3, 3])


@pytest.fixture(scope="module")
def placed_work(capture_dir, tmp_path_factory) -> Path:
    """An annotation state of the capture: every object placed at step 0, every step visited (carried forward),
    the cursor back at step 0."""
    work = tmp_path_factory.mktemp("placed") / "work"
    session = Session.open(capture_dir, work)
    _place_at_truth(session)
    session.auto()
    session.go_to(0)
    return work


@pytest.fixture
def session(capture_dir, placed_work, tmp_path) -> Session:
    """A real Session on a copy of `placed_work` (step 0, object 0 selected)."""
    shutil.copytree(placed_work, tmp_path / "work")
    return Session.open(capture_dir, tmp_path / "work")


class Recorder:
    """Wraps a session and records the names of the Session methods called on it."""

    def __init__(self, session):
        object.__setattr__(self, "_session", session)
        object.__setattr__(self, "calls", [])

    def __getattr__(self, name):
        value = getattr(self._session, name)
        if callable(value) and name in SESSION_METHODS:
            def call(*args, **kwargs):
                self.calls.append(name)
                return value(*args, **kwargs)
            return call
        return value


@pytest.fixture(scope="module")
def capture(capture_dir):
    from dsr_bench.dataset.capture import load_capture

    return load_capture(capture_dir)


def _spread(points, *_args) -> np.ndarray:
    """A picker: 4 points far apart (first, last and two between)."""
    return np.linspace(0, len(points) - 1, 4).astype(int)


# --- silhouettes and outlines --------------------------------------------------------------------------


def _hull_distance(points_uv: np.ndarray, corners_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(inside (P,), distance to the boundary (P,), perimeter) of pixel centres relative to the convex hull of
    the corners."""
    from scipy.spatial import ConvexHull

    hull = corners_uv[ConvexHull(corners_uv).vertices]
    a, b = hull, np.roll(hull, -1, axis=0)
    ab = b - a
    ap = points_uv[:, None, :] - a[None]
    t = np.clip((ap * ab).sum(-1) / (ab * ab).sum(-1), 0, 1)
    dist = np.linalg.norm(ap - t[..., None] * ab, axis=-1).min(1)
    cross = ab[None, :, 0] * ap[..., 1] - ab[None, :, 1] * ap[..., 0]
    inside = np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)
    return inside, dist, float(np.linalg.norm(ab, axis=1).sum())


def test_outline_lies_on_projected_box_silhouette_boundary():
    camera = make_camera("front", 240, 320)
    extents = np.array([0.10, 0.06, 0.05])
    vertices, faces = _box(extents)
    pose = np.array([0.5, 0.02, 0.025, *_yaw(30)])
    image = np.zeros((240, 320, 3), np.uint8)
    image[..., 2] = 40
    out = images.outline_overlay(image, camera, [(vertices, faces)], pose[None], colors=np.array([[1.0, 1.0, 1.0]]))
    assert out.shape == image.shape and out.dtype == np.uint8
    assert np.all(image[..., 2] == 40) and np.all(image[..., :2] == 0)  # input untouched
    changed = np.any(out != image, axis=-1)
    assert np.all(out[changed] == 255) and np.array_equal(out[~changed], image[~changed])

    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * extents / 2
    corners_uv, z = camera.project(corners @ pose_to_matrix(pose)[:3, :3].T + pose[:3])
    assert np.all(z > 0)
    v, u = np.nonzero(np.ones((240, 320), bool))
    inside, dist, perimeter = _hull_distance(np.stack([u, v], 1).astype(float), corners_uv)
    inside, dist = inside.reshape(240, 320), dist.reshape(240, 320)
    # every outline pixel is a silhouette pixel next to its boundary ...
    assert changed.sum() > 0
    assert np.all(inside[changed] | (dist[changed] < 0.05))
    assert dist[changed].max() <= 1.5
    # ... the interior and the outside stay untouched ...
    assert not np.any(changed & inside & (dist > 1.5))
    assert not np.any(changed & ~inside & (dist > 0.05))
    # ... and the outline goes all the way round (one pixel per pixel of perimeter, roughly)
    assert 0.7 * perimeter < changed.sum() < 1.6 * perimeter


def test_outline_selected_on_top_and_thicker():
    camera = make_camera("front", 120, 160)
    mesh = _box((0.06, 0.06, 0.06))
    poses = np.array([[0.5, 0.0, 0.03, 0, 0, 0, 1], [0.5, 0.0, 0.03, 0, 0, 0, 1]])  # coincident objects
    image = np.zeros((120, 160, 3), np.uint8)
    out = images.outline_overlay(image, camera, [mesh, mesh], poses, selected=0)
    sel = np.all(out == np.round(np.array(images.SELECTED_COLOR) * 255).astype(np.uint8), axis=-1)
    white = np.all(out == 255, axis=-1)
    assert sel.sum() > 0 and white.sum() == 0  # the selected outline covers the other, identical one
    one = images.outline_overlay(image, camera, [mesh], poses[:1], colors=np.ones((1, 3)))
    assert sel.sum() > np.all(one == 255, axis=-1).sum()  # selected: one pixel thicker
    assert np.array_equal(images.outline_overlay(image, camera, [], np.zeros((0, 7))), image)
    with pytest.raises(ValueError, match="does not match camera"):
        images.outline_overlay(image[:-1], camera, [mesh], poses[:1])


def _edge_distance(camera, vertices, faces, pose, pixels: np.ndarray) -> np.ndarray:
    """Distance (px) of pixel centres (P, 2) (row, col) to the nearest projected edge of the mesh's part in front."""
    from dsr_bench.geometry import rigid_inverse, transform_points

    points = transform_points(rigid_inverse(camera.extrinsics), images.posed(vertices, pose))
    points, faces = images.clip_near(points, faces)
    k = camera.intrinsics
    uv = points[:, :2] / points[:, 2:3] * np.diag(k)[:2] + k[:2, 2]
    a, b = uv[faces].reshape(-1, 2), uv[np.roll(faces, -1, axis=1)].reshape(-1, 2)
    p = pixels[:, ::-1].astype(np.float64)[:, None]
    t = np.clip(((p - a) * (b - a)).sum(-1) / ((b - a) ** 2).sum(-1), 0, 1)
    return np.linalg.norm(p - (a + t[..., None] * (b - a)), axis=-1).min(1)


@pytest.mark.parametrize("where", ["table", "image edge", "straddling the camera plane"])
def test_silhouettes_match_a_full_image_ray_cast(where):
    import open3d as o3d

    camera = make_camera("front", 90, 120)
    vertices, faces = _box((0.08, 0.05, 0.05))
    if where == "table":
        pose = np.array([0.5, 0.0, 0.025, *_yaw(20)])
    elif where == "image edge":
        pose = np.array([1.1, 0.1, 0.025, *_yaw(-10)])  # its centre projects just outside the right edge
    else:  # a long box through the camera's centre plane: some vertices behind it
        vertices = vertices * [1.0, 30.0, 1.0]
        pose = np.array([*camera.extrinsics[:3, 3] + [0.0, 0.0, -0.1], 0, 0, 0, 1])
    masks = images.silhouette_masks(camera, [(vertices, faces)], pose[None])
    assert masks.shape == (1, 90, 120) and masks.dtype == bool
    # reference: open3d's ray caster (float32) through every pixel centre
    dirs = camera.ray_directions_world().reshape(-1, 3)
    rays = np.hstack([np.broadcast_to(camera.extrinsics[:3, 3], dirs.shape), dirs]).astype(np.float32)
    world = images.posed(vertices, pose)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(world.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    reference = np.isfinite(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()).reshape(90, 120)
    assert reference.any() and masks[0].sum() > 0.99 * reference.sum()
    differ = np.argwhere(masks[0] != reference)  # only centres on a triangle's edge may go either way
    assert len(differ) == 0 or _edge_distance(camera, vertices, faces, pose, differ).max() < 1e-3
    if where == "image edge":
        assert reference[:, -1].any() and not reference.all()
    unset = images.silhouette_masks(camera, [(vertices, faces)], np.full((1, 7), np.nan))
    assert not unset.any()


def test_clip_near_keeps_the_part_in_front():
    points = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, -1.0], [0.0, 1.0, -1.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]])
    faces = np.array([[0, 1, 2],  # one vertex in front: one triangle
                      [0, 1, 3],  # two in front (shares the crossing edge 0-1): two triangles
                      [0, 3, 4]])  # all in front: kept as it is
    out, kept = images.clip_near(points, faces, near=0.5)
    assert np.array_equal(out[:5], points) and np.all(out[np.unique(kept), 2] >= 0.5)
    assert len(kept) == 4 and [0, 3, 4] in kept.tolist()
    # one cut point per crossing edge (0-1 shared, 0-2, 1-3), on the plane and on its edge
    cuts = out[5:]
    assert len(cuts) == 3 and np.allclose(cuts[:, 2], 0.5)
    for expected in ([0.25, 0.0, 0.5], [0.0, 0.25, 0.5], [1.0, 0.75, 0.5]):
        assert any(np.allclose(c, expected) for c in cuts)

    def area(tri):
        return 0.5 * np.linalg.norm(np.cross(tri[1] - tri[0], tri[2] - tri[0]))

    # the triangles cover each triangle's part in front exactly: the tip (1/4 scale) of the first, all but the
    # tip (3/4 scale) behind of the second
    total = sum(area(out[f]) for f in kept if 4 not in f)
    assert np.isclose(total, area(points[[0, 1, 2]]) / 16 + area(points[[0, 1, 3]]) * (1 - 9 / 16))
    assert len(images.clip_near(points - [0, 0, 10], faces, near=0.5)[1]) == 0  # all behind


def test_outline_of_object_behind_camera_is_empty():
    camera = make_camera("front", 60, 80)
    behind = camera.extrinsics[:3, 3] - 0.5 * camera.extrinsics[:3, 2]
    out = images.outline_overlay(np.zeros((60, 80, 3), np.uint8), camera, [_box((0.05, 0.05, 0.05))],
                                 np.array([[*behind, 0, 0, 0, 1]]))
    assert not out.any()


def test_mask_boundary_and_scaled_camera():
    mask = np.zeros((10, 12), bool)
    mask[2:7, 3:9] = True
    edge = images.mask_boundary(mask)
    assert edge.sum() == 2 * 5 + 2 * 6 - 4 and not edge[3:6, 4:8].any()
    assert images.mask_boundary(mask, 3).sum() == mask.sum()
    cam = make_camera("front", 240, 320)
    small = images.scaled_camera(cam, 160)
    assert (small.height, small.width) == (120, 160)
    point = np.array([0.55, 0.05, 0.04])
    assert np.allclose(small.project(point)[0], cam.project(point)[0] / 2)


# --- keys --------------------------------------------------------------------------------------------


def test_keymap_keys_codes_and_help_are_unique_and_complete():
    codes = [keys.glfw_code(k) for k in keys.KEYMAP]
    assert len(set(codes)) == len(codes)  # no two keys share a GLFW code
    assert len({k.upper() for k in keys.KEYMAP}) == len(keys.KEYMAP)
    for required in ("1", "5", "Tab", "Space", "Enter", "Esc", "Z", "Y", "N", "P", "M", "R", "T", "G"):
        assert required in keys.KEYMAP
    help_text = "\n".join(keys.key_help_lines())
    for key, binding in keys.KEYMAP.items():
        assert binding.group in help_text
        assert any(key in line.split() for line in keys.key_help_lines())
    assert {b.method for b in keys.KEYMAP.values()} - {None} <= SESSION_METHODS
    for method in SESSION_METHODS:  # the window's Session interface is the Session's
        assert callable(getattr(Session, method, None)), f"Session has no method {method}"
    for prop in SESSION_PROPERTIES:
        assert isinstance(getattr(Session, prop, None), property), f"Session has no property {prop}"


def test_docs_list_every_key():
    text = (Path(__file__).resolve().parents[1] / "docs" / "annotator.md").read_text()
    assert "\n## Keys\n" in text, "docs/annotator.md lacks its Keys section"
    section = text.split("\n## Keys\n", 1)[1].split("\n## ", 1)[0]
    for key in keys.KEYMAP:
        if key.isdigit() and key not in ("1", "5"):  # written `1` ... `5`
            continue
        assert f"`{key}`" in section, f"docs/annotator.md, Keys: key {key} ({keys.KEYMAP[key].label}) is missing"


@pytest.mark.parametrize("key", list(keys.KEYMAP))
def test_every_key_calls_its_session_method(session, key):
    session.go_to(1)  # so that both 'next' and 'previous' exist
    session.nudge(0, translation=(0.001, 0, 0))  # so that undo has something
    rec = Recorder(session)
    echoed = []
    ctl = keys.Controller(rec, picker=_spread, echo=echoed.append)
    before = session.poses().copy()
    changed = ctl.press(key)
    binding = keys.KEYMAP[key]
    assert "panel" in changed
    if binding.method is None:
        assert not set(rec.calls) & MUTATING, rec.calls
    elif key.isdigit() and int(key) > session.num_objects:
        assert "select" not in rec.calls and "no object" in ctl.view.message
    else:
        assert binding.method in rec.calls, (key, rec.calls)
    if binding.method == "nudge":
        assert "meshes" in changed and not np.allclose(session.poses(), before)
    if key == "F":
        assert echoed and "step" in echoed[0]
    if key == "Esc":
        assert ctl.view.quit


def test_nudges_use_view_steps_and_frame(session):
    ctl = keys.Controller(session, echo=lambda s: None)
    p0 = session.poses()[0].copy()
    ctl.press("d")
    assert np.allclose(session.poses()[0][:3] - p0[:3], [0.001, 0, 0])
    ctl.press("G")
    ctl.press("W")
    assert np.allclose(session.poses()[0][:3] - p0[:3], [0.001, 0.01, 0])
    ctl.press("T")
    assert ctl.view.frame == "object"
    ctl.press("E")  # +z in object axes
    up = pose_to_matrix(p0)[:3, 2]
    assert np.allclose(session.poses()[0][:3] - p0[:3], [0.001, 0.01, 0] + 0.01 * up)
    ctl.press("Z")
    assert np.allclose(session.poses()[0][:3] - p0[:3], [0.001, 0.01, 0])
    ctl.press("Tab")
    assert session.selected == 1
    ctl.press("5")
    assert session.selected == 1 and "no object 5" in ctl.view.message


def test_a_merged_nudge_moves_its_count_of_steps_in_one_change(session):
    ctl = keys.Controller(session, echo=lambda s: None)
    p0, depth = session.poses()[0].copy(), session.undo_depth
    assert "meshes" in ctl.press("D", count=3)
    assert np.allclose(session.poses()[0][:3] - p0[:3], [0.003, 0, 0]) and session.undo_depth == depth + 1
    assert "+3 mm" in ctl.view.message
    ctl.press("O", count=2)  # +2 degrees of yaw, one change
    assert session.undo_depth == depth + 2 and "+2 deg" in ctl.view.message
    ctl.press("Tab", count=4)  # not a nudge: once
    assert session.selected == 1


def test_session_errors_become_messages(session):
    ctl = keys.Controller(session, echo=lambda s: None)
    changed = ctl.press("C")  # no previous step at step 0
    assert "previous step" in ctl.view.message and changed == {"panel"}
    ctl.press("P")
    assert "no step -1" in ctl.view.message and session.step == 0
    ctl.press("?")
    assert "does nothing" in ctl.view.message
    picks = iter([np.array([0, 1]), np.array([0, 1])])
    ctl.picker = lambda *a: next(picks)
    ctl.press("M")
    assert "need 3 or more" in ctl.view.message
    picks = iter([np.array([0, 1, 2]), np.array([0, 1])])
    ctl.press("M")
    assert "same number" in ctl.view.message
    ctl.picker = None  # no window to pick in
    assert ctl.press("M") == {"panel"} and "needs the annotator window" in ctl.view.message


def test_help_lines_and_panel(session, capture):
    session.nudge(1, translation=(0.0, 0.001, 0.0))
    session.select(1)
    view = keys.ViewState(coarse=True, message="hello")
    lines = panel.help_lines(session, view)
    text = "\n".join(lines)
    assert lines[0].startswith(f"step 0/{capture.num_steps}") and capture.objects[1].name in lines[0]
    assert "status: initialised" in text and keys.format_score(session.score(1)) in text and "rmse" in text
    assert "coarse 10 mm / 5 deg" in text and f"undo {session.undo_depth}   redo 0" in text and "> hello" in text
    assert all(line in lines for line in keys.key_help_lines())
    image = panel.Panel(session, view).image()
    h, w = capture.cameras["front"].height, capture.cameras["front"].width
    img_h = round(h * panel.PANEL_IMAGE_WIDTH / w)
    assert image.dtype == np.uint8 and image.shape[1] == panel.PANEL_TEXT_WIDTH + panel.PANEL_IMAGE_WIDTH
    assert image.shape[0] >= 2 * img_h
    text_area = image[:, : panel.PANEL_TEXT_WIDTH]
    assert (text_area.max(-1) > 200).sum() > 500  # text was drawn
    selected_rgb = np.round(np.array(images.SELECTED_COLOR) * 255).astype(np.uint8)
    assert np.all(image[:, panel.PANEL_TEXT_WIDTH:] == selected_rgb, axis=-1).sum() > 20  # the selected outline


@pytest.mark.parametrize("screen", [(1920, 1080), (1600, 1000), (1024, 700)])
def test_panel_is_drawn_at_its_window_size_with_the_legend(session, screen):
    lay = win.layout_for(session, screen)
    view = keys.ViewState(message="No point has been picked")
    pan = panel.Panel(session, view, text_width=lay.text_width, image_width=lay.image_width,
                      font_size=lay.font_size, height=lay.panel[3])
    image = pan.image()
    assert image.shape == (lay.panel[3], lay.panel[2], 3)  # exactly the panel window: shown 1:1, nothing cut
    text = image[:, : lay.text_width]
    for label, color in panel.LEGEND:  # a swatch of every mesh colour in the text column
        rgb = np.round(np.asarray(color) * 255).astype(np.uint8)
        assert np.all(text == rgb, axis=-1).sum() >= 25, label
    ramp = np.round(images.residual_ramp(np.array([0.0, 0.5, 1.0])) * 255).astype(np.uint8)
    for rgb in ramp:  # the residual scale's ends and middle
        assert np.all(np.abs(text.astype(int) - rgb) <= 3, axis=-1).sum() >= 5
    # the camera images are muted: every saturated pixel there is an outline in a mesh colour
    cam = session.capture.cameras["front"]
    title_h, img_h = lay.font_size + 5, round(cam.height * lay.image_width / cam.width)
    rows = np.r_[title_h:title_h + img_h, 2 * title_h + img_h:2 * (title_h + img_h)]  # the images, not their titles
    cams = image[rows, lay.text_width:].reshape(-1, 3).astype(np.float64) / 255
    mx, mn = cams.max(-1), cams.min(-1)
    saturated = cams[(mx - mn) > images.MUTED_SATURATION * mx + 3 / 255]  # beyond rounding to uint8
    outline_rgb = np.round(np.array([c for _, c in panel.LEGEND]) * 255) / 255
    assert len(saturated) > 20
    assert np.abs(saturated[:, None] - outline_rgb[None]).max(-1).min(1).max() < 1e-6
    # the legend lies below the text rows and within the window on 1600 x 1000 and larger
    natural = panel.Panel(session, view, text_width=lay.text_width, image_width=lay.image_width,
                          font_size=lay.font_size).image()
    if screen[1] >= 1000:
        assert natural.shape[0] <= lay.panel[3]


def test_the_shown_cloud_covers_every_object_and_follows_the_state(session):
    from scipy.spatial import cKDTree

    from dsr_bench.annotator import align
    from dsr_bench.annotator.session import DISPLAY_TABLE_VOXEL, DISPLAY_VOXEL, voxel_subset
    from dsr_bench.annotator.thresholds import THRESHOLDS

    points, colors, _ = session.cloud()
    index = session.shown()
    assert len(index) < len(points) and np.all(np.diff(index) > 0)  # a subset, each point once, in cloud order
    assert np.array_equal(voxel_subset(points, DISPLAY_VOXEL, DISPLAY_TABLE_VOXEL, THRESHOLDS.table_margin), index)
    # every point the cameras measured has a drawn point within its cube's diagonal: no surface left out
    high = points[:, 2] > THRESHOLDS.table_margin
    for part, voxel in ((high, DISPLAY_VOXEL), (~high, DISPLAY_TABLE_VOXEL)):
        d, _ = cKDTree(points[index][part[index]]).query(points[part])
        assert d.max() <= voxel * np.sqrt(3) + 1e-9
    # each object's measured surface (cloud points within 3 mm of its posed samples) is drawn densely
    drawn = cKDTree(points[index])
    for obj in range(session.num_objects):
        surface = align.posed_samples(session.samples(obj), pose_to_matrix(session.poses()[obj]))[0]
        d, _ = cKDTree(surface).query(points)
        on_it = (d < 0.003) & high
        assert on_it.sum() > 30
        assert drawn.query(points[on_it])[0].max() <= DISPLAY_VOXEL * np.sqrt(3) + 1e-9
        assert (d[index] < 0.003).sum() >= 0.25 * on_it.sum()
    # what the window draws: the shown points, the capture's colours or the residual's of the current poses
    ctl = keys.Controller(session, echo=lambda text: None)
    shown, shown_colors = ctl.cloud()
    assert np.array_equal(shown, points[index]) and np.array_equal(shown_colors, colors[index])
    ctl.press("R")
    _, residual = ctl.cloud()
    assert np.array_equal(residual, session.residual_colors()[index])  # only the shown points, the same colours
    ctl.press("D")  # +1 mm: the residual colours near the moved object follow it
    moved = ctl.cloud()[1]
    assert np.array_equal(moved, session.residual_colors()[index]) and not np.array_equal(moved, residual)
    session.go_to(1)  # another step: its own subset of its own cloud
    assert np.array_equal(ctl.cloud()[0], session.cloud(1)[0][session.shown(1)])


def test_the_panel_redraws_only_what_changed_and_draws_what_a_fresh_one_draws(session, capture):
    lay = win.layout_for(session, (1600, 1000))
    view = keys.ViewState()
    kept = panel.Panel(session, view, text_width=lay.text_width, image_width=lay.image_width,
                       font_size=lay.font_size, height=lay.panel[3], width=lay.panel[2])
    kept.image()
    calls = []
    real = panel.silhouette_masks

    def counting(*args):
        calls.append(args)
        return real(*args)

    panel.silhouette_masks = counting
    try:
        session.nudge(1, translation=(0.002, 0.0, 0.0))  # one object moved: only its outlines are rasterised
        first = kept.image()
        assert len(calls) == len(capture.cameras)
        session.select(1)  # a selection: the thicker outline of the newly selected, the thinner of the other
        view.message = "a message"
        second = kept.image()
    finally:
        panel.silhouette_masks = real
    fresh = panel.Panel(session, view, text_width=lay.text_width, image_width=lay.image_width,
                        font_size=lay.font_size, height=lay.panel[3], width=lay.panel[2]).image()
    assert np.array_equal(second, fresh) and not np.array_equal(first, second)
    # the outlines are images.outline_overlay's
    s = session
    cam = next(iter(capture.cameras))
    small = images.scaled_camera(capture.cameras[cam].camera, lay.image_width)
    base = np.full((small.height, small.width, 3), 90, np.uint8)
    meshes = [capture.mesh(i) for i in range(s.num_objects)]
    colors = images.object_colors(s.status(), s.selected)
    assert np.array_equal(kept.overlay(cam, small, base, s.poses(), colors, s.selected),
                          images.outline_overlay(base, small, meshes, s.poses(), colors=colors, selected=s.selected))


def test_residual_scale_is_the_sessions(session):
    colors = session.residual_colors()
    coloured = colors[np.ptp(colors, axis=1) > 1e-6]  # the points near a mesh (the others are grey)
    assert len(coloured) > 50
    ramp = images.residual_ramp(np.linspace(0, 1, 2001))
    from scipy.spatial import cKDTree

    d, _ = cKDTree(ramp).query(coloured)
    assert d.max() < 2e-3  # every residual colour the cloud shows is on the legend's scale


def test_format_score():
    from dsr_bench.annotator.align import FitScore

    assert keys.format_score(None) == "fit: -"
    assert keys.format_score(FitScore(float("nan"), 0.0, 0.0, False, "unset")) == "fit: - (unset)"
    assert keys.format_score(FitScore(0.002, 0.8, 0.9, True, "")) == "fit: rmse 2.0 mm, coverage 0.80, fitness 0.90"
    assert keys.format_score(FitScore(0.002, 0.5, 0.9, False, "coverage 50% < 65%")).endswith(
        ", poor: coverage 50% < 65%")


@pytest.mark.parametrize("display", [None, "wayland only", ":87"])
def test_run_without_display_is_a_user_error(session, monkeypatch, display):
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if display is None:
        monkeypatch.delenv("DISPLAY", raising=False)
    elif display == "wayland only":  # open3d's windows need X11 (XWayland sets DISPLAY)
        if not sys.platform.startswith("linux"):
            pytest.skip("X11 is needed on Linux only")
        monkeypatch.delenv("DISPLAY", raising=False)
        monkeypatch.setenv("WAYLAND_DISPLAY", "wayland-0")
    else:  # a display nobody serves (open3d alone would fall back to an invisible offscreen window)
        if Path(f"/tmp/.X11-unix/X{display[1:]}").exists():
            pytest.skip(f"an X server runs on {display}")
        monkeypatch.setenv("DISPLAY", display)
    with pytest.raises(UserError, match="xvfb-run") as err:
        win.run(session)
    assert "\n" not in str(err.value) and ("DISPLAY is not set" if display != ":87" else display) in str(err.value)


# --- the real window under a virtual display ------------------------------------------------------------

ORANGE_MIN_SATURATION = 0.6


def _orange(image: np.ndarray) -> np.ndarray:
    """Pixels of the selected-object colour (orange) under shading: saturated, hue about 30 degrees."""
    rgb = image.astype(np.float64) / 255
    mx, mn = rgb.max(-1), rgb.min(-1)
    sat = np.where(mx > 0, (mx - mn) / np.maximum(mx, 1e-9), 0)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    hue_ok = (r == mx) & (g > 0.45 * r) & (g < 0.75 * r) & (b < 0.1 * r)  # SELECTED_COLOR is (1, 0.55, 0)
    return hue_ok & (sat > ORANGE_MIN_SATURATION) & (mx > 0.25)


def _view_silhouette(params: dict, vertices, faces, pose) -> np.ndarray:
    from dsr_bench.geometry import Camera

    k = params["intrinsic"]
    cam = Camera("view", int(params["height"]), int(params["width"]), k, np.linalg.inv(params["extrinsic"]))
    return images.silhouette_masks(cam, [(vertices, faces)], pose[None])[0]


def display_child(capture_dir: str, work_dir: str, out: str) -> None:
    """Run in a subprocess under Xvfb: open the window, press keys, save screenshots to `out` (.npz)."""
    session = Session.open(Path(capture_dir), Path(work_dir))  # every object unset
    window = win.AnnotatorWindow(session, width=480, height=360, echo=lambda s: None)
    window.render()
    unset = window.screenshot()
    truth = session.capture.truth_poses()
    for obj in range(session.num_objects):  # exact initial poses through the pick API
        v, _ = session.capture.mesh(obj)
        picks = v[np.unique([v[:, 0].argmin(), v[:, 0].argmax(), v[:, 1].argmin(), v[:, 1].argmax(),
                             v[:, 2].argmax()])]
        m = pose_to_matrix(truth[0][obj])
        session.init_from_picks(obj, picks, picks @ m[:3, :3].T + m[:3, 3])
    window.refresh()
    window.press("V")  # the default view again (it is already: the silhouettes below assume it)
    for _ in range(2):
        window.render()
    obj = int(session.selected)
    pose_before = np.asarray(session.poses()[obj]).copy()
    before = window.screenshot()
    cam = window.vis.get_view_control().convert_to_pinhole_camera_parameters()
    params = {"intrinsic": cam.intrinsic.intrinsic_matrix, "extrinsic": cam.extrinsic,
              "width": cam.intrinsic.width, "height": cam.intrinsic.height}
    window._on_key("G", window.vis)  # through the registered callback's path: coarse steps
    for _ in range(4):
        window._on_key("D", window.vis)  # +x, 4 cm
    window.render()
    after = window.screenshot()
    pose_after = np.asarray(session.poses()[obj]).copy()
    panel_shot = window.panel_screenshot()
    selected_before_keys = int(session.selected)
    real_keys = shutil.which("xdotool") is not None
    messages: list[str] = []
    press = window.ctl.press

    def logged(key, count=1):
        changed = press(key, count)
        messages.append(f"{key}: {window.ctl.view.message}")
        return changed

    window.ctl.press = logged
    if real_keys:  # real X key events through open3d's key callbacks, in the window's own loop
        main, pick = "annotator: 3D", "pick >= 3 cloud points"
        script = [(main, "m", "+" + pick), (pick, "q", "!" + pick),  # pick mode, closed without picks
                  (main, "Tab", "-"), (main, "Escape", "!" + main)]
        typist = _send_keys(script)
        threading.Thread(target=_watchdog, args=(window,), daemon=True).start()
        window.loop()
        alive = bool(window.ctl.view.message == "watchdog")
        typist.kill()
        typist.wait()
    else:
        window.ctl.picker = lambda *a: np.zeros(0, np.int64)
        for key in ("M", "Tab", "Esc"):
            window.press(key)
        alive = window.render()
    selected_after_keys = int(session.selected)
    window.close()
    v, f = session.capture.mesh(obj)
    np.savez(out, unset=unset, before=before, after=after, panel=panel_shot, pose_before=pose_before,
             pose_after=pose_after, sil_before=_view_silhouette(params, v, f, pose_before),
             sil_after=_view_silhouette(params, v, f, pose_after), alive=alive, real_keys=real_keys,
             selected=[selected_before_keys, selected_after_keys], messages=np.array(messages))


XDO_SCRIPT = r"""
set -u
find() { xdotool search --name "$1" 2>/dev/null | head -n 1; }
wait_for() { for _ in $(seq 400); do id=$(find "$1"); [ -n "$id" ] && { echo "$id"; return 0; }; sleep 0.05; done
             return 1; }
while [ $# -ge 3 ]; do
  title=$1 key=$2 until=$3; shift 3
  for _ in $(seq 5); do  # resend when the expected window has not appeared ("+T") / gone ("!T") in 5 s
    id=$(wait_for "$title") || break
    xdotool windowfocus --sync "$id" 2>/dev/null; xdotool key --window "$id" "$key"
    [ "$until" = - ] && { sleep 0.2; break; }
    done=0
    for _ in $(seq 100); do
      case $until in
        +*) [ -n "$(find "${until#+}")" ] && { done=1; break; } ;;
        !*) [ -z "$(find "${until#!}")" ] && { done=1; break; } ;;
      esac
      sleep 0.05
    done
    [ $done = 1 ] && break
  done
done
"""


def _send_keys(script: list[tuple[str, str, str]]) -> subprocess.Popen:
    """Type keys with xdotool from another process (open3d's blocking `run` of the pick window holds the
    GIL): `script` is (window title part, key, until) triples; a key is sent once its window exists and
    again until `until` holds: '-' once, '+T' a window titled T exists, '!T' none does."""
    args = [part for triple in script for part in triple]
    return subprocess.Popen(["bash", "-c", XDO_SCRIPT, "xdo", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def _watchdog(window, timeout: float = 60.0) -> None:
    """Stop the window's loop if it has not quit within `timeout` s (its message then reads 'watchdog'): a guard
    against a hang, under the child's 90 s; on a loaded machine (the suite beside other jobs, load 6) the typed keys
    took longer than 20 s."""
    deadline = time.monotonic() + timeout
    while not window.ctl.view.quit and time.monotonic() < deadline:
        time.sleep(0.05)
    if not window.ctl.view.quit:
        window.ctl.view.message = "watchdog"
        window.ctl.view.quit = True


def _run_child(call: str) -> None:
    """Run `call` (an expression on this module as `t`, e.g. "t.picker_child('out.npz')") in a fresh Python on a
    private virtual display (helpers.virtual_display); fails the test with the child's output when it fails."""
    code = (f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); import test_annotator_window as t; "
            + call)
    with virtual_display("1600x1200x24") as display_env:
        env = {**display_env, "PYTHONPATH": str(Path(__file__).parents[1])}
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=90, env=env,
                              cwd=str(Path(__file__).parents[1]))
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]


def test_window_renders_and_moves_the_selected_mesh_under_xvfb(capture_dir, tmp_path):
    out = tmp_path / "shots.npz"
    _run_child(f"t.display_child({str(capture_dir)!r}, {str(tmp_path / 'work')!r}, {str(out)!r})")
    shots = np.load(out)
    before, after, panel_shot = shots["before"], shots["after"], shots["panel"]
    # objects still unset: no mesh drawn in the selected colour, only the cloud
    assert shots["unset"].std() > 10 and _orange(shots["unset"])[shots["sil_before"]].mean() < 0.3
    assert before.shape == (360, 480, 3) and after.shape == before.shape
    # not blank: many distinct colours, far from a uniform background
    background = np.all(np.abs(before.astype(int) - before[0, 0].astype(int)) < 8, axis=-1)
    assert background.mean() < 0.97 and before.std() > 10
    assert len(np.unique(before.reshape(-1, 3), axis=0)) > 50
    # the nudge moved the selected object 4 cm along +x in table axes
    assert np.allclose(shots["pose_after"][:3] - shots["pose_before"][:3], [0.04, 0, 0], atol=1e-6)
    # the selected mesh is drawn where its pose projects, before and after, and its pixels moved with it
    sil_b, sil_a = shots["sil_before"], shots["sil_after"]
    orange_b, orange_a = _orange(before), _orange(after)
    assert sil_b.sum() > 100
    assert orange_b[sil_b].mean() > 0.5 and orange_a[sil_a].mean() > 0.5
    only_before = sil_b & ~sil_a
    assert only_before.sum() > 20 and orange_a[only_before].mean() < 0.5
    c_b = np.argwhere(orange_b & sil_b).mean(0)
    c_a = np.argwhere(orange_a & sil_a).mean(0)
    expected = np.argwhere(sil_a).mean(0) - np.argwhere(sil_b).mean(0)
    assert np.linalg.norm(expected) > 5
    assert np.linalg.norm((c_a - c_b) - expected) < 3
    # the panel window shows text and the camera images with outlines; Esc ended the loop
    assert panel_shot.std() > 10 and np.any(_orange(panel_shot))
    assert not shots["alive"]  # Esc ended the window's loop (not the watchdog)
    before_keys, after_keys = (int(x) for x in shots["selected"])
    assert after_keys != before_keys  # Tab selected the next object (X key events when xdotool is installed)
    messages = [str(m) for m in shots["messages"]]
    assert [m.split(":")[0] for m in messages] == ["M", "Tab", "Esc"], messages
    assert "need 3 or more" in messages[0]  # pick mode opened its window, which closed with no picks


def picker_child(out: str) -> None:
    """Run under Xvfb: a mesh pick window on a can with sparse samples; click between samples and on nothing."""
    import trimesh
    from scipy.spatial import cKDTree

    from dsr_bench.annotator.picking import PICK_DEPTH_MARGIN, ClickPicker, project

    can = trimesh.creation.cylinder(radius=0.033, height=0.12)
    v, f = np.asarray(can.vertices), np.asarray(can.faces)
    samples = keys.mesh_samples(v, f, count=400)  # sparse: gaps of several pixels between samples
    said: list[str] = []
    picker = ClickPicker(samples, None, "pick test", mesh=(v, f), say=said.append, width=640, height=480)
    for _ in range(3):
        picker.vis.poll_events()
        picker.vis.update_renderer()
    params = picker.vis.get_view_control().convert_to_pinhole_camera_parameters()
    uv, z = project(samples, params.intrinsic.intrinsic_matrix, params.extrinsic)
    depth = np.asarray(picker.vis.capture_depth_float_buffer(do_render=True), np.float64)
    px = np.clip(np.round(uv).astype(int), 0, [depth.shape[1] - 1, depth.shape[0] - 1])
    visible = z <= depth[px[:, 1], px[:, 0]] + PICK_DEPTH_MARGIN
    # a pixel on the drawn mesh between samples: 3-8 px from the nearest visible one
    drawn = np.argwhere(depth > 0)[:, ::-1].astype(np.float64)
    gap, _ = cKDTree(uv[visible]).query(drawn)
    between = drawn[(gap >= 3) & (gap <= 8)][0]
    nearest_visible = np.flatnonzero(visible)[cKDTree(uv[visible]).query(between)[1]]
    hidden_near = int((~visible & (np.linalg.norm(uv - between, axis=1) < 12)).sum())
    got = picker.click(*between)
    first_message = said[-1]
    missed = picker.click(2.0, 2.0)  # a corner: nothing drawn near it
    picker.drop_last()
    left = len(picker.picked)
    picker.done = True
    picker.run()
    np.savez(out, got=-1 if got is None else got, nearest=nearest_visible, visible=visible, hidden_near=hidden_near,
             gap=float(np.linalg.norm(uv[nearest_visible] - between)), missed=-1 if missed is None else missed,
             left=left, said=np.array([first_message, *said[-2:]]), frac_visible=visible.mean())


def test_mesh_pick_window_picks_the_nearest_visible_sample_under_xvfb(tmp_path):
    out = tmp_path / "pick.npz"
    _run_child(f"t.picker_child({str(out)!r})")
    r = np.load(out)
    assert 0.2 < float(r["frac_visible"]) < 0.8  # the far side of the can is hidden by its near side
    assert float(r["gap"]) >= 3  # the click was between samples ...
    assert int(r["got"]) == int(r["nearest"]) and bool(r["visible"][int(r["got"])])  # ... and picked the nearest
    said = [str(m) for m in r["said"]]
    assert said[0].startswith("picked point 1")
    assert int(r["missed"]) == -1 and said[1].startswith("no point within")  # a click on nothing: said so
    assert int(r["left"]) == 0 and "dropped" in said[2]


def mouse_child(out: str) -> None:
    """Run under Xvfb with xdotool: a left drag rotates the pick window's view, a real shift + click picks."""
    import trimesh

    from dsr_bench.annotator.picking import ClickPicker

    can = trimesh.creation.cylinder(radius=0.033, height=0.12)
    v, f = np.asarray(can.vertices), np.asarray(can.faces)
    picker = ClickPicker(keys.mesh_samples(v, f, count=400), None, "mouse test", mesh=(v, f), say=lambda s: None,
                         width=400, height=300, left=0, top=0)

    def frames(n: int = 5) -> None:
        for _ in range(n):
            picker.vis.poll_events()
            picker.vis.update_renderer()
            time.sleep(0.02)

    def xdo(*args: str) -> None:
        subprocess.run(["xdotool", *args], check=True, timeout=10)

    frames()
    view = picker.vis.get_view_control()
    before = view.convert_to_pinhole_camera_parameters().extrinsic.copy()
    wid = subprocess.run(["xdotool", "search", "--name", "mouse test"], capture_output=True, text=True,
                         timeout=10).stdout.split()[0]
    xdo("mousemove", "--window", wid, "200", "150", "mousedown", "1")
    frames(2)
    for i in range(10):
        xdo("mousemove", "--window", wid, str(200 + 10 * i), "150")
        frames(1)
    xdo("mouseup", "1")
    frames()
    rotated = not np.allclose(before, view.convert_to_pinhole_camera_parameters().extrinsic)
    picked_by_drag = len(picker.picked)
    xdo("mousemove", "--window", wid, "200", "150", "keydown", "shift", "click", "1", "keyup", "shift")
    frames()
    np.savez(out, rotated=rotated, picked_by_drag=picked_by_drag, picked=len(picker.picked))
    picker.done = True
    picker.run()


def test_pick_window_mouse_rotates_and_shift_click_picks_under_xvfb(tmp_path):
    if shutil.which("xdotool") is None:
        pytest.skip("xdotool is not installed: no real mouse events")
    out = tmp_path / "mouse.npz"
    _run_child(f"t.mouse_child({str(out)!r})")
    r = np.load(out)
    assert bool(r["rotated"]) and int(r["picked_by_drag"]) == 0  # a plain drag turns the view and picks nothing
    assert int(r["picked"]) == 1  # shift + click on the can's middle picks a sample


def resize_child(capture_dir: str, work_dir: str, out: str) -> None:
    """Run under Xvfb with xdotool: open the window laid out for 1600 x 1000, resize the panel window (as a user
    or window manager would) larger, then smaller, and record what the panel draws after each."""
    from dsr_bench.annotator.layout import panel_layout

    session = Session.open(Path(capture_dir), Path(work_dir))
    _place_at_truth(session)
    window = win.AnnotatorWindow(session, echo=lambda s: None, screen=(1600, 1000))
    cam = next(iter(session.capture.cameras.values())).camera
    wid = subprocess.run(["xdotool", "search", "--name", "annotator: cameras"], capture_output=True, text=True,
                         timeout=10).stdout.split()[0]
    record: dict = {"laid_out": np.array([window.layout.panel[2], window.layout.panel[3], window.panel.image_width])}
    for name, (w, h) in (("larger", (1000, 1150)), ("smaller", (560, 250))):
        subprocess.run(["xdotool", "windowsize", wid, str(w), str(h)], check=True, timeout=10)
        for _ in range(40):  # until GLFW has seen the new size
            window.render()
            if window.panel_window_size() == (w, h):
                break
            time.sleep(0.05)
        window.render()
        shot = window.panel_screenshot()
        record[name] = shot
        record[name + "_image"] = np.asarray(window.panel_image).copy()
        record[name + "_widths"] = np.array([window.panel.text_width, window.panel.image_width])
        record[name + "_expected"] = np.array(panel_layout(w, h, window.layout.text_width,
                                                           image_aspect=cam.height / cam.width,
                                                           max_image_width=cam.width))
        record[name + "_size"] = np.array([w, h])
    window.close()
    np.savez(out, **record)


def test_the_panel_is_laid_out_again_when_its_window_is_resized_under_xvfb(capture_dir, tmp_path):
    if shutil.which("xdotool") is None:
        pytest.skip("xdotool is not installed: no window to resize from outside")
    out = tmp_path / "resize.npz"
    _run_child(f"t.resize_child({str(capture_dir)!r}, {str(tmp_path / 'work')!r}, {str(out)!r})")
    r = np.load(out)
    selected_rgb = np.round(np.array(images.SELECTED_COLOR) * 255).astype(np.uint8)
    for name in ("larger", "smaller"):
        w, h = (int(x) for x in r[name + "_size"])
        # the panel is drawn at the window's new size, 1:1 (the screenshot is the panel image itself, not stretched)
        assert r[name + "_image"].shape == (h, w, 3) and r[name].shape == (h, w, 3)
        assert np.abs(r[name].astype(int) - r[name + "_image"].astype(int)).max() <= 2
        # with the text column and camera images laid out for that size
        assert list(r[name + "_widths"]) == list(r[name + "_expected"])
        text_w = int(r[name + "_widths"][0])
        assert (r[name][:, :text_w].max(-1) > 200).sum() > 300  # text
        assert np.all(r[name][:, text_w:] == selected_rgb, axis=-1).sum() > 10  # the selected outline on an image
    # the test capture's images are 160 px wide: shown at most that wide, smaller where the window is lower
    assert int(r["larger_widths"][1]) >= int(r["laid_out"][2]) > int(r["smaller_widths"][1])


def test_keys_drive_a_real_session(capture_dir, tmp_path):
    session = Session.open(capture_dir, tmp_path / "work")  # every object unset
    rec = Recorder(session)
    echoed: list[str] = []
    ctl = keys.Controller(rec, picker=_spread, echo=echoed.append)
    assert ctl.press("Space") == {"panel"} and "no pose" in ctl.view.message  # unset: a message, no exception
    ctl.press("M")  # picks 4 cloud points and 4 mesh samples (a wrong but valid pose)
    assert rec.calls.count("init_from_picks") == 1 and session.status()[0] == "initialised"
    _place_at_truth(session)
    ctl.press("2")
    assert session.selected == 1
    p0 = session.poses()[1].copy()
    assert "meshes" in ctl.press("A")
    assert np.allclose(session.poses()[1][:3] - p0[:3], [-0.001, 0, 0], atol=1e-9)
    ctl.press("Space")
    assert session.status()[1] in ("snapped", "initialised") and "rmse" in ctl.view.message
    ctl.press("Enter")
    assert session.status()[1] == "confirmed"
    ctl.press("Z")
    assert session.status()[1] != "confirmed" and "undone" in ctl.view.message
    ctl.press("Y")
    assert session.status()[1] == "confirmed"
    assert "cloud" in ctl.press("N") and session.step == 1
    ctl.press("C")
    assert session.status()[1] == "initialised"
    points, colors = ctl.cloud()
    ctl.press("R")
    points_r, colors_r = ctl.cloud()
    assert np.array_equal(points, points_r) and colors_r.shape == colors.shape and not np.allclose(colors_r, colors)
    ctl.press("F")
    assert echoed and session.capture.objects[1].name[:20] in echoed[-1]
    assert f"undo {session.undo_depth}   redo 0" in "\n".join(panel.help_lines(rec, ctl.view))
    assert session.undo_depth > 0
    ctl.press("P")
    assert session.step == 0
    ctl.press("X")  # step 1's object 2 was set by hand (C): nothing carried from step 0 is stale
    assert ctl.view.message.startswith("nothing to re-carry")
    ctl.press("B")  # object 1 at step 0 (picked, unchecked) is the next to look at after object 2, wrapping around
    assert ctl.view.message.startswith("step ") and "object " in ctl.view.message
    ctl.press("Esc")
    assert ctl.view.quit
    assert set(rec.calls) >= {b.method for b in keys.KEYMAP.values()} - {None}
