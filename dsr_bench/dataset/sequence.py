"""Writing and reading sequence files (one HDF5 file per sequence, see `dsr_bench.dataset.schema`).

Files are written to a temporary name in the same directory and renamed into place, so a reader
never sees a partial file under its final name; the writer computes the file's digests
(`dsr_bench.dataset.digests`) from the arrays it writes, and `file_digests` recomputes them from a file.
Reading validates the format marker and schema version before anything else.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from dsr_bench.atomic import atomic_path
from dsr_bench.constants import FORMAT_NAME, READABLE_SCHEMA_VERSIONS, SCHEMA_VERSION
from dsr_bench.dataset.derived import DERIVED_FROM_ATTR, SOURCES, derivable_from, derive_steps, derived_shape
from dsr_bench.dataset.digests import Fingerprint, FingerprintAccumulator, digest_attrs, group_digests
from dsr_bench.dataset.schema import FIELDS, REQUIRED_ATTRS, check_array, dataset_path, resolve_shape
from dsr_bench.dataset.storage import GZIP1, read_steps, write_array
from dsr_bench.errors import UserError
from dsr_bench.geometry import Camera


class SequenceFormatError(UserError):
    """A file is not a readable sequence of this toolkit's format."""


class SequenceNotFoundError(UserError, FileNotFoundError):
    """No file at a sequence's path: a UserError (one line, exit 2), and a FileNotFoundError for callers that
    catch that."""


def _create_dataset(f: h5py.Group, name: str, array: np.ndarray) -> h5py.Dataset:
    """Write one array in the format's storage layout (`dsr_bench.dataset.storage.write_array`)."""
    return write_array(f, name, array)


#: The root attribute listing the arrays a file leaves out because they follow from others (JSON list of paths).
DERIVED_ATTR = "derived_arrays"


def points_name(camera: str) -> str:
    """The HDF5 path of a camera's world points (derivable from its depth)."""
    return f"cameras/{camera}/points"


def derive_points(depth: np.ndarray, camera) -> np.ndarray:
    """World points (..., H, W, 3) float32 of z-depth images (..., H, W) in metres, NaN where depth is 0: each pixel's
    ray (`Camera.ray_directions_world`, unit camera z) times its depth, plus the camera centre, in float64. Exactly
    the generator's points, which is why a file may leave them out."""
    depth = np.asarray(depth)
    rays = camera.ray_directions_world()  # (H, W, 3), computed once for every image: `Camera.backproject`'s terms
    points = rays * depth[..., None] + np.asarray(camera.extrinsics, np.float64)[:3, 3]
    points[depth <= 0] = np.nan
    return points.astype(np.float32)


def _derivable_points(arrays: Mapping[str, np.ndarray], cameras: Mapping[str, dict]) -> list[str]:
    """The cameras' points that equal `derive_points` of their depth bit for bit (NaN payloads included)."""
    names = []
    for cam, spec in cameras.items():
        points, depth = arrays.get(points_name(cam)), arrays.get(f"cameras/{cam}/depth")
        if points is None or depth is None or np.asarray(points).dtype != np.float32:
            continue
        derived = derive_points(depth, Camera.from_attrs(cam, spec))
        if derived.shape == np.shape(points) and np.array_equal(derived.view(np.uint32),
                                                                np.ascontiguousarray(points).view(np.uint32)):
            names.append(points_name(cam))
    return names


