"""Writing and reading sequence files (one HDF5 file per sequence, see `dsr_bench.schema`).

Files are written to a temporary name in the same directory and renamed into place, so a reader
never sees a partial file under its final name. Reading validates the format marker and schema
version before anything else.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from dsr_bench.constants import FORMAT_NAME, SCHEMA_VERSION
from dsr_bench.schema import FIELDS, REQUIRED_ATTRS, check_array, dataset_path, resolve_shape


from dsr_bench.errors import UserError


class SequenceFormatError(UserError):
    """A file is not a readable sequence of this toolkit's format."""


#: HDF5 storage: one chunk per step, gzip level 1 (fast random access by step, small files, fast to
#: write and read; byte shuffling made these mostly-constant arrays larger and slower).
_COMPRESSION = {"compression": "gzip", "compression_opts": 1}


def _chunks(shape: tuple[int, ...]) -> tuple[int, ...] | None:
    if len(shape) < 2 or int(np.prod(shape)) < 4096:
        return None
    return (1,) + tuple(shape[1:])


def _encode_attr(value: Any) -> Any:
    if isinstance(value, (dict, list, tuple)) and not (
        isinstance(value, (list, tuple)) and value and all(isinstance(v, (int, float)) for v in value)
    ):
        return json.dumps(value, sort_keys=True)
    return value


def field_for(name: str):
    """The schema field of an HDF5 dataset path ('cameras/<camera>/<field>' or a field name)."""
    return FIELDS.get(name.rsplit("/", 1)[-1] if name.startswith("cameras/") else name)


def write_sequence(
    path: str | Path,
    arrays: Mapping[str, np.ndarray],
    attrs: Mapping[str, Any],
    meshes: Mapping[int, tuple[np.ndarray, np.ndarray]] | None = None,
    extras: Mapping[str, np.ndarray] | None = None,
) -> Path:
    """Validate and atomically write one sequence file.

    arrays: HDF5 path -> array (camera fields as 'cameras/<name>/<field>'); attrs: root attributes
    (dicts and lists of objects are stored as JSON strings); meshes: object index -> (vertices (V,3)
    float, faces (F,3) int) in the object's mesh frame, metres, stored under meshes/<index>/;
    extras: datasets outside the schema, written as given (e.g. `official/...` of an import).
    """
    path = Path(path)
    num_steps, num_objects = int(attrs["num_steps"]), int(attrs["num_objects"])
    cameras = attrs["cameras"]
    problems = [f"extra dataset {name!r} must live under official/" for name in (extras or {})
                if not name.startswith("official/")]
    for key in REQUIRED_ATTRS:
        if key not in attrs and key not in ("format", "schema_version"):
            problems.append(f"missing attribute {key!r}")
    for name, array in arrays.items():
        field = field_for(name)
        if field is None:
            problems.append(f"unknown dataset {name!r}")
            continue
        image_shape = (cameras[name.split("/")[1]]["height"], cameras[name.split("/")[1]]["width"]) if field.camera else None
        expected = resolve_shape(field, num_steps, num_objects, image_shape) if field.camera else resolve_shape(
            field, num_steps, num_objects)
        problems += check_array(field, np.asarray(array), expected, name)
    for field in FIELDS.values():
        names = [dataset_path(field, c) for c in cameras] if field.camera else [field.name]
        problems += [f"missing dataset {n!r}" for n in names if field.required and n not in arrays]
    if problems:
        raise SequenceFormatError(f"refusing to write {path.name}: " + "; ".join(problems))

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with h5py.File(tmp, "w", track_order=True) as f:
            f.attrs["format"] = FORMAT_NAME
            f.attrs["schema_version"] = SCHEMA_VERSION
            for key, value in attrs.items():
                f.attrs[key] = _encode_attr(value)
            for name in sorted(arrays):
                array = np.ascontiguousarray(arrays[name])
                field = field_for(name)
                chunks = _chunks(array.shape)
                ds = f.create_dataset(
                    name, data=array, chunks=chunks, track_times=False, **(_COMPRESSION if chunks else {})
                )
                ds.attrs["units"] = field.units
            for name in sorted(extras or {}):
                array = np.ascontiguousarray(extras[name])
                chunks = _chunks(array.shape)
                f.create_dataset(name, data=array, chunks=chunks, track_times=False, **(_COMPRESSION if chunks else {}))
            for index, (vertices, faces) in sorted((meshes or {}).items()):
                g = f.create_group(f"meshes/{index}")
                g.create_dataset("vertices", data=np.asarray(vertices, np.float32), track_times=False, **_COMPRESSION)
                g.create_dataset("faces", data=np.asarray(faces, np.int32), track_times=False, **_COMPRESSION)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


class SequenceReader:
    """Lazy reader of one sequence file: arrays are read per request, never the whole file.

    >>> with SequenceReader("seq_0000.h5") as seq:
    ...     tsdf0 = seq.read("tsdf", 0)           # (128, 128, 48) float32
    ...     flow = seq.read("scene_flow_3d", 3)   # (3, 128, 128, 48) voxels, (dy, dx, dz)
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"sequence file not found: {self.path}")
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as exc:
            raise SequenceFormatError(f"{self.path}: not a readable HDF5 file ({exc})") from None
        fmt = self._file.attrs.get("format")
        version = self._file.attrs.get("schema_version")
        if fmt != FORMAT_NAME:
            self._file.close()
            raise SequenceFormatError(
                f"{self.path}: not a dsr-bench sequence (format attribute {fmt!r}); official release files "
                "are converted with `dsr-bench import-official SRC DST`"
            )
        if version != SCHEMA_VERSION:
            self._file.close()
            raise SequenceFormatError(
                f"{self.path}: schema version {version}, this toolkit reads {SCHEMA_VERSION}; upgrade dsr-bench"
            )
        self.attrs: dict[str, Any] = {}
        for key, value in self._file.attrs.items():
            if isinstance(value, str) and value[:1] in "[{":
                value = json.loads(value)
            self.attrs[key] = value
        self.name: str = str(self.attrs.get("sequence", self.path.stem))
        self.num_steps: int = int(self.attrs["num_steps"])
        self.num_objects: int = int(self.attrs["num_objects"])
        self.objects: list[dict] = list(self.attrs["objects"])
        self.cameras: dict[str, dict] = dict(self.attrs["cameras"])

    # context manager -----------------------------------------------------------------------------
    def __enter__(self) -> SequenceReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._file.close()

    # access ----------------------------------------------------------------------------------------
    def __contains__(self, name: str) -> bool:
        return name in self._file

    def dataset(self, name: str) -> h5py.Dataset:
        """The raw h5py dataset (for slicing without loading)."""
        if name not in self._file:
            raise KeyError(f"{self.path.name}: no dataset {name!r}")
        return self._file[name]

    def read(self, name: str, index: int | slice | None = None) -> np.ndarray:
        """Read a dataset, or one step / a range of steps of it along the first axis."""
        ds = self.dataset(name)
        return ds[()] if index is None else ds[index]

    def camera(self, name: str = "front"):
        """The `dsr_bench.geometry.Camera` of a stored camera."""
        from dsr_bench.geometry import Camera

        spec = self.cameras[name]
        return Camera(name, int(spec["height"]), int(spec["width"]), np.array(spec["intrinsics"]),
                      np.array(spec["extrinsics"]))

    def mesh(self, index: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Vertices and faces of object `index` (0-based) in its mesh frame, if embedded."""
        key = f"meshes/{index}"
        if key not in self._file:
            return None
        return self._file[key]["vertices"][()], self._file[key]["faces"][()]
