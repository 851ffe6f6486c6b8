"""Closed solids built in numpy alone: boxes, solids of revolution and cylinders, scaled and moved.

The built-in object sets (`cube`, `procedural`, `procedural-novel`) are made of these, so generating
them imports no mesh library: trimesh's import (with scipy.spatial) cost every worker process 0.65 s
before its first procedural sequence. Each function is, bit for bit, what trimesh (5.2, where checked)
gives for the same call, because the objects of the pinned splits were first built with trimesh:

- `box_solid(size, centre)`: `trimesh.creation.box(extents=size, transform=translation_matrix(centre))`;
- `revolve_solid(profile, sections)`: `trimesh.creation.revolve(profile, sections=sections)`, its
  vertices merged as `Trimesh(..., process=True)` merges them (rounded to 1e-8, first occurrence kept);
- `cylinder_solid(radius, height, sections)`: `trimesh.creation.cylinder(...)`;
- `scaled(solid, factor)`, `translated(solid, offset)`: `mesh.apply_scale(factor)`,
  `mesh.apply_translation(offset)` (trimesh's homogeneous product adds exact zeros, so each coordinate
  is one rounded product or sum, and a -0.0 becomes +0.0; a transform within 1e-8 of the identity
  leaves the mesh as it is);
- volume and centre of mass: the surface integrals as `trimesh.triangles.mass_properties` writes them.

The centre of mass is subtracted from every vertex of a sequence's meshes, so a last-bit difference
here would change the mesh digests and the ground truth of the pinned splits; `tests/test_objects.py`
compares every function with trimesh, and every built-in object of 1,500 scenes per set with the
objects trimesh built.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The unit cube's corners and outward triangles, in trimesh's order (trimesh/resources/templates/creation.json).
UNIT_CORNERS = np.array([[0, 0, 0], [0, 0, 1], [0, 1, 0], [0, 1, 1], [1, 0, 0], [1, 0, 1], [1, 1, 0], [1, 1, 1]],
                        dtype=np.float64)
BOX_FACES = np.array([[1, 3, 0], [4, 1, 0], [0, 3, 2], [2, 4, 0], [1, 7, 3], [5, 1, 4], [5, 7, 1], [3, 7, 2],
                      [6, 4, 2], [2, 7, 6], [6, 5, 4], [7, 5, 6]], dtype=np.int64)
#: Divisors of the surface integrals (volume; first moments; second moments; products).
_INTEGRAL_DIVISORS = np.array([6, 24, 24, 24, 60, 60, 60, 120, 120, 120], dtype=np.float64)
#: trimesh's tol.merge: vertices equal after rounding to this are merged; thinner triangles are dropped
MERGE_TOLERANCE = 1e-8
MERGE_DIGITS = 8
#: trimesh leaves a mesh alone under a transform this close to the identity
IDENTITY_TOLERANCE = 1e-8


@dataclass(frozen=True)
class Solid:
    """A closed triangle mesh: vertices (V, 3) float64 metres, faces (F, 3) int64 (outward), its volume (m^3)
    and centre of mass (3,) (uniform density). Has what `make_spec` reads of a solid."""

    vertices: np.ndarray
    faces: np.ndarray
    volume: float
    center_mass: np.ndarray

    @property
    def is_watertight(self) -> bool:
        """Every directed edge appears once and its reverse once: closed and consistently wound."""
        edges = self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        directed = np.unique(edges, axis=0)
        reverse = np.unique(edges[:, ::-1], axis=0)
        return len(directed) == len(edges) and np.array_equal(directed, reverse)


def solid(vertices: np.ndarray, faces: np.ndarray) -> Solid:
    """A `Solid` from a closed, outward triangle mesh (float64 metres, int64 indices)."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    volume, center_mass = mass_properties(vertices, faces)
    return Solid(vertices, faces, volume, center_mass)


def box_solid(size, centre=(0.0, 0.0, 0.0)) -> Solid:
    """A box of edge lengths `size` (3,) centred at `centre` (3,), metres."""
    size = np.asarray(size, dtype=np.float64)
    if size.shape != (3,) or not np.all(size > 0):
        raise ValueError(f"a box needs three positive edge lengths, not {size!r}")
    vertices = (UNIT_CORNERS - 0.5) * size + np.asarray(centre, dtype=np.float64)
    return solid(vertices, BOX_FACES.copy())


