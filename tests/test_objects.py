"""Object sets: closed solids of sensible size, deterministic sampling, and the ShapeNet / YCB readers
on tiny fixture trees in both the release and the official processed layouts."""

from pathlib import Path

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")

from dsr_bench.errors import UserError  # noqa: E402
from generators.objects import OBJECT_SET_NAMES, get_object_set  # noqa: E402
from generators.objects.external import SHAPENET_SYNSETS, YCB_LARGE, YCB_NORMAL  # noqa: E402

BUILTIN = ("cube", "procedural", "procedural-novel")


@pytest.mark.parametrize("name", BUILTIN)
def test_builtin_sets_are_closed_solids_that_fit(name):
    objects = get_object_set(name).sample(np.random.default_rng(3), 12)
    assert len(objects) == 12
    for obj in objects:
        volumes = []
        for part in obj.parts:
            mesh = trimesh.Trimesh(part.vertices, part.faces, process=False)
            assert mesh.is_watertight and mesh.volume > 0, obj.model_id
            volumes.append((mesh.volume, mesh.center_mass))
        com = sum(v * c for v, c in volumes) / sum(v for v, _ in volumes)
        assert np.linalg.norm(com) < 1e-3, obj.model_id  # object frame origin at the centre of mass
        extent = obj.extent()
        assert np.all(extent > 0.005) and extent.max() < 0.2 and extent[2] < 0.19, (obj.model_id, extent)
        assert obj.mass > 0 and len(obj.mesh_sha256()) == 64
        assert obj.identity()["set"] == name


@pytest.mark.parametrize("name", BUILTIN)
def test_sampling_is_deterministic(name):
    a = get_object_set(name).sample(np.random.default_rng(11), 4)
    b = get_object_set(name).sample(np.random.default_rng(11), 4)
    assert [o.identity() for o in a] == [o.identity() for o in b]
    c = get_object_set(name).sample(np.random.default_rng(12), 4)
    assert [o.identity() for o in a] != [o.identity() for o in c]


def test_novel_set_is_disjoint_from_training_categories():
    rng = np.random.default_rng(0)
    train = {o.category for _ in range(30) for o in get_object_set("procedural").sample(rng, 4)}
    novel = {o.category for _ in range(30) for o in get_object_set("procedural-novel").sample(rng, 4)}
    assert train <= {"mug", "bottle", "can", "phone", "sofa", "box"} and {"mug", "sofa", "bottle"} <= train
    assert not train & novel and len(novel) >= 8


def test_procedural_mix_rules():
    rng = np.random.default_rng(1)
    scenes = [get_object_set("procedural").sample(rng, 4) for _ in range(200)]
    large = [sum(o.is_large for o in s) for s in scenes]
    assert max(large) == 1 and 0.35 < np.mean(large) < 0.65  # one optional large object, p = 0.5
    categories = [o.category for s in scenes for o in s]
    # a can is forced with p = 0.3 (else one of 5 categories), then a non-large object becomes a small box
    # with p = 0.3; one object in 8 is large on average (p = 0.5 per 4-object scene)
    p_box = 0.3 * (1 - 0.5 / 4)
    p_can = (0.3 + 0.7 / 5) * (1 - p_box)
    assert abs(categories.count("can") / len(categories) - p_can) < 0.05
    assert abs(categories.count("box") / len(categories) - p_box) < 0.05


def _open_box_mesh() -> "trimesh.Trimesh":
    box = trimesh.creation.box([0.6, 0.4, 0.8])
    box.update_faces(np.arange(len(box.faces)) != 0)  # a hole: not watertight
    return box


