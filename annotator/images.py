"""Image helpers of the annotator's panel: object colours, mesh silhouettes and their outlines on colour images.

Pure numpy (PIL for resizing, scipy for the outline): no window, no Session. Silhouettes are rasterised with the
library's exact rasteriser (`dsr_bench.render.raster`), the one that renders every generated image.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from dsr_bench.geometry import Camera, pose_to_matrix, resized_camera, rigid_inverse, transform_points

#: RGB 0..1 colours: the selected object, and the others by annotation status.
SELECTED_COLOR = (1.0, 0.55, 0.0)
STATUS_COLORS: dict[str, tuple[float, float, float]] = {
    "unset": (0.6, 0.6, 0.6),
    "initialised": (0.35, 0.55, 0.95),
    "snapped": (0.2, 0.8, 0.85),
    "confirmed": (0.25, 0.8, 0.3),
}
#: Capture colours in the 3D view keep at most this saturation (HSV), so that no object's own colour can be taken for
#: a status colour (`muted_colors`); every status colour drawn in 3D is at least STATUS_MIN_SATURATION.
MUTED_SATURATION = 0.3
STATUS_MIN_SATURATION = 0.6
#: The depth-residual colour scale's top (m): `residual_ramp` reaches red there (`Session.residual_colors`, the
#: panel's legend).
RESIDUAL_SCALE = 0.01
#: Cloud points higher than this (m) above the table that no posed mesh explains (none within 2 x RESIDUAL_SCALE)
#: are red in the residual colours too; below it lies the table's measured surface (its noise and calibration
#: error reach a few millimetres), which stays grey.
RESIDUAL_FLOOR = 0.005
#: An object's preview (`mesh_preview`) is seen from this direction (from the side and above, as the pick window
#: shows a mesh) and lit from the viewer's side, a little from above.
PREVIEW_DIRECTION = (0.55, -0.65, 0.52)
#: Silhouettes keep the parts of a mesh at least this far in front of the camera (m, camera z): a ray through a
#: pixel centre sees what lies in front of the camera, and the projection of points nearer than this overflows.
SILHOUETTE_NEAR = 1e-6


def posed(vertices: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World vertices (V, 3) of object-frame vertices (V, 3) at a pose (7,)."""
    m = pose_to_matrix(pose)
    return np.asarray(vertices, np.float64) @ m[:3, :3].T + m[:3, 3]


def object_colors(statuses: Sequence[str], selected: int | None) -> np.ndarray:
    """(N, 3) RGB 0..1: the selected object orange, the others by status (`STATUS_COLORS`)."""
    colors = np.array([STATUS_COLORS.get(s, STATUS_COLORS["unset"]) for s in statuses], dtype=np.float64)
    colors = colors.reshape(-1, 3)
    if selected is not None and 0 <= selected < len(colors):
        colors[selected] = SELECTED_COLOR
    return colors


def clip_near(points: np.ndarray, faces: np.ndarray, near: float = SILHOUETTE_NEAR) -> tuple[np.ndarray, np.ndarray]:
    """A camera-frame triangle mesh (points (V, 3), faces (F, 3)) cut to its part at z >= near: (points', faces').

    Triangles wholly in front are kept as they are, wholly nearer ones dropped, and the others replaced by the one
    or two triangles of their part in front; the points where an edge crosses the plane are appended (one per edge,
    computed from its lower-indexed end, so the triangles sharing the edge share the point and stay watertight).
    """
    points = np.asarray(points, np.float64)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    front = points[:, 2] >= near
    count = front[faces].sum(1)
    keep = faces[count == 3]
    part = faces[(count == 1) | (count == 2)]
    if len(part) == 0:
        return points, keep
    one = front[part].sum(1) == 1  # one vertex in front (else two)
    # roll each triangle (keeping its orientation) so that its odd vertex comes first: the one in front of one,
    # the one behind of two
    odd = np.where(one, front[part].argmax(1), (~front[part]).argmax(1))
    part = np.take_along_axis(part, (odd[:, None] + np.arange(3)) % 3, axis=1)
    ends = np.concatenate([part[:, [0, 1]], part[:, [2, 0]]])  # the crossing edges: (odd, next), (previous, odd)
    edges, which = np.unique(np.sort(ends, axis=1), axis=0, return_inverse=True)
    lo, hi = points[edges[:, 0]], points[edges[:, 1]]
    cut = lo + ((near - lo[:, 2]) / (hi[:, 2] - lo[:, 2]))[:, None] * (hi - lo)
    cut[:, 2] = near
    which = len(points) + which.reshape(2, -1)
    after, before = which[0], which[1]  # the cut points on edges (odd, next) and (previous, odd)
    a, b, c = part[:, 0], part[:, 1], part[:, 2]
    single = np.stack([a, after, before], 1)[one]  # the tip in front
    quad = ~one  # the two in front (b, c) and the cut points form a quad: two triangles
    pair = np.concatenate([np.stack([b, c, before], 1)[quad], np.stack([b, before, after], 1)[quad]])
    return np.vstack([points, cut]), np.vstack([keep, single, pair])