def revolve_solid(profile, sections: int) -> Solid:
    """The solid swept by a (radius, height) profile (N, 2), metres, turned once about z in `sections`
    slices; the profile starts and ends on the axis and runs counter-clockwise (outward faces)."""
    profile = np.asarray(profile, dtype=np.float64)
    if profile.ndim != 2 or profile.shape[1] != 2 or len(profile) < 3:
        raise ValueError(f"a revolved profile needs (N >= 3, 2) points, not shape {profile.shape}")
    theta = np.linspace(0, np.pi * 2.0, sections + 1)
    points = np.column_stack((np.cos(theta), np.sin(theta)))
    per = len(profile)
    radius, height = profile[:, 0], profile[:, 1]
    around = np.tile(points, (1, per)).reshape((-1, 2)) * np.tile(radius, len(points)).reshape((-1, 1))
    vertices = np.column_stack((around, np.tile(height, len(points))))[:-per]  # the last slice is the first again
    # one slice's two triangles per profile segment, less the zero-area ones (on the axis)
    single = np.tile(np.array([0, per, 1, 1, per, per + 1]), per - 1).reshape((-1, 3))
    single += np.tile(np.arange(per - 1), (2, 1)).T.reshape((-1, 1))
    single = single[_triangle_areas(vertices[single]) > MERGE_TOLERANCE]
    offset = np.tile(np.arange(sections) * per, (len(single), 1)).T.reshape((-1, 1))
    faces = (np.tile(single.ravel(), sections).reshape((-1, 3)) + offset) % len(vertices)
    vertices, faces = merge_vertices(vertices, faces)
    return solid(vertices, faces)


def cylinder_solid(radius: float, height: float, sections: int) -> Solid:
    """A cylinder about z, centred on the origin, metres."""
    half = abs(float(height)) / 2.0
    return revolve_solid([[0, -half], [radius, -half], [radius, half], [0, half]], sections)


def scaled(part: Solid, factor) -> Solid:
    """`part` scaled about the origin by `factor` (a number, or (3,) per axis)."""
    factor = np.asarray(factor, dtype=np.float64)
    linear = np.eye(3) * factor if factor.ndim == 0 else np.diag(factor)
    if _near_identity(linear, np.zeros(3)):
        return part
    return solid(part.vertices * np.broadcast_to(factor, (3,)) + 0.0, part.faces)


def translated(part: Solid, offset) -> Solid:
    """`part` moved by `offset` (3,), metres."""
    offset = np.asarray(offset, dtype=np.float64)
    if offset.shape != (3,):
        raise ValueError(f"a translation needs 3 coordinates, not {offset!r}")
    if _near_identity(np.eye(3), offset):
        return part
    return solid(part.vertices + offset, part.faces)


def bounds(parts: list) -> np.ndarray:
    """(2, 3): the lowest and highest coordinate of all `parts` together (m)."""
    stacked = np.concatenate([np.asarray(p.vertices, dtype=np.float64) for p in parts])
    return np.array([stacked.min(axis=0), stacked.max(axis=0)])


def merge_vertices(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices equal after rounding to 1e-8 made one (the first kept, in order of first occurrence),
    unreferenced ones dropped; the faces renumbered."""
    referenced = np.zeros(len(vertices), dtype=bool)
    referenced[faces] = True
    rounded = (vertices * 10 ** MERGE_DIGITS).round().astype(np.int64)[referenced]
    _, first, inverse = np.unique(rounded, axis=0, return_index=True, return_inverse=True)
    order = first.argsort()
    renumber = np.zeros(len(vertices), dtype=np.int64)
    renumber[referenced] = order.argsort()[inverse.reshape(-1)]
    kept = np.flatnonzero(referenced)[first[order]]
    return vertices[kept], renumber[faces.reshape(-1)].reshape((-1, 3))


def mass_properties(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.float64, np.ndarray]:
    """Volume and centre of mass (3,) of a closed, outward triangle mesh of uniform density: the divergence-
    theorem integrals of Eberly's "Polyhedral Mass Properties", written as trimesh.triangles.mass_properties
    writes them (every operation and its order kept, so the results agree to the last bit)."""
    triangles = np.asarray(vertices, dtype=np.float64)[faces]
    vectors = triangles[:, 1:, :] - triangles[:, :2, :]
    crosses = np.cross(vectors[:, 0], vectors[:, 1])
    f1 = triangles[:, 0, :] + triangles[:, 1, :] + triangles[:, 2, :]
    f2 = (triangles[:, 0, :] ** 2 + triangles[:, 1, :] ** 2 + triangles[:, 0, :] * triangles[:, 1, :]
          + triangles[:, 2, :] * f1)
    integral = np.zeros((10, len(f1)))
    integral[0] = crosses[:, 0] * f1[:, 0]
    integral[1:4] = (crosses * f2).T
    # rows 4-9 (second moments and products) do not enter volume or centre; each row is summed alone
    integrated = integral.sum(axis=1) / _INTEGRAL_DIVISORS
    volume = integrated[0]
    return volume, integrated[1:4] / volume


def _triangle_areas(triangles: np.ndarray) -> np.ndarray:
    """Areas (n,) of triangles (n, 3, 3), as trimesh.triangles.area computes them."""
    vectors = triangles[:, 1:, :] - triangles[:, :2, :]
    crosses = np.cross(vectors[:, 0], vectors[:, 1])
    return np.sqrt((crosses ** 2).sum(axis=1)) / 2.0


def _near_identity(linear: np.ndarray, offset: np.ndarray) -> bool:
    """Whether trimesh would leave a mesh alone under this affine map (its two identity checks)."""
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = linear, offset
    difference = matrix - np.eye(4)
    return float(np.ptp(difference)) < IDENTITY_TOLERANCE or float(np.abs(difference).max()) < IDENTITY_TOLERANCE