def _derivable_from_official(arrays: Mapping[str, np.ndarray], extras: Mapping[str, np.ndarray],
                             cameras: Mapping[str, dict], from_depth: list[str]) -> dict[str, str]:
    """The arrays of an import that are its `official/` arrays cast (`dsr_bench.dataset.derived`), bit for bit."""
    if not any(name.startswith("official/") for name in extras):
        return {}
    depth, spec = arrays.get("cameras/front/depth"), cameras.get("front")
    last_points = None if depth is None or spec is None else \
        (lambda: derive_points(np.asarray(depth)[-1], Camera.from_attrs("front", spec)))
    return derivable_from({k: v for k, v in arrays.items() if k not in from_depth}, extras, last_points)


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
    """Validate and atomically write one sequence file; returns its path.

    arrays: HDF5 path -> array (camera fields as 'cameras/<name>/<field>'); attrs: root attributes
    (dicts and lists of objects are stored as JSON strings); meshes: object index -> (vertices (V,3)
    float, faces (F,3) int) in the object's mesh frame, metres, stored under meshes/<index>/;
    extras: datasets outside the schema, written as given (e.g. `official/...` of an import).

    The digest attributes (`dsr_bench.dataset.digests.digest_attrs` of the arrays and extras, and of
    `attrs["objects"]`) are computed here and written after `attrs`: callers pass none (any in `attrs` are
    replaced). Raises SequenceFormatError (every problem in one line) for an array or attribute the schema refuses.
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
        if field.camera:
            camera = cameras[name.split("/")[1]]
            expected = resolve_shape(field, num_steps, num_objects, (camera["height"], camera["width"]))
        else:
            expected = resolve_shape(field, num_steps, num_objects)
        problems += check_array(field, np.asarray(array), expected, name)
    for field in FIELDS.values():
        names = [dataset_path(field, c) for c in cameras] if field.camera else [field.name]
        problems += [f"missing dataset {n!r}" for n in names if field.required and n not in arrays]
    if problems:
        raise SequenceFormatError(f"refusing to write {path.name}: " + "; ".join(problems))
    # the caller's attributes in their order, then the digests (replacing any given: a file's are its arrays')
    attrs = {**attrs, **digest_attrs({**arrays, **(extras or {})}, attrs["objects"])}

    derived = _derivable_points(arrays, cameras)  # left out: the reader derives them from depth
    derived_from = _derivable_from_official(arrays, extras or {}, cameras, derived)  # an import's casts, left out
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:  # temporary + lock, renamed when complete (dsr_bench.atomic)
        with h5py.File(tmp, "w", track_order=True) as f:
            f.attrs["format"] = FORMAT_NAME
            f.attrs["schema_version"] = SCHEMA_VERSION
            for key, value in attrs.items():
                f.attrs[key] = _encode_attr(value)
            if derived:
                f.attrs[DERIVED_ATTR] = json.dumps(derived)
            if derived_from:
                f.attrs[DERIVED_FROM_ATTR] = json.dumps(derived_from, sort_keys=True)
            for name in sorted(set(arrays) - set(derived) - set(derived_from)):
                array = np.ascontiguousarray(arrays[name])
                field = field_for(name)
                ds = _create_dataset(f, name, array)
                ds.attrs["units"] = field.units
            for name, extra in sorted((extras or {}).items()):
                array = np.ascontiguousarray(extra)
                _create_dataset(f, name, array)
            for index, (vertices, faces) in sorted((meshes or {}).items()):
                g = f.create_group(f"meshes/{index}")
                g.create_dataset("vertices", data=np.asarray(vertices, np.float32), track_times=False, **GZIP1)
                g.create_dataset("faces", data=np.asarray(faces, np.int32), track_times=False, **GZIP1)
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
            raise SequenceNotFoundError(f"sequence file not found: {self.path}; check the path, or generate or "
                                        "import the dataset it belongs to")
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
        if version not in READABLE_SCHEMA_VERSIONS:
            self._file.close()
            earlier = isinstance(version, (int, np.integer)) and version < SCHEMA_VERSION
            fix = ("it holds an earlier benchmark version's data: regenerate it (`dsr-bench generate`) or re-import "
                   "it (`dsr-bench import-official`)" if earlier else "upgrade dsr-bench")
            readable = ", ".join(map(str, READABLE_SCHEMA_VERSIONS))
            raise SequenceFormatError(f"{self.path}: schema version {version}, this toolkit reads {readable}; {fix}")
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
        #: arrays left out of the file and derived on reading (a camera's points, from its depth)
        self.derived: frozenset[str] = frozenset(self.attrs.pop(DERIVED_ATTR, []))
        unknown = [n for n in self.derived if n not in {points_name(c) for c in self.cameras}
                   or f"cameras/{n.split('/')[1]}/depth" not in self._file or n in self._file]
        if unknown:
            self._file.close()
            raise SequenceFormatError(f"{self.path}: {DERIVED_ATTR} lists {sorted(unknown)}, which cannot be derived "
                                      "(only a camera's points, from its stored depth); regenerate the file")
        #: an import's arrays left out as casts of its `official/` arrays (`dsr_bench.dataset.derived`): name -> source
        self.derived_from: dict[str, str] = dict(self.attrs.pop(DERIVED_FROM_ATTR, {}))
        unknown = [n for n, src in self.derived_from.items() if SOURCES.get(n) != src or src not in self._file
                   or n in self._file or (n.endswith("/points") and "cameras/front/depth" not in self._file)]
        if unknown:
            self._file.close()
            raise SequenceFormatError(f"{self.path}: {DERIVED_FROM_ATTR} lists {sorted(unknown)}, which cannot be "
                                      "derived from what the file stores; import it again")
        self.derived = self.derived | frozenset(self.derived_from)

    # context manager -----------------------------------------------------------------------------
    def __enter__(self) -> SequenceReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._file.close()

    # access ----------------------------------------------------------------------------------------
    def __contains__(self, name: str) -> bool:
        return name in self._file or name in self.derived

    def dataset(self, name: str) -> h5py.Dataset:
        """The raw h5py dataset of a stored array (for slicing without loading); `read` also derives the others."""
        if name not in self._file:
            derived = f" (derived on reading: read it with .read({name!r}))" if name in self.derived else ""
            raise KeyError(f"{self.path.name}: no dataset {name!r}{derived}")
        return self._file[name]

    def shape_and_dtype(self, name: str) -> tuple[tuple[int, ...], np.dtype]:
        """The shape and dtype of an array, stored or derived, without reading it."""
        if name in self.derived_from:
            return derived_shape(name, tuple(self.dataset(self.derived_from[name]).shape)), np.dtype(np.float32)
        if name in self.derived:
            depth = self.dataset(f"cameras/{name.split('/')[1]}/depth")
            return tuple(depth.shape) + (3,), np.dtype(np.float32)
        ds = self.dataset(name)
        return tuple(ds.shape), ds.dtype

    def array_names(self) -> list[str]:
        """Every array of the sequence, stored or derived, but the meshes (sorted)."""
        names: list[str] = list(self.derived)
        self._file.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset)
                              and not n.startswith("meshes/") else None)
        return sorted(names)

    def read(self, name: str, index: int | slice | None = None) -> np.ndarray:
        """Read an array, or one step / a range of steps of it along the first axis. Arrays the file leaves out
        (`derived`: a camera's points) are derived from what it stores (`derive_points`, `derived_from`)."""
        if name in self.derived_from:
            return self._read_derived_from(name, index)
        if name in self.derived:
            camera = name.split("/")[1]
            return derive_points(self.read(f"cameras/{camera}/depth", index), self.camera(camera))
        ds = self.dataset(name)
        if index is None:
            return read_steps(ds, 0, ds.shape[0]) if ds.ndim > 1 else ds[()]
        if ds.ndim > 1 and isinstance(index, (int, np.integer)) and -ds.shape[0] <= index < ds.shape[0]:
            step = int(index) % ds.shape[0]
            return read_steps(ds, step, step + 1)[0]
        if ds.ndim > 1 and isinstance(index, slice) and index.step in (None, 1):
            start, stop, _ = index.indices(ds.shape[0])
            return read_steps(ds, start, max(start, stop))
        return ds[index]

    def _read_derived_from(self, name: str, index: int | slice | None) -> np.ndarray:
        """An array the file derives from one of its `official/` arrays (`dsr_bench.dataset.derived`)."""
        source = self.dataset(self.derived_from[name])
        steps = derived_shape(name, tuple(source.shape))[0]
        if isinstance(index, (int, np.integer)) and -steps <= index < steps:
            start, stop = int(index) % steps, int(index) % steps + 1
        elif isinstance(index, slice) and index.step in (None, 1):
            start, stop, _ = index.indices(steps)
            stop = max(start, stop)
        else:
            start, stop = 0, steps
        if stop == start:
            shape = derived_shape(name, tuple(source.shape))
            return np.zeros((0,) + shape[1:], np.float32)
        out = derive_steps(name, lambda a, b: read_steps(source, a, b), source.shape[0],
                           lambda: derive_points(self.read("cameras/front/depth", steps - 1), self.camera("front")),
                           start, stop)
        if isinstance(index, (int, np.integer)) and -steps <= index < steps:
            return out[0]
        if index is None or (isinstance(index, slice) and index.step in (None, 1)):
            return out
        return out[index]

    def camera(self, name: str = "front"):
        """The `dsr_bench.geometry.Camera` of a stored camera."""
        return Camera.from_attrs(name, self.cameras[name])

    def mesh(self, index: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Vertices and faces of object `index` (0-based) in its mesh frame, if embedded."""
        key = f"meshes/{index}"
        if key not in self._file:
            return None
        return self._file[key]["vertices"][()], self._file[key]["faces"][()]


# --- digests of a file -------------------------------------------------------------------------------
def file_fingerprints(path: str | Path) -> tuple[dict[str, Fingerprint], list[dict]]:
    """Fingerprints (`dsr_bench.dataset.digests.Fingerprint`) of every array of a sequence file but `meshes/`
    (streamed one step at a time, memory of one step of the largest array), and its object list."""
    with SequenceReader(path) as seq:
        out = {}
        for name in seq.array_names():  # stored and derived (a camera's points)
            shape, dtype = seq.shape_and_dtype(name)
            acc = FingerprintAccumulator(name, dtype, shape)
            if len(shape) == 0 or shape[0] == 0:
                acc.update(np.asarray(seq.read(name)))
            else:
                for i in range(shape[0]):
                    acc.update(np.asarray(seq.read(name, i))[None])
            out[name] = acc.result()
        return out, list(seq.objects)


def file_digests(path: str | Path) -> dict:
    """`dsr_bench.dataset.digests.digest_attrs` of a sequence file recomputed from its arrays, with the
    fingerprints as well (`fingerprints`: {name: Fingerprint})."""
    prints, objects = file_fingerprints(path)
    per_array = {name: fp.sha256 for name, fp in prints.items()}
    return {"array_sha256": per_array, **group_digests(per_array, objects), "fingerprints": prints}
