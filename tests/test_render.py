"""The renderer in the library (`dsr_bench.render`): its one factory names the cameras, and the generator and the
annotator are siblings on it (neither imports the other; the library imports neither, not even lazily)."""

import ast
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from dsr_bench.constants import IMAGE_SHAPE, TSDF_IMAGE_SHAPE
from dsr_bench.geometry import make_camera, resized_camera
from dsr_bench.render import SceneRenderer, create_renderer

REPO = Path(__file__).resolve().parents[1]

#: A unit-ish box (12 triangles, outward normals) as one closed part.
_BOX_VERTICES = np.array([[x, y, z] for x in (-0.03, 0.03) for y in (-0.02, 0.02) for z in (-0.025, 0.025)])
_BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
_BOX = SimpleNamespace(parts=[SimpleNamespace(vertices=_BOX_VERTICES, faces=_BOX_FACES)], color=(0.2, 0.4, 0.8))


def test_cameras_named_are_the_benchmarks_at_the_image_shape():
    renderer = create_renderer([_BOX], cameras=("front", "back"), image_shape=(48, 64))
    assert isinstance(renderer, SceneRenderer)
    assert list(renderer.cameras) == ["front", "back"]
    for name, camera in renderer.cameras.items():
        assert camera.as_attrs() == make_camera(name, 48, 64).as_attrs()
    assert renderer.tsdf_camera.as_attrs() == make_camera("front", *TSDF_IMAGE_SHAPE).as_attrs()
    default = create_renderer([_BOX])
    assert list(default.cameras) == ["front"]
    assert (default.cameras["front"].height, default.cameras["front"].width) == IMAGE_SHAPE


def test_cameras_given_are_used_as_given():
    """A capture's calibrated cameras (here a resized one, not the benchmark's size) render at their own size."""
    own = resized_camera(make_camera("front", 96, 128), 30, 40)
    renderer = create_renderer([_BOX], cameras={"front": own}, tsdf_image_shape=(24, 32))
    assert renderer.cameras["front"] is own
    assert (renderer.tsdf_camera.height, renderer.tsdf_camera.width) == (24, 32)
    pose = np.array([[0.5, 0.0, 0.025, 0.0, 0.0, 0.0, 1.0]])
    images = renderer.render_camera(*renderer.scene(pose), "front")
    assert images.depth.shape == (30, 40) and images.color.shape == (30, 40, 3)
    assert (images.mask == 1).any() and (images.mask == 0).any()  # the box, and the table around it


def _imported(package: str) -> dict[str, set[str]]:
    """Every module each file of `package` imports, at any depth (function-level imports included)."""
    out = {}
    for path in sorted((REPO / package).rglob("*.py")):
        names = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module)
        out[str(path.relative_to(REPO))] = names
    return out


def _home(module: str) -> str:
    """The folder of the repository a module lives in: dsr_bench.generators.episode -> generators (installed under
    the library's name, kept in its own folder), dsr_bench.render -> dsr_bench, numpy -> numpy."""
    parts = module.split(".")
    if parts[0] == "dsr_bench" and len(parts) > 1 and parts[1] in ("generators", "annotator"):
        return parts[1]
    return parts[0]


def _offenders(package: str, forbidden: tuple[str, ...]) -> list[str]:
    return [f"{path}: {name}" for path, names in _imported(package).items() for name in sorted(names)
            if _home(name) in forbidden]


def test_no_sideways_or_upward_import():
    """The annotator renders through the library, not the generator; the library imports neither of them."""
    assert _imported("annotator") and _imported("dsr_bench")  # the walk found the sources
    assert "dsr_bench.render" in set().union(*_imported("generators").values())
    assert "dsr_bench.generators.episode" in set().union(*_imported("generators").values())  # under one namespace
    assert _offenders("annotator", ("generators",)) == []
    assert _offenders("generators", ("annotator",)) == []
    assert _offenders("dsr_bench", ("generators", "annotator")) == []


def test_the_finder_of_offenders_finds_one():
    assert _home("dsr_bench.annotator.session") == "annotator" and _home("dsr_bench.geometry") == "dsr_bench"
    assert _home("generators.run") == "generators" and _home("dsr_bench") == "dsr_bench"
