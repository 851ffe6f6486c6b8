"""ShapeNet and YCB object sets, read from the user's copies (their licences forbid redistribution).

Layouts understood (ROOT from `--object-root`, else DSR_BENCH_SHAPENET / DSR_BENCH_YCB):
- ShapeNetCore v2: ROOT/<synset>/<model_id>/models/model_normalized.obj (y up, unit diagonal).
- YCB release: ROOT/<name>/google_16k/textured.obj, ROOT/<name>/tsdf/textured.obj or
  ROOT/<name>/poisson/textured.ply (z up, metres).
- The official processed layout: ROOT/[object_models/]shapenet/<synset>/<model_id>/ and
  ROOT/[object_models/]ycb/<official id>/ (e.g. flipped-065-a_cups), each with obj.urdf naming a
  mesh and its scale, and model_com.binvox (z up, origin at the centre of mass).
The model lists are the official ones (catalog.py); every listed model must be present.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dsr_bench.errors import UserError
from dsr_bench.generators.objects.builtin import NORMALISED_DIAGONAL, category_scale, choose_large, sample_category_mix
from dsr_bench.generators.objects.catalog import SHAPENET_MODELS, YCB_LARGE, YCB_NORMAL, ycb_release_name
from dsr_bench.generators.objects.solid import load_solid
from dsr_bench.generators.objects.spec import ObjectSpec, make_spec, random_color

if TYPE_CHECKING:
    import trimesh

ENV = {"shapenet": "DSR_BENCH_SHAPENET", "ycb": "DSR_BENCH_YCB"}
LAYOUTS = {
    "shapenet": "ROOT/<synset>/<model_id>/models/model_normalized.obj (ShapeNetCore v2) or "
                "ROOT/[object_models/]shapenet/<synset>/<model_id>/obj.urdf (official processed)",
    "ycb": "ROOT/<name>/google_16k/textured.obj (YCB release; or tsdf/textured.obj, poisson/textured.ply) or "
           "ROOT/[object_models/]ycb/<official id>/obj.urdf (official processed)",
}
#: Where each set's meshes come from (their licences forbid redistribution: the user downloads a copy).
SOURCES = {
    "shapenet": "ShapeNetCore v2 (https://shapenet.org: sign up, then download ShapeNetCore v2 and unzip it; or the "
                "authors' processed shapenet.zip)",
    "ycb": "the YCB object models (https://www.ycbbenchmarks.com/: their google_16k meshes; or the authors' "
           "processed ycb.zip)",
}
YCB_RELEASE_MESHES = ("google_16k/textured.obj", "tsdf/textured.obj", "poisson/textured.ply")
YCB_PITCH = 0.002  # m: voxel size when a YCB mesh must be made solid
_MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off")


@dataclass(frozen=True)
class ModelSource:
    """Where one model's mesh lives and how to bring it to metres, z up."""

    model_id: str
    mesh: Path
    binvox: Path | None  # the official solid voxelisation, same frame and units as the mesh
    unit_scale: float  # source units -> metres (before the category scale)
    up_y: bool = False  # ShapeNetCore v2 release meshes are y up
    flip: bool = False  # turn upside down (official "flipped-" cups)
    fill: bool = False  # fill a hollow underside (official "filled-" Duplo bricks)


def _missing(set_name: str, root: Path | None, detail: str) -> UserError:
    where = f"in {root}" if root is not None else f"no --object-root given and ${ENV[set_name]} unset"
    return UserError(f"--objects {set_name}: {detail} ({where}); pass --object-root PATH or set {ENV[set_name]} to "
                     f"your copy of {SOURCES[set_name]}; expected layout: {LAYOUTS[set_name]}")


def _resolve_root(set_name: str, object_root: str | Path | None) -> Path:
    value = object_root if object_root is not None else (os.environ.get(ENV[set_name]) or None)
    root = Path(value).expanduser() if value is not None else None
    if root is None:
        raise _missing(set_name, None, "no mesh directory")
    if not root.is_dir():
        raise UserError(f"--objects {set_name}: mesh directory {root} not found; pass --object-root PATH or set "
                        f"{ENV[set_name]} to your copy of {SOURCES[set_name]}; expected layout: {LAYOUTS[set_name]}")
    return root


def _list_missing(missing: list[str], total: int) -> str:
    shown = ", ".join(missing[:4]) + (", ..." if len(missing) > 4 else "")
    return f"{len(missing)} of {total} official models missing ({shown})"


def read_urdf_mesh(urdf: Path) -> tuple[Path, float]:
    """The mesh file (visual first, else collision) and its uniform scale named by an official obj.urdf."""
    try:
        tree = ET.parse(urdf).getroot()
    except (ET.ParseError, OSError) as exc:
        raise UserError(f"{urdf}: unreadable URDF ({exc}); replace the file") from None
    for tag in ("visual", "collision"):
        mesh = tree.find(f".//{tag}/geometry/mesh")
        filename = mesh.get("filename") if mesh is not None else None
        if mesh is not None and filename:
            name = filename.removeprefix("package://").removeprefix("file://")
            path = Path(name) if Path(name).is_absolute() else urdf.parent / name
            try:
                scale = np.array([float(v) for v in mesh.get("scale", "1 1 1").split()], dtype=np.float64)
            except ValueError:
                scale = np.zeros(0)
            if scale.shape != (3,) or not np.all(scale > 0) or np.ptp(scale) > 1e-9 * scale.max():
                raise UserError(f"{urdf}: mesh scale {mesh.get('scale')!r} is not one positive number three "
                                "times; the object sets need uniform scales")
            if not path.is_file():
                raise UserError(f"{urdf}: its mesh {path} does not exist; restore it")
            return path, float(scale[0])
    raise UserError(f"{urdf}: no <mesh filename=...> in its visual or collision geometry; replace the file")


