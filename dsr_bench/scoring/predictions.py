"""The predictions contract: one HDF5 file per test sequence, named like the sequence.

PRED_DIR/seq_0042.h5 holds, for each push t = 0..T-1 (made after observations 0..t and action t):
  mask       (T, 128, 128, 48) uint8    amodal instance slots: 0 empty, 1..num_slots
  motion     (T, 3, 128, 128, 48) float16 or float32  scene flow t -> t+1 in voxels, (dy, dx, dz)
  motion_2d  (T, 240, 320, 3) float16/32, optional    front-camera flow in metres, (dy, dx, dz)
and, with mask, the root attribute `num_slots` (K - 1, the number of object slots the model has: a
scalar integer in 1..254; slot numbers are the model's own, matching is the metric's job). Every file states, in
string root attributes (`prediction_attrs`, which `write_predictions` writes), the sequence it predicts (`sequence`:
its name without .h5), `flow_components` "dy,dx,dz" and, with mask, `axis_order` "y,x,z" (volumes (Y, X, Z) = world
y, world x, z); another sequence (a file copied under another's name), another layout, or none, is refused.
mask and motion come together (the 3D track, optionally with motion_2d); a file with motion_2d alone
is a 2D-only prediction (the 2D track: image-space models), scored on the 2D flow only, and needs no
num_slots (if present, it must still be valid). A directory is all 3D or all 2D-only.
PRED_DIR/meta.json optionally describes the method: a JSON object of at most 1 MiB with string
"name", "description", "code_url", "hardware", an object "parameters" and a number
"seconds_per_step". `dsr-bench predict` also records where the predictions came from, string
"data" (the dataset directory, absolute) and "split" (`record_source`), from which `evaluate` and
`view` infer --data and --split (`infer_source`); they describe a machine, not the method, so
results do not carry them.

What a prediction file must not be, so that a score cannot be borrowed, hang or crash the
evaluator (`check_prediction_header`, `file_problem`, `read_meta`; nothing is read before these pass):
- anything but a regular file of PRED_DIR's own (a FIFO, a directory, a device, a symlink, even to a sibling);
- a file whose root holds anything but those datasets: no extra dataset or group, no soft,
  external or user-defined link, no dataset linked twice; mask without motion or motion without mask;
  none of mask, motion and motion_2d;
- a dataset whose bytes are not in the file itself: virtual datasets (other files' data, or zeros
  when their source is missing) and external raw storage (`external=`);
- a dataset compressed with a filter other than gzip, shuffle, fletcher32 or lzf (plugins), a filter twice or
  two compressors (gzip of gzip: a 7 kB file inflates to 1 GB);
- a chunk layout that would cost the evaluator memory out of proportion to the data: more than
  MAX_STEP_CHUNKS chunks per step (HDF5 keeps about 6.6 kB for each chunk one read touches, written or not),
  or a chunk holding more bytes than the whole dataset (HDF5 inflates a chunk whole);
- a shape or dtype other than the contract's, checked before any data is read, so memory stays
  bounded by the sequence's size;
- a missing or wrong `sequence`, `axis_order` or `flow_components` (`check_layout_attrs`).
"""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path

import h5py
import numpy as np
from h5py import h5d, h5l, h5o, h5z

from dsr_bench.atomic import atomic_path, write_text
from dsr_bench.constants import AXIS_ORDER, FLOW_COMPONENTS, GRID_SHAPE, IMAGE_SHAPE
from dsr_bench.errors import UserError

PREDICTION_FORMAT = "dsr-bench-predictions"
MOTION_DTYPES = (np.dtype("float16"), np.dtype("float32"))
MAX_SLOTS = 254
#: the datasets a prediction file may hold at its root; motion_2d is optional
DATASETS = ("mask", "motion", "motion_2d")
#: filters every h5py build decodes without a plugin
FILTERS = {h5z.FILTER_DEFLATE: "gzip", h5z.FILTER_SHUFFLE: "shuffle", h5z.FILTER_FLETCHER32: "fletcher32",
           32000: "lzf"}
