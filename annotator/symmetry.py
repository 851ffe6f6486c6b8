"""Symmetries of an object mesh, found by testing candidate rotations on the mesh itself (for the BOP export's
`models_info.json`, `annotator.bop`).

A symmetry is a rigid motion S (x -> R x + t) that maps the mesh's surface onto itself: every surface point moved by S
lies within `tolerance` of the surface. Every symmetry of a surface keeps its area-weighted centroid g in place, so
the candidates are rotations about g (t = g - R g):

- continuous: a rotation about the model's z, x or y axis through g (z tried first) by every angle; tested at ten
  angles spread over the turn (15 to 330 degrees). Found for a can or a bottle standing in its model frame (a
  polygonal can of 40 sides is 0.14 mm off a cylinder). At most one axis is kept (a sphere's second and third axes
  are left out);
- discrete, beside a continuous axis: a half turn about the first other model axis that maps the object onto itself
  (a can's upside-down twin). One is enough: every other flip is it composed with a turn about the axis;
- discrete, without one: the 23 turns of the cube's rotation group about the model axes (half and quarter turns,
  turns about the diagonals) and the 3-, 5-, 6- and 8-fold turns about each model axis; those that pass are closed
  under composition (each product tested too), so the list is a group less its identity (a box of three different
  sides: the half turns about x, y and z).

Units: whatever the mesh's are (the BOP export passes millimetres). Vectorised numpy + scipy's KD-tree.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import product

import numpy as np

#: Default tolerance of the symmetry test, in the mesh's units when it is in millimetres: a twin this close is as
#: good as the annotation (its floor is 2-3 mm) and BOP's pose errors should not tell it apart.
TOLERANCE_MM = 1.0
#: Angles (degrees) at which a continuous symmetry is tested.
CONTINUOUS_TEST_DEG = (15.0, 40.0, 72.0, 100.0, 137.0, 180.0, 205.0, 251.0, 290.0, 330.0)
#: Surface points tested per candidate.
TEST_POINTS = 4000


@dataclass
class Symmetries:
    """Symmetries of a mesh: `discrete` 4x4 transforms (model -> model, the mesh's units), `continuous` as
    (axis (3,) unit, offset (3,) a point on the axis); `errors`: the largest surface distance found per discrete
    transform, and for the continuous axis over its tested angles (same order)."""

    discrete: list[np.ndarray] = field(default_factory=list)
    continuous: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    discrete_errors: list[float] = field(default_factory=list)
    continuous_errors: list[float] = field(default_factory=list)


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """3x3 rotation by `angle` radians about the unit `axis` (3,), right-handed (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def surface_samples(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int = 0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """`count` points (count, 3) drawn uniformly by area on the mesh's triangles (seeded), and each one's triangle."""
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[np.asarray(faces, dtype=np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    which = rng.choice(len(tri), size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    w = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)
    return np.einsum("nk,nkd->nd", w, tri[which]), which


def surface_centroid(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted centroid (3,) of the mesh's surface: kept in place by every symmetry of the surface."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return (tri.mean(axis=1) * area[:, None]).sum(axis=0) / area.sum()


def _point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Euclidean distance (M,) from points p (M, 3) to triangles (a, b, c) (M, 3 each), row by row."""
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-15
    unit = n / np.where(ok, norm, 1.0)[:, None]
    height = np.einsum("md,md->m", p - a, unit)
    foot = p - height[:, None] * unit
    inside = ok.copy()
    for u, w in ((a, b), (b, c), (c, a)):  # the foot is on the inner side of all three edges
        inside &= np.einsum("md,md->m", np.cross(w - u, foot - u), unit) >= 0.0
    best = np.where(inside, np.abs(height), np.inf)
    for u, w in ((a, b), (b, c), (c, a)):
        e = w - u
        length2 = np.einsum("md,md->m", e, e)
        s = np.clip(np.einsum("md,md->m", p - u, e) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(p - (u + s[:, None] * e), axis=1))
    return best


class SurfaceDistance:
    """Distance from points to a mesh's surface: exact to the triangles of the `candidates` surface samples
    nearest each point (dense samples, so the nearest triangle is among them: at worst an upper bound)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, samples: int = 60000, candidates: int = 12):
        from scipy.spatial import cKDTree

        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        points, tri = surface_samples(self.vertices, self.faces, samples, seed=1)
        corner_tri = np.repeat(np.arange(len(self.faces)), 3)  # each vertex tagged with a triangle using it
        self._points = np.vstack([points, self.vertices[self.faces.reshape(-1)]])
        self._tri = np.concatenate([tri, corner_tri])
        self._tree = cKDTree(self._points)
        self._k = candidates

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Distances (M,) of points (M, 3) to the surface, the mesh's units."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        _, idx = self._tree.query(p, k=self._k)
        tri = self.faces[self._tri[idx]]  # (M, k, 3)
        v = self.vertices
        q = np.repeat(p, self._k, axis=0)
        d = _point_triangle_distance(q, v[tri[..., 0]].reshape(-1, 3), v[tri[..., 1]].reshape(-1, 3),
                                     v[tri[..., 2]].reshape(-1, 3))
        return d.reshape(len(p), self._k).min(axis=1)


def _about(rot: np.ndarray, centre: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = centre - rot @ centre
    return m


def _cube_group() -> list[np.ndarray]:
    """The 24 rotations that map the coordinate axes onto themselves (signed permutation matrices, det +1)."""
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[np.arange(3), perm] = signs
            if np.linalg.det(m) > 0:
                out.append(m)
    return out


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.abs(a[:3, :3] - b[:3, :3]).max() < 1e-6)


def find_symmetries(vertices: np.ndarray, faces: np.ndarray, tolerance: float = TOLERANCE_MM) -> Symmetries:
    """The symmetries of a mesh (vertices (V, 3), faces (F, 3)) within `tolerance` (the mesh's units): see the module
    docstring for the candidates. The largest distance of TEST_POINTS surface points moved by a candidate to the
    surface must be within `tolerance`."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    distance = SurfaceDistance(v, f)
    points, _ = surface_samples(v, f, TEST_POINTS, seed=2)
    points = np.vstack([points, v])  # the corners too: a box's corner is where a wrong turn shows most
    centre = surface_centroid(v, f)

    def error(m: np.ndarray) -> float:
        quick = distance(points[::16] @ m[:3, :3].T + m[:3, 3]).max()  # most candidates fail on a few points
        if quick > tolerance:
            return float(quick)
        return float(distance(points @ m[:3, :3].T + m[:3, 3]).max())

    out = Symmetries()
    axes = np.eye(3)[[2, 0, 1]]  # z, x, y
    for axis in axes:
        errs = [error(_about(rotation_about(axis, np.radians(deg)), centre)) for deg in CONTINUOUS_TEST_DEG]
        if max(errs) <= tolerance:
            out.continuous.append((axis.copy(), centre.copy()))
            out.continuous_errors.append(max(errs))
            break
    if out.continuous:
        axis = out.continuous[0][0]
        for other in axes:
            if abs(float(other @ axis)) > 0.5:
                continue
            m = _about(rotation_about(other, np.pi), centre)
            e = error(m)
            if e <= tolerance:
                out.discrete.append(m)
                out.discrete_errors.append(e)
                break
        return out
    candidates = [_about(r, centre) for r in _cube_group() if not np.allclose(r, np.eye(3))]
    for axis in np.eye(3):
        for n in (3, 5, 6, 8):
            for k in range(1, n):
                m = _about(rotation_about(axis, 2.0 * np.pi * k / n), centre)
                if not any(_same(m, c) for c in candidates):
                    candidates.append(m)
    found: list[tuple[np.ndarray, float]] = []
    for m in candidates:
        e = error(m)
        if e <= tolerance:
            found.append((m, e))
    grown = True
    while grown:  # close under composition: a product of symmetries is one (tested, as errors add up)
        grown = False
        for (a, _), (b, _) in product(list(found), repeat=2):
            m = a @ b
            if _same(m, np.eye(4)) or any(_same(m, g) for g, _ in found):
                continue
            e = error(m)
            if e <= tolerance:
                found.append((m, e))
                grown = True
    out.discrete = [m for m, _ in found]
    out.discrete_errors = [e for _, e in found]
    return out
