"""Closed solids from meshes we did not write: binvox reading, voxel filling, marching cubes, disk cache.

All lengths are in the source file's units (ShapeNet: unit bounding-box diagonal; YCB: metres);
voxel grids are indexed (x, y, z) with voxel i centred at origin + (i + 0.5) * pitch (the binvox spec).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from dsr_bench.atomic import atomic_path, clean_temporaries
from dsr_bench.errors import UserError

#: Bump when the solid-making method changes, so that cached solids are rebuilt.
SOLID_METHOD_VERSION = 3
#: Rays per point for the inside test of open meshes (majority vote of ray-crossing parities).
OCCUPANCY_RAYS = 9
MAX_GRID = 160  # voxels along the longest side of a voxelisation


def _trimesh():
    import trimesh

    return trimesh


def cache_dir() -> Path:
    """Where processed solids are kept: $DSR_BENCH_CACHE/solids (default ~/.cache/dsr-bench/solids)."""
    return Path(os.environ.get("DSR_BENCH_CACHE") or Path.home() / ".cache" / "dsr-bench") / "solids"


def read_binvox(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a binvox file: occupancy (X, Y, Z) bool, grid origin (3,) and voxel pitch (3,) in the
    model's units, so that voxel (i, j, k) is centred at origin + ((i, j, k) + 0.5) * pitch."""
    try:
        with open(path, "rb") as f:
            if not f.readline().startswith(b"#binvox"):
                raise ValueError("not a binvox file (no '#binvox' header)")
            header: dict[str, list[str]] = {}
            while True:
                line = f.readline()
                if not line:
                    raise ValueError("header ends before 'data'")
                words = line.decode("ascii").split()
                if words and words[0] == "data":
                    break
                if words:
                    header[words[0]] = words[1:]
            dims = np.array([int(v) for v in header["dim"]], dtype=np.int64)
            translate = np.array([float(v) for v in header.get("translate", ["0", "0", "0"])], dtype=np.float64)
            scale = float(header.get("scale", ["1"])[0])
            raw = np.frombuffer(f.read(), dtype=np.uint8)
    except (OSError, ValueError, KeyError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: unreadable binvox file ({exc}); replace it or delete it to voxelise the "
                        "mesh") from None
    if dims.shape != (3,) or np.any(dims <= 0) or translate.shape != (3,) or not scale > 0 or len(raw) % 2:
        raise UserError(f"{path}: malformed binvox header or data; replace it or delete it to voxelise the mesh")
    values, counts = raw[0::2], raw[1::2].astype(np.int64)
    if counts.sum() != dims.prod():
        raise UserError(f"{path}: binvox data holds {counts.sum()} voxels, its header says {dims.prod()}; "
                        "replace it or delete it to voxelise the mesh")
    flat = np.repeat(values > 0, counts)
    occupancy = flat.reshape(dims[0], dims[2], dims[1]).transpose(0, 2, 1)  # stored x-z-y, y fastest
    return occupancy, translate, scale / dims.astype(np.float64)