#: the most chunks one step of a prediction dataset may span (what one step's read touches): HDF5 keeps about 6.6 kB
#: per chunk a read touches, so a step's read costs at most ~7 MB beyond its data (reasonable layouts: 1-384)
MAX_STEP_CHUNKS = 1024
#: the fix named when a chunk layout is refused
CHUNK_FIX = "write it with write_predictions, or in chunks of one step"
META_NAME = "meta.json"
META_MAX_BYTES = 1 << 20
#: meta.json's known keys and the JSON types they must have
META_TYPES: dict[str, tuple[tuple[type, ...], str]] = {
    "name": ((str,), "a string"), "description": ((str,), "a string"), "code_url": ((str,), "a string"),
    "hardware": ((str,), "a string"), "parameters": ((dict,), "an object"),
    "seconds_per_step": ((int, float), "a number"),
}


def prediction_attrs(sequence: str, three_d: bool = True) -> dict[str, str]:
    """The root attributes a prediction file of `sequence` states besides num_slots: the sequence, the flow components
    and, in a 3D file (mask and motion), the axis order. By hand: `f.attrs.update(prediction_attrs("seq_0042"))`."""
    attrs = {"sequence": sequence, "flow_components": FLOW_COMPONENTS}
    return {**attrs, "axis_order": AXIS_ORDER} if three_d else attrs


def write_predictions(path: str | Path, mask: np.ndarray | None = None, motion: np.ndarray | None = None,
                      num_slots: int | None = None, motion_2d: np.ndarray | None = None) -> Path:
    """Validate arrays against the contract and write them atomically to `path` (.h5).

    3D: mask (T, 128, 128, 48) uint8 slots and motion (T, 3, 128, 128, 48) float16/32 voxels (dy, dx, dz), with
    num_slots (1..254), optionally motion_2d (T, 240, 320, 3) float16/32 metres (dy, dx, dz). 2D-only: motion_2d
    alone (mask and motion None; num_slots, then unused, is not written). The file states `prediction_attrs`."""
    path = Path(path)
    problems = []
    if (mask is None) != (motion is None):
        given, other = ("mask", "motion") if motion is None else ("motion", "mask")
        raise UserError(f"refusing to write {path.name}: {given} without {other}; mask and motion come together "
                        "(give both, or neither with motion_2d for a 2D-only prediction)")
    if mask is None and motion_2d is None:
        raise UserError(f"refusing to write {path.name}: no arrays; give mask, motion and num_slots (3D), "
                        "or motion_2d alone (2D-only)")
    steps = None
    if mask is not None:
        mask, motion = np.asarray(mask), np.asarray(motion)
        steps = mask.shape[0] if mask.ndim else 0
        if mask.ndim != 4 or mask.shape[1:] != GRID_SHAPE or mask.dtype != np.uint8:
            problems.append(f"mask must be (T, {', '.join(map(str, GRID_SHAPE))}) uint8, got {mask.shape} {mask.dtype}")
        if motion.shape != (steps, 3) + GRID_SHAPE or motion.dtype not in MOTION_DTYPES:
            problems.append(f"motion must be (T, 3, {', '.join(map(str, GRID_SHAPE))}) float16/float32, "
                            f"got {motion.shape} {motion.dtype}")
        elif not np.all(np.isfinite(motion)):
            problems.append("motion has NaN or inf")
        if num_slots is None:
            problems.append(f"num_slots is required with mask (the number of object slots, 1..{MAX_SLOTS})")
        elif not 1 <= num_slots <= MAX_SLOTS:
            problems.append(f"num_slots {num_slots} must be 1..{MAX_SLOTS}")
        elif mask.size and int(mask.max()) > num_slots:
            problems.append(f"mask has slot {int(mask.max())} > num_slots {num_slots}")
    if motion_2d is not None:
        motion_2d = np.asarray(motion_2d)
        expected = ((steps,) if steps is not None else motion_2d.shape[:1]) + IMAGE_SHAPE + (3,)
        if motion_2d.ndim != 4 or motion_2d.shape != expected or motion_2d.dtype not in MOTION_DTYPES:
            problems.append(f"motion_2d must be (T, {', '.join(map(str, IMAGE_SHAPE))}, 3) float16/float32"
                            f"{' (T as in mask)' if steps is not None else ''}, got {motion_2d.shape} "
                            f"{motion_2d.dtype}")
        elif not np.all(np.isfinite(motion_2d)):
            problems.append("motion_2d has NaN or inf")
    if problems:
        raise UserError(f"refusing to write {path.name}: " + "; ".join(problems))
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = PREDICTION_FORMAT
        f.attrs.update(prediction_attrs(path.stem, three_d=mask is not None))
        opts = {"compression": "gzip", "compression_opts": 1}
        if mask is not None:
            assert num_slots is not None  # checked above with mask
            f.attrs["num_slots"] = int(num_slots)
            f.create_dataset("mask", data=mask, chunks=(1,) + GRID_SHAPE, track_times=False, **opts)
            # byte-shuffled before deflate: the same values, a full grid's dense float motion written in 139 ms
            # instead of 205 and 6% smaller (measured on a (3, 128, 128, 48) float32 field)
            f.create_dataset("motion", data=motion, chunks=(1, 3) + GRID_SHAPE, track_times=False, shuffle=True,
                             **opts)
        if motion_2d is not None:
            f.create_dataset("motion_2d", data=motion_2d, chunks=(1,) + IMAGE_SHAPE + (3,), track_times=False, **opts)
    return path


