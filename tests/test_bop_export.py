"""The annotator's BOP export (`dsr-bench annotate --bop`, issue 32 part 3) checked against the BOP format's text
(the BOP toolkit's docs/bop_datasets_format.md), read back by a reader written here from that text, not with the
exporter's code: the layout (camera.json, models/ with models_info.json, test/<scene_id>/), every key, units (mm),
models centred on their bounding box with the poses moved so the scene is unchanged, scene_gt_info's counts and boxes
from the masks and the measured depth, symmetries that map each model onto itself, and a symmetric can's twin scored
small by BOP's symmetry-aware errors (MSSD, ADD-S) while plain ADD is large.

Fixture: the simulated capture of tests/conftest.py (3 objects: box 0 of sides 64 x 108 x 64 mm, a can lying on its
side, box 2 of 66 x 114 x 34 mm; 3 pushes; 240 x 320), posed at its true poses.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dsr_bench.geometry import pose_to_matrix
from helpers import place_from_truth

CAMERA_KEYS = {"cx", "cy", "fx", "fy", "width", "height", "depth_scale"}
SCENE_CAMERA_KEYS = {"cam_K", "depth_scale", "cam_R_w2c", "cam_t_w2c"}
SCENE_GT_KEYS = {"obj_id", "cam_R_m2c", "cam_t_m2c"}
GT_INFO_KEYS = {"bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib", "visib_fract"}
INFO_KEYS = {"diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z"}


# --- a reader written from the format's text ----------------------------------------------------------------------


def read_json(path: Path) -> dict:
    """A BOP json file: its string keys that are numbers (image ids, object ids) as ints."""
    d = json.loads(path.read_text())
    return {int(k) if isinstance(k, str) and k.isdigit() else k: v for k, v in d.items()} if isinstance(d, dict) else d


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An ASCII PLY model (the format's "PLY (ascii) ... with vertex normals"): vertices (V, 3), normals (V, 3),
    triangles (F, 3), from its header's element counts and property names."""
    lines = path.read_text().splitlines()
    assert lines[0] == "ply" and lines[1] == "format ascii 1.0", "BOP models are ASCII PLY"
    end = lines.index("end_header")
    counts, props, current = {}, [], None
    for line in lines[2:end]:
        words = line.split()
        if words[0] == "element":
            current = words[1]
            counts[current] = int(words[2])
        elif words[0] == "property" and current == "vertex":
            props.append(words[-1])
    nv, nf = counts["vertex"], counts["face"]
    table = np.array([[float(x) for x in line.split()] for line in lines[end + 1:end + 1 + nv]])
    col = {name: k for k, name in enumerate(props)}
    vertices = table[:, [col["x"], col["y"], col["z"]]]
    normals = table[:, [col["nx"], col["ny"], col["nz"]]]
    faces = np.array([[int(x) for x in line.split()] for line in lines[end + 1 + nv:end + 1 + nv + nf]])
    assert (faces[:, 0] == 3).all()
    return vertices, normals, faces[:, 1:]


def read_png(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im)


def matrix(values, shape) -> np.ndarray:
    """A row-major ("saved row-wise") matrix."""
    return np.asarray(values, dtype=np.float64).reshape(shape)


def symmetry_transforms(info: dict, max_step: float = 0.01) -> list[np.ndarray]:
    """The symmetries of a models_info entry as 4x4 transforms: the identity and the discrete ones, each composed with
    the continuous ones discretised so that a vertex at the diameter from the axis moves at most `max_step` of the
    diameter per step (the format's definition of a continuous symmetry: a rotation by any angle about `axis` through
    `offset`)."""
    from dsr_bench.annotator.symmetry import rotation_about

    discrete = [np.eye(4)] + [matrix(m, (4, 4)) for m in info.get("symmetries_discrete", [])]
    continuous = [np.eye(4)]
    for sym in info.get("symmetries_continuous", []):
        steps = int(np.ceil(np.pi / max_step))
        offset = np.asarray(sym["offset"], np.float64)
        continuous = []
        for i in range(steps):
            m = np.eye(4)
            m[:3, :3] = rotation_about(np.asarray(sym["axis"]), 2 * np.pi * i / steps)
            m[:3, 3] = offset - m[:3, :3] @ offset
            continuous.append(m)
    return [c @ d for d in discrete for c in continuous]


