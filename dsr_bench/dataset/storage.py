"""How sequence arrays lie in HDF5: chunks, filters, and the fast raw-chunk reader and writer.

Every per-step array has chunks of one step (random access by step) compressed with deflate level 1,
HDF5's built-in gzip filter, so any HDF5 reader without plugins opens the files (h5py, h5dump, MATLAB).
The 3D flow is stored in (Y, X) tiles instead, `GRID_TILE` voxels on a side with the whole Z column
(chunks (1, 3, 16, 16, 48)): it is zero except on the objects, which cover about 30% of the tiles,
and an all-zero tile is never written (HDF5 reads it as the dataset's fill value, 0). The chunks of the 3D
flow, the 2D flow and the depth go through HDF5's byte-shuffle filter before deflate (also built in):
their floats compress 1.3-1.8x smaller.
Everything is lossless: a read returns the array that was written, bit for bit.

The writer compresses each chunk itself (ISA-L when the optional `isal` package is installed, else
zlib skipping all-zero 16 KiB blocks) and writes it raw; the reader inflates raw chunks itself (ISA-L
when available, never beyond a chunk's size) and falls back to h5py for any other layout.
"""

from __future__ import annotations

import itertools
import zlib

import h5py
import numpy as np

from dsr_bench.constants import GRID_SHAPE
from dsr_bench.dataset.arraybytes import nonzero_rows

#: deflate level 1 through HDF5's gzip filter: what every chunked array uses
GZIP1 = {"compression": "gzip", "compression_opts": 1}
#: voxels on a side of the (Y, X) tiles of the tiled grids
GRID_TILE = 16
#: the ground-truth grids stored in tiles (the amodal mask is not: as uint8 it deflates to 5 kB a step either way and
#: reads faster in one chunk)
TILED_GRIDS = ("scene_flow_3d",)
#: arrays whose chunks are byte-shuffled before deflate (by the last part of their path): 26-45% smaller; the TSDF,
#: the points and the masks compress better without
SHUFFLED = ("scene_flow_3d", "scene_flow_2d", "depth")
#: the same for the official release's arrays an import keeps under `official/` (float64 points, 2D flow and
#: heightmaps, float32 depth): 30-45% smaller than deflate alone
OFFICIAL_SHUFFLED = ("pts_small", "scene_flow_2d", "depth_image", "depth_heightmap")
#: the deflate level of those `official/` arrays: an import writes them once and they are read only to rebuild the
#: release's own files, so they are compressed harder than generated arrays (level 1, for the generator's speed):
#: 20-25% smaller than at level 1
OFFICIAL_LEVEL = 6
#: more chunks per step than this and the reader leaves the file to h5py (a file we did not write)
MAX_CHUNKS_PER_STEP = 4096


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
        return zlib.compress(data.data, 1)
    zero = ~data[:blocks * _ZERO_BLOCK].view(np.uint64).reshape(blocks, -1).any(axis=1)
    if not zero.any():
        return zlib.compress(data.data, 1)
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
            piece = data[start:stop].data  # a memoryview: zlib's buffer (numpy's stubs type it so)
            out.append(compressor.compress(piece))
            out.append(compressor.flush(zlib.Z_FULL_FLUSH))
            adler = zlib.adler32(piece, (b << 16) | a)
            a, b = adler & 0xFFFF, adler >> 16
    out.append(compressor.flush(zlib.Z_FINISH))
    out.append(((b << 16) | a).to_bytes(4, "big"))
    return b"".join(out)


def _decompressobj_factory():
    """zlib-stream decompressor objects: ISA-L's (about 2x zlib's speed) when `isal` is installed, else zlib's."""
    try:
        from isal import isal_zlib
    except ImportError:
        return zlib.decompressobj
    return isal_zlib.decompressobj


_DECOMPRESSOBJ = _decompressobj_factory()


