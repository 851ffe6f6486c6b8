"""The official DSR release layout: a validated reader and a lossless importer into our format.

Official layout: SRC/<seq>_<step>.hdf5 for steps 0..T-1 (T = 10) and SRC/train.txt, SRC/test.txt
listing sequence ids. Step t holds the observation at t and push t; the last step's `next` group
holds the final observation (without a TSDF). See docs/format.md for the field mapping.

Import is lossless: each official dataset either converts exactly into a schema field (checked
value by value) or is kept unchanged under `official/<name>` (stacked over steps) in the new file;
`official_arrays()` rebuilds the official arrays of any step from an imported file.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from dsr_bench.atomic import clean_temporaries, write_text
from dsr_bench.constants import GRID_SHAPE, PUSH_HEIGHT, PUSH_LENGTH
from dsr_bench.dataset.manifest import build_manifest, write_manifest
from dsr_bench.dataset.schema import sequence_header
from dsr_bench.dataset.sequence import write_sequence
from dsr_bench.errors import UserError
from dsr_bench.geometry import direction_vector, make_camera, pixel_to_world
from dsr_bench.geometry.tsdf import integrate_tsdf

#: name -> (shape, dtype) of each per-step dataset of the official release.
OFFICIAL_STEP = {
    "action": ((3,), "int64"),
    "tsdf": (GRID_SHAPE, "float32"),
    "mask_3d": (GRID_SHAPE, "int64"),
    "scene_flow_3d": (GRID_SHAPE + (3,), "float64"),
    "color_image": ((960, 1280, 3), "uint8"),
    "depth_image": ((960, 1280), "float32"),
    "color_image_small": ((240, 320, 3), "uint8"),
    "depth_image_small": ((240, 320), "float32"),
    "mask_2d": ((240, 320), "float64"),
    "scene_flow_2d": ((240, 320, 3), "float64"),
    "pts_small": ((3, 240, 320), "float64"),
    "color_heightmap": ((128, 128, 3), "uint8"),
    "depth_heightmap": ((128, 128), "float64"),
    "positions": ((None, 3), "float64"),
    "orientations": ((None, 4), "float64"),
}
#: Datasets of the final observation in the last step's `next` group.
OFFICIAL_NEXT = ("color_image", "depth_image", "color_image_small", "depth_image_small", "color_heightmap",
                 "depth_heightmap", "mask_3d", "mask_2d", "positions", "orientations")
_STEP_FILE = re.compile(r"^(?P<seq>.+)_(?P<step>\d+)\.hdf5$")


def _dtype_ok(dtype: np.dtype, expected: str) -> bool:
    """Loose dtype check: integer data must be integers, float data numbers, images bytes."""
    kind = np.dtype(dtype).kind
    if expected == "uint8":
        return np.dtype(dtype) == np.uint8
    if expected.startswith("int"):
        return kind in "iu"
    return kind in "fiu"


def _check_shape(path, name: str, got: tuple[int, ...], expected: tuple) -> None:
    if len(got) != len(expected) or any(e is not None and g != e for g, e in zip(got, expected)):
        raise UserError(f"{path}: {name} has shape {tuple(got)}, expected "
                        f"{tuple('N' if e is None else e for e in expected)}; is this an official DSR step file?")


def check_dataset(path: Path, name: str, ds: h5py.Dataset) -> None:
    """UserError naming the file unless an official dataset (`name` or `next/name`) has the published
    shape and dtype."""
    base = name.rsplit("/", 1)[-1]
    shape, dtype = OFFICIAL_STEP[base]
    _check_shape(path, name, ds.shape, shape)
    if not _dtype_ok(ds.dtype, dtype):
        raise UserError(f"{path}: {name} has dtype {ds.dtype}, expected {dtype}; is this an official DSR step file?")


@dataclass(frozen=True)
class OfficialSequence:
    """One official sequence: its id and its step files `<id>_<step>.hdf5` in step order.

    Files are opened per call (nothing stays open); every dataset read is checked against the
    published shapes and dtypes, with a one-line UserError naming the file and the dataset.
    """

    seq_id: str
    files: tuple[Path, ...]

    @property
    def num_steps(self) -> int:
        return len(self.files)

    def read(self, step: int, name: str) -> np.ndarray:
        """One dataset of step file `step` (`next/<name>` for the final observation of the last step)."""
        if not 0 <= step < self.num_steps:
            raise UserError(f"sequence {self.seq_id}: step {step} outside 0..{self.num_steps - 1}")
        path = self.files[step]
        try:
            with h5py.File(path, "r") as f:
                if name not in f:
                    raise UserError(f"{path}: missing dataset {name!r}; is this an official DSR step file?")
                check_dataset(path, name, f[name])
                return f[name][()]
        except OSError as exc:
            raise UserError(f"{path}: unreadable HDF5 file ({exc})") from None

    def read_step(self, step: int) -> dict[str, np.ndarray]:
        """Every dataset of step file `step` (and `next/...` for the last step), validated."""
        path = self.files[step]
        out: dict[str, np.ndarray] = {}
        try:
            with h5py.File(path, "r") as f:
                for name in OFFICIAL_STEP:
                    if name not in f:
                        raise UserError(f"{path}: missing dataset {name!r}; is this an official DSR step file?")
                    check_dataset(path, name, f[name])
                    out[name] = f[name][()]
                if step == self.num_steps - 1:
                    if "next" not in f:
                        raise UserError(f"{path}: the last step has no 'next' group (final observation)")
                    for name in OFFICIAL_NEXT:
                        if name not in f["next"]:
                            raise UserError(f"{path}: missing dataset 'next/{name}'")
                        check_dataset(path, f"next/{name}", f["next"][name])
                        out[f"next/{name}"] = f["next"][name][()]
        except OSError as exc:
            raise UserError(f"{path}: unreadable HDF5 file ({exc})") from None
        n = len(out["positions"])
        if len(out["orientations"]) != n or ("next/positions" in out and (
                len(out["next/positions"]) != n or len(out["next/orientations"]) != n)):
            raise UserError(f"{path}: positions and orientations list different numbers of objects")
        return out


def find_official_sequences(src: str | Path) -> dict[str, OfficialSequence]:
    """Every sequence of an official-layout directory, with contiguous steps 0..T-1 checked."""
    src = Path(src)
    if not src.is_dir():
        raise UserError(f"official data directory not found: {src}; give the data folder of the authors' release "
                        "(https://github.com/columbia-ai-robotics/dsr: its README's data download), e.g. its test/")
    steps: dict[str, dict[int, Path]] = {}
    for path in src.glob("*.hdf5"):
        m = _STEP_FILE.match(path.name)
        if m:
            steps.setdefault(m["seq"], {})[int(m["step"])] = path
    if not steps:
        raise UserError(f"{src}: no <seq>_<step>.hdf5 files; is this the official release's data directory?")
    out = {}
    for seq_id, files in sorted(steps.items()):
        expected = list(range(max(files) + 1))
        missing = [s for s in expected if s not in files]
        if missing:
            raise UserError(f"{src}: sequence {seq_id} lacks step files {missing} (have {sorted(files)})")
        last = files[expected[-1]]
        try:
            with h5py.File(last, "r") as f:
                has_next = "next" in f
        except OSError as exc:
            raise UserError(f"{last}: unreadable HDF5 file ({exc})") from None
        if not has_next:
            raise UserError(f"{last}: the last step file of sequence {seq_id} has no 'next' group (final observation); "
                            f"step files after {expected[-1]} are missing or this one is damaged")
        out[seq_id] = OfficialSequence(seq_id, tuple(files[s] for s in expected))
    return out


def read_official_split(src: str | Path, split: str) -> list[str]:
    """Sequence ids listed in SRC/<split>.txt (train / test)."""
    path = Path(src) / f"{split}.txt"
    if not path.is_file():
        raise UserError(f"{path} not found; the official release lists its splits in train.txt and test.txt")
    return [line.strip() for line in path.read_text().splitlines() if line.strip()]


def _exact(array: np.ndarray, dtype) -> np.ndarray | None:
    """`array` cast to dtype if every value survives the round trip, else None."""
    cast = array.astype(dtype)
    same = np.array_equal(cast.astype(array.dtype), array, equal_nan=True)
    return cast if same else None


def sequence_name(seq_id: str) -> str:
    """Our sequence name for an official id: seq_0042 for '42', else seq_<id>."""
    return f"seq_{int(seq_id):04d}" if seq_id.isdigit() else f"seq_{seq_id}"


def convert_sequence(seq: OfficialSequence) -> tuple[dict, dict, dict]:
    """(schema arrays, official/ extras, attributes) of an official sequence, losslessly.

    Raises UserError where the release's data cannot be held exactly where it must be: mask ids
    outside 0..255, or 3D flow values that float32 cannot represent (the release's flow is
    integer-valued voxels).
    """
    T = seq.num_steps
    steps = [seq.read_step(t) for t in range(T)]
    last = steps[-1]
    counts = {len(s["positions"]) for s in steps} | {len(last["next/positions"])}
    if len(counts) != 1:
        raise UserError(f"sequence {seq.seq_id}: the number of objects changes between steps ({sorted(counts)})")
    dtypes = {name: str(value.dtype) for name, value in last.items()}

    def obs(name: str) -> np.ndarray:  # stack observation t = 0..T (the last from `next`)
        return np.stack([s[name] for s in steps] + [last[f"next/{name}"]])

    def per_step(name: str) -> np.ndarray:  # stack push t = 0..T-1
        return np.stack([s[name] for s in steps])

    extras: dict[str, np.ndarray] = {}
    arrays: dict[str, np.ndarray] = {}
    exact_fields: list[str] = []

    def place(schema_name: str, official_name: str, value: np.ndarray, dtype, source: np.ndarray) -> None:
        """Store `value` as `dtype`; if that loses anything, keep the official `source` too."""
        converted = _exact(value, dtype)
        if converted is None:
            arrays[schema_name] = value.astype(dtype)
            extras[f"official/{official_name}"] = source
        else:
            arrays[schema_name] = converted
            exact_fields.append(official_name)

    # volumes
    cam_hr = make_camera("front", 960, 1280)
    tsdf_last = integrate_tsdf(last["next/depth_image"].astype(np.float64), cam_hr)
    tsdf = per_step("tsdf")
    tsdf32 = _exact(tsdf, np.float32)
    if tsdf32 is None:
        extras["official/tsdf"], tsdf32 = tsdf, tsdf.astype(np.float32)
    else:
        exact_fields.append("tsdf")
    arrays["tsdf"] = np.concatenate([tsdf32, tsdf_last[None]])
    masks = obs("mask_3d")
    if masks.min() < 0 or masks.max() > 255:
        raise UserError(f"sequence {seq.seq_id}: mask_3d ids in {int(masks.min())}..{int(masks.max())}; only "
                        "0..255 fit our uint8 mask_3d, so it cannot be imported")
    place("mask_3d", "mask_3d", masks, np.uint8, masks)
    flow = np.moveaxis(per_step("scene_flow_3d"), -1, 1)
    flow32 = _exact(flow, np.float32)
    if flow32 is None:
        bad = flow[flow.astype(np.float32).astype(flow.dtype) != flow]
        raise UserError(f"sequence {seq.seq_id}: scene_flow_3d holds values float32 cannot represent exactly "
                        f"(e.g. {bad.flat[0]!r}); the release's flow is integer-valued voxels, so these files are "
                        "not official DSR data")
    arrays["scene_flow_3d"] = flow32
    exact_fields.append("scene_flow_3d")
    actions = per_step("action")
    place("action", "action", actions, np.int64, actions)
    starts = np.concatenate([pixel_to_world(arrays["action"][:, 1:]), np.full((T, 1), PUSH_HEIGHT)], 1)
    arrays["push_start"] = starts
    arrays["push_end"] = starts + np.concatenate([direction_vector(arrays["action"][:, 0]) * PUSH_LENGTH,
                                                  np.zeros((T, 1))], 1)
    for name in ("positions", "orientations"):
        value = obs(name)
        if _exact(value, np.float64) is None:
            extras[f"official/{name}"] = value
    arrays["object_poses"] = np.concatenate([obs("positions"), obs("orientations")], -1).astype(np.float64)
    place("heightmap", "depth_heightmap", obs("depth_heightmap"), np.float32, obs("depth_heightmap"))
    # front camera 2D data
    place("cameras/front/color", "color_image_small", obs("color_image_small"), np.uint8, obs("color_image_small"))
    place("cameras/front/depth", "depth_image_small", obs("depth_image_small"), np.float32, obs("depth_image_small"))
    place("cameras/front/mask", "mask_2d", obs("mask_2d"), np.uint8, obs("mask_2d"))
    pts = per_step("pts_small")  # the final observation has no points in the release
    cam = make_camera("front", 240, 320)
    pts_last = cam.backproject(last["next/depth_image_small"].astype(np.float64))
    arrays["cameras/front/points"] = np.concatenate([np.moveaxis(pts, 1, -1), pts_last[None]]).astype(np.float32)
    extras["official/pts_small"] = pts
    flow2d = per_step("scene_flow_2d")
    place("cameras/front/scene_flow_2d", "scene_flow_2d", flow2d, np.float32, flow2d)
    # what has no home in the schema
    extras["official/color_image"] = obs("color_image")
    extras["official/depth_image"] = obs("depth_image")
    extras["official/color_heightmap"] = obs("color_heightmap")
    num_objects = arrays["object_poses"].shape[1]
    objects = [{"set": "official", "category": "unknown", "model_id": f"object_{i + 1}", "scale": 1.0,
                "mesh_sha256": "", "is_large": False} for i in range(num_objects)]
    attrs = sequence_header(
        sequence=sequence_name(seq.seq_id), seed=-1, num_steps=T, num_objects=num_objects, object_set="official",
        policy="official", generator_args={"official_id": seq.seq_id}, source="official-import", objects=objects,
        cameras={"front": cam},
        official_id=seq.seq_id, official_exact_fields=sorted(set(exact_fields)), official_dtypes=dtypes,
        official_files=[p.name for p in seq.files],
        official_notes="tsdf[T] integrated from next/depth_image (960x1280) by dsr-bench; points[T] "
                       "back-projected from next/depth_image_small; push_start/end derived from the action",
    )
    return arrays, extras, attrs


#: official name -> (our dataset, how to turn ours back into the official layout)
_SCHEMA_HOME = {
    "tsdf": ("tsdf", None),
    "mask_3d": ("mask_3d", None),
    "scene_flow_3d": ("scene_flow_3d", lambda v: np.moveaxis(v, 0, -1)),
    "action": ("action", None),
    "color_image_small": ("cameras/front/color", None),
    "depth_image_small": ("cameras/front/depth", None),
    "mask_2d": ("cameras/front/mask", None),
    "scene_flow_2d": ("cameras/front/scene_flow_2d", None),
    "depth_heightmap": ("heightmap", None),
}


def official_arrays(reader, step: int) -> dict[str, np.ndarray]:
    """The official datasets of step file `step` (with `next/...` for the last), rebuilt bit for bit
    from an imported file (a `dsr_bench.dataset.sequence.SequenceReader`), in the release's dtypes."""
    if reader.attrs.get("source") != "official-import":
        raise UserError(f"{reader.path}: not imported from the official release "
                        f"(source {reader.attrs.get('source')!r})")
    exact = set(reader.attrs.get("official_exact_fields", []))
    dtypes = reader.attrs.get("official_dtypes", {})
    T = reader.num_steps

    def get(name: str, t: int) -> np.ndarray:
        key = f"next/{name}" if t == T else name
        dtype = np.dtype(dtypes.get(key, OFFICIAL_STEP[name][1]))
        if name in ("positions", "orientations"):
            if f"official/{name}" in reader:
                return reader.read(f"official/{name}", t)
            pose = reader.read("object_poses", t)
            return (pose[:, :3] if name == "positions" else pose[:, 3:]).astype(dtype)
        if name in exact and name in _SCHEMA_HOME:
            ours, back = _SCHEMA_HOME[name]
            value = reader.read(ours, t)
            return (back(value) if back else value).astype(dtype)
        return reader.read(f"official/{name}", t)

    out = {name: get(name, step) for name in OFFICIAL_STEP}
    if step == T - 1:
        out.update({f"next/{name}": get(name, T) for name in OFFICIAL_NEXT})
    return out


