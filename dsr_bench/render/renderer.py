"""Observations of a scene of posed object meshes: images, TSDF, heightmap and amodal voxels.

Rendering is exact rasterisation of the object meshes (`dsr_bench.render.raster`) over an analytic table
plane: z-depth, instance masks and world points come from the same pixel-centre samples, and the
same bits on every x86-64 CPU (no ray tracer that picks its code path by instruction set, no BLAS,
no transcendental function). Amodal occupancy counts surface crossings of each object's closed
solid parts along vertical lines: a voxel belongs to an object when its solid meets the voxel-sized
cube around the voxel's sample point, on a sub-grid of MASK_SUBSAMPLES per axis (the official
masks: a dense solid point set rounded to the nearest sample point). Independent of the physics
engine: it sees meshes and poses only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dsr_bench.cache import FrozenCache, camera_key
from dsr_bench.constants import (
    GRID_BOUNDS,
    GRID_SHAPE,
    MASK_SUBSAMPLES,
    VOXEL_SAMPLE_OFFSET,
    VOXEL_SIZE,
)
from dsr_bench.geometry import Camera, pose_to_matrix, transform_points
from dsr_bench.geometry.tsdf import ProjectiveTSDF
from dsr_bench.render import raster

TABLE_COLOR = np.array([0.78, 0.74, 0.66])
_LIGHT = np.array([0.3, -0.5, 0.81])
LIGHT_DIRECTION = _LIGHT / np.sqrt(_LIGHT[0] * _LIGHT[0] + _LIGHT[1] * _LIGHT[1] + _LIGHT[2] * _LIGHT[2])
#: The table: the plane z = 0 over this square around the workspace centre (m).
TABLE_HALF_SIZE = 1.0
TABLE_CENTRE = (0.5, 0.0)
#: Camera-frame z (m) a vertex must exceed to be drawn (objects behind a camera are not seen).
NEAR_PLANE = 1e-3
#: Heightmap samples per cell and axis (4: every 1 mm).
HEIGHTMAP_SUBSAMPLES = 4


@dataclass
class CameraImages:
    """One camera's view: colour (H,W,3) uint8, z-depth (H,W) m, visible ids (H,W), world points (H,W,3)."""

    color: np.ndarray
    depth: np.ndarray
    mask: np.ndarray
    points: np.ndarray


@dataclass
class Observation:
    """Everything observed or known at one time step."""

    images: dict[str, CameraImages]
    tsdf: np.ndarray  # (Y, X, Z) float32
    heightmap: np.ndarray  # (Y, X) float32 metres
    mask_3d: np.ndarray  # (Y, X, Z) uint8
    visible_fraction: np.ndarray  # (N,) float32


@dataclass(frozen=True)
class PosedScene:
    """The objects' triangles at one set of poses, in the world frame.

    vertices (V, 3) m; faces (F, 3); instance (F,) object id i + 1 of each face; normals (F, 3) unit
    world normals; parts: per object, the (first, stop) face ranges of its closed parts."""

    vertices: np.ndarray
    faces: np.ndarray
    instance: np.ndarray
    normals: np.ndarray
    parts: tuple[tuple[tuple[int, int], ...], ...]


def _triangle_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normals (F, 3) of triangles (right-hand rule), each product written out in a fixed order."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    u, v = b - a, c - a
    n = np.stack([u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1], u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2],
                  u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]], axis=1)
    length = np.sqrt(n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1] + n[:, 2] * n[:, 2])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(length[:, None] > 0, n / length[:, None], 0.0)


#: The table's rendering per camera (rays, depth, shade) and its TSDF, built once per process: a renderer
#: is made for every scene attempt, and these cost more than rendering a step.
_TABLE_VIEWS = FrozenCache(16)


