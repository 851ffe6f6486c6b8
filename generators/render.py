"""Observations of a scene of posed object meshes: images, TSDF, heightmap and amodal voxels.

Rendering is exact ray casting of the object meshes (open3d's Embree-backed RaycastingScene), not a
rasteriser approximation: z-depth, instance masks and world points come from the same ray hits.
Amodal occupancy is evaluated at voxel centres against each object's closed solids, so `mask_3d` is
the true solid at the exact pose. Independent of the physics engine: it sees meshes and poses only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dsr_bench.constants import GRID_BOUNDS, GRID_SHAPE, IMAGE_SHAPE, TSDF_IMAGE_SHAPE, VOXEL_SIZE
from dsr_bench.geometry import Camera, make_camera, pose_to_matrix
from dsr_bench.tsdf import ProjectiveTSDF

TABLE_COLOR = np.array([0.78, 0.74, 0.66])
LIGHT_DIRECTION = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
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
    return vertices @ m[:3, :3].T + m[:3, 3]


class SceneRenderer:
    """Renders the benchmark's observations of a fixed set of objects at any poses.

    objects: sequence of ObjectSpec-like items with `.parts` (each `.vertices` (V,3) m, `.faces` (F,3))
    and `.color` (RGB 0..1); cameras: names of the stored cameras ('front', optionally 'back').
    """

    def __init__(self, objects, cameras: tuple[str, ...] = ("front",), image_shape=IMAGE_SHAPE,
                 tsdf_image_shape=TSDF_IMAGE_SHAPE):
        import open3d as o3d

        self._o3d = o3d
        self.parts = [[(np.asarray(p.vertices, np.float64), np.asarray(p.faces, np.int64)) for p in obj.parts]
                      for obj in objects]
        self.colors = np.array([obj.color for obj in objects], dtype=np.float64).reshape(-1, 3)
        self.cameras: dict[str, Camera] = {name: make_camera(name, *image_shape) for name in cameras}
        self.tsdf_camera = make_camera("front", *tsdf_image_shape)
        self._rays = {name: self._camera_rays(cam) for name, cam in self.cameras.items()}
        self._tsdf_rays = self._camera_rays(self.tsdf_camera)
        self._tsdf = ProjectiveTSDF(self.tsdf_camera)
        rows, cols = np.meshgrid(np.arange(GRID_SHAPE[0]), np.arange(GRID_SHAPE[1]), indexing="ij")
        x = GRID_BOUNDS[0, 0] + (cols + 0.5) * VOXEL_SIZE
        y = GRID_BOUNDS[1, 0] + (rows + 0.5) * VOXEL_SIZE
        origins = np.stack([x, y, np.full_like(x, _HEIGHTMAP_RAY_START)], -1).reshape(-1, 3)
        down = np.broadcast_to([0.0, 0.0, -1.0], origins.shape)
        self._heightmap_rays = o3d.core.Tensor(np.hstack([origins, down]).astype(np.float32))
        self._table = self._table_mesh()

    # ray helpers -----------------------------------------------------------------------------------
    def _camera_rays(self, camera: Camera):
        dirs = camera.ray_directions_world().reshape(-1, 3)
        origins = np.broadcast_to(camera.extrinsics[:3, 3], dirs.shape)
        return self._o3d.core.Tensor(np.hstack([origins, dirs]).astype(np.float32))

    @staticmethod
    def _table_mesh() -> tuple[np.ndarray, np.ndarray]:
        cx, cy, h = 0.5, 0.0, _TABLE_HALF_SIZE
        verts = np.array([[cx - h, cy - h, 0], [cx + h, cy - h, 0], [cx + h, cy + h, 0], [cx - h, cy + h, 0]], float)
        return verts, np.array([[0, 1, 2], [0, 2, 3]])

    def _scene(self, poses: np.ndarray, objects: list[int] | None = None, table: bool = True):
        """A raycasting scene and the instance id (0 = table) of each geometry id."""
        o3d = self._o3d
        scene = o3d.t.geometry.RaycastingScene()
        ids = []
        if table:
            v, f = self._table
            scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
            ids.append(0)
        for i in objects if objects is not None else range(len(self.parts)):
            for v, f in self.parts[i]:
                scene.add_triangles(o3d.core.Tensor(_transform(v, poses[i]).astype(np.float32)),
                                    o3d.core.Tensor(f.astype(np.uint32)))
                ids.append(i + 1)
        return scene, np.array(ids, dtype=np.int64)

    @staticmethod
    def _hits(scene, rays, ids):
        result = scene.cast_rays(rays)
        t = result["t_hit"].numpy().astype(np.float64)
        geom = result["geometry_ids"].numpy().astype(np.int64)
        valid = np.isfinite(t)
        instance = np.where(valid, ids[np.where(valid, geom, 0)], -1)
        return t, instance, result["primitive_normals"].numpy(), valid

    # observation -----------------------------------------------------------------------------------
    def render_camera(self, scene, ids, name: str) -> CameraImages:
        """Colour, z-depth, visible ids and world points of camera `name`."""
        camera, rays = self.cameras[name], self._rays[name]
        t, instance, normals, valid = self._hits(scene, rays, ids)
        h, w = camera.height, camera.width
        depth = np.where(valid, t, 0.0).astype(np.float32)
        base = np.where(instance[:, None] > 0, self.colors[np.maximum(instance, 1) - 1], TABLE_COLOR)
        shade = 0.35 + 0.65 * np.clip(np.abs(normals @ LIGHT_DIRECTION), 0.0, 1.0)
        color = np.where(valid[:, None], base * shade[:, None], 0.0)
        r = rays.numpy().astype(np.float64)
        points = np.where(valid[:, None], r[:, :3] + r[:, 3:] * np.where(valid, t, 0.0)[:, None], np.nan)
        return CameraImages(
            color=np.round(color * 255).astype(np.uint8).reshape(h, w, 3),
            depth=depth.reshape(h, w),
            mask=np.maximum(instance, 0).astype(np.uint8).reshape(h, w),
            points=points.astype(np.float32).reshape(h, w, 3),
        )

    def heightmap(self, scene) -> np.ndarray:
        """Top-down heightmap (Y, X) float32 in metres over the workspace cells (what the policy sees)."""
        t = scene.cast_rays(self._heightmap_rays)["t_hit"].numpy().astype(np.float64)
        height = np.where(np.isfinite(t), _HEIGHTMAP_RAY_START - t, 0.0)
        return np.maximum(height, 0.0).astype(np.float32).reshape(GRID_SHAPE[:2])

    def tsdf(self, scene, ids) -> np.ndarray:
        """Front-view TSDF (Y, X, Z) float32 from a fine depth image (TSDF_IMAGE_SHAPE)."""
        t, _, _, valid = self._hits(scene, self._tsdf_rays, ids)
        depth = np.where(valid, t, 0.0).reshape(self.tsdf_camera.height, self.tsdf_camera.width)
        return self._tsdf(depth)

    def amodal_mask(self, poses: np.ndarray) -> np.ndarray:
        """Amodal instance ids (Y, X, Z) uint8: voxel centres inside each object's solid at its pose."""
        o3d = self._o3d
        mask = np.zeros(GRID_SHAPE, dtype=np.uint8)
        lo, shape = GRID_BOUNDS[:, 0], np.array(GRID_SHAPE)[[1, 0, 2]]  # (x, y, z) order
        for i, parts in enumerate(self.parts):
            world = [(_transform(v, poses[i]), f) for v, f in parts]
            allv = np.vstack([v for v, _ in world])
            start = np.clip(np.floor((allv.min(0) - lo) / VOXEL_SIZE - 0.5).astype(int), 0, shape)
            stop = np.clip(np.ceil((allv.max(0) - lo) / VOXEL_SIZE + 0.5).astype(int), 0, shape)
            if np.any(stop <= start):
                continue
            ix, iy, iz = (np.arange(a, b) for a, b in zip(start, stop))
            gy, gx, gz = np.meshgrid(iy, ix, iz, indexing="ij")
            centers = lo + (np.stack([gx, gy, gz], -1).reshape(-1, 3) + 0.5) * VOXEL_SIZE
            query = o3d.core.Tensor(centers.astype(np.float32))
            inside = np.zeros(len(centers), dtype=bool)
            for v, f in world:
                scene = o3d.t.geometry.RaycastingScene()
                scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
                inside |= scene.compute_occupancy(query).numpy() > 0.5
            block = mask[start[1]:stop[1], start[0]:stop[0], start[2]:stop[2]]
            block[inside.reshape(block.shape) & (block == 0)] = i + 1
        return mask

    def visible_fraction(self, poses: np.ndarray, visible_mask: np.ndarray) -> np.ndarray:
        """Visible / amodal silhouette pixels of each object in the front camera, (N,) float32."""
        camera = self.cameras["front"]
        rays = self._rays["front"].numpy()
        out = np.zeros(len(self.parts), dtype=np.float32)
        for i in range(len(self.parts)):
            allv = np.vstack([_transform(v, poses[i]) for v, _ in self.parts[i]])
            uv, z = camera.project(allv)
            if np.any(z <= 0):
                u0, v0, u1, v1 = 0, 0, camera.width, camera.height
            else:
                u0, v0 = np.clip(np.floor(uv.min(0)).astype(int) - 1, 0, [camera.width, camera.height])
                u1, v1 = np.clip(np.ceil(uv.max(0)).astype(int) + 2, 0, [camera.width, camera.height])
            if u1 <= u0 or v1 <= v0:
                continue
            sub = rays.reshape(camera.height, camera.width, 6)[v0:v1, u0:u1].reshape(-1, 6)
            scene, _ = self._scene(poses, objects=[i], table=False)
            silhouette = np.isfinite(scene.cast_rays(self._o3d.core.Tensor(sub))["t_hit"].numpy()).sum()
            out[i] = min(1.0, (visible_mask == i + 1).sum() / silhouette) if silhouette else 0.0
        return out

    def observe(self, poses: np.ndarray) -> Observation:
        """Render every observation of the objects at `poses` (N, 7)."""
        scene, ids = self._scene(poses)
        images = {name: self.render_camera(scene, ids, name) for name in self.cameras}
        return Observation(
            images=images,
            tsdf=self.tsdf(scene, ids),
            heightmap=self.heightmap(scene),
            mask_3d=self.amodal_mask(poses),
            visible_fraction=self.visible_fraction(poses, images["front"].mask),
        )