def _import_one(args: tuple[OfficialSequence, str]) -> str:
    seq, dst = args
    arrays, extras, attrs = convert_sequence(seq)
    write_sequence(Path(dst) / f"{attrs['sequence']}.h5", arrays, attrs, extras=extras)
    return attrs["sequence"]


def _already_imported(path: Path, seq_id: str) -> bool | None:
    """True if `path` is a complete import of official `seq_id`, False if it is another import, None
    if it is not an import at all."""
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("source") != "official-import":
                return None
            return f.attrs.get("official_id") == seq_id and "content_sha256" in f.attrs
    except OSError:
        return False


def import_official(src: str | Path, dst: str | Path, split: str | None = None, workers: int = 1,
                    progress: Callable[[str], None] | None = None) -> list[str]:
    """Convert an official-layout directory (all sequences, or those of SRC/<split>.txt) into a
    dsr-bench dataset directory with splits/ and manifest.json; return our sequence names.

    Resumable: files in DST that are complete imports of the same sequences are kept; a DST that
    holds files of another origin is refused. `progress(name)` is called after each sequence.
    """
    if workers < 1:
        raise UserError(f"--workers {workers}: must be at least 1")
    sequences = find_official_sequences(src)
    split_files = [split] if split is not None else [s for s in ("train", "test") if (Path(src) / f"{s}.txt").is_file()]
    lists = {}
    for name in split_files:
        ids = read_official_split(src, name)
        unknown = [i for i in ids if i not in sequences]
        if unknown:
            raise UserError(f"{src}/{name}.txt lists {len(unknown)} sequences with no step files (e.g. {unknown[0]}); "
                            "copy them in or remove them from the list")
        lists[name] = ids
    chosen = lists[split] if split is not None else list(sequences)
    names = {sequence_name(i): i for i in chosen}
    if len(names) != len(chosen):
        raise UserError(f"{src}: sequence ids {sorted(chosen)[:5]}... map to the same name (e.g. '7' and '007')")
    dst = Path(dst)
    if dst.exists():
        for path in sorted(dst.glob("seq_*.h5")):
            status = _already_imported(path, names.get(path.stem, ""))
            if status is None or (status is False and path.stem in names):
                raise UserError(f"{dst} already holds {path.name}, which is not an import of this release's "
                                f"sequence {names.get(path.stem, path.stem)}; choose an empty DST directory")
        clean_temporaries(dst, "seq_*.h5")  # an interrupted run's partial files (never a live writer's)
        if (dst / "splits").is_dir():
            clean_temporaries(dst / "splits", "*.txt")
    todo = [sequences[i] for name, i in names.items() if not (dst / f"{name}.h5").is_file()]
    dst.mkdir(parents=True, exist_ok=True)
    jobs = [(seq, str(dst)) for seq in todo]
    if workers > 1 and len(jobs) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=mp.get_context("spawn")) as pool:
            for name in pool.map(_import_one, jobs):
                if progress:
                    progress(name)
    else:
        for job in jobs:
            name = _import_one(job)
            if progress:
                progress(name)
    (dst / "splits").mkdir(exist_ok=True)
    for name, ids in lists.items():
        write_text(dst / "splits" / f"{name}.txt", "".join(f"{sequence_name(i)}\n" for i in ids))
    write_manifest(dst, build_manifest(dst))
    return sorted(names)