def mssd(est: np.ndarray, gt: np.ndarray, points: np.ndarray, syms: list[np.ndarray]) -> float:
    """Maximum symmetry-aware surface distance (mm): min over symmetries S of max_x |est x - gt S x|."""
    moved = points @ est[:3, :3].T + est[:3, 3]
    return min(float(np.linalg.norm(moved - (points @ (gt @ s)[:3, :3].T + (gt @ s)[:3, 3]), axis=1).max())
               for s in syms)


def add_s(est: np.ndarray, gt: np.ndarray, points: np.ndarray) -> float:
    """ADD-S (ADI): mean distance from each model point at gt to the nearest model point at est (mm)."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points @ est[:3, :3].T + est[:3, 3]).query(points @ gt[:3, :3].T + gt[:3, 3])
    return float(d.mean())


def _samples(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int) -> np.ndarray:
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(tri), count, p=area / area.sum())
    a, b = rng.random(count), rng.random(count)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    t = tri[pick]
    return t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])


# --- the export ----------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def exported(capture_dir, truth, tmp_path_factory):
    from dsr_bench.annotator.session import Session
    from dsr_bench.cli import main

    work = tmp_path_factory.mktemp("bop_work")
    session = Session.open(capture_dir, work)
    place_from_truth(session, truth)
    for t in range(1, session.num_steps + 1):
        session.go_to(t)
    out = tmp_path_factory.mktemp("bop_out") / "bop"
    assert main(["annotate", str(capture_dir), "--work", str(work), "--bop", str(out), "--allow-unchecked"]) == 0
    return Session.open(capture_dir, work), out


def test_the_layout_and_every_key_are_the_formats(exported):
    session, bop = exported
    capture = session.capture
    marker = json.loads((bop / "dsr_bop.json").read_text())
    assert marker["split"] == "test" and marker["scenes"] == {"000000": {"camera": "front"},
                                                             "000001": {"camera": "back"}}
    camera = read_json(bop / "camera.json")
    assert set(camera) == CAMERA_KEYS
    front = capture.cameras["front"]
    assert (camera["width"], camera["height"]) == (front.width, front.height)
    np.testing.assert_allclose([camera["fx"], camera["fy"], camera["cx"], camera["cy"]],
                               front.intrinsics[[0, 1, 0, 1], [0, 1, 2, 2]])
    assert camera["depth_scale"] == pytest.approx(front.depth_scale * 1000)  # mm per depth unit
    info = read_json(bop / "models" / "models_info.json")
    assert sorted(info) == [1, 2, 3]
    for obj_id, entry in info.items():
        assert INFO_KEYS <= set(entry) <= INFO_KEYS | {"symmetries_discrete", "symmetries_continuous"}
        assert (bop / "models" / f"obj_{obj_id:06d}.ply").is_file()
    targets = json.loads((bop / "test_targets_bop19.json").read_text())
    assert targets and all(set(t) == {"scene_id", "im_id", "obj_id", "inst_count"} for t in targets)
    steps = list(range(session.num_steps + 1))
    for scene_id, scene in marker["scenes"].items():
        root = bop / "test" / scene_id
        cams, gts, infos = (read_json(root / f) for f in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"))
        assert sorted(cams) == sorted(gts) == sorted(infos) == steps
        calib = capture.cameras[scene["camera"]]
        for im_id in steps:
            assert set(cams[im_id]) == SCENE_CAMERA_KEYS
            np.testing.assert_allclose(matrix(cams[im_id]["cam_K"], (3, 3)), calib.intrinsics)
            w2c = np.eye(4)
            w2c[:3, :3], w2c[:3, 3] = matrix(cams[im_id]["cam_R_w2c"], (3, 3)), np.asarray(cams[im_id]["cam_t_w2c"])
            w2c[:3, 3] /= 1000.0  # mm
            np.testing.assert_allclose(w2c @ calib.extrinsics, np.eye(4), atol=1e-9)
            for name in ("rgb", "depth"):
                assert (root / name / f"{im_id:06d}.png").read_bytes() == capture.image_path(
                    im_id, scene["camera"], "color" if name == "rgb" else "depth").read_bytes()
            assert [g["obj_id"] for g in gts[im_id]] == [1, 2, 3] and len(infos[im_id]) == 3
            for gt_idx, (gt, gi) in enumerate(zip(gts[im_id], infos[im_id])):
                assert set(gt) == SCENE_GT_KEYS and set(gi) == GT_INFO_KEYS
                rot = matrix(gt["cam_R_m2c"], (3, 3))
                assert np.allclose(rot @ rot.T, np.eye(3), atol=1e-9) and np.linalg.det(rot) > 0.999
                assert 300 < np.linalg.norm(gt["cam_t_m2c"]) < 2000  # mm: the cameras are 0.5-1.5 m away
                for name in ("mask", "mask_visib"):
                    mask = read_png(root / name / f"{im_id:06d}_{gt_idx:06d}.png")
                    assert mask.shape == (calib.height, calib.width) and set(np.unique(mask)) <= {0, 255}
                if gi["px_count_visib"] > 0:
                    assert {"scene_id": int(scene_id), "im_id": im_id, "obj_id": gt["obj_id"],
                            "inst_count": 1} in targets


def test_models_are_in_mm_centred_on_their_box_and_the_scene_is_unchanged(exported):
    session, bop = exported
    capture = session.capture
    info = read_json(bop / "models" / "models_info.json")
    marker = json.loads((bop / "dsr_bop.json").read_text())
    for obj_id, entry in info.items():
        vertices, normals, faces = read_ply(bop / "models" / f"obj_{obj_id:06d}.ply")
        mesh_v, mesh_f = capture.mesh(obj_id - 1)
        offset = np.asarray(marker["model_offset_mm"][str(obj_id)])
        np.testing.assert_allclose(vertices, mesh_v * 1000.0 - offset, atol=1e-4)  # mm, moved by the offset
        np.testing.assert_array_equal(faces, mesh_f)
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-4)  # origin at the bounding-box centre
        np.testing.assert_allclose([entry["min_x"], entry["min_y"], entry["min_z"]], lo, atol=1e-6)
        np.testing.assert_allclose([entry["size_x"], entry["size_y"], entry["size_z"]], hi - lo, atol=1e-6)
        pairwise = np.linalg.norm(vertices[:, None] - vertices[None], axis=-1)
        assert entry["diameter"] == pytest.approx(pairwise.max(), abs=1e-6)
        assert 60 < entry["diameter"] < 200  # mm
    # a model point lands where the DSR pose puts it (the offsets are ~0 here: boxes and a can have their centre of
    # mass on the box centre; test_models_off_their_box_centre_... moves one 30 mm)
    for scene_id, scene in marker["scenes"].items():
        calib = capture.cameras[scene["camera"]]
        w2c = np.linalg.inv(calib.extrinsics)
        gts = read_json(bop / "test" / scene_id / "scene_gt.json")
        for im_id, entries in gts.items():
            poses = session.poses(im_id)
            for gt in entries:
                i = gt["obj_id"] - 1
                x_dsr = capture.mesh(i)[0]
                x_bop = x_dsr * 1000.0 - np.asarray(marker["model_offset_mm"][str(gt["obj_id"])])
                there = x_bop @ matrix(gt["cam_R_m2c"], (3, 3)).T + np.asarray(gt["cam_t_m2c"])
                m = w2c @ pose_to_matrix(poses[i])
                np.testing.assert_allclose(there, (x_dsr @ m[:3, :3].T + m[:3, 3]) * 1000.0, atol=1e-6)


class _Shifted:
    """A session (or its capture) whose object 1 mesh is moved by `d` (m) and whose poses of it are moved back: the
    same scene with the DSR origin 30 mm off the bounding-box centre (as a bottle's centre of mass is)."""

    def __init__(self, inner, d: np.ndarray, is_capture: bool = False):
        self._inner, self._d, self._is_capture = inner, d, is_capture
        if not is_capture:
            self.capture = _Shifted(inner.capture, d, is_capture=True)

    def mesh(self, i: int):
        v, f = self._inner.mesh(i)
        return (v + self._d, f) if i == 1 else (v, f)

    def poses(self, step=None):
        from dsr_bench.geometry import matrix_to_pose

        p = self._inner.poses(step)
        back = np.eye(4)
        back[:3, 3] = -self._d
        p[1] = matrix_to_pose(pose_to_matrix(p[1]) @ back)
        return p

    def __getattr__(self, name):
        return getattr(self._inner, name)


def test_models_off_their_box_centre_are_moved_and_their_poses_with_them(exported, tmp_path):
    """The same scene with object 2's mesh 30 mm off its origin exports the same models and the same model ->
    camera poses (BOP's origin is the box centre, wherever the DSR origin was); only model_offset_mm says where."""
    from dsr_bench.annotator.bop import export_bop

    session, bop = exported
    d = np.array([0.03, -0.02, 0.01])
    out = export_bop(_Shifted(session, d), tmp_path / "shifted", allow_unchecked=True)
    a, b = (json.loads((p / "dsr_bop.json").read_text())["model_offset_mm"] for p in (bop, out))
    np.testing.assert_allclose(np.subtract(b["2"], a["2"]), d * 1000.0, atol=1e-9)
    assert a["1"] == b["1"] and a["3"] == b["3"]
    np.testing.assert_allclose(read_ply(out / "models" / "obj_000002.ply")[0],
                               read_ply(bop / "models" / "obj_000002.ply")[0], atol=1e-4)
    for scene_id in ("000000", "000001"):
        ga, gb = (read_json(p / "test" / scene_id / "scene_gt.json") for p in (bop, out))
        for im_id in ga:
            for x, y in zip(ga[im_id], gb[im_id]):
                np.testing.assert_allclose(x["cam_R_m2c"], y["cam_R_m2c"], atol=1e-9)
                np.testing.assert_allclose(x["cam_t_m2c"], y["cam_t_m2c"], atol=1e-6)  # mm
        ia, ib = (read_json(p / "test" / scene_id / "scene_gt_info.json") for p in (bop, out))
        assert ia == ib


def _model_depth(vertices, faces, rot, t, k, shape) -> tuple[np.ndarray, np.ndarray]:
    """The posed model alone from dense surface samples: per pixel (H, W) the nearest sample's z (mm; inf where none)
    and the farthest z of the samples of its front surface (within 10 mm of the nearest): the range the depth at the
    pixel's centre lies in (a surface seen at a grazing angle spans several mm across a pixel)."""
    pts = _samples(vertices, faces, 400_000, 3) @ rot.T + t
    u = np.rint(pts[:, 0] / pts[:, 2] * k[0, 0] + k[0, 2]).astype(int)
    v = np.rint(pts[:, 1] / pts[:, 2] * k[1, 1] + k[1, 2]).astype(int)
    inside = (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    u, v, z = u[inside], v[inside], pts[inside, 2]
    near = np.full(shape, np.inf)
    np.minimum.at(near, (v, u), z)
    front = z <= near[v, u] + 10.0
    far = np.full(shape, -np.inf)
    np.maximum.at(far, (v[front], u[front]), z[front])
    return near, far


def test_scene_gt_info_follows_from_the_masks_and_the_measured_depth(exported):
    """px_count_visib = mask_visib's pixels, px_count_valid = the silhouette's pixels with a depth, visib_fract =
    visib / all, the boxes (x, y, w, h) of the masks; a silhouette pixel is visible exactly where the measured
    distance is within 15 mm of the model's or missing (checked away from the 15 mm edge, where a sample z-buffer is
    exact enough)."""
    session, bop = exported
    marker = json.loads((bop / "dsr_bop.json").read_text())
    models = {o: read_ply(bop / "models" / f"obj_{o:06d}.ply") for o in (1, 2, 3)}
    checked_visible = checked_hidden = occluded = 0
    for scene_id in marker["scenes"]:
        root = bop / "test" / scene_id
        cams, gts, infos = (read_json(root / f) for f in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"))
        for im_id, entries in gts.items():
            k = matrix(cams[im_id]["cam_K"], (3, 3))
            depth = read_png(root / "depth" / f"{im_id:06d}.png").astype(np.float64) * cams[im_id]["depth_scale"]
            rows, cols = np.mgrid[0:depth.shape[0], 0:depth.shape[1]]
            ray = np.sqrt(1 + ((cols - k[0, 2]) / k[0, 0]) ** 2 + ((rows - k[1, 2]) / k[1, 1]) ** 2)
            for gt_idx, (gt, gi) in enumerate(zip(entries, infos[im_id])):
                mask = read_png(root / "mask" / f"{im_id:06d}_{gt_idx:06d}.png") > 0
                visib = read_png(root / "mask_visib" / f"{im_id:06d}_{gt_idx:06d}.png") > 0
                assert not (visib & ~mask).any()
                assert gi["px_count_visib"] == visib.sum()
                assert gi["px_count_valid"] == (mask & (depth > 0)).sum()
                assert gi["px_count_all"] >= mask.sum() > 0
                assert gi["visib_fract"] == pytest.approx(gi["px_count_visib"] / gi["px_count_all"])
                for box, m in ((gi["bbox_obj"], mask), (gi["bbox_visib"], visib)):
                    ys, xs = np.nonzero(m)
                    assert box == [xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min()]
                occluded += gi["visib_fract"] < 0.9
                near, far = _model_depth(*models[gt["obj_id"]][::2], matrix(gt["cam_R_m2c"], (3, 3)),
                                         np.asarray(gt["cam_t_m2c"]), k, depth.shape)
                sure = mask & np.isfinite(near)
                # model distance - measured distance (mm), at the least and the most the pixel's samples give
                low, high = (near - depth) * ray - 1.0, (far - depth) * ray + 1.0
                visible_rule = (depth == 0) | (high <= 15.0)
                clear = sure & ((depth == 0) | (high <= 15.0) | (low > 15.0))
                assert (visib[clear] == visible_rule[clear]).all(), (scene_id, im_id, gt_idx)
                checked_visible += int((clear & visible_rule).sum())
                checked_hidden += int((clear & ~visible_rule).sum())
    assert checked_visible > 5000 and checked_hidden > 50 and occluded >= 1, (checked_visible, checked_hidden,
                                                                              occluded)


def test_gt_info_counts_the_silhouette_beyond_the_image():
    """A 100 mm cube 1 m in front of a 500 px focal length, half out of the image on the left: px_count_all counts
    the whole silhouette, the mask only the part inside; the measured depth decides what is visible."""
    import trimesh

    from dsr_bench.annotator.bop import gt_info

    box = trimesh.creation.box((100.0, 100.0, 100.0))
    k = np.array([[500.0, 0, 100.0], [0, 500.0, 100.0], [0, 0, 1]])
    t = np.array([-200.0, 0.0, 1050.0])  # centre projects to u = 100 - 95 = 5: about half the silhouette left of 0
    none = np.zeros((200, 200))
    entry, sil, visib = gt_info(np.asarray(box.vertices), np.asarray(box.faces), np.eye(3), t, k, none)
    # front face u -25..25 (50 x 50 px) and the right side face to u 31.8: ~56 x 50 in all, 32 x 50 in the image
    assert 2700 < entry["px_count_all"] < 2900 and 1500 < sil.sum() < 1700
    assert entry["bbox_obj"][0] < 0 and entry["bbox_obj"][2] > 45  # not clipped to the image
    assert entry["px_count_valid"] == 0 and entry["px_count_visib"] == sil.sum()  # no depth: visible (bop19)
    front = np.full((200, 200), 1000.0 - 20.0)  # the box's face is at 1000 mm: something 20 mm nearer hides it
    entry, _, _ = gt_info(np.asarray(box.vertices), np.asarray(box.faces), np.eye(3), t, k, front)
    assert entry["px_count_visib"] == 0 and entry["bbox_visib"] == [-1, -1, -1, -1] and entry["visib_fract"] == 0
    assert entry["px_count_valid"] == sil.sum()
    near = np.full((200, 200), 1000.0 - 10.0)  # 10 mm nearer than the front face: within the 15 mm tolerance
    entry, _, _ = gt_info(np.asarray(box.vertices), np.asarray(box.faces), np.eye(3), t, k, near)
    assert 1200 < entry["px_count_visib"] < 1400 < sil.sum()  # the front face (25 x 50 px), not the side behind it
    far = np.full((200, 200), 1500.0)  # measured behind the model: nothing hides it
    entry, _, _ = gt_info(np.asarray(box.vertices), np.asarray(box.faces), np.eye(3), t, k, far)
    assert entry["px_count_visib"] == sil.sum()


# --- symmetries ----------------------------------------------------------------------------------------------------


def _off_surface(vertices: np.ndarray, faces: np.ndarray, transform: np.ndarray) -> float:
    """Largest distance (mm) of the model's surface samples moved by `transform` to the nearest of dense samples of
    the unmoved surface (an upper bound of the distance to the surface, by the samples' spacing)."""
    from scipy.spatial import cKDTree

    dense = cKDTree(np.vstack([_samples(vertices, faces, 300_000, 1), vertices]))
    moved = _samples(vertices, faces, 3000, 2) @ transform[:3, :3].T + transform[:3, 3]
    return float(dense.query(moved)[0].max())


def test_declared_symmetries_map_each_model_onto_itself(exported):
    from dsr_bench.annotator.symmetry import rotation_about

    _, bop = exported
    info = read_json(bop / "models" / "models_info.json")
    # box 1: 64 x 108 x 64 mm (square across y): the 7 turns of a square prism's group; box 3 (66 x 114 x 34): the
    # three half turns; the can (2): any turn about its axis z, and upside down
    assert len(info[1]["symmetries_discrete"]) == 7 and "symmetries_continuous" not in info[1]
    assert len(info[3]["symmetries_discrete"]) == 3 and "symmetries_continuous" not in info[3]
    (cont,) = info[2]["symmetries_continuous"]
    np.testing.assert_allclose(cont["axis"], [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(cont["offset"][:2], [0, 0], atol=1e-6)
    assert len(info[2]["symmetries_discrete"]) == 1
    for obj_id, entry in info.items():
        vertices, _, faces = read_ply(bop / "models" / f"obj_{obj_id:06d}.ply")
        transforms = [matrix(m, (4, 4)) for m in entry.get("symmetries_discrete", [])]
        for sym in entry.get("symmetries_continuous", []):
            for deg in (17.0, 90.0, 163.0, 271.0):
                m = np.eye(4)
                m[:3, :3] = rotation_about(np.asarray(sym["axis"]), np.radians(deg))
                m[:3, 3] = np.asarray(sym["offset"]) - m[:3, :3] @ np.asarray(sym["offset"])
                transforms.append(m)
        for m in transforms:
            assert np.allclose(m[3], [0, 0, 0, 1]) and np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-9)
            assert _off_surface(vertices, faces, m) < 1.5, (obj_id, m)  # 1 mm tolerance + the samples' spacing
    # and the test can fail: a quarter turn about z of box 3 (66 x 114 mm) is no symmetry
    vertices, _, faces = read_ply(bop / "models" / "obj_000003.ply")
    quarter = np.eye(4)
    quarter[:3, :3] = rotation_about(np.array([0.0, 0.0, 1.0]), np.pi / 2)
    assert _off_surface(vertices, faces, quarter) > 20


def test_a_symmetric_twin_of_the_can_is_scored_small_with_the_declared_symmetries(exported):
    """The can's pose and its twin (turned 73.3 degrees about its axis and upside down: the same surface, the
    rotation error 180 degrees): BOP's MSSD with the declared symmetries and ADD-S are small, ADD (no symmetry) is
    as large as the can."""
    from dsr_bench.annotator.symmetry import rotation_about

    _, bop = exported
    info = read_json(bop / "models" / "models_info.json")[2]
    vertices, _, faces = read_ply(bop / "models" / "obj_000002.ply")
    gt_entry = read_json(bop / "test" / "000000" / "scene_gt.json")[1][1]
    assert gt_entry["obj_id"] == 2
    gt = np.eye(4)
    gt[:3, :3], gt[:3, 3] = matrix(gt_entry["cam_R_m2c"], (3, 3)), gt_entry["cam_t_m2c"]
    turn = np.eye(4)
    turn[:3, :3] = rotation_about(np.asarray(info["symmetries_continuous"][0]["axis"]), np.radians(73.3))
    flip = np.eye(4)
    flip[:3, :3] = rotation_about(np.array([1.0, 0.0, 0.0]), np.pi)
    twin = gt @ turn @ flip
    syms = symmetry_transforms(info)
    points = np.vstack([vertices, _samples(vertices, faces, 2000, 5)])
    add = float(np.linalg.norm(points @ (twin[:3, :3] - gt[:3, :3]).T + (twin[:3, 3] - gt[:3, 3]), axis=1).mean())
    assert add > 50.0  # mm: without symmetries the twin is counted far off
    assert mssd(twin, gt, points, [np.eye(4)]) > 80.0
    assert mssd(twin, gt, points, syms) < 0.01 * info["diameter"]  # within BOP's discretisation of the turn
    assert add_s(twin, gt, np.vstack([vertices, _samples(vertices, faces, 30000, 6)])) < 1.0
    # a real error stays one: the can 10 mm off along its axis
    off = gt.copy()
    off[:3, 3] += gt[:3, 2] * 10.0
    assert mssd(off, gt, points, syms) > 9.0


@pytest.mark.parametrize("shape, discrete, continuous", [
    ("hexagonal prism", 11, False),  # D6: 6-fold about z and 6 half turns across it
    ("cone", 0, True),  # any turn about z, never upside down; its axis is off the box centre in z only
    ("cylinder", 1, True),
    ("box with a knob", 0, False),
    ("cube", 23, False),
])
def test_find_symmetries_on_shapes(shape, discrete, continuous):
    import trimesh

    from dsr_bench.annotator.symmetry import find_symmetries

    make = {"hexagonal prism": lambda: trimesh.creation.cylinder(30.0, 80.0, sections=6),
            "cone": lambda: trimesh.creation.cone(30.0, 80.0, sections=64),
            "cylinder": lambda: trimesh.creation.cylinder(30.0, 80.0, sections=48),
            "box with a knob": lambda: trimesh.util.concatenate([
                trimesh.creation.box((60.0, 40.0, 30.0)),
                trimesh.creation.box((10.0, 10.0, 10.0), transform=trimesh.transformations.translation_matrix(
                    [20.0, 10.0, 20.0]))]),
            "cube": lambda: trimesh.creation.box((50.0, 50.0, 50.0))}[shape]()
    v = np.asarray(make.vertices, np.float64)
    v = v - (v.min(axis=0) + v.max(axis=0)) / 2
    found = find_symmetries(v, np.asarray(make.faces))
    assert len(found.discrete) == discrete and bool(found.continuous) == continuous
    assert all(e <= 1.0 for e in found.discrete_errors + found.continuous_errors)
    for axis, offset in found.continuous:
        np.testing.assert_allclose(axis, [0, 0, 1], atol=1e-12)
        np.testing.assert_allclose(offset[:2], [0, 0], atol=1e-6)  # a point on the axis