def is_2d_only(f: h5py.File) -> bool:
    """Whether an open prediction file (its header checked) is a 2D-only prediction: motion_2d without mask and
    motion. Reads no array data."""
    return "mask" not in f and "motion" not in f and "motion_2d" in f


def _kind(mode: int) -> str:
    """A file type in words, for a mode that is not a regular file's."""
    for test, word in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device")):
        if test(mode):
            return word
    return "not a regular file"


#: the fix named when a symlink stands in a predictions directory
LINK_FIX = "a predictions directory holds regular files only: copy the file in place of the link"


def file_problem(path: Path, root: Path) -> str | None:
    """Why `path` may not be read as a file of the directory `root` (None: a regular file of its own). Only stats: a
    FIFO is never opened. A symlink is refused wherever it leads (to a sibling: one file for two sequences)."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return "missing"
    except OSError as exc:
        return f"cannot be read ({exc.strerror})"
    if stat.S_ISLNK(mode):
        try:
            target = path.resolve(strict=True)
        except (OSError, RuntimeError):
            return f"is a dangling or looping symlink; {LINK_FIX}"
        if not target.is_relative_to(root.resolve()):
            return f"resolves outside the predictions directory (a symlink leading out of it); {LINK_FIX}"
        return f"is a symlink to {_show(target.name)} in the predictions directory; {LINK_FIX}"
    if not stat.S_ISREG(mode):
        return f"is {_kind(mode)}, not a regular file"
    return None


def _show(raw: bytes | str, limit: int = 80) -> str:
    """A name or path from a file, quoted on one line and cut to `limit` characters in the middle (a
    path's start and its file name stay readable)."""
    text = raw.decode("utf-8", "backslashreplace") if isinstance(raw, bytes) else raw
    if len(text) > limit:
        head = limit // 2 - 2
        text = text[:head] + "..." + text[len(text) - (limit - head - 3):]
    return repr(text)


def check_num_slots(attrs: h5py.AttributeManager) -> list[str]:
    """Problems of the root attribute num_slots: a scalar integer (not a boolean) in 1..MAX_SLOTS.
    Its shape and type are checked before its value is read."""
    expected = f"attribute num_slots must be a scalar integer in 1..{MAX_SLOTS}"
    if "num_slots" not in attrs:
        return [f"{expected}, it is missing"]
    aid = attrs.get_id("num_slots")
    try:
        dtype = aid.dtype
    except (TypeError, ValueError):
        return [f"{expected}, got an unsupported HDF5 type"]
    if aid.shape is None:
        return [f"{expected}, got an empty attribute"]
    if aid.shape != ():
        return [f"{expected}, got an array of shape {aid.shape}"]
    if dtype.kind == "b":
        return [f"{expected}, got a boolean"]
    if dtype.kind in "SUO" or h5py.check_string_dtype(dtype) is not None:
        return [f"{expected}, got a string"]
    if dtype.kind not in "iuf" or dtype.itemsize > 16:
        return [f"{expected}, got type {dtype}"]
    value = attrs["num_slots"]
    if dtype.kind == "f":
        return [f"{expected}, got the float {float(value)!r} (store an integer type, e.g. np.int64)"]
    if not 1 <= int(value) <= MAX_SLOTS:
        return [f"{expected}, got {int(value)}"]
    return []


def _string_attr(attrs: h5py.AttributeManager, key: str) -> tuple[str | None, str]:
    """(A scalar string attribute's value, "") or (None, what it is instead), checked before its value is read."""
    if key not in attrs:
        return None, "it is missing"
    aid = attrs.get_id(key)
    try:
        dtype = aid.dtype
    except (TypeError, ValueError):
        return None, "got an unsupported HDF5 type"
    if aid.shape != ():
        return None, "got an empty attribute" if aid.shape is None else f"got an array of shape {aid.shape}"
    if dtype.kind != "S" and h5py.check_string_dtype(dtype) is None:
        return None, f"got type {dtype}"
    value = attrs[key]
    return (value.decode("utf-8", "backslashreplace") if isinstance(value, bytes) else str(value)), ""


def check_layout_attrs(attrs: h5py.AttributeManager, sequence: str, three_d: bool) -> list[str]:
    """Problems of the attributes stating what a prediction file predicts (`prediction_attrs`): `sequence`, the one it
    is named for; `flow_components` and (3D, or where present) `axis_order`, the contract's."""
    problems = []
    value, got = _string_attr(attrs, "sequence")
    if value is None:
        problems.append(f"attribute sequence must name the sequence this file predicts ({sequence!r}), {got}; "
                        "write it with write_predictions, or set prediction_attrs")
    elif value != sequence:
        problems.append(f"attribute sequence is {_show(value)}, but the file is {sequence}.h5: another sequence's "
                        "predictions under this one's name; write each sequence's own predictions")
    expected = {"flow_components": (FLOW_COMPONENTS, "motion components (dy, dx, dz)")}
    if three_d or "axis_order" in attrs:
        expected["axis_order"] = (AXIS_ORDER, "volumes (T, Y, X, Z) = world y, world x, z")
    for key, (want, words) in expected.items():
        value, got = _string_attr(attrs, key)
        if value != want:
            problems.append(f"attribute {key} must be {want!r} ({words}), "
                            f"{got if value is None else 'got ' + _show(value)}; store the arrays in that order "
                            "and say so (write_predictions does)")
    return problems


def _storage_problems(name: str, dset: h5py.Dataset) -> list[str]:
    """A dataset whose bytes are not in this file, or need a filter plugin to decode. Reads no data."""
    plist = dset.id.get_create_plist()
    layout = plist.get_layout()
    problems = []
    if layout == h5d.VIRTUAL:
        count = plist.get_virtual_count()
        sources = sorted({plist.get_virtual_filename(i) for i in range(count)})
        shown = ", ".join(_show(s) for s in sources[:2]) + (f" and {len(sources) - 2} more" if len(sources) > 2 else "")
        problems.append(f"{name}: a virtual dataset (its data are read from {shown or 'nowhere'}, or are zeros when "
                        "those are missing); write the arrays into the file itself")
    elif layout not in (h5d.CONTIGUOUS, h5d.CHUNKED, h5d.COMPACT):
        problems.append(f"{name}: unknown storage layout {layout}; write the arrays with h5py's defaults")
    if plist.get_external_count():
        raw = plist.get_external(0)[0]
        problems.append(f"{name}: stored in external raw file(s) ({_show(raw)}); write the arrays into the file itself")
    codes = []
    for i in range(plist.get_nfilters()):
        code, _flags, _values, label = plist.get_filter(i)
        codes.append(code)
        if code not in FILTERS:
            shown = f" ({_show(label)})" if label else ""
            problems.append(f"{name}: compressed with HDF5 filter {code}{shown}, which needs a plugin; "
                            f"use {', '.join(FILTERS.values())} or none")
    repeated = sorted({FILTERS.get(c, str(c)) for c in codes if codes.count(c) > 1})
    compressors = [FILTERS[c] for c in codes if c in (h5z.FILTER_DEFLATE, 32000)]
    if repeated or len(compressors) > 1:
        what = f"filter {' and '.join(repeated)} more than once" if repeated else " and ".join(compressors)
        pipeline = " -> ".join(FILTERS.get(c, str(c)) for c in codes)
        problems.append(f"{name}: compressed with {what} (filters {pipeline}); one compressor at most, each filter "
                        "once: write it with write_predictions")
    return problems


def _chunk_problems(name: str, dset: h5py.Dataset) -> list[str]:
    """A chunk layout that would cost the evaluator memory out of proportion to the data: more than
    MAX_STEP_CHUNKS chunks per step (one step's read touches them all, and HDF5 keeps ~6.6 kB for each, written
    or not), or a chunk holding more bytes than the dataset (possible when resizable; HDF5 inflates a chunk whole).
    Reads the layout from the header only: the limits hold whatever the chunks hold, even nothing."""
    chunks, shape = dset.chunks, dset.shape
    if chunks is None or len(chunks) != len(shape) or not shape:
        return []  # contiguous or compact: a read touches the bytes it selects
    per_step = math.prod(-(-s // c) for s, c in zip(shape[1:], chunks[1:]))
    problems = []
    if per_step > MAX_STEP_CHUNKS:
        total = -(-shape[0] // chunks[0]) * per_step
        problems.append(f"{name}: chunks {chunks} split each step into {per_step} chunks ({total} in all), more "
                        f"than the {MAX_STEP_CHUNKS} allowed (HDF5 keeps about 6.6 kB per chunk a read touches); "
                        f"{CHUNK_FIX}")
    itemsize = dset.id.get_type().get_size()
    chunk_bytes, data_bytes = math.prod(chunks) * itemsize, math.prod(shape) * itemsize
    if data_bytes and chunk_bytes > data_bytes:
        problems.append(f"{name}: chunks {chunks} hold {chunk_bytes} bytes each, more than the whole dataset "
                        f"{shape} ({data_bytes} bytes; HDF5 inflates a chunk whole); {CHUNK_FIX}")
    return problems


def _root_problems(f: h5py.File) -> tuple[list[str], set[str], set[str]]:
    """Problems of the root group's links, the names it holds, and the contract datasets found as
    plain hard links. Never follows a link: soft and external links are named, not opened."""
    names: list[bytes] = []
    f.id.links.iterate(names.append)
    problems, found, unexpected = [], set(), []
    present = {raw.decode("utf-8", "backslashreplace") for raw in names}
    for raw in names:
        name = raw.decode("utf-8", "backslashreplace")
        info = f.id.links.get_info(raw)
        if info.type == h5l.TYPE_SOFT:
            problems.append(f"{_show(name)} is a soft link to {_show(f.id.links.get_val(raw))}; links are refused, "
                            "write the arrays into the file itself")
            continue
        if info.type == h5l.TYPE_EXTERNAL:
            target, path = f.id.links.get_val(raw)
            problems.append(f"{_show(name)} is an external link to {_show(target)}:{_show(path)}; links are refused, "
                            "write the arrays into the file itself")
            continue
        if info.type != h5l.TYPE_HARD:
            problems.append(f"{_show(name)} is a user-defined link (type {info.type}); links are refused")
            continue
        obj = h5o.get_info(f.id, raw)
        if name not in DATASETS:
            unexpected.append(name)
        elif obj.type != h5o.TYPE_DATASET:
            problems.append(f"{name!r} is {'a group' if obj.type == h5o.TYPE_GROUP else 'not a dataset'}, "
                            "expected a dataset")
        elif obj.rc != 1:
            problems.append(f"{name!r} is linked {obj.rc} times; each dataset must appear once")
        else:
            found.add(name)
    if unexpected:
        more = f" and {len(unexpected) - 3} more" if len(unexpected) > 3 else ""
        shown = ", ".join(_show(n) for n in unexpected[:3]) + more
        problems.append(f"unexpected root member(s) {shown}: only {', '.join(DATASETS)} may exist")
    return problems, present, found


def check_prediction_header(f: h5py.File, num_steps: int, sequence: str | None = None) -> list[str]:
    """Structural problems of an open prediction file for a sequence of `num_steps` pushes: the
    root's members and links, num_slots, each dataset's shape, dtype, storage, filters and chunk layout, and (given
    the `sequence` it is named for) the attributes stating what it predicts (`check_layout_attrs`). Reads no
    array data, so it is safe (and cheap) on any file."""
    links, present, found = _root_problems(f)
    has_3d = "mask" in present or "motion" in present
    problems = check_num_slots(f.attrs) if has_3d or "num_slots" in f.attrs else []
    if sequence is not None:
        problems += check_layout_attrs(f.attrs, sequence, has_3d)
    problems += links
    if ("mask" in present) != ("motion" in present):
        given, other = ("mask", "motion") if "mask" in present else ("motion", "mask")
        problems.append(f"{given!r} without {other!r}: mask and motion come together (write both, or neither "
                        "with motion_2d for a 2D-only prediction)")
    elif not has_3d and "motion_2d" not in present:
        problems.append("missing datasets: 'mask' and 'motion' (3D), or 'motion_2d' alone (2D-only)")
    specs = {"mask": ((num_steps,) + GRID_SHAPE, (np.dtype("uint8"),)),
             "motion": ((num_steps, 3) + GRID_SHAPE, MOTION_DTYPES),
             "motion_2d": ((num_steps,) + IMAGE_SHAPE + (3,), MOTION_DTYPES)}
    for name, (shape, dtypes) in specs.items():
        if name not in found:  # absent: reported above; present but not a plain dataset: by _root_problems
            continue
        dset = f[name]
        if dset.shape != shape:
            problems.append(f"{name}: shape {dset.shape}, expected {shape}")
        try:
            dtype = dset.dtype
        except (TypeError, ValueError):
            dtype = None
        if dtype is None or dtype not in dtypes:
            shown = "of an unsupported HDF5 type" if dtype is None else dtype
            problems.append(f"{name}: dtype {shown}, expected {' or '.join(map(str, dtypes))}")
        problems += _storage_problems(name, dset) + _chunk_problems(name, dset)
    return problems


def _load_meta(pred_dir: Path) -> tuple[dict | None, str | None]:
    """PRED_DIR/meta.json as a JSON object, or (None, its problem); (None, None) when there is none.
    Checked before reading: a regular file inside the directory, at most META_MAX_BYTES."""
    path = pred_dir / META_NAME
    if not os.path.lexists(path):
        return None, None
    problem = file_problem(path, pred_dir)
    if problem:
        return None, problem
    size = path.stat().st_size
    if size > META_MAX_BYTES:
        return None, f"{size} bytes, more than the {META_MAX_BYTES} allowed"
    try:
        with open(path, "rb") as fh:  # a regular file: opening cannot block
            raw = json.loads(fh.read(META_MAX_BYTES + 1).decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        return None, f"not valid JSON ({type(exc).__name__}: {' '.join(str(exc).split())[:200]})"
    if not isinstance(raw, dict):
        return None, f"must hold a JSON object, not {type(raw).__name__}"
    return raw, None


def read_meta(pred_dir: Path) -> tuple[dict, list[str]]:
    """PRED_DIR/meta.json's known keys and its problems ({} and [] when there is none). Checked
    before reading: a regular file inside the directory, at most META_MAX_BYTES."""
    raw, problem = _load_meta(pred_dir)
    if raw is None:
        return {}, [problem] if problem else []
    problems = []
    for key, (types, words) in META_TYPES.items():
        if key in raw:
            value = raw[key]
            if not isinstance(value, types) or isinstance(value, bool):
                problems.append(f"{key!r} must be {words}, got {type(value).__name__}")
            elif isinstance(value, float) and not math.isfinite(value):
                problems.append(f"{key!r} must be a finite number, got {value}")
    if not problems and "name" in raw and not raw["name"].strip():
        problems.append("'name' must not be empty")
    meta = {k: raw[k] for k in META_TYPES if k in raw}
    return ({}, problems) if problems else (meta, [])


def record_source(pred_dir: str | Path, data_dir: str | Path, split: str) -> Path:
    """Add the dataset directory (absolute) and the split that PRED_DIR's predictions were made from to its
    meta.json (created if absent), atomically; returns the file."""
    pred_dir = Path(pred_dir)
    raw, problem = _load_meta(pred_dir)
    if problem:
        raise UserError(f"{pred_dir / META_NAME}: {problem}; delete it and predict again")
    meta = dict(raw or {}, data=str(Path(data_dir).resolve()), split=split)
    return write_text(pred_dir / META_NAME, json.dumps(meta, indent=1) + "\n")


def meta_source(pred_dir: str | Path) -> tuple[Path, str | None]:
    """The dataset directory and split that PRED_DIR/meta.json names (`record_source`). UserError, naming what
    is missing and the fix (--data DIR), when it names no dataset directory or one that does not exist."""
    pred_dir = Path(pred_dir)
    path = pred_dir / META_NAME
    raw, problem = _load_meta(pred_dir)
    if raw is None:
        found = f"{path}: {problem}" if problem else f"{path} not found"
        raise UserError(f"{found}, so the dataset of these predictions is unknown; give it with --data DIR")
    data, split = raw.get("data"), raw.get("split")
    if not isinstance(data, str) or not data.strip():
        raise UserError(f"{path} names no dataset directory (its 'data', which `dsr-bench predict` writes); "
                        "give it with --data DIR")
    if not Path(data).is_dir():
        raise UserError(f"{path} names the dataset directory {_show(data)}, which does not exist; "
                        "give the dataset with --data DIR")
    if split is not None and (not isinstance(split, str) or not split.strip()):
        raise UserError(f"{path}: 'split' must be a split name, got {_show(json.dumps(split))}; "
                        "give the split with --split NAME")
    return Path(data), split


def infer_source(pred_dir: str | Path, data_dir: Path | None, split: str | None
                 ) -> tuple[Path, str | None, str | None]:
    """(data directory, split, note) for a command on PRED_DIR: `data_dir` and `split` as given, else inferred
    from PRED_DIR/meta.json (`meta_source`). The split is inferred only for the dataset that meta.json names
    (given or inferred); `note` says on one line what was inferred (None: nothing)."""
    pred_dir = Path(pred_dir)
    inferred = []
    if data_dir is None:
        data_dir, named_split = meta_source(pred_dir)
        inferred.append(f"data: {data_dir}")
    elif split is None:
        try:
            named_data, named_split = meta_source(pred_dir)
        except UserError:  # explicit --data: meta.json's problems are the evaluator's to report
            named_split = None
        else:
            named_split = named_split if named_data.resolve() == Path(data_dir).resolve() else None
    else:
        named_split = None
    if split is None and named_split is not None:
        split = named_split
        inferred.append(f"split: {split}")
    note = f"{', '.join(inferred)} (from {pred_dir / META_NAME})" if inferred else None
    return data_dir, split, note