def _table_view(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rays (H*W, 6) float64 origin + direction with unit camera z, table depth (H*W,) float64 with
    inf where the ray misses the table, table shade (H*W,)): analytic ray-plane intersection."""
    return _TABLE_VIEWS.get(camera_key(camera), lambda: _build_table_view(camera))


def _build_table_view(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    dirs = camera.ray_directions_world().reshape(-1, 3)
    origin = np.asarray(camera.extrinsics, np.float64)[:3, 3]
    rays = np.hstack([np.broadcast_to(origin, dirs.shape), dirs])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(dirs[:, 2] < 0, (0.0 - origin[2]) / dirs[:, 2], np.inf)
    x = origin[0] + dirs[:, 0] * t
    y = origin[1] + dirs[:, 1] * t
    on_table = ((t > 0) & (np.abs(x - TABLE_CENTRE[0]) <= TABLE_HALF_SIZE)
                & (np.abs(y - TABLE_CENTRE[1]) <= TABLE_HALF_SIZE))
    depth = np.where(on_table, t, np.inf)
    shade = np.full(len(depth), _shade(np.abs(LIGHT_DIRECTION[2])))
    return rays, depth, shade


def _shade(cos_abs):
    """Lambertian shade 0.35 + 0.65 * clip(|n . l|, 0, 1)."""
    return 0.35 + 0.65 * np.clip(cos_abs, 0.0, 1.0)


def _column_space(vertices: np.ndarray, scale: int = 1, offset: float = 0.5) -> np.ndarray:
    """Column coordinates (V, 2) = (u along x, v along y) of world vertices on a grid of `scale`
    columns per cell: column s along an axis samples bound_min + (s + 0.5) / scale * VOXEL_SIZE
    - (0.5 - offset) * VOXEL_SIZE. scale 1, offset 0.5: the heightmap's cell centres; scale
    MASK_SUBSAMPLES, offset VOXEL_SAMPLE_OFFSET: the sub-samples of the voxels' cubes."""
    shift = (0.5 - offset) * scale - 0.5
    u = (vertices[:, 0] - GRID_BOUNDS[0, 0]) / VOXEL_SIZE * scale + shift
    v = (vertices[:, 1] - GRID_BOUNDS[1, 0]) / VOXEL_SIZE * scale + shift
    return np.stack([u, v], axis=1)


#: Heights (m) of the voxels' vertical sub-samples, (Z * MASK_SUBSAMPLES,), increasing.
_Z_SUBSAMPLES = GRID_BOUNDS[2, 0] + VOXEL_SIZE * (
    (np.arange(GRID_SHAPE[2] * MASK_SUBSAMPLES) + 0.5) / MASK_SUBSAMPLES - 0.5 + VOXEL_SAMPLE_OFFSET)


