"""Writing and reading sequence files (one HDF5 file per sequence, see `dsr_bench.dataset.schema`).

Files are written to a temporary name in the same directory and renamed into place, so a reader
never sees a partial file under its final name. Reading validates the format marker and schema
version before anything else.
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from dsr_bench.atomic import atomic_path
from dsr_bench.constants import FORMAT_NAME, SCHEMA_VERSION
from dsr_bench.dataset.schema import FIELDS, REQUIRED_ATTRS, check_array, dataset_path, resolve_shape


from dsr_bench.errors import UserError


class SequenceFormatError(UserError):
    """A file is not a readable sequence of this toolkit's format."""


#: HDF5 storage: one chunk per step, gzip level 1 (fast random access by step, small files, fast to
#: write and read; byte shuffling made these mostly-constant arrays larger and slower).
_COMPRESSION = {"compression": "gzip", "compression_opts": 1}


def _fast_deflate():
    """A zlib-format compressor faster than zlib's own at level 1 (ISA-L, the optional `isal`
    package), or None. HDF5's gzip filter reads any zlib stream, so files stay plain gzip files."""
    try:
        from isal import isal_zlib
    except ImportError:
        return None
    return lambda data: isal_zlib.compress(data, 1)


_DEFLATE = _fast_deflate()

#: zlib's level 1 runs at ~0.6 GB/s even on zeros, and flow and mask chunks are mostly zero: without
#: ISA-L, all-zero 16 KiB blocks skip the compressor (see `_deflate_sparse`).
_ZERO_BLOCK = 16384
_ZERO_RUNS: dict[int, bytes] = {}  # raw deflate of 2**j zero blocks, each ending in a full flush


def _deflated_zeros(blocks: int) -> bytes:
    """Raw deflate data (byte-aligned, history reset, not final) of `blocks` zero blocks."""
    out = []
    j = 0
    while blocks:
        if blocks & 1:
            if j not in _ZERO_RUNS:
                c = zlib.compressobj(1, zlib.DEFLATED, -15)
                _ZERO_RUNS[j] = c.compress(bytes(_ZERO_BLOCK << j)) + c.flush(zlib.Z_FULL_FLUSH)
            out.append(_ZERO_RUNS[j])
        blocks >>= 1
        j += 1
    return b"".join(out)


def _deflate_sparse(data: np.ndarray) -> bytes:
    """A zlib stream (level 1) of the bytes `data` (uint8, 1-D, contiguous) in which runs of all-zero
    16 KiB blocks are not fed to the compressor but spliced in precompressed.

    Each run of other blocks is compressed and ended with a full flush (byte-aligned output, no
    back-references across it), so the pieces concatenate into one valid deflate stream; the
    Adler-32 of a zero run is updated in closed form (a unchanged, b += n * a)."""
    blocks = len(data) // _ZERO_BLOCK
    if blocks < 2:
        return zlib.compress(data, 1)
    zero = ~data[:blocks * _ZERO_BLOCK].view(np.uint64).reshape(blocks, -1).any(axis=1)
    if not zero.any():
        return zlib.compress(data, 1)
    kinds = np.append(zero, False)  # the tail after the last whole block is compressed
    edges = np.concatenate(([0], np.flatnonzero(kinds[1:] != kinds[:-1]) + 1, [len(kinds)]))
    compressor = zlib.compressobj(1, zlib.DEFLATED, -15)
    out = [b"\x78\x01"]  # zlib header: deflate, 32 KiB window, fastest
    a, b = 1, 0
    for first, last in zip(edges[:-1], edges[1:]):
        start, stop = int(first) * _ZERO_BLOCK, min(int(last) * _ZERO_BLOCK, len(data))
        if stop <= start:
            continue
        if kinds[first]:
            out.append(_deflated_zeros(int(last - first)))
            b = (b + (stop - start) * a) % 65521
        else:
            piece = data[start:stop]
            out.append(compressor.compress(piece))
            out.append(compressor.flush(zlib.Z_FULL_FLUSH))
            adler = zlib.adler32(piece, (b << 16) | a)
            a, b = adler & 0xFFFF, adler >> 16
    out.append(compressor.flush(zlib.Z_FINISH))
    out.append(((b << 16) | a).to_bytes(4, "big"))
    return b"".join(out)


def _fast_inflate():
    """zlib-stream decompressor: ISA-L's (about 2x zlib's speed) when `isal` is installed, else zlib's."""
    try:
        from isal import isal_zlib
    except ImportError:
        return zlib.decompress
    return isal_zlib.decompress


