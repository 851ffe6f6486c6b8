"""Boxes as closed solids in numpy alone, so that a box scene (`--objects cube`) never imports trimesh.

A `BoxSolid` has what `make_spec` reads of a solid (vertices, faces, is_watertight, volume,
center_mass) and is bit for bit what trimesh (5.2, where checked) gives for `trimesh.creation.box(extents=size,
transform=translation_matrix(centre))`: the same corner and triangle tables, the same vertex
arithmetic (corners - 0.5, times the size, plus the centre: every product exact) and the same
surface integral for volume and centre of mass, in the same numpy operations and order. The centre
of mass is subtracted from every vertex of a sequence's meshes, so a last-bit difference here would
change the mesh digests and the ground truth of the pinned cube splits; `tests/test_objects.py`
compares with trimesh where it is installed.
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


@dataclass(frozen=True)
class BoxSolid:
    """An axis-aligned box: vertices (8, 3) float64 metres, faces (12, 3) int64 (outward, closed)."""

    vertices: np.ndarray
    faces: np.ndarray
    volume: float
    center_mass: np.ndarray
    is_watertight: bool = True


def box_solid(size, centre=(0.0, 0.0, 0.0)) -> BoxSolid:
    """A box of edge lengths `size` (3,) centred at `centre` (3,), metres."""
    size = np.asarray(size, dtype=np.float64)
    if size.shape != (3,) or not np.all(size > 0):
        raise ValueError(f"a box needs three positive edge lengths, not {size!r}")
    vertices = (UNIT_CORNERS - 0.5) * size + np.asarray(centre, dtype=np.float64)
    faces = BOX_FACES.copy()
    volume, center_mass = mass_properties(vertices, faces)
    return BoxSolid(vertices, faces, volume, center_mass)


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