def inflate_exact(raw: bytes, nbytes: int) -> bytes | None:
    """The zlib stream `raw` inflated, when it holds exactly `nbytes` bytes and nothing after; else None.

    Never inflates more than nbytes + 1 bytes, so a hostile chunk (a file we did not write) cannot
    make the reader allocate more than its chunk's size."""
    d = _DECOMPRESSOBJ()
    try:
        out = d.decompress(raw, nbytes + 1)
    except zlib.error:
        return None
    if len(out) != nbytes or not d.eof or d.unconsumed_tail or d.unused_data:
        return None
    return out


def shuffle_bytes(data: np.ndarray, itemsize: int) -> np.ndarray:
    """HDF5's shuffle filter: the bytes (uint8, 1-D) of n items regrouped as all first bytes, then all second
    bytes, ... (byte k of item i goes to k * n + i)."""
    return np.ascontiguousarray(data.reshape(-1, itemsize).T).reshape(-1)


def unshuffle_bytes(data: np.ndarray, itemsize: int) -> np.ndarray:
    """The inverse of `shuffle_bytes` (a new writable uint8 array)."""
    planes = data.reshape(itemsize, -1)
    out = np.empty((planes.shape[1], itemsize), dtype=np.uint8)
    for k in range(itemsize):
        out[:, k] = planes[k]
    return out.reshape(-1)