_INFLATE = _fast_inflate()


def read_steps(ds: h5py.Dataset, start: int, stop: int) -> np.ndarray:
    """Steps [start, stop) of a per-step dataset, shape (stop - start, *ds.shape[1:]).

    For this format's layout (one chunk per step, gzip only) the chunks are read raw and inflated here
    (ISA-L when available: the training loader's main cost); any other layout is read through h5py.
    """
    step_shape = tuple(ds.shape[1:])
    fast = (ds.chunks == (1,) + step_shape and ds.compression == "gzip" and not ds.shuffle
            and not ds.fletcher32 and ds.scaleoffset is None and 0 <= start <= stop <= ds.shape[0])
    if not fast:
        return ds[start:stop]
    out = np.empty((stop - start,) + step_shape, dtype=ds.dtype)
    origin = (0,) * len(step_shape)
    for i, t in enumerate(range(start, stop)):
        try:
            mask, raw = ds.id.read_direct_chunk((t,) + origin)
        except (OSError, KeyError, ValueError, RuntimeError):  # e.g. a chunk never written (fill value)
            mask, raw = 1, b""
        if mask:  # a filter was skipped for this chunk, or no chunk: let HDF5 decode it
            out[i] = ds[t]
            continue
        out[i] = np.frombuffer(_INFLATE(raw), dtype=ds.dtype).reshape(step_shape)
    return out


def _create_dataset(f, name: str, array: np.ndarray, chunks: tuple[int, ...] | None):
    """Create dataset `name` from a C-contiguous array: one chunk per step, gzip level 1 when chunked.

    Each step's chunk is compressed here (ISA-L if installed, else zlib skipping zero blocks) and
    written as is: the same stored array and filter pipeline; only the compressed bytes differ."""
    if chunks is None or array.dtype.kind not in "fiu" or chunks != (1,) + array.shape[1:]:
        return f.create_dataset(name, data=array, chunks=chunks, track_times=False,
                                **(_COMPRESSION if chunks else {}))
    deflate = _DEFLATE or _deflate_sparse
    ds = f.create_dataset(name, shape=array.shape, dtype=array.dtype, chunks=chunks, track_times=False,
                          **_COMPRESSION)
    rest = (0,) * (array.ndim - 1)
    for i in range(array.shape[0]):
        ds.id.write_direct_chunk((i,) + rest, deflate(array[i].reshape(-1).view(np.uint8)))
    return ds


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
    with atomic_path(path) as tmp:  # temporary + lock, renamed when complete (dsr_bench.atomic)
        with h5py.File(tmp, "w", track_order=True) as f:
            f.attrs["format"] = FORMAT_NAME
            f.attrs["schema_version"] = SCHEMA_VERSION
            for key, value in attrs.items():
                f.attrs[key] = _encode_attr(value)
            for name in sorted(arrays):
                array = np.ascontiguousarray(arrays[name])
                field = field_for(name)
                ds = _create_dataset(f, name, array, _chunks(array.shape))
                ds.attrs["units"] = field.units
            for name in sorted(extras or {}):
                array = np.ascontiguousarray(extras[name])
                _create_dataset(f, name, array, _chunks(array.shape))
            for index, (vertices, faces) in sorted((meshes or {}).items()):
                g = f.create_group(f"meshes/{index}")
                g.create_dataset("vertices", data=np.asarray(vertices, np.float32), track_times=False, **_COMPRESSION)
                g.create_dataset("faces", data=np.asarray(faces, np.int32), track_times=False, **_COMPRESSION)
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
            fix = ("it holds an earlier benchmark version's data: regenerate it (`dsr-bench generate`) or re-import "
                   "it (`dsr-bench import-official`)" if isinstance(version, (int, np.integer)) and version < SCHEMA_VERSION
                   else "upgrade dsr-bench")
            raise SequenceFormatError(f"{self.path}: schema version {version}, this toolkit reads {SCHEMA_VERSION}; {fix}")
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
        if index is None:
            return ds[()]
        if ds.ndim > 1 and isinstance(index, (int, np.integer)) and -ds.shape[0] <= index < ds.shape[0]:
            step = int(index) % ds.shape[0]
            return read_steps(ds, step, step + 1)[0]
        if ds.ndim > 1 and isinstance(index, slice) and index.step in (None, 1):
            start, stop, _ = index.indices(ds.shape[0])
            return read_steps(ds, start, max(start, stop))
        return ds[index]

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
