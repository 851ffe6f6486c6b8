"""Object sets of the generator: `get_object_set(name, object_root)` -> an ObjectSet whose
`sample(rng, count)` returns `ObjectSpec`s (closed solid parts, colour, mass) deterministically."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from dsr_bench.errors import UserError
from generators.objects.spec import ObjectSpec, Part

OBJECT_SET_NAMES: tuple[str, ...] = ("cube", "shapenet", "ycb", "procedural", "procedural-novel")

__all__ = ["OBJECT_SET_NAMES", "ObjectSet", "ObjectSpec", "Part", "get_object_set"]


class ObjectSet(Protocol):
    name: str

    def sample(self, rng: np.random.Generator, count: int) -> list[ObjectSpec]: ...


def get_object_set(name: str, object_root: str | Path | None = None) -> ObjectSet:
    """The named object set; external sets are checked for their meshes here, before any work."""
    from generators.objects import builtin

    if name == "cube":
        return builtin.CubeSet()
    if name == "procedural":
        return builtin.ProceduralSet()
    if name == "procedural-novel":
        return builtin.ProceduralNovelSet()
    if name in ("shapenet", "ycb"):
        from generators.objects import external

        return external.open_external_set(name, object_root)
    raise UserError(f"--objects {name!r} is not an object set; choose one of: {', '.join(OBJECT_SET_NAMES)}")
