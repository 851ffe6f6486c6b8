"""ShapeNet and YCB object sets, read from the user's copies (their licences forbid redistribution).

Layouts understood (ROOT from `--object-root` or DSR_BENCH_SHAPENET / DSR_BENCH_YCB):
- ShapeNetCore v2: ROOT/<synset>/<model_id>/models/model_normalized.obj (y up, unit diagonal).
- YCB release: ROOT/<name>/google_16k/textured.obj, ROOT/<name>/tsdf/textured.obj or
  ROOT/<name>/poisson/textured.ply (z up, metres).
- The official processed layout: ROOT/[object_models/]shapenet/<synset>/<model_id>/ and
  ROOT/[object_models/]ycb/<name>/, each with a mesh file, obj.urdf and model_com.binvox (z up).
Meshes that are not closed solids are made solid: the shipped binvox when present, otherwise a
voxelisation at 2 mm filled and meshed with marching cubes. Solids are cached on disk
(DSR_BENCH_CACHE, default ~/.cache/dsr-bench) keyed by the source file's hash.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from dsr_bench.errors import UserError
from generators.objects.builtin import CATEGORY_SCALES, NORMALISED_DIAGONAL, P_FORCE_CAN, P_LARGE, P_RANDOM_BOX, _small_box
from generators.objects.spec import ObjectSpec, make_spec, random_color

#: ShapeNetCore synsets of the five training categories and the official model counts.
SHAPENET_SYNSETS = {"bottle": ("02876657", 14), "can": ("02946921", 6), "mug": ("03797390", 5),
                    "sofa": ("04256520", 9), "phone": ("04401088", 10)}
#: The official novel-object lists (cups flipped upside down, as in the official code).
YCB_NORMAL = ("005_tomato_soup_can", "007_tuna_fish_can", "008_pudding_box", "009_gelatin_box",
              "010_potted_meat_can", "025_mug", "061_foam_brick", "077_rubiks_cube", "065-a_cups", "065-d_cups",
              "065-g_cups", "073-a_lego_duplo", "073-b_lego_duplo", "073-c_lego_duplo", "073-d_lego_duplo",
              "073-f_lego_duplo")
YCB_LARGE = ("002_master_chef_can", "004_sugar_box", "006_mustard_bottle", "065-j_cups",
             "071_nine_hole_peg_test", "051_large_clamp")
YCB_FLIPPED_PREFIX = "065-"
SOLID_PITCH = 0.002  # m
ENV = {"shapenet": "DSR_BENCH_SHAPENET", "ycb": "DSR_BENCH_YCB"}
LAYOUTS = {
    "shapenet": "ROOT/<synset>/<model_id>/models/model_normalized.obj (ShapeNetCore v2) or "
                "ROOT/[object_models/]shapenet/<synset>/<model_id>/ (official processed)",
    "ycb": "ROOT/<name>/google_16k/textured.obj (YCB release) or ROOT/[object_models/]ycb/<name>/ (official processed)",
}
_MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off")


def _missing(set_name: str, root: Path | None, detail: str) -> UserError:
    where = f"{root}" if root else f"no --object-root and ${ENV[set_name]} unset"
    return UserError(f"--objects {set_name}: {detail} ({where}); pass --object-root PATH or set {ENV[set_name]}; "
                     f"expected layout: {LAYOUTS[set_name]}")


def _cache_dir() -> Path:
    return Path(os.environ.get("DSR_BENCH_CACHE", Path.home() / ".cache" / "dsr-bench")) / "solids"


def _processed_mesh(model_dir: Path) -> Path | None:
    meshes = sorted(p for p in model_dir.iterdir() if p.suffix.lower() in _MESH_SUFFIXES and "collision" not in p.name)
    return meshes[0] if meshes else None


def load_solid(mesh_path: Path, binvox: Path | None = None, up_y: bool = False):
    """A closed trimesh solid (source units) from a mesh file: as is when watertight, else from the
    binvox or a filled 2 mm-equivalent voxelisation. Cached on disk by content hash."""
    import trimesh

    digest = hashlib.sha256(mesh_path.read_bytes()).hexdigest()[:32]
    cache = _cache_dir() / f"{digest}_{int(up_y)}.npz"
    if cache.exists():
        data = np.load(cache)
        return trimesh.Trimesh(data["vertices"], data["faces"], process=False)
    try:
        mesh = trimesh.load(mesh_path, force="mesh", process=True)
    except Exception as exc:
        raise UserError(f"{mesh_path}: cannot read mesh ({type(exc).__name__}: {exc}); replace the file") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise UserError(f"{mesh_path}: no triangles in the mesh file; replace the file")
    if up_y:  # ShapeNetCore v2 is y up: rotate +90 deg about x so that z is up
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    if not (mesh.is_watertight and mesh.volume > 0):
        grid = None
        if binvox is not None and binvox.exists() and not up_y:
            with open(binvox, "rb") as f:
                grid = trimesh.exchange.binvox.load_binvox(f)
        if grid is None:
            pitch = float(np.linalg.norm(mesh.extents)) / 96.0  # ~2 mm once scaled to a 0.15-0.2 m diagonal
            grid = mesh.voxelized(pitch).fill()
        solid = grid.marching_cubes
        solid.apply_transform(grid.transform)
        mesh = solid
        if not mesh.is_watertight:
            raise UserError(f"{mesh_path}: could not make a closed solid of this mesh; replace the file")
    if mesh.volume < 0:
        mesh.invert()
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_name(f".{cache.name}.{os.getpid()}.npz")
    np.savez(tmp, vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.faces))
    os.replace(tmp, cache)
    return mesh


def _resolve_root(set_name: str, object_root) -> Path:
    root = object_root or os.environ.get(ENV[set_name])
    root = Path(root).expanduser() if root else None
    if root is None or not root.is_dir():
        raise _missing(set_name, root, "mesh directory not found")
    return root


class ShapeNetSet:
    """The five ShapeNet training categories with the official scales and mix rules.

    The official 44 model ids are not listed in the release notes this toolkit follows: each category
    takes the first K ids (sorted) found in the copy, K being the official count; the official
    processed layout holds exactly the official models, so with it the set is the official one.
    """

    name = "shapenet"

    def __init__(self, object_root=None):
        root = _resolve_root(self.name, object_root)
        self.models: dict[str, list[tuple[str, Path, Path | None, bool]]] = {}
        base = next((b for b in (root / "object_models" / "shapenet", root / "shapenet", root)
                     if any((b / s).is_dir() for s, _ in SHAPENET_SYNSETS.values())), None)
        if base is None:
            raise _missing(self.name, root, "no ShapeNet synset directories (e.g. 02876657)")
        for category, (synset, count) in SHAPENET_SYNSETS.items():
            entries = []
            for model_dir in sorted(p for p in (base / synset).glob("*") if p.is_dir()):
                release = model_dir / "models" / "model_normalized.obj"
                if release.is_file():
                    entries.append((model_dir.name, release, None, True))
                elif (mesh := _processed_mesh(model_dir)) is not None:
                    entries.append((model_dir.name, mesh, model_dir / "model_com.binvox", False))
            if not entries:
                raise _missing(self.name, root, f"no {category} models in {base / synset}")
            self.models[category] = entries[:count]

    def _load(self, category: str, rng: np.random.Generator, large: bool) -> ObjectSpec:
        model_id, mesh_path, binvox, up_y = self.models[category][int(rng.integers(len(self.models[category])))]
        low, high = CATEGORY_SCALES[category][1 if large else 0]
        scale = float(rng.uniform(low, high))
        solid = load_solid(mesh_path, binvox, up_y).copy()
        solid.apply_scale(NORMALISED_DIAGONAL * scale / float(np.linalg.norm(solid.extents)))
        solid.apply_translation([0, 0, -solid.bounds[0, 2]])
        return make_spec(self.name, category, model_id, scale, [solid], random_color(rng), large)

    def sample(self, rng: np.random.Generator, count: int) -> list[ObjectSpec]:
        large = int(rng.integers(count)) if rng.random() < P_LARGE else -1
        out = []
        for i in range(count):
            category = str(rng.choice(tuple(SHAPENET_SYNSETS)))
            if rng.random() < P_FORCE_CAN:
                category = "can"
            if i != large and rng.random() < P_RANDOM_BOX:
                out.append(_small_box(rng, self.name))
            else:
                out.append(self._load(category, rng, i == large))
        return out


class YCBSet:
    """The official YCB novel-object lists (normal, and one optional large object per scene)."""

    name = "ycb"

    def __init__(self, object_root=None):
        root = _resolve_root(self.name, object_root)
        base = next((b for b in (root / "object_models" / "ycb", root / "ycb", root)
                     if any((b / n).is_dir() for n in YCB_NORMAL + YCB_LARGE)), root)
        self.models: dict[str, tuple[Path, Path | None]] = {}
        missing = []
        for name in YCB_NORMAL + YCB_LARGE:
            d = base / name
            found = next((d / sub for sub in ("google_16k/textured.obj", "tsdf/textured.obj", "poisson/textured.ply")
                          if (d / sub).is_file()), None)
            if found is None and d.is_dir():
                found = _processed_mesh(d)
            if found is None:
                missing.append(name)
            else:
                self.models[name] = (found, d / "model_com.binvox")
        if missing:
            raise _missing(self.name, root, f"{len(missing)} of {len(YCB_NORMAL + YCB_LARGE)} models missing "
                                            f"({', '.join(missing[:4])}{', ...' if len(missing) > 4 else ''})")

    def _load(self, name: str, rng: np.random.Generator, large: bool) -> ObjectSpec:
        import trimesh

        mesh_path, binvox = self.models[name]
        solid = load_solid(mesh_path, binvox).copy()
        if name.startswith(YCB_FLIPPED_PREFIX):
            solid.apply_transform(trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0]))
        solid.apply_translation([0, 0, -solid.bounds[0, 2]])
        return make_spec(self.name, name, name, 1.0, [solid], random_color(rng), large)

    def sample(self, rng: np.random.Generator, count: int) -> list[ObjectSpec]:
        large = int(rng.integers(count)) if rng.random() < P_LARGE else -1
        return [self._load(str(rng.choice(YCB_LARGE if i == large else YCB_NORMAL)), rng, i == large)
                for i in range(count)]


def open_external_set(name: str, object_root=None):
    """The ShapeNet or YCB set from the user's copy (checked now, before any generation)."""
    return ShapeNetSet(object_root) if name == "shapenet" else YCBSet(object_root)
