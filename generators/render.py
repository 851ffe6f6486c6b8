"""Observations of a scene of posed object meshes: images, TSDF, heightmap and amodal voxels.

Rendering is exact ray casting of the object meshes (open3d's Embree-backed RaycastingScene), not a
rasteriser approximation: z-depth, instance masks and world points come from the same ray hits.
Amodal occupancy is evaluated at voxel centres against each object's closed solids, so `mask_3d` is
the true solid at the exact pose. Independent of the physics engine: it sees meshes and poses only.

Speed without changing a bit: rays, the table and the TSDF's voxel projections are built once per
process; `observe` casts only the rays that pass near an object (a ray's hit depends on that ray and
the triangles it meets alone), takes every other pixel, heightmap cell and TSDF voxel from the
cached table-only rendering, and the TSDF reads only the pixels its voxels project to.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dsr_bench.constants import GRID_BOUNDS, GRID_SHAPE, IMAGE_SHAPE, TSDF_IMAGE_SHAPE, VOXEL_SIZE
from dsr_bench.geometry import Camera, dot_last, make_camera, pose_to_matrix, transform_points, vector_norm
from dsr_bench.tsdf import ProjectiveTSDF

TABLE_COLOR = np.array([0.78, 0.74, 0.66])
LIGHT_DIRECTION = np.array([0.3, -0.5, 0.81]) / vector_norm(np.array([0.3, -0.5, 0.81]))
_TABLE_HALF_SIZE = 1.0
_HEIGHTMAP_RAY_START = 1.0


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


def _transform(vertices: np.ndarray, pose: np.ndarray) -> np.ndarray:
    m = pose_to_matrix(pose)
    return transform_points(m, vertices)


def _camera_key(camera: Camera) -> tuple:
    return (camera.height, camera.width, np.asarray(camera.intrinsics, np.float64).tobytes(),
            np.asarray(camera.extrinsics, np.float64).tobytes())


#: Constant inputs of every renderer (camera and heightmap rays, the table), built once per process:
#: a renderer is made for every scene attempt, and these cost more than rendering a step.
_CACHE: dict[tuple, object] = {}
_MAX_CACHED = 64


def _cached(key: tuple, build):
    hit = _CACHE.get(key)
    if hit is None:
        hit = build()
        if len(_CACHE) >= _MAX_CACHED:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = hit
    return hit


def _frozen(value):
    """`value` (an array or a dataclass of arrays) made read-only, for the per-process cache."""
    for a in vars(value).values() if hasattr(value, "__dataclass_fields__") else (value,):
        a.setflags(write=False)
    return value


def _faces_tensor(o3d, faces: np.ndarray):
    return o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32))


class SceneRenderer:
    """Renders the benchmark's observations of a fixed set of objects at any poses.

    objects: sequence of ObjectSpec-like items with `.parts` (each `.vertices` (V,3) m, `.faces` (F,3))
    and `.color` (RGB 0..1); cameras: names of the benchmark's cameras ('front', optionally 'back') at
    `image_shape`, or a dict name -> `dsr_bench.geometry.Camera` (e.g. a capture's calibrated cameras).
    """

    def __init__(self, objects, cameras: tuple[str, ...] | dict[str, Camera] = ("front",), image_shape=IMAGE_SHAPE,
                 tsdf_image_shape=TSDF_IMAGE_SHAPE):
        import open3d as o3d

        self._o3d = o3d
        self.parts = [[(np.asarray(p.vertices, np.float64), np.asarray(p.faces, np.int64)) for p in obj.parts]
                      for obj in objects]
        self._faces = [[_faces_tensor(o3d, f) for _, f in parts] for parts in self.parts]
        self.colors = np.array([obj.color for obj in objects], dtype=np.float64).reshape(-1, 3)
        self.cameras: dict[str, Camera] = dict(cameras) if isinstance(cameras, dict) else {
            name: make_camera(name, *image_shape) for name in cameras}
        self.tsdf_camera = make_camera("front", *tsdf_image_shape)
        self._rays = {name: self._camera_rays(cam) for name, cam in self.cameras.items()}
        self._tsdf_rays = self._camera_rays(self.tsdf_camera)
        self._tsdf = ProjectiveTSDF(self.tsdf_camera)
        self._tsdf_key = (_camera_key(self.tsdf_camera), self._tsdf.truncation, self._tsdf.grid_shape)
        self._tsdf_pixel_rays = _cached(("tsdf-pixel-rays",) + self._tsdf_key, lambda: o3d.core.Tensor(
            np.ascontiguousarray(self._tsdf_rays.numpy()[self._tsdf.pixels])))
        self._heightmap_rays = _cached(("heightmap-rays",), lambda: self._make_heightmap_rays(o3d))
        self._table = self._table_mesh()
        self._table_tensors = _cached(("table",), lambda: tuple(
            o3d.core.Tensor(a) for a in (self._table[0].astype(np.float32), self._table[1].astype(np.uint32))))
        self._rays64: dict[str, tuple] = {}

    # ray helpers -----------------------------------------------------------------------------------
    @staticmethod
    def _make_heightmap_rays(o3d):
        rows, cols = np.meshgrid(np.arange(GRID_SHAPE[0]), np.arange(GRID_SHAPE[1]), indexing="ij")
        x = GRID_BOUNDS[0, 0] + (cols + 0.5) * VOXEL_SIZE
        y = GRID_BOUNDS[1, 0] + (rows + 0.5) * VOXEL_SIZE
        origins = np.stack([x, y, np.full_like(x, _HEIGHTMAP_RAY_START)], -1).reshape(-1, 3)
        down = np.broadcast_to([0.0, 0.0, -1.0], origins.shape)
        return o3d.core.Tensor(np.hstack([origins, down]).astype(np.float32))

    def _camera_rays(self, camera: Camera):
        """The camera's rays (H*W, 6) float32 tensor (origin, z-unit direction), cached per process."""
        def build():
            dirs = camera.ray_directions_world().reshape(-1, 3)
            origins = np.broadcast_to(camera.extrinsics[:3, 3], dirs.shape)
            return self._o3d.core.Tensor(np.hstack([origins, dirs]).astype(np.float32))
        return _cached(("camera-rays", _camera_key(camera)), build)

    def _rays_float64(self, name: str) -> np.ndarray:
        """Camera `name`'s rays as float64 numpy (N, 6), converted once per rays tensor."""
        rays = self._rays[name]
        hit = self._rays64.get(name)
        if hit is None or hit[0] is not rays:
            hit = (rays, rays.numpy().astype(np.float64))
            self._rays64[name] = hit
        return hit[1]

    @staticmethod
    def _table_mesh() -> tuple[np.ndarray, np.ndarray]:
        cx, cy, h = 0.5, 0.0, _TABLE_HALF_SIZE
        verts = np.array([[cx - h, cy - h, 0], [cx + h, cy - h, 0], [cx + h, cy + h, 0], [cx - h, cy + h, 0]], float)
        return verts, np.array([[0, 1, 2], [0, 2, 3]])

    def scene(self, poses: np.ndarray):
        """The raycasting scene of the table and the objects at `poses` (N, 7), and the instance id of each
        geometry (0 = table, i + 1 = object i); pass both to `render_camera`."""
        return self._scene(poses)

    def _scene(self, poses: np.ndarray, objects: list[int] | None = None, table: bool = True, world=None):
        """A raycasting scene and the instance id (0 = table) of each geometry id.

        world: the objects' posed parts (`_posed_parts(poses)`), if at hand."""
        o3d = self._o3d
        scene = o3d.t.geometry.RaycastingScene()
        ids = []
        if table:
            scene.add_triangles(*self._table_tensors)
            ids.append(0)
        for i in objects if objects is not None else range(len(self.parts)):
            posed = world[i] if world is not None else self._posed_object(i, poses[i])
            for (vertices, _), f in zip(posed, self._faces[i]):
                scene.add_triangles(vertices, f)
                ids.append(i + 1)
        return scene, np.array(ids, dtype=np.int64)

    def _posed_object(self, i: int, pose: np.ndarray) -> list[tuple]:
        """Object i's parts at `pose`: (float32 vertex tensor, float64 vertices) per part."""
        out = []
        for v, _ in self.parts[i]:
            posed = _transform(v, pose)
            out.append((self._o3d.core.Tensor(posed.astype(np.float32)), posed))
        return out

    def _posed_parts(self, poses: np.ndarray) -> list[list[tuple]]:
        """Every object's `_posed_object`: computed once per observation and shared by its parts."""
        return [self._posed_object(i, poses[i]) for i in range(len(self.parts))]

    # rays that miss every object -------------------------------------------------------------------
    def _table_hits(self, kind: tuple, rays) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t_hit, geometry_ids, primitive_normals) of `rays` cast against the table alone, per process.

        A ray that passes no object hits exactly this in any scene: Embree's hit of a ray on a
        triangle is computed from that ray and triangle only (and the table is geometry 0 of every
        scene). `observe` casts only the rays near an object and takes the rest from here."""
        def build():
            scene = self._o3d.t.geometry.RaycastingScene()
            scene.add_triangles(*self._table_tensors)
            result = scene.cast_rays(rays)
            out = tuple(np.array(result[k].numpy()) for k in ("t_hit", "geometry_ids", "primitive_normals"))
            for a in out:
                a.setflags(write=False)
            return out
        return _cached(("table-hits",) + kind, build)

    def _cast_near(self, scene, rays, table, near: np.ndarray | None):
        """(t_hit, geometry_ids, primitive_normals) of every ray: those flagged `near` (None: all) are
        cast in `scene`, the others take their table-only hit."""
        if near is None:
            result = scene.cast_rays(rays)
            return tuple(result[k].numpy() for k in ("t_hit", "geometry_ids", "primitive_normals"))
        t, geom, normals = (a.copy() for a in table)
        index = np.flatnonzero(near)
        if len(index):
            result = scene.cast_rays(self._o3d.core.Tensor(rays.numpy()[index]))
            t[index] = result["t_hit"].numpy()
            geom[index] = result["geometry_ids"].numpy()
            normals[index] = result["primitive_normals"].numpy()
        return t, geom, normals

    @staticmethod
    def _near_pixels(camera: Camera, world: list[np.ndarray]) -> np.ndarray | None:
        """Pixels (H*W,) bool whose ray may hit an object: each object's projected vertex box with a
        pixel of margin (its triangles project inside it); None (every pixel) when a vertex is not
        well in front of the camera."""
        near = np.zeros((camera.height, camera.width), dtype=bool)
        size = np.array([camera.width, camera.height])
        for allv in world:
            uv, z = camera.project(allv)
            if not (np.all(z > 1e-3) and np.all(np.isfinite(uv))):
                return None
            u0, v0 = np.clip(np.floor(uv.min(0)).astype(int) - 1, 0, size)
            u1, v1 = np.clip(np.ceil(uv.max(0)).astype(int) + 2, 0, size)
            near[v0:v1, u0:u1] = True
        return near.reshape(-1)

    @staticmethod
    def _near_cells(world: list[np.ndarray]) -> np.ndarray:
        """Heightmap cells (Y*X,) bool whose vertical ray may hit an object: each object's xy vertex
        box, widened by a cell."""
        near = np.zeros(GRID_SHAPE[:2], dtype=bool)
        size = np.array([GRID_SHAPE[1], GRID_SHAPE[0]])  # (x, y) cells
        for allv in world:
            lo = np.floor((allv[:, :2].min(0) - GRID_BOUNDS[:2, 0]) / VOXEL_SIZE).astype(int) - 1
            hi = np.ceil((allv[:, :2].max(0) - GRID_BOUNDS[:2, 0]) / VOXEL_SIZE).astype(int) + 2
            (c0, r0), (c1, r1) = np.clip(lo, 0, size), np.clip(hi, 0, size)
            near[r0:r1, c0:c1] = True
        return near.reshape(-1)

    # observation -----------------------------------------------------------------------------------
    def render_camera(self, scene, ids, name: str) -> CameraImages:
        """Colour, z-depth, visible ids and world points of camera `name`."""
        return self._camera_images(name, ids, *self._cast_near(scene, self._rays[name], None, None))

    def _camera_images(self, name: str, ids, t: np.ndarray, geometry_ids: np.ndarray,
                       normals: np.ndarray) -> CameraImages:
        camera = self.cameras[name]
        valid = np.isfinite(t)  # t: float32, inf where no hit
        invalid = ~valid
        h, w = camera.height, camera.width
        depth = np.where(valid, t, np.float32(0.0))
        instance = np.where(valid, ids[np.where(valid, geometry_ids, 0)], 0)
        # colour = (table or object colour) * Lambertian shade, 0 where no hit; same arithmetic as
        # base * (0.35 + 0.65 * clip(|n . l|, 0, 1)) in float64, then round(x * 255)
        palette = np.vstack([TABLE_COLOR, self.colors])
        color = palette[instance]
        shade = dot_last(normals, LIGHT_DIRECTION)
        np.abs(shade, out=shade)
        np.clip(shade, 0.0, 1.0, out=shade)
        shade *= 0.65
        shade += 0.35
        color *= shade[:, None]
        color[invalid] = 0.0
        color *= 255
        np.round(color, out=color)
        # world points = origin + direction * t in float64, NaN where no hit
        r = self._rays_float64(name)
        points = r[:, 3:] * depth.astype(np.float64)[:, None]
        points += r[:, :3]
        points[invalid] = np.nan
        return CameraImages(
            color=color.astype(np.uint8).reshape(h, w, 3),
            depth=depth.reshape(h, w),
            mask=instance.astype(np.uint8).reshape(h, w),
            points=points.astype(np.float32).reshape(h, w, 3),
        )

    def _camera_images_near(self, name: str, ids, hits, index: np.ndarray, table: CameraImages) -> CameraImages:
        """`_camera_images` of `hits` where only the pixels `index` may differ from the table-only
        images `table`: those are computed (the same element-wise arithmetic), the rest copied."""
        t, geometry_ids, normals = hits
        shade = dot_last(normals, LIGHT_DIRECTION)[index]  # the full-image product, as in `_camera_images`
        np.abs(shade, out=shade)
        np.clip(shade, 0.0, 1.0, out=shade)
        shade *= 0.65
        shade += 0.35
        t = t[index]
        valid = np.isfinite(t)
        invalid = ~valid
        depth = np.where(valid, t, np.float32(0.0))
        instance = np.where(valid, ids[np.where(valid, geometry_ids[index], 0)], 0)
        color = np.vstack([TABLE_COLOR, self.colors])[instance]
        color *= shade[:, None]
        color[invalid] = 0.0
        color *= 255
        np.round(color, out=color)
        r = self._rays_float64(name)[index]
        points = r[:, 3:] * depth.astype(np.float64)[:, None]
        points += r[:, :3]
        points[invalid] = np.nan
        out = CameraImages(*(np.array(a) for a in (table.color, table.depth, table.mask, table.points)))
        h, w = out.depth.shape
        rows, cols = np.divmod(index, w)
        out.color[rows, cols] = color.astype(np.uint8)
        out.depth[rows, cols] = depth
        out.mask[rows, cols] = instance.astype(np.uint8)
        out.points[rows, cols] = points.astype(np.float32)
        return out

    def heightmap(self, scene) -> np.ndarray:
        """Top-down heightmap (Y, X) float32 in metres over the workspace cells (what the policy sees)."""
        return self._heightmap_from(scene.cast_rays(self._heightmap_rays)["t_hit"].numpy())

    @staticmethod
    def _heightmap_from(t: np.ndarray) -> np.ndarray:
        t = t.astype(np.float64)
        height = np.where(np.isfinite(t), _HEIGHTMAP_RAY_START - t, 0.0)
        return np.maximum(height, 0.0).astype(np.float32).reshape(GRID_SHAPE[:2])

    def tsdf(self, scene, ids) -> np.ndarray:
        """Front-view TSDF (Y, X, Z) float32 from a fine depth image (TSDF_IMAGE_SHAPE).

        Only the pixels the TSDF reads are ray cast (each ray's hit does not depend on the others)."""
        return self._tsdf_from(scene.cast_rays(self._tsdf_pixel_rays)["t_hit"].numpy())

    def _tsdf_from(self, t: np.ndarray) -> np.ndarray:
        return self._tsdf.from_pixel_depths(np.where(np.isfinite(t), t, np.float32(0.0)).astype(np.float64))

    def amodal_mask(self, poses: np.ndarray, world=None) -> np.ndarray:
        """Amodal instance ids (Y, X, Z) uint8: voxel centres inside each object's solid at its pose."""
        o3d = self._o3d
        world = self._posed_parts(poses) if world is None else world
        mask = np.zeros(GRID_SHAPE, dtype=np.uint8)
        lo, shape = GRID_BOUNDS[:, 0], np.array(GRID_SHAPE)[[1, 0, 2]]  # (x, y, z) order
        for i in range(len(self.parts)):
            allv = np.vstack([v for _, v in world[i]])
            start = np.clip(np.floor((allv.min(0) - lo) / VOXEL_SIZE - 0.5).astype(int), 0, shape)
            stop = np.clip(np.ceil((allv.max(0) - lo) / VOXEL_SIZE + 0.5).astype(int), 0, shape)
            if np.any(stop <= start):
                continue
            ny, nx, nz = stop[1] - start[1], stop[0] - start[0], stop[2] - start[2]
            centers = np.empty((ny, nx, nz, 3), dtype=np.float32)  # (x, y, z) of the block's voxel centres
            for axis, n, dst in ((0, nx, (None, slice(None), None)), (1, ny, (slice(None), None, None)),
                                 (2, nz, (None, None, slice(None)))):
                c = lo[axis] + (np.arange(start[axis], start[axis] + n) + 0.5) * VOXEL_SIZE
                centers[..., axis] = c.astype(np.float32)[dst]
            query = o3d.core.Tensor(centers.reshape(-1, 3))
            inside = np.zeros(ny * nx * nz, dtype=bool)
            for (vertices, _), f in zip(world[i], self._faces[i]):
                scene = o3d.t.geometry.RaycastingScene()
                scene.add_triangles(vertices, f)
                inside |= scene.compute_occupancy(query).numpy() > 0.5
            block = mask[start[1]:stop[1], start[0]:stop[0], start[2]:stop[2]]
            block[inside.reshape(block.shape) & (block == 0)] = i + 1
        return mask

    def visible_fraction(self, poses: np.ndarray, visible_mask: np.ndarray, world=None) -> np.ndarray:
        """Visible / amodal silhouette pixels of each object in the front camera, (N,) float32."""
        camera = self.cameras["front"]
        rays = self._rays["front"].numpy()
        world = self._posed_parts(poses) if world is None else world
        out = np.zeros(len(self.parts), dtype=np.float32)
        for i in range(len(self.parts)):
            allv = np.vstack([v for _, v in world[i]])
            uv, z = camera.project(allv)
            if np.any(z <= 0):
                u0, v0, u1, v1 = 0, 0, camera.width, camera.height
            else:
                u0, v0 = np.clip(np.floor(uv.min(0)).astype(int) - 1, 0, [camera.width, camera.height])
                u1, v1 = np.clip(np.ceil(uv.max(0)).astype(int) + 2, 0, [camera.width, camera.height])
            if u1 <= u0 or v1 <= v0:
                continue
            sub = rays.reshape(camera.height, camera.width, 6)[v0:v1, u0:u1].reshape(-1, 6)
            scene, _ = self._scene(poses, objects=[i], table=False, world=world)
            silhouette = np.isfinite(scene.cast_rays(self._o3d.core.Tensor(sub))["t_hit"].numpy()).sum()
            out[i] = min(1.0, (visible_mask == i + 1).sum() / silhouette) if silhouette else 0.0
        return out

    def observe(self, poses: np.ndarray) -> Observation:
        """Render every observation of the objects at `poses` (N, 7).

        The same as `render_camera`, `tsdf` and `heightmap` of `_scene(poses)`, but only the rays that
        pass near an object are cast and turned into pixels and voxels; the others take their
        (cached) table-only values."""
        posed = self._posed_parts(poses)
        scene, ids = self._scene(poses, world=posed)
        world = [np.vstack([v for _, v in parts]) for parts in posed]
        images = {}
        for name, camera in self.cameras.items():
            rays, key = self._rays[name], _camera_key(camera)
            near = self._near_pixels(camera, world)
            if near is None or rays is not _CACHE.get(("camera-rays", key)):
                # rays replaced after construction (e.g. a calibrated camera), or an object behind it
                images[name] = self._camera_images(name, ids, *self._cast_near(scene, rays, None, None))
                continue
            table_hits = self._table_hits(("camera", key), rays)
            table_images = _cached(("table-images", key), lambda: _frozen(self._camera_images(
                name, np.zeros(1, np.int64), *table_hits)))
            hits = self._cast_near(scene, rays, table_hits, near)
            images[name] = self._camera_images_near(name, ids, hits, np.flatnonzero(near), table_images)
        near = self._near_pixels(self.tsdf_camera, world)
        if near is None:
            tsdf = self._tsdf_from(self._cast_near(scene, self._tsdf_pixel_rays, None, None)[0])
        else:
            near = near[self._tsdf.pixels]
            tsdf_table = self._table_hits(("tsdf",) + self._tsdf_key, self._tsdf_pixel_rays)
            t = self._cast_near(scene, self._tsdf_pixel_rays, tsdf_table, near)[0]
            base = _cached(("table-tsdf",) + self._tsdf_key, lambda: _frozen(self._tsdf_from(tsdf_table[0])))
            tsdf = self._tsdf.update_pixels(base, np.where(np.isfinite(t), t, np.float32(0.0)), near)
        heightmap_table = self._table_hits(("heightmap",), self._heightmap_rays)
        t_height = self._cast_near(scene, self._heightmap_rays, heightmap_table, self._near_cells(world))[0]
        return Observation(
            images=images,
            tsdf=tsdf,
            heightmap=self._heightmap_from(t_height),
            mask_3d=self.amodal_mask(poses, world=posed),
            visible_fraction=self.visible_fraction(poses, images["front"].mask, world=posed),
        )
