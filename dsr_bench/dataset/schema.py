"""The sequence file schema: every dataset's shape, dtype, units and meaning, in one table.

The writer, the reader, `dsr-bench validate` and DATASHEET.md's schema table all come from
`SEQUENCE_SCHEMA`; every producer (the generator, the annotator's export, the official import, the test
sequences) builds its root attributes with `sequence_header`. Shapes use symbols: T pushes (T + 1
observations), N objects, H x W the image size of the stored 2D data, and the grid (128, 128, 48) in (y, x, z)
order.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from dsr_bench import __version__
from dsr_bench.constants import (
    AXIS_ORDER, FLOW_COMPONENTS, GRID_BOUNDS, GRID_SHAPE, IMAGE_SHAPE, NUM_DIRECTIONS, VOXEL_SIZE,
)

GRID_SYMBOLS = ("Y", "X", "Z")
GROUND_TRUTH, OBSERVATION = "ground truth", "observation"


@dataclass(frozen=True)
class Field:
    """One HDF5 dataset of a sequence file."""

    name: str
    shape: tuple[str, ...]
    dtype: str
    units: str
    description: str
    camera: bool = False  # lives under cameras/<name>/
    required: bool = True
    value_range: tuple[float, float] | None = None
    #: "ground truth": what scores a model and what the policy decided, reproduced bit for bit on any
    #: CPU; "observation": what the cameras render (images, depth, TSDF, heightmap, 2D ground truth),
    #: reproduced to a stated tolerance (see `dsr_bench.dataset.digests`).
    group: str = OBSERVATION


SEQUENCE_SCHEMA: tuple[Field, ...] = (
    Field("tsdf", ("T+1", "Y", "X", "Z"), "float32", "truncation (0.02 m)",
          "Front-view TSDF at each voxel's corner: min(1, (depth - z) / trunc), +1 where unseen or free",
          value_range=(-1.0, 1.0)),
    Field("mask_3d", ("T+1", "Y", "X", "Z"), "uint8", "instance id",
          "Amodal instance ids: voxels whose cube (one voxel around its corner) meets each object's solid at its "
          "pose: 0 empty, 1..N objects", group=GROUND_TRUTH),
    Field("scene_flow_3d", ("T", "3", "Y", "X", "Z"), "float32", "voxels (0.4 cm), (dy, dx, dz)",
          "Rigid motion t -> t+1 of each object at the corners of its amodal voxels at t; 0 elsewhere",
          group=GROUND_TRUTH),
    Field("action", ("T", "3"), "int64", "[direction 0..7, row, col]",
          "Push: direction d (angle d*pi/4 in world xy), start cell (row along y, col along x)", group=GROUND_TRUTH),
    Field("push_start", ("T", "3"), "float64", "m, world (x, y, z)",
          "Tool tip commanded at the push start: the start cell's centre, 5 mm above the table", group=GROUND_TRUTH),
    Field("push_end", ("T", "3"), "float64", "m, world (x, y, z)",
          "Tool tip where the push phase ended (the arm's computed path, about 14.6 cm along the commanded 15 cm)",
          group=GROUND_TRUTH),
    Field("object_poses", ("T+1", "N", "7"), "float64", "m and unit quaternion (x, y, z, qx, qy, qz, qw)",
          "World pose of each object's mesh frame at each observation", group=GROUND_TRUTH),
    Field("visible_fraction", ("T+1", "N"), "float32", "fraction",
          "Visible pixels / amodal silhouette pixels of each object in the front camera", required=False,
          value_range=(0.0, 1.0)),
    Field("heightmap", ("T+1", "Y", "X"), "float32", "m above the table",
          "Top-down heightmap over the workspace (4 mm cells, the highest surface over each), what the push "
          "policy sees"),
    Field("color", ("T+1", "H", "W", "3"), "uint8", "RGB", "Colour image", camera=True),
    Field("depth", ("T+1", "H", "W"), "float32", "m, z-depth (0 = no return)", "Depth along the optical axis",
          camera=True),
    Field("mask", ("T+1", "H", "W"), "uint8", "instance id", "Visible instance ids: 0 table/background, 1..N",
          camera=True),
    Field("points", ("T+1", "H", "W", "3"), "float32", "m, world (x, y, z) (NaN = no return)",
          "World point of each pixel (stored, or derived from depth on reading: docs/format.md, 'Storage')",
          camera=True),
    Field("scene_flow_2d", ("T", "H", "W", "3"), "float32", "m, world (dy, dx, dz)",
          "World displacement t -> t+1 of the surface point seen at each pixel; 0 for the background",
          camera=True),
    Field("policy/chosen_object", ("T",), "int64", "object index 0..N-1", "Object the policy chose to push",
          required=False, group=GROUND_TRUTH),
    Field("policy/object_probs", ("T", "N"), "float32", "probability", "Object choice distribution", required=False,
          group=GROUND_TRUTH),
    Field("policy/direction_scores", ("T", str(NUM_DIRECTIONS)), "float32", "score",
          "Direction scores (NaN for the uniform policy)", required=False, group=GROUND_TRUTH),
    Field("policy/direction_probs", ("T", str(NUM_DIRECTIONS)), "float32", "probability",
          "Direction choice distribution", required=False, group=GROUND_TRUTH),
    Field("policy/attempts", ("T",), "int64", "count",
          "Samples drawn until a valid push was found (start-point search)", required=False, group=GROUND_TRUTH),
)

FIELDS: dict[str, Field] = {f.name: f for f in SEQUENCE_SCHEMA}

#: Root attributes every sequence carries.
REQUIRED_ATTRS: tuple[str, ...] = (
    "format", "schema_version", "sequence", "seed", "num_steps", "num_objects", "object_set", "policy",
    "generator_args", "toolkit_version", "source", "grid_bounds", "grid_shape", "voxel_size", "axis_order",
    "flow_components", "objects", "cameras",
)


def sequence_header(*, sequence: str, seed: int, num_steps: int, num_objects: int, object_set: str, policy: str,
                    generator_args: Mapping[str, Any], source: str, objects: list[dict], cameras: Mapping[str, Any],
                    versions: Mapping[str, Any] | None = None, **extra: Any) -> dict[str, Any]:
    """The root attributes of a sequence file, in the order they are written: `REQUIRED_ATTRS` (but `format` and
    `schema_version`, which `write_sequence` adds), the toolkit version and the grid's constants filled in, the
    versions of other tools that made it (`versions`, e.g. pybullet_version) right after toolkit_version, then
    `extra` (a producer's own attributes) in the order given; `write_sequence` adds the digests after them.
    `cameras`: name -> `dsr_bench.geometry.Camera` (stored as `Camera.as_attrs`)."""
    clash = sorted(set(extra) & set(REQUIRED_ATTRS) | set(versions or {}) & set(REQUIRED_ATTRS))
    if clash:
        raise ValueError(f"sequence_header: {clash} are required attributes, passed by their own arguments")
    header: dict[str, Any] = {
        "sequence": sequence, "seed": seed, "num_steps": num_steps, "num_objects": num_objects,
        "object_set": object_set, "policy": policy, "generator_args": generator_args, "toolkit_version": __version__,
        **(versions or {}),
        "source": source, "grid_bounds": GRID_BOUNDS.tolist(), "grid_shape": list(GRID_SHAPE),
        "voxel_size": VOXEL_SIZE, "axis_order": AXIS_ORDER, "flow_components": FLOW_COMPONENTS, "objects": objects,
        "cameras": {name: camera.as_attrs() for name, camera in cameras.items()},
    }
    header.update(extra)
    return header


def resolve_shape(field: Field, num_steps: int, num_objects: int,
                  image_shape: tuple[int, int] = IMAGE_SHAPE) -> tuple[int, ...]:
    """The concrete shape of a field for a sequence of T pushes and N objects."""
    sizes = {
        "T": num_steps, "T+1": num_steps + 1, "N": num_objects,
        "H": image_shape[0], "W": image_shape[1],
        "Y": GRID_SHAPE[0], "X": GRID_SHAPE[1], "Z": GRID_SHAPE[2],
    }
    return tuple(sizes[s] if s in sizes else int(s) for s in field.shape)


def dataset_path(field: Field, camera: str | None = None) -> str:
    """HDF5 path of a field (camera fields live under cameras/<camera>/)."""
    if field.camera:
        if camera is None:
            raise ValueError(f"field {field.name!r} needs a camera name")
        return f"cameras/{camera}/{field.name}"
    return field.name


class Shaped(Protocol):
    """What `check_array` reads: an array, an h5py dataset, or a record of a stored shape and dtype."""

    @property
    def shape(self) -> tuple[int, ...]: ...

    @property
    def dtype(self) -> Any: ...


def check_array(field: Field, array: Shaped, expected_shape: tuple[int, ...], where: str) -> list[str]:
    """Problems (empty if none) with an array against its field's shape and dtype."""
    problems = []
    if tuple(array.shape) != tuple(expected_shape):
        problems.append(f"{where}: shape {tuple(array.shape)}, expected {tuple(expected_shape)}")
    if np.dtype(array.dtype) != np.dtype(field.dtype):
        problems.append(f"{where}: dtype {array.dtype}, expected {field.dtype}")
    return problems
