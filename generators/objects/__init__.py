"""Object sets of the generator: `get_object_set(name, object_root)` -> an ObjectSet whose
`sample(rng, count)` returns `ObjectSpec`s (closed solid parts, colour, mass) deterministically."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from dsr_bench.errors import UserError
from dsr_bench.generators.objects.spec import ObjectSpec, Part

#: The object sets, one entry each: name -> (its class, "module:Class", imported on use; whether it reads meshes
#: from --object-root, which it checks when made). Every list of object-set names is this table's, in its order.
OBJECT_SETS: dict[str, tuple[str, bool]] = {
    "cube": ("dsr_bench.generators.objects.builtin:CubeSet", False),
    "shapenet": ("dsr_bench.generators.objects.external:ShapeNetSet", True),
    "ycb": ("dsr_bench.generators.objects.external:YCBSet", True),
    "procedural": ("dsr_bench.generators.objects.builtin:ProceduralSet", False),
    "procedural-novel": ("dsr_bench.generators.objects.builtin:ProceduralNovelSet", False),
}
OBJECT_SET_NAMES: tuple[str, ...] = tuple(OBJECT_SETS)

__all__ = ["OBJECT_SETS", "OBJECT_SET_NAMES", "ObjectSet", "ObjectSpec", "Part", "get_object_set"]


class ObjectSet(Protocol):
    name: str

    def sample(self, rng: np.random.Generator, count: int) -> list[ObjectSpec]: ...


def get_object_set(name: str, object_root: str | Path | None = None) -> ObjectSet:
    """The named object set; external sets are checked for their meshes here, before any work."""
    from importlib import import_module

    if name not in OBJECT_SETS:
        raise UserError(f"--objects {name!r} is not an object set; choose one of: {', '.join(OBJECT_SET_NAMES)}")
    where, meshes = OBJECT_SETS[name]
    module, _, attr = where.partition(":")
    cls = getattr(import_module(module), attr)
    return cls(object_root) if meshes else cls()
