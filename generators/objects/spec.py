"""What the simulator needs to know about an object: its closed solid parts, colour and mass."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Every object of the official generator weighs 0.05 kg (pybullet changeDynamics mass=0.05).
OFFICIAL_MASS = 0.05  # kg


@dataclass(frozen=True)
class Part:
    """One closed, watertight, outward-oriented solid: vertices (V, 3) metres, faces (F, 3)."""

    vertices: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True)
class ObjectSpec:
    """An object instance: the union of its parts, in a frame with the origin at the centre of mass
    and z up in its natural resting pose."""

    set: str
    category: str
    model_id: str
    scale: float
    parts: tuple[Part, ...]
    color: tuple[float, float, float]
    mass: float
    is_large: bool = False

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """All parts concatenated: vertices (V, 3) float64 m, faces (F, 3) int64."""
        vertices, faces, offset = [], [], 0
        for part in self.parts:
            vertices.append(part.vertices)
            faces.append(part.faces + offset)
            offset += len(part.vertices)
        return np.vstack(vertices).astype(np.float64), np.vstack(faces).astype(np.int64)

    def mesh_sha256(self) -> str:
        """SHA-256 of the mesh (`dsr_bench.dataset.manifest.mesh_sha256`: float64 vertices, then int64 faces)."""
        from dsr_bench.dataset.manifest import mesh_sha256

        return mesh_sha256(*self.mesh())

    def extent(self) -> np.ndarray:
        """Axis-aligned size (3,) in metres."""
        vertices, _ = self.mesh()
        return vertices.max(0) - vertices.min(0)

    def identity(self) -> dict:
        """JSON-able identity stored with every sequence."""
        return {"set": self.set, "category": self.category, "model_id": self.model_id, "scale": float(self.scale),
                "mesh_sha256": self.mesh_sha256(), "is_large": bool(self.is_large),
                "color": [float(c) for c in self.color], "mass": float(self.mass)}


def make_spec(set_name: str, category: str, model_id: str, scale: float, meshes: list, color, is_large: bool,
              mass: float = OFFICIAL_MASS) -> ObjectSpec:
    """An ObjectSpec from closed solids (metres; trimesh meshes, or `generators.objects.primitives.Solid`: anything
    with vertices, faces, is_watertight, volume and center_mass): checks each is a closed solid and moves the origin to
    the centre of mass (volume-weighted over parts, uniform density; the small overlaps of our built-in
    parts are counted twice, which moves it well under 1 mm)."""
    volumes, centres = [], []
    for mesh in meshes:
        if not mesh.is_watertight or mesh.volume <= 0:
            raise ValueError(f"{set_name}/{model_id}: a part is not a closed solid")
        volumes.append(mesh.volume)
        centres.append(mesh.center_mass)
    com = np.average(np.array(centres), axis=0, weights=np.array(volumes))
    parts = tuple(Part(_frozen(np.asarray(m.vertices, np.float64) - com), _frozen(np.asarray(m.faces, np.int64)))
                  for m in meshes)
    red, green, blue = (float(c) for c in color)
    return ObjectSpec(set_name, category, model_id, float(scale), parts, (red, green, blue), float(mass),
                      bool(is_large))


def _frozen(array: np.ndarray) -> np.ndarray:
    """A read-only contiguous copy (specs are shared between workers and hashed)."""
    out = np.array(array, order="C", copy=True)
    out.setflags(write=False)
    return out


def random_color(rng: np.random.Generator) -> tuple[float, float, float]:
    """A saturated colour (HSV with random hue), distinct from the beige table."""
    import colorsys

    return colorsys.hsv_to_rgb(float(rng.uniform()), float(rng.uniform(0.5, 0.9)), float(rng.uniform(0.45, 0.95)))