def silhouette_masks(camera: Camera, meshes: Sequence[tuple[np.ndarray, np.ndarray]], poses: np.ndarray) -> np.ndarray:
    """Amodal silhouettes (N, H, W) bool of meshes (vertices (V,3) m object frame, faces (F,3)) at poses (N,7).

    Pixel (v, u) is inside object i when its centre (integer u, v, as in `Camera.ray_directions_world`) lies in
    the projection of one of mesh i's triangles in front of the camera (their part in front, `clip_near`),
    ignoring the other objects: the pixels whose ray hits the mesh. Rasterised with `dsr_bench.render.raster`
    (a centre exactly on a triangle's edge belongs to one side, by its rule). Unset poses (NaN rows) give empty
    silhouettes.
    """
    from dsr_bench.render.raster import rasterize

    h, w = camera.height, camera.width
    to_camera = rigid_inverse(camera.extrinsics)
    k = np.asarray(camera.intrinsics, np.float64)
    out = np.zeros((len(meshes), h * w), dtype=bool)
    for i, ((vertices, faces), pose) in enumerate(zip(meshes, np.asarray(poses, np.float64))):
        if len(faces) == 0 or not np.all(np.isfinite(pose)):  # unset poses (NaN rows) have no silhouette
            continue
        points, front = clip_near(transform_points(to_camera, posed(vertices, pose)), faces)
        uv = points[:, :2] / points[:, 2:3] * np.diag(k)[:2] + k[:2, 2]  # as Camera.project
        out[i, rasterize(uv, front, h, w).sample] = True
    return out.reshape(len(meshes), h, w)


def mask_boundary(mask: np.ndarray, thickness: int = 1) -> np.ndarray:
    """Inner boundary (H, W) bool of a mask: its pixels within `thickness` pixels of the outside."""
    from scipy.ndimage import binary_erosion

    mask = np.asarray(mask, bool)
    if thickness <= 0 or not mask.any():
        return np.zeros_like(mask)
    return mask & ~binary_erosion(mask, iterations=thickness, border_value=0)


def outline_overlay(color: np.ndarray, camera: Camera, meshes: Sequence[tuple[np.ndarray, np.ndarray]],
                    poses: np.ndarray, *, colors: np.ndarray | None = None, selected: int | None = None,
                    thickness: int = 1) -> np.ndarray:
    """A copy of a colour image (H, W, 3) uint8 with each mesh's projected silhouette outline drawn on it.

    camera: the image's calibration (its size must match); meshes: (vertices (V,3) m object frame,
    faces (F,3)) per object; poses (N,7) world. Outline = the inner boundary of the amodal silhouette
    (`silhouette_masks`), `thickness` px wide (the selected object's one pixel wider), in `colors`
    (N,3) RGB 0..1 (default: the selected object orange, the others white). Objects are drawn in
    index order with the selected one last, so its outline is on top.
    """
    color = np.asarray(color)
    if color.shape != (camera.height, camera.width, 3):
        raise ValueError(f"image {color.shape} does not match camera {camera.name!r} "
                         f"({camera.height}, {camera.width}, 3)")
    out = color.astype(np.uint8, copy=True)
    n = len(meshes)
    if n == 0:
        return out
    if colors is None:
        colors = np.ones((n, 3))
        if selected is not None and 0 <= selected < n:
            colors[selected] = SELECTED_COLOR
    rgb = np.round(np.clip(np.asarray(colors, np.float64), 0, 1) * 255).astype(np.uint8)
    masks = silhouette_masks(camera, meshes, poses)
    order = [i for i in range(n) if i != selected] + ([selected] if selected is not None and 0 <= selected < n else [])
    for i in order:
        edge = mask_boundary(masks[i], thickness + (1 if i == selected else 0))
        out[edge] = rgb[i]
    return out