def _processed_source(model_id: str, model_dir: Path, default_scale: float = 1.0, **flags) -> ModelSource | None:
    """A model of the official processed layout (obj.urdf and the mesh and scale it names; without a
    URDF, the first mesh file at default_scale), or None when the directory holds neither."""
    urdf = model_dir / "obj.urdf"
    binvox_path = model_dir / "model_com.binvox"
    binvox = binvox_path if binvox_path.is_file() else None
    if urdf.is_file():
        mesh, scale = read_urdf_mesh(urdf)
        return ModelSource(model_id, mesh, binvox, scale, **flags)
    if model_dir.is_dir():
        meshes = sorted(p for p in model_dir.iterdir() if p.suffix.lower() in _MESH_SUFFIXES and p.is_file())
        if meshes:
            return ModelSource(model_id, meshes[0], binvox, default_scale, **flags)
    return None


class _SolidCache:
    """Per-process memo of the solids (the disk cache holds them across processes)."""

    def __init__(self) -> None:
        self._solids: dict[ModelSource, trimesh.Trimesh] = {}

    def solid(self, source: ModelSource, pitch: float | None):
        import trimesh

        if source not in self._solids:
            solid = load_solid(source.mesh, source.binvox, pitch=pitch, fill_columns=source.fill)
            if source.up_y:  # +90 deg about x: y up -> z up
                solid.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
            if source.flip:  # upside down: 180 deg about x
                solid.apply_transform(trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0]))
            solid.apply_scale(source.unit_scale)
            self._solids[source] = solid
        return self._solids[source].copy()


class ShapeNetSet:
    """The official 44 ShapeNet models of the five training categories, official scales and scene mix."""

    name = "shapenet"

    def __init__(self, object_root: str | Path | None = None) -> None:
        root = _resolve_root(self.name, object_root)
        candidates = (root / "object_models" / "shapenet", root / "shapenet", root)
        base = next((b for b in candidates if any((b / s).is_dir() for s, _ in SHAPENET_MODELS.values())), None)
        if base is None:
            raise _missing(self.name, root, "no ShapeNet synset directory (e.g. 02876657)")
        self.models: dict[str, list[ModelSource]] = {}
        missing: list[str] = []
        total = 0
        for category, (synset, ids) in SHAPENET_MODELS.items():
            self.models[category] = []
            for model_id in ids:
                total += 1
                model_dir = base / synset / model_id
                release = model_dir / "models" / "model_normalized.obj"
                source: ModelSource | None
                if release.is_file():
                    source = ModelSource(model_id, release, None, NORMALISED_DIAGONAL, up_y=True)
                else:
                    source = _processed_source(model_id, model_dir, default_scale=NORMALISED_DIAGONAL)
                if source is None:
                    missing.append(f"{synset}/{model_id}")
                else:
                    self.models[category].append(source)
        if missing:
            raise _missing(self.name, base, _list_missing(missing, total))
        self._cache = _SolidCache()

    def _build(self, category: str, rng: np.random.Generator, is_large: bool) -> ObjectSpec:
        sources = self.models[category]
        source = sources[int(rng.integers(len(sources)))]
        scale = category_scale(rng, category, is_large)
        solid = self._cache.solid(source, None)
        solid.apply_scale(scale)
        return make_spec(self.name, category, source.model_id, scale, [solid], random_color(rng), is_large)

    def sample(self, rng: np.random.Generator, count: int) -> list[ObjectSpec]:
        return sample_category_mix(rng, count, self.name, self._build)


class YCBSet:
    """The official YCB novel-object lists (normal, and one optional large object per scene), real sizes."""

    name = "ycb"

    def __init__(self, object_root: str | Path | None = None) -> None:
        root = _resolve_root(self.name, object_root)
        ids = YCB_NORMAL + YCB_LARGE
        candidates = (root / "object_models" / "ycb", root / "ycb", root)
        base = next((b for b in candidates
                     if any((b / n).is_dir() or (b / ycb_release_name(n)).is_dir() for n in ids)), root)
        self.models: dict[str, ModelSource] = {}
        missing = []
        for official_id in ids:
            name = ycb_release_name(official_id)
            flags = {"flip": official_id.startswith("flipped-"), "fill": official_id.startswith("filled-")}
            source = _processed_source(official_id, base / official_id)  # processed: already flipped/filled
            if source is None:
                release = next((base / name / sub for sub in YCB_RELEASE_MESHES if (base / name / sub).is_file()),
                               None)
                if release is not None:
                    source = ModelSource(official_id, release, None, 1.0, **flags)
                else:
                    source = _processed_source(official_id, base / name, **flags)
            if source is None:
                missing.append(official_id)
            else:
                self.models[official_id] = source
        if missing:
            raise _missing(self.name, base, _list_missing(missing, len(ids)))
        self._cache = _SolidCache()

    def _build(self, official_id: str, rng: np.random.Generator, is_large: bool) -> ObjectSpec:
        solid = self._cache.solid(self.models[official_id], YCB_PITCH)
        return make_spec(self.name, ycb_release_name(official_id), official_id, 1.0, [solid], random_color(rng),
                         is_large)

    def sample(self, rng: np.random.Generator, count: int) -> list[ObjectSpec]:
        large = choose_large(rng, count)
        out = []
        for i in range(count):
            names = YCB_LARGE if i == large else YCB_NORMAL
            out.append(self._build(names[int(rng.integers(len(names)))], rng, i == large))
        return out


def open_external_set(name: str, object_root: str | Path | None = None) -> ShapeNetSet | YCBSet:
    """The ShapeNet or YCB set from the user's copy (checked now, before any generation)."""
    return ShapeNetSet(object_root) if name == "shapenet" else YCBSet(object_root)
