"""The exact rasteriser: fragments equal a brute-force test of every sample, watertight coverage, solids."""

from __future__ import annotations

import numpy as np
import pytest

from dsr_bench.render import raster

trimesh = pytest.importorskip("trimesh")


def _brute_force(points: np.ndarray, faces: np.ndarray, height: int, width: int) -> set[tuple[int, int]]:
    """(triangle, sample) pairs by testing every sample against every triangle, one at a time, with the
    same canonical edge functions and on-edge rule (written out independently of the vectorised code)."""
    out = set()
    for f, (i0, i1, i2) in enumerate(faces):
        a, b, c = points[i0], points[i1], points[i2]
        area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        if area == 0:
            continue
        for v in range(height):
            for u in range(width):
                ok = True
                for x, y in ((i1, i2), (i2, i0), (i0, i1)):
                    lo, hi = min(x, y), max(x, y)
                    du, dv = points[hi] - points[lo]
                    e = du * (v - points[lo][1]) - dv * (u - points[lo][0])
                    if x > y:
                        e = -e
                    tu, tv = points[y] - points[x]
                    if area < 0:
                        e, tu, tv = -e, -tu, -tv
                    on_edge_ok = (tv > 0) or (tv == 0 and tu < 0)
                    if not (e > 0 or (e == 0 and on_edge_ok)):
                        ok = False
                        break
                if ok:
                    out.add((f, v * width + u))
    return out


def test_fragments_equal_a_brute_force_test_of_every_sample():
    rng = np.random.default_rng(0)
    points = rng.uniform(-2, 14, (30, 2))
    points[:6] = np.round(points[:6])  # vertices on samples, edges through samples: the on-edge rule decides
    points[6] = [3.0, 3.0]
    points[7] = [9.0, 3.0]
    faces = rng.integers(0, 30, (60, 3))
    faces[0] = [6, 7, 0]
    frags = raster.rasterize(points, faces, 12, 13)
    assert set(zip(frags.triangle.tolist(), frags.sample.tolist())) == _brute_force(points, faces, 12, 13)
    assert np.allclose(frags.weights.sum(1), 1) and np.all(frags.weights >= 0)
    # weights reproduce the sample's position
    u, v = frags.sample % 13, frags.sample // 13
    corner = points[faces[frags.triangle]]
    assert np.allclose(np.einsum("mk,mkd->md", frags.weights, corner), np.stack([u, v], 1))


def test_a_closed_mesh_covers_every_pixel_of_its_silhouette_exactly_once_per_side():
    """Watertight: the front faces of a closed mesh partition its silhouette's pixels (no pixel falls
    through a shared edge, none is drawn twice), also for vertices and edges exactly on samples."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    for offset in ((31.0, 27.0), (31.5, 27.25)):  # the first puts vertices on integer samples
        pts = sphere.vertices[:, :2] + offset
        frags = raster.rasterize(pts, sphere.faces, 60, 64)
        normals_z = sphere.face_normals[:, 2]
        front = normals_z[frags.triangle] > 0
        count_front = np.bincount(frags.sample[front], minlength=60 * 64)
        count_back = np.bincount(frags.sample[~front], minlength=60 * 64)
        covered = (count_front + count_back) > 0
        assert count_front[covered].max() == 1 and count_back[covered].max() == 1
        assert np.array_equal(count_front > 0, count_back > 0)  # every line through the sphere enters and exits
        # the silhouette is the disc of radius ~20 around the offset
        v, u = np.divmod(np.arange(60 * 64), 64)
        r = np.hypot(u - offset[0], v - offset[1])
        assert covered[r < 19.0].all() and not covered[r > 20.01].any()


def test_solid_intervals_of_a_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=10.0)
    verts = sphere.vertices + [16.0, 16.0, 0.0]
    frags = raster.rasterize(verts[:, :2], sphere.faces, 32, 32)
    z = raster.interpolate(frags, sphere.faces, verts[:, 2])
    samples = np.arange(-12.0, 12.0, 0.5)
    columns, first, stop = raster.solid_intervals(frags, z, samples)
    inside = np.zeros((32 * 32, len(samples)), bool)
    for c, a, b in zip(columns, first, stop):
        inside[c, a:b] = True
    v, u = np.divmod(np.arange(32 * 32), 32)
    radius = np.sqrt((u[:, None] - 16.0) ** 2 + (v[:, None] - 16.0) ** 2 + samples[None, :] ** 2)
    assert inside[radius < 9.8].all() and not inside[radius > 10.01].any()  # the mesh is inscribed
    assert len(np.unique(columns)) == len(columns)  # one run per column of a convex solid