def scaled_camera(camera: Camera, width: int) -> Camera:
    """The same camera at another image width, its height scaled alike (rounded to a whole pixel), through
    `dsr_bench.geometry.resized_camera` (pixel centres stay at integers)."""
    height = max(1, int(round(camera.height * width / camera.width)))
    return resized_camera(camera, height, width)


def resize_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """An (H, W, 3) uint8 image resized to (height, width) (bilinear, PIL)."""
    from PIL import Image

    if image.shape[:2] == (height, width):
        return np.asarray(image, np.uint8)
    return np.asarray(Image.fromarray(np.asarray(image, np.uint8)).resize((width, height), Image.Resampling.BILINEAR))


def muted_colors(colors: np.ndarray, saturation: float = MUTED_SATURATION) -> np.ndarray:
    """RGB colours (M, 3) 0..1 with their HSV saturation scaled down to at most `saturation` (hue and value kept):
    the 3D view's capture colours, which then cannot be mistaken for the saturated status colours."""
    rgb = np.asarray(colors, np.float64).reshape(-1, 3)
    s = float(saturation)
    out = rgb * s  # = max - (max - rgb) * s, in two passes over the (600k-point) cloud
    out += ((1.0 - s) * rgb.max(1))[:, None]
    return np.clip(out, 0.0, 1.0, out=out).reshape(np.shape(colors))


def residual_ramp(x: np.ndarray) -> np.ndarray:
    """RGB (M, 3) 0..1 of residuals x (M,) as fractions of the scale: blue (0) through green and yellow to red (1),
    the ramp of `annotator.session.Session.residual_colors`."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.stack([np.clip(2 * x, 0, 1), np.clip(2 - 2 * x, 0, 1) * np.clip(2 * x + 0.5, 0, 1),
                     np.clip(1 - 2 * x, 0, 1)], axis=1)


def mesh_preview(vertices: np.ndarray, faces: np.ndarray, size: int, extent: float,
                 color: Sequence[float] | np.ndarray = (0.7, 0.7, 0.72),
                 background: Sequence[int] = (44, 44, 50)) -> np.ndarray:
    """A small picture (size, size, 3) uint8 of a mesh (vertices (V, 3) m in its own frame, faces (F, 3)): seen
    from PREVIEW_DIRECTION, orthographic, `extent` m across the picture (one scale for all of a scene's objects
    keeps their sizes comparable), centred on its bounding box, each face shaded by its angle to the light, in
    `color` (RGB 0..1) on `background` (RGB 0..255). Rasterised with `dsr_bench.render.raster` (the nearest face
    per pixel)."""
    from dsr_bench.render.raster import interpolate, nearest, rasterize

    size = int(size)
    out = np.empty((size, size, 3), np.uint8)
    out[...] = np.asarray(background, np.uint8)
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(f) == 0 or not np.all(np.isfinite(v)) or extent <= 0:
        return out
    back = np.asarray(PREVIEW_DIRECTION, np.float64)
    back /= np.linalg.norm(back)
    up = np.array([0.0, 0.0, 1.0]) - back[2] * back
    up /= np.linalg.norm(up)
    right = np.cross(up, back)
    p = v - 0.5 * (v.min(0) + v.max(0))
    scale = (size - 2) / float(extent)
    uv = np.stack([size / 2 - 0.5 + (p @ right) * scale, size / 2 - 0.5 - (p @ up) * scale], axis=1)
    frags = rasterize(uv, f, size, size)
    if len(frags.sample) == 0:
        return out
    _, face = nearest(frags, interpolate(frags, f, -(p @ back)), size * size)
    hit = face >= 0
    tri = v[f[face[hit]]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    light = back + 0.4 * up
    shade = 0.3 + 0.7 * np.abs(normal @ (light / np.linalg.norm(light)))  # either winding: |cos|
    rgb = np.clip(np.asarray(color, np.float64)[None] * shade[:, None], 0, 1)
    out.reshape(-1, 3)[hit] = np.round(rgb * 255).astype(np.uint8)
    return out