def test_shapenet_release_layout_and_open_mesh(tmp_path, monkeypatch):
    monkeypatch.setenv("DSR_BENCH_CACHE", str(tmp_path / "cache"))
    for category, (synset, _) in SHAPENET_SYNSETS.items():
        for k in range(2):
            d = tmp_path / "ShapeNetCore.v2" / synset / f"{category}{k:02d}" / "models"
            d.mkdir(parents=True)
            mesh = _open_box_mesh() if k == 0 else trimesh.creation.cylinder(0.3, 0.8)
            mesh.export(d / "model_normalized.obj")
    objects = get_object_set("shapenet", tmp_path / "ShapeNetCore.v2").sample(np.random.default_rng(0), 16)
    for obj in objects:
        mesh = trimesh.Trimesh(*obj.mesh(), process=False)
        assert mesh.is_watertight and mesh.volume > 0
        assert obj.category == "box" or obj.model_id[:-2] == obj.category
        if obj.category != "box":
            diagonal = np.linalg.norm(obj.extent())
            low, high = {"bottle": (0.7, 1.2), "can": (0.7, 1.2), "mug": (0.8, 1.2), "sofa": (0.4, 1.2),
                         "phone": (0.7, 1.1)}[obj.category]
            assert 0.15 * low * 0.9 < diagonal < 0.15 * high * 1.1  # 0.15 m diagonal x scale (voxelised: +-10%)
    assert list((tmp_path / "cache" / "solids").glob("*.npz"))  # solids are cached


def test_shapenet_processed_layout(tmp_path, monkeypatch):
    monkeypatch.setenv("DSR_BENCH_CACHE", str(tmp_path / "cache"))
    for synset, _ in SHAPENET_SYNSETS.values():
        d = tmp_path / "object_models" / "shapenet" / synset / "abc123"
        d.mkdir(parents=True)
        trimesh.creation.box([0.05, 0.06, 0.07]).export(d / "model_com.obj")
        (d / "obj.urdf").write_text("<robot/>")
    monkeypatch.setenv("DSR_BENCH_SHAPENET", str(tmp_path))
    objects = get_object_set("shapenet").sample(np.random.default_rng(2), 8)
    assert {o.model_id for o in objects if o.category != "box"} == {"abc123"}


def test_ycb_release_layout_flips_cups(tmp_path, monkeypatch):
    monkeypatch.setenv("DSR_BENCH_CACHE", str(tmp_path / "cache"))
    for name in YCB_NORMAL + YCB_LARGE:
        d = tmp_path / name / "google_16k"
        d.mkdir(parents=True)
        cone = trimesh.creation.cone(0.04, 0.08)  # apex up; a flipped cup has its apex down
        cone.export(d / "textured.obj")
    ycb = get_object_set("ycb", tmp_path)
    objects = ycb.sample(np.random.default_rng(5), 40)
    for obj in objects:
        v, _ = obj.mesh()
        top_width = np.ptp(v[v[:, 2] > v[:, 2].max() - 0.005][:, 0])
        if obj.category.startswith("065-"):
            assert top_width > 0.05  # flipped: the wide base is up
        else:
            assert top_width < 0.02


def test_missing_sets_name_flag_variable_and_layout(tmp_path, monkeypatch):
    monkeypatch.delenv("DSR_BENCH_YCB", raising=False)
    with pytest.raises(UserError) as err:
        get_object_set("ycb")
    assert "--object-root" in str(err.value) and "DSR_BENCH_YCB" in str(err.value) and "google_16k" in str(err.value)
    (tmp_path / "005_tomato_soup_can" / "google_16k").mkdir(parents=True)
    with pytest.raises(UserError, match="models missing"):
        get_object_set("ycb", tmp_path)
    with pytest.raises(UserError, match="no ShapeNet synset"):
        get_object_set("shapenet", tmp_path)
    with pytest.raises(UserError, match="is not an object set"):
        get_object_set("lego")
    assert set(OBJECT_SET_NAMES) == {"cube", "shapenet", "ycb", "procedural", "procedural-novel"}


def test_unreadable_mesh_is_a_user_error(tmp_path, monkeypatch):
    monkeypatch.setenv("DSR_BENCH_CACHE", str(tmp_path / "cache"))
    from generators.objects.external import load_solid

    bad = tmp_path / "broken.obj"
    bad.write_text("this is not an obj file\n")
    with pytest.raises(UserError, match="broken.obj"):
        load_solid(Path(bad))