def mesh_from_occupancy(occupancy: np.ndarray, origin: np.ndarray, pitch: np.ndarray):
    """A closed, outward-oriented trimesh around the occupied voxels (marching cubes at the 0.5 level,
    so the surface passes halfway between occupied and free voxel centres)."""
    from skimage.measure import marching_cubes

    tm = _trimesh()
    if not occupancy.any():
        raise ValueError("no occupied voxel")
    padded = np.pad(occupancy.astype(np.float32), 1)
    verts, faces, _, _ = marching_cubes(padded, level=0.5)
    verts = (verts - 1.0 + 0.5) * np.asarray(pitch, np.float64) + np.asarray(origin, np.float64)
    mesh = tm.Trimesh(verts.astype(np.float64), faces.astype(np.int64), process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def voxelise_open_mesh(mesh, pitch: float, fill_columns: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Occupancy (X, Y, Z), grid origin and pitch (raised to fit MAX_GRID voxels) of a possibly open
    mesh: voxels whose centre lies within half a pitch of the surface, plus those a majority of
    ray-parity tests put inside, with enclosed cavities filled.
    fill_columns: also fill every column below its highest occupied voxel (hollow bases, e.g. Duplo)."""
    import open3d as o3d
    from scipy import ndimage

    lo, hi = mesh.bounds
    pitch = max(float(pitch), float(np.max(hi - lo)) / MAX_GRID)
    origin = lo - pitch  # one free voxel of margin
    shape = np.ceil((hi - lo) / pitch).astype(np.int64) + 2
    axes = [origin[a] + (np.arange(shape[a]) + 0.5) * pitch for a in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).astype(np.float32)

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    query = o3d.core.Tensor(centres)
    inside = scene.compute_occupancy(query, nsamples=OCCUPANCY_RAYS).numpy() > 0
    # voxels the surface passes within half a pitch of: at least one layer under any surface, so thin
    # walls survive and holes narrower than a voxel are sealed before the cavity fill
    inside |= scene.compute_distance(query).numpy() <= 0.5 * pitch
    inside = ndimage.binary_fill_holes(inside)
    if fill_columns:
        top = inside.shape[2] - 1 - np.argmax(inside[:, :, ::-1], axis=2)
        any_z = inside.any(axis=2)
        z = np.arange(inside.shape[2])
        inside = any_z[:, :, None] & (z[None, None, :] <= top[:, :, None])
        inside[:, :, 0] = False  # keep the margin free
    return inside, origin, pitch


def load_mesh(path: Path):
    """A trimesh from a mesh file we did not write; UserError when it cannot be read or has no triangles."""
    tm = _trimesh()
    try:
        mesh = tm.load(path, force="mesh", process=True, skip_materials=True)
    except Exception as exc:  # trimesh raises many types on bad files
        raise UserError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc}); replace the file") from None
    if not isinstance(mesh, tm.Trimesh) or len(mesh.faces) == 0:
        raise UserError(f"{path}: no triangles in the mesh file; replace the file")
    if not np.all(np.isfinite(mesh.vertices)):
        raise UserError(f"{path}: non-finite vertex coordinates; replace the file")
    return mesh


def _file_digest(path: Path | None) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path is not None else "-"


def load_solid(mesh_path: Path, binvox: Path | None = None, *, pitch: float | None = None,
               fill_columns: bool = False):
    """A closed, outward-oriented trimesh solid in the source file's units and frame.

    A watertight mesh with positive volume is used as is; otherwise the solid is the shipped binvox
    (when given and present) or a voxelisation of the mesh at 1/96 of its bounding-box diagonal, or
    at `pitch` (source units) when that is finer, meshed by marching cubes. fill_columns forces the
    voxelisation and fills hollow bases. Results are cached on disk keyed by the source files' hashes."""
    tm = _trimesh()
    binvox = binvox if binvox is not None and binvox.is_file() else None
    key = hashlib.sha256(f"v{SOLID_METHOD_VERSION}|{_file_digest(mesh_path)}|{_file_digest(binvox)}|"
                         f"{pitch!r}|{fill_columns}".encode()).hexdigest()[:40]
    cache = cache_dir() / f"{key}.npz"
    if cache.is_file():
        try:
            with np.load(cache) as data:
                vertices, faces = data["vertices"].astype(np.float64), data["faces"].astype(np.int64)
            mesh = tm.Trimesh(vertices, faces, process=False)
            if mesh.is_watertight and mesh.volume > 0:
                return mesh
        except Exception:  # a damaged cache entry is rebuilt below
            pass
    mesh = load_mesh(mesh_path)
    if fill_columns or not (mesh.is_watertight and mesh.volume > 0):
        if binvox is not None and not fill_columns:
            occupancy, origin, vox_pitch = read_binvox(binvox)
        else:
            step = float(np.linalg.norm(mesh.extents)) / 96.0
            step = step if pitch is None else min(step, float(pitch))
            occupancy, origin, used = voxelise_open_mesh(mesh, step, fill_columns=fill_columns)
            vox_pitch = np.full(3, used)
        try:
            mesh = mesh_from_occupancy(occupancy, origin, vox_pitch)
        except ValueError:
            raise UserError(f"{mesh_path}: the mesh encloses no volume; replace the file") from None
        if not (mesh.is_watertight and mesh.volume > 0):
            raise UserError(f"{mesh_path}: could not make a closed solid of this mesh; replace the file")
    elif mesh.volume < 0:
        mesh.invert()
    cache.parent.mkdir(parents=True, exist_ok=True)
    clean_temporaries(cache.parent, cache.name)  # a killed run's partial entry (never a live writer's)
    with atomic_path(cache) as tmp, open(tmp, "wb") as f:  # a file object: np.savez would add .npz to a name
        np.savez(f, vertices=np.asarray(mesh.vertices, np.float64), faces=np.asarray(mesh.faces, np.int64))
    return tm.Trimesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), process=False)