class SceneRenderer:
    """Renders the benchmark's observations of a fixed set of objects at any poses (made by
    `dsr_bench.render.create_renderer`, which names the cameras).

    objects: sequence of ObjectSpec-like items with `.parts` (each `.vertices` (V,3) m, `.faces` (F,3))
    and `.color` (RGB 0..1); cameras: name -> `dsr_bench.geometry.Camera` of the images ('front' for the
    visible fractions); tsdf_camera: the camera whose fine depth image the TSDF is fused from.
    """

    def __init__(self, objects, cameras: dict[str, Camera], tsdf_camera: Camera):
        self.parts = [[(np.asarray(p.vertices, np.float64), np.asarray(p.faces, np.int64)) for p in obj.parts]
                      for obj in objects]
        self.colors = np.array([obj.color for obj in objects], dtype=np.float64).reshape(-1, 3)
        self.cameras: dict[str, Camera] = dict(cameras)
        self.tsdf_camera = tsdf_camera
        self._tsdf = ProjectiveTSDF(self.tsdf_camera)
        self._palette = np.vstack([TABLE_COLOR, self.colors])

    # the posed scene -------------------------------------------------------------------------------
    def scene(self, poses: np.ndarray) -> tuple[PosedScene, np.ndarray]:
        """The objects' world triangles at `poses` (N, 7), and the instance id of each face (0 is the
        table, i + 1 object i); pass both to `render_camera`."""
        vertices, faces, instance, parts = [], [], [], []
        offset = first = 0
        for i, object_parts in enumerate(self.parts):
            matrix = pose_to_matrix(poses[i])
            ranges = []
            for v, f in object_parts:
                vertices.append(transform_points(matrix, v))
                faces.append(f + offset)
                instance.append(np.full(len(f), i + 1, dtype=np.int64))
                ranges.append((first, first + len(f)))
                offset += len(v)
                first += len(f)
            parts.append(tuple(ranges))
        all_vertices = np.vstack(vertices) if vertices else np.zeros((0, 3))
        all_faces = np.vstack(faces) if faces else np.zeros((0, 3), np.int64)
        face_instance = np.concatenate(instance) if instance else np.zeros(0, np.int64)
        scene = PosedScene(all_vertices, all_faces, face_instance, _triangle_normals(all_vertices, all_faces),
                           tuple(parts))
        return scene, face_instance

    # cameras ---------------------------------------------------------------------------------------
    @staticmethod
    def _camera_fragments(scene: PosedScene, camera: Camera) -> tuple[raster.Fragments, np.ndarray]:
        """Fragments of every face in `camera` and their z-depth (faces with a vertex nearer than the
        near plane are skipped)."""
        uv, z = camera.project(scene.vertices)
        uv = np.where((z > NEAR_PLANE)[:, None], uv, np.nan)
        fragments = raster.rasterize(uv, scene.faces, camera.height, camera.width)
        return fragments, raster.perspective_depth(fragments, scene.faces, z)

    @staticmethod
    def _first_hit(scene: PosedScene, camera: Camera, fragments, depth) -> tuple[np.ndarray, np.ndarray]:
        """Per pixel (H*W,) the z-depth of the first surface (inf where none) and the face it is on
        (-1 for the table or nothing)."""
        _, table_depth, _ = _table_view(camera)
        nearest, face = raster.nearest(fragments, depth, camera.height * camera.width)
        on_object = (face >= 0) & (nearest <= table_depth)
        return np.where(on_object, nearest, table_depth), np.where(on_object, face, -1)

    def render_camera(self, scene: PosedScene, ids: np.ndarray, name: str) -> CameraImages:
        """Colour, z-depth, visible ids and world points of camera `name`."""
        camera = self.cameras[name]
        return self._images(scene, ids, camera, *self._camera_fragments(scene, camera))

    def _images(self, scene: PosedScene, ids: np.ndarray, camera: Camera, fragments, frag_depth) -> CameraImages:
        rays, _, table_shade = _table_view(camera)
        depth64, face = self._first_hit(scene, camera, fragments, frag_depth)
        valid = np.isfinite(depth64)
        depth = np.where(valid, depth64, 0.0).astype(np.float32)
        on_face = face >= 0
        instance = np.where(on_face, ids[np.where(on_face, face, 0)], 0)
        normals = scene.normals[np.where(on_face, face, 0)]
        light = LIGHT_DIRECTION
        cos = normals[:, 0] * light[0] + normals[:, 1] * light[1] + normals[:, 2] * light[2]
        shade = np.where(on_face, _shade(np.abs(cos)), table_shade)
        color = self._palette[instance] * shade[:, None]
        color[~valid] = 0.0
        color = np.round(color * 255)
        # world points = origin + direction * (the stored float32 depth), NaN where nothing is hit
        points = rays[:, 3:] * depth.astype(np.float64)[:, None] + rays[:, :3]
        points[~valid] = np.nan
        h, w = camera.height, camera.width
        return CameraImages(color=color.astype(np.uint8).reshape(h, w, 3), depth=depth.reshape(h, w),
                            mask=instance.astype(np.uint8).reshape(h, w),
                            points=points.astype(np.float32).reshape(h, w, 3))

    def tsdf(self, scene: PosedScene) -> np.ndarray:
        """Front-view TSDF (Y, X, Z) float32 from a fine z-depth image (TSDF_IMAGE_SHAPE, float32)."""
        camera = self.tsdf_camera
        fragments, depth = self._camera_fragments(scene, camera)
        depth64, face = self._first_hit(scene, camera, fragments, depth)
        seen = np.where(np.isfinite(depth64), depth64, 0.0).astype(np.float32)
        pixels = self._tsdf.pixels
        return self._tsdf.update_pixels(self._table_tsdf(), seen[pixels], face[pixels] >= 0)

    def _table_tsdf(self) -> np.ndarray:
        """The TSDF of the table alone (cached per process and camera)."""
        def build() -> np.ndarray:
            _, table_depth, _ = _table_view(self.tsdf_camera)
            seen = np.where(np.isfinite(table_depth), table_depth, 0.0).astype(np.float32)
            return self._tsdf.from_pixel_depths(seen[self._tsdf.pixels])

        return _TABLE_VIEWS.get(("tsdf",) + camera_key(self.tsdf_camera), build)

    # top-down views --------------------------------------------------------------------------------
    @staticmethod
    def _columns(vertices: np.ndarray, faces: np.ndarray, scale: int = 1, offset: float = 0.5
                 ) -> tuple[raster.Fragments, np.ndarray]:
        """Fragments of `faces` over the grid's columns (orthographic, looking down; see
        `_column_space`) and their z."""
        fragments = raster.rasterize(_column_space(vertices, scale, offset), faces, GRID_SHAPE[0] * scale,
                                     GRID_SHAPE[1] * scale)
        return fragments, raster.interpolate(fragments, faces, vertices[:, 2])

    def heightmap(self, scene: PosedScene) -> np.ndarray:
        """Top-down heightmap (Y, X) float32 in metres over the workspace cells (what the policy sees):
        the highest surface over each cell, 0 on the table, sampled on HEIGHTMAP_SUBSAMPLES^2 points
        of the cell (the official heightmap bins a top-down point cloud into the cells: a cell that an
        object covers in part is as high as the object)."""
        k = HEIGHTMAP_SUBSAMPLES
        fragments, z = self._columns(scene.vertices, scene.faces, k, 0.5)
        fine = raster.highest(fragments, z, GRID_SHAPE[0] * GRID_SHAPE[1] * k * k)
        cells = fine.reshape(GRID_SHAPE[0], k, GRID_SHAPE[1], k).max(axis=(1, 3))
        return cells.astype(np.float32)

    def amodal_mask(self, poses_or_scene) -> np.ndarray:
        """Amodal instance ids (Y, X, Z) uint8: the voxels whose cube (one voxel's edge, centred on
        the sample point) meets each object's solid at its pose, tested on MASK_SUBSAMPLES^3
        sub-samples (a voxel of two objects goes to the lower id)."""
        scene = poses_or_scene if isinstance(poses_or_scene, PosedScene) else self.scene(poses_or_scene)[0]
        k = MASK_SUBSAMPLES
        sub_width = GRID_SHAPE[1] * k
        levels = GRID_SHAPE[2]
        mask = np.zeros((GRID_SHAPE[0] * GRID_SHAPE[1], levels), dtype=np.uint8)
        for i, ranges in enumerate(scene.parts):
            runs = []
            for first, stop in ranges:  # parts of one object: their union
                fragments, z = self._columns(scene.vertices, scene.faces[first:stop], k, VOXEL_SAMPLE_OFFSET)
                columns, lo, hi = raster.solid_intervals(fragments, z, _Z_SUBSAMPLES)
                cell = (columns // sub_width // k) * GRID_SHAPE[1] + (columns % sub_width) // k
                runs.append((cell, lo // k, (hi - 1) // k + 1))  # the voxel levels the run touches
            cell, lo, hi = (np.concatenate(parts) for parts in zip(*runs))
            if len(cell) == 0:
                continue
            touched, which = np.unique(cell, return_inverse=True)
            count = np.zeros((len(touched), levels + 1), dtype=np.int32)
            np.add.at(count, (which, lo), 1)
            np.add.at(count, (which, hi), -1)
            inside = np.cumsum(count[:, :-1], axis=1) > 0
            block = mask[touched]
            block[inside & (block == 0)] = i + 1
            mask[touched] = block
        return mask.reshape(GRID_SHAPE)

    # visibility ------------------------------------------------------------------------------------
    def visible_fraction(self, poses_or_scene, visible_mask: np.ndarray, fragments=None) -> np.ndarray:
        """Visible / amodal silhouette pixels of each object in the front camera, (N,) float32."""
        scene = poses_or_scene if isinstance(poses_or_scene, PosedScene) else self.scene(poses_or_scene)[0]
        camera = self.cameras["front"]
        if fragments is None:
            fragments = self._camera_fragments(scene, camera)[0]
        owner = scene.instance[fragments.triangle]
        out = np.zeros(len(self.parts), dtype=np.float32)
        counts = np.bincount(visible_mask.reshape(-1), minlength=len(self.parts) + 1)
        for i in range(len(self.parts)):
            silhouette = len(np.unique(fragments.sample[owner == i + 1]))
            out[i] = min(1.0, counts[i + 1] / silhouette) if silhouette else 0.0
        return out

    # observation -----------------------------------------------------------------------------------
    def observe(self, poses: np.ndarray) -> Observation:
        """Render every observation of the objects at `poses` (N, 7)."""
        scene, ids = self.scene(poses)
        images, front_fragments = {}, None
        for name, camera in self.cameras.items():
            fragments, depth = self._camera_fragments(scene, camera)
            images[name] = self._images(scene, ids, camera, fragments, depth)
            if name == "front":
                front_fragments = fragments
        return Observation(
            images=images,
            tsdf=self.tsdf(scene),
            heightmap=self.heightmap(scene),
            mask_3d=self.amodal_mask(scene),
            visible_fraction=self.visible_fraction(scene, images["front"].mask, front_fragments),
        )