def _chunk_layout(ds: h5py.Dataset) -> tuple[int, ...] | None:
    """The chunk shape of one step (a tile of it, or all of it) when the fast reader may read `ds` (chunks of one
    step that tile it exactly, gzip with or without shuffle and nothing else); None otherwise."""
    chunks, shape = ds.chunks, ds.shape
    if chunks is None or len(shape) < 2 or chunks[0] != 1 or ds.compression != "gzip" or ds.fletcher32 \
            or ds.scaleoffset is not None or any(s % c for s, c in zip(shape[1:], chunks[1:])):
        return None
    tile = tuple(chunks[1:])
    if tile != tuple(shape[1:]) and (np.prod([s // c for s, c in zip(shape[1:], tile)]) > MAX_CHUNKS_PER_STEP
                                     or ds.fillvalue != 0):
        return None
    return tile


def _inflate_chunk(ds: h5py.Dataset, offset: tuple[int, ...], nbytes: int) -> np.ndarray | None:
    """The bytes (uint8, 1-D) of the chunk at `offset`, unshuffled when the dataset shuffles, or None where
    HDF5 must decode it (a filter skipped for it). A chunk that went through every filter but does not inflate to
    exactly its chunk's bytes raises OSError: HDF5's own decoder would inflate it whole (a "gzip bomb" of a file
    we did not write can inflate a kilobyte to gigabytes) before keeping a chunk's worth."""
    try:
        mask, raw = ds.id.read_direct_chunk(offset)
    except (OSError, KeyError, ValueError, RuntimeError):  # e.g. a chunk never written (fill value)
        return None
    if mask:
        return None
    inflated = inflate_exact(raw, nbytes)
    if inflated is None:
        raise OSError(f"{ds.name}: chunk at {offset} does not inflate to its {nbytes} bytes")
    data = np.frombuffer(inflated, dtype=np.uint8)
    return unshuffle_bytes(data, ds.dtype.itemsize) if ds.shuffle else data


def _inflated_step(ds: h5py.Dataset, t: int, tile: tuple[int, ...],
                   columns: np.ndarray | None = None) -> np.ndarray | None:
    """Step t, inflated from its raw chunks, or None where h5py must read it. A step in one chunk comes back
    read-only (no copy); a tiled step is assembled in zeros from its written tiles. `columns` (bool, the step's
    shape but its last axis, all False), for tiles spanning that axis: set True where a written tile's Z column
    holds a non-zero byte (a tile never written is all zero)."""
    step_shape = tuple(ds.shape[1:])
    itemsize = ds.dtype.itemsize
    if tile == step_shape:
        data = _inflate_chunk(ds, (t,) + (0,) * len(step_shape), int(np.prod(step_shape)) * itemsize)
        return None if data is None else data.view(ds.dtype).reshape(step_shape)
    out = np.zeros(step_shape, dtype=ds.dtype)
    nbytes = int(np.prod(tile)) * itemsize
    for corner in itertools.product(*(range(0, s, c) for s, c in zip(step_shape, tile))):
        offset = (t,) + corner
        if ds.id.get_chunk_info_by_coord(offset).byte_offset is None:
            continue  # never written: the fill value, 0 (`_chunk_layout` admits fill value 0 only)
        data = _inflate_chunk(ds, offset, nbytes)
        if data is None:
            return None
        block = data.view(ds.dtype).reshape(tile)
        where = tuple(slice(o, o + c) for o, c in zip(corner, tile))
        out[where] = block
        if columns is not None:
            columns[where[:-1]] = nonzero_rows(block.reshape(-1, tile[-1])).reshape(tile[:-1])
    return out


def check_chunks_inflate(ds: h5py.Dataset, start: int, stop: int) -> None:
    """Raise OSError unless every stored chunk of a deflated dataset that steps [start, stop) touch inflates to exactly
    its chunk's bytes (for layouts HDF5 decodes itself: its gzip decoder inflates a chunk whole, however large,
    before keeping a chunk's worth). A chunk is inflated once, never beyond its size; nothing is kept."""
    if ds.chunks is None or ds.compression != "gzip" or stop <= start:
        return
    nbytes = int(np.prod(ds.chunks)) * ds.dtype.itemsize
    first, last = start // ds.chunks[0] * ds.chunks[0], stop
    for index in range(ds.id.get_num_chunks()):
        info = ds.id.get_chunk_info(index)
        if not first <= info.chunk_offset[0] < last:
            continue
        mask, raw = ds.id.read_direct_chunk(info.chunk_offset)
        if ds.fletcher32:  # its checksum follows the deflated bytes
            raw = raw[:-4]
        if mask & (1 << _filter_position(ds, h5py.h5z.FILTER_DEFLATE)):  # stored as is
            exact = len(raw) == nbytes
        else:
            exact = inflate_exact(raw, nbytes) is not None
        if not exact:
            raise OSError(f"{ds.name}: chunk at {tuple(info.chunk_offset)} does not inflate to its {nbytes} bytes")


def _filter_position(ds: h5py.Dataset, filter_id: int) -> int:
    """The position of a filter in a dataset's pipeline (the bit of a chunk's filter mask that says it was skipped)."""
    plist = ds.id.get_create_plist()
    for i in range(plist.get_nfilters()):
        if plist.get_filter(i)[0] == filter_id:
            return i
    return 0


def read_step(ds: h5py.Dataset, t: int) -> np.ndarray:
    """Step t (0 <= t < len) of a per-step dataset, shape ds.shape[1:]; read-only and without a copy where the
    step is one raw chunk inflated here (see `read_steps`)."""
    tile = _chunk_layout(ds)
    if tile is not None and 0 <= t < ds.shape[0]:
        step = _inflated_step(ds, t, tile)
        if step is not None:
            return step
    check_chunks_inflate(ds, t, t + 1)
    return ds[t]


def read_step_and_columns(ds: h5py.Dataset, t: int) -> tuple[np.ndarray, np.ndarray]:
    """Step t of a per-step grid (..., Z) and which of its Z columns hold a non-zero byte (bool, shape[1:-1]).

    For this format's tiled grids (tiles spanning the whole Z column) only the tiles written are looked at: a tile
    never written is the fill value 0, so the columns are found at a fraction of a full pass's cost; any other
    layout is read whole and every column is looked at (`dsr_bench.dataset.arraybytes.nonzero_rows`)."""
    step_shape = tuple(ds.shape[1:])
    tile = _chunk_layout(ds)
    if tile is not None and tile != step_shape and tile[-1] == step_shape[-1] and 0 <= t < ds.shape[0]:
        columns = np.zeros(step_shape[:-1], dtype=bool)
        out = _inflated_step(ds, t, tile, columns)
        if out is not None:
            return out, columns
    step = read_step(ds, t)  # HDF5 decodes it: every column looked at
    return step, nonzero_rows(np.ascontiguousarray(step).reshape(-1, step_shape[-1])).reshape(step_shape[:-1])


def read_steps(ds: h5py.Dataset, start: int, stop: int) -> np.ndarray:
    """Steps [start, stop) of a per-step dataset, shape (stop - start, *ds.shape[1:]), a new array.

    For this format's layouts (chunks of one step or tiles of it, gzip, with or without shuffle) the chunks
    are read raw and inflated here (ISA-L when available: the training loader's main cost; a chunk never
    inflates beyond its size); any other layout, and any chunk HDF5 must decode, is read through h5py."""
    tile = _chunk_layout(ds)
    if tile is None or not 0 <= start <= stop <= ds.shape[0]:
        check_chunks_inflate(ds, max(start, 0), min(stop, ds.shape[0]))
        return ds[start:stop]
    out = np.empty((stop - start,) + tuple(ds.shape[1:]), dtype=ds.dtype)
    for i, t in enumerate(range(start, stop)):
        step = _inflated_step(ds, t, tile)
        if step is None:
            check_chunks_inflate(ds, t, t + 1)
            step = ds[t]
        out[i] = step
    return out


def step_chunks(shape: tuple[int, ...]) -> tuple[int, ...] | None:
    """The chunks of an array of `shape`: one step (first axis) per chunk; None (contiguous) when small."""
    if len(shape) < 2 or int(np.prod(shape)) < 4096:
        return None
    return (1,) + tuple(shape[1:])


def write_array(f: h5py.Group, name: str, array: np.ndarray, level: int = 1) -> h5py.Dataset:
    """Create dataset `name` from a C-contiguous array in this format's layout (see the module's text): chunks of
    one step, deflate level 1; the grids of `TILED_GRIDS` in (Y, X) tiles with all-zero tiles not written. Numeric
    chunks are compressed here and written raw (the same stored array and filter pipeline as h5py's own write;
    only the compressed bytes differ). `level`: another deflate level (a copy shipped over a slow link:
    scripts/slim_dataset.py); the files the toolkit writes use 1, but an import's `official/` arrays OFFICIAL_LEVEL
    (and, like the 3D flow, the depth and the 2D flow, its float arrays are byte-shuffled: `OFFICIAL_SHUFFLED`)."""
    if level == 1 and name.startswith("official/"):
        level = OFFICIAL_LEVEL
    gzip = GZIP1 if level == 1 else {"compression": "gzip", "compression_opts": level}
    chunks = step_chunks(array.shape)
    tiled = name in TILED_GRIDS and tuple(array.shape[-3:]) == GRID_SHAPE
    last = name.rsplit("/", 1)[-1]
    shuffle = array.dtype.itemsize > 1 and (last in OFFICIAL_SHUFFLED if name.startswith("official/")
                                            else last in SHUFFLED)
    if chunks is not None and tiled:
        chunks = chunks[:-3] + (GRID_TILE, GRID_TILE, GRID_SHAPE[2])
    if chunks is None or array.dtype.kind not in "fiu":
        return f.create_dataset(name, data=array, chunks=chunks, track_times=False, **(gzip if chunks else {}))
    deflate = (_DEFLATE or _deflate_sparse) if level == 1 else (lambda data: zlib.compress(data, level))
    ds = f.create_dataset(name, shape=array.shape, dtype=array.dtype, chunks=chunks, track_times=False,
                          shuffle=shuffle, fillvalue=0, **gzip)
    tile = chunks[1:]
    corners = list(itertools.product(*(range(0, s, c) for s, c in zip(array.shape[1:], tile))))
    for t in range(array.shape[0]):
        for corner in corners:
            block = array[(t,) + tuple(slice(o, o + c) for o, c in zip(corner, tile))]
            if tiled and not block.any():
                continue  # read back as the fill value, 0
            data = np.ascontiguousarray(block).reshape(-1).view(np.uint8)
            if shuffle:
                data = shuffle_bytes(data, array.dtype.itemsize)
            ds.id.write_direct_chunk((t,) + corner, deflate(data))
    return ds
