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
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from dsr_bench.constants import GRID_SHAPE, PUSH_HEIGHT, PUSH_LENGTH
from dsr_bench.errors import UserError

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


@dataclass(frozen=True)
class OfficialSequence:
    """One official sequence: its id and its step files in order."""

    seq_id: str
    files: tuple[Path, ...]

    @property
    def num_steps(self) -> int:
        return len(self.files)

    def read_step(self, step: int) -> dict[str, np.ndarray]:
        """The datasets of step file `step` (and `next/...` for the last step), validated."""
        path = self.files[step]
        out: dict[str, np.ndarray] = {}
        try:
            with h5py.File(path, "r") as f:
                for name, (shape, _) in OFFICIAL_STEP.items():
                    if name not in f:
                        raise UserError(f"{path}: missing dataset {name!r}; is this an official DSR step file?")
                    out[name] = f[name][()]
                    _check_shape(path, name, out[name].shape, shape)
                if step == self.num_steps - 1:
                    if "next" not in f:
                        raise UserError(f"{path}: the last step has no 'next' group (final observation)")
                    for name in OFFICIAL_NEXT:
                        if name not in f["next"]:
                            raise UserError(f"{path}: missing dataset 'next/{name}'")
                        out[f"next/{name}"] = f["next"][name][()]
                        _check_shape(path, f"next/{name}", out[f"next/{name}"].shape, OFFICIAL_STEP[name][0])
        except OSError as exc:
            raise UserError(f"{path}: unreadable HDF5 file ({exc})") from None
        return out


def _check_shape(path, name, got, expected) -> None:
    if len(got) != len(expected) or any(e is not None and g != e for g, e in zip(got, expected)):
        raise UserError(f"{path}: {name} has shape {tuple(got)}, expected {tuple('N' if e is None else e for e in expected)}")


def find_official_sequences(src: str | Path) -> dict[str, OfficialSequence]:
    """Every sequence of an official-layout directory, with contiguous steps 0..T-1 checked."""
    src = Path(src)
    if not src.is_dir():
        raise UserError(f"official data directory not found: {src}")
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
    """(schema arrays, official/ extras, attributes) of an official sequence, losslessly."""
    from dsr_bench import __version__
    from dsr_bench.constants import AXIS_ORDER, FLOW_COMPONENTS, GRID_BOUNDS, VOXEL_SIZE
    from dsr_bench.geometry import direction_vector, make_camera, pixel_to_world
    from dsr_bench.tsdf import integrate_tsdf

    T = seq.num_steps
    steps = [seq.read_step(t) for t in range(T)]
    last = steps[-1]

    def obs(name: str) -> np.ndarray:  # stack observation t = 0..T (the last from `next`)
        return np.stack([s[name] for s in steps] + [last[f"next/{name}"]])

    stacked = {name: np.stack([s[name] for s in steps]) for name in ("action", "tsdf", "scene_flow_3d")}
    extras: dict[str, np.ndarray] = {}
    arrays: dict[str, np.ndarray] = {}
    exact_fields: list[str] = []

    def place(schema_name: str, official_name: str, value: np.ndarray, dtype, source: np.ndarray) -> None:
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
    arrays["tsdf"] = np.concatenate([stacked["tsdf"].astype(np.float32), tsdf_last[None]])
    masks = obs("mask_3d")
    if masks.min() < 0 or masks.max() > 255:
        raise UserError(f"sequence {seq.seq_id}: mask_3d ids outside 0..255 cannot be stored as uint8")
    place("mask_3d", "mask_3d", masks, np.uint8, masks)
    flow = np.moveaxis(stacked["scene_flow_3d"], -1, 1)
    place("scene_flow_3d", "scene_flow_3d", flow, np.float32, stacked["scene_flow_3d"])
    arrays["action"] = stacked["action"].astype(np.int64)
    starts = np.concatenate([pixel_to_world(arrays["action"][:, 1:]), np.full((T, 1), PUSH_HEIGHT)], 1)
    arrays["push_start"] = starts
    arrays["push_end"] = starts + np.concatenate([direction_vector(arrays["action"][:, 0]) * PUSH_LENGTH,
                                                  np.zeros((T, 1))], 1)
    arrays["object_poses"] = np.concatenate([obs("positions"), obs("orientations")], -1).astype(np.float64)
    place("heightmap", "depth_heightmap", obs("depth_heightmap"), np.float32, obs("depth_heightmap"))
    # front camera 2D data
    place("cameras/front/color", "color_image_small", obs("color_image_small"), np.uint8, obs("color_image_small"))
    place("cameras/front/depth", "depth_image_small", obs("depth_image_small"), np.float32, obs("depth_image_small"))
    place("cameras/front/mask", "mask_2d", obs("mask_2d"), np.uint8, obs("mask_2d"))
    pts = np.stack([s["pts_small"] for s in steps])  # the final observation has no points in the release
    cam = make_camera("front", 240, 320)
    pts_last = cam.backproject(last["next/depth_image_small"].astype(np.float64))
    arrays["cameras/front/points"] = np.concatenate([np.moveaxis(pts, 1, -1), pts_last[None]]).astype(np.float32)
    extras["official/pts_small"] = pts
    flow2d = np.stack([s["scene_flow_2d"] for s in steps])
    place("cameras/front/scene_flow_2d", "scene_flow_2d", flow2d, np.float32, flow2d)
    # what has no home in the schema
    extras["official/color_image"] = obs("color_image")
    extras["official/depth_image"] = obs("depth_image")
    extras["official/color_heightmap"] = obs("color_heightmap")
    num_objects = arrays["object_poses"].shape[1]
    objects = [{"set": "official", "category": "unknown", "model_id": f"object_{i + 1}", "scale": 1.0,
                "mesh_sha256": "", "is_large": False} for i in range(num_objects)]
    attrs = {
        "sequence": sequence_name(seq.seq_id), "seed": -1, "num_steps": T, "num_objects": num_objects,
        "object_set": "official", "policy": "official", "generator_args": {"official_id": seq.seq_id},
        "toolkit_version": __version__, "source": "official-import", "grid_bounds": GRID_BOUNDS.tolist(),
        "grid_shape": list(GRID_SHAPE), "voxel_size": VOXEL_SIZE, "axis_order": AXIS_ORDER,
        "flow_components": FLOW_COMPONENTS, "objects": objects,
        "cameras": {"front": {"height": 240, "width": 320, "intrinsics": cam.intrinsics.tolist(),
                              "extrinsics": cam.extrinsics.tolist(), "convention": "opencv, camera-to-world"}},
        "official_id": seq.seq_id, "official_exact_fields": sorted(exact_fields),
        "official_notes": "tsdf[T] integrated from next/depth_image (960x1280) by dsr-bench; points[T] "
                          "back-projected from next/depth_image_small; push_start/end derived from the action",
    }
    return arrays, extras, attrs


def official_arrays(reader, step: int) -> dict[str, np.ndarray]:
    """The official datasets of step `step` rebuilt from an imported file (SequenceReader)."""
    exact = set(reader.attrs.get("official_exact_fields", []))
    T = reader.num_steps

    def get(official: str, schema: str, t: int, dtype, transform=None):
        if official in exact:
            value = reader.read(schema, t)
            value = transform(value) if transform else value
            return value.astype(dtype)
        return reader.read(f"official/{official}", t)

    out = {
        "action": reader.read("action", step),
        "tsdf": reader.read("tsdf", step),
        "mask_3d": get("mask_3d", "mask_3d", step, np.int64),
        "scene_flow_3d": get("scene_flow_3d", "scene_flow_3d", step, np.float64, lambda v: np.moveaxis(v, 0, -1)),
        "color_image": reader.read("official/color_image", step),
        "depth_image": reader.read("official/depth_image", step),
        "color_image_small": get("color_image_small", "cameras/front/color", step, np.uint8),
        "depth_image_small": get("depth_image_small", "cameras/front/depth", step, np.float32),
        "mask_2d": get("mask_2d", "cameras/front/mask", step, np.float64),
        "scene_flow_2d": get("scene_flow_2d", "cameras/front/scene_flow_2d", step, np.float64),
        "pts_small": reader.read("official/pts_small", step),
        "color_heightmap": reader.read("official/color_heightmap", step),
        "depth_heightmap": get("depth_heightmap", "heightmap", step, np.float64),
        "positions": reader.read("object_poses", step)[:, :3],
        "orientations": reader.read("object_poses", step)[:, 3:],
    }
    if step == T - 1:
        for name in OFFICIAL_NEXT:
            schema_source = {"mask_3d": ("mask_3d", "mask_3d", np.int64), "mask_2d": ("mask_2d", "cameras/front/mask", np.float64),
                             "color_image_small": ("color_image_small", "cameras/front/color", np.uint8),
                             "depth_image_small": ("depth_image_small", "cameras/front/depth", np.float32),
                             "depth_heightmap": ("depth_heightmap", "heightmap", np.float64)}.get(name)
            if name in ("positions", "orientations"):
                pose = reader.read("object_poses", T)
                out[f"next/{name}"] = pose[:, :3] if name == "positions" else pose[:, 3:]
            elif schema_source:
                out[f"next/{name}"] = get(schema_source[0], schema_source[1], T, schema_source[2])
            else:
                out[f"next/{name}"] = reader.read(f"official/{name}", T)
    return out


def import_official(src: str | Path, dst: str | Path) -> list[str]:
    """Convert every sequence of an official directory into a dataset directory; return our names."""
    import os

    from dsr_bench.manifest import build_manifest, content_digest, write_manifest
    from dsr_bench.sequence import write_sequence

    sequences = find_official_sequences(src)
    dst = Path(dst)
    dst.mkdir(parents=True, exist_ok=True)
    names = []
    for seq in sequences.values():
        arrays, extras, attrs = convert_sequence(seq)
        attrs["content_sha256"] = content_digest({**arrays, **extras}, attrs["objects"])
        write_sequence(dst / f"{attrs['sequence']}.h5", arrays, attrs, extras=extras)
        names.append(attrs["sequence"])
    (dst / "splits").mkdir(exist_ok=True)
    for split in ("train", "test"):
        if (Path(src) / f"{split}.txt").is_file():
            ids = read_official_split(src, split)
            unknown = [i for i in ids if i not in sequences]
            if unknown:
                raise UserError(f"{src}/{split}.txt lists sequences with no files (e.g. {unknown[0]})")
            target = dst / "splits" / f"{split}.txt"
            tmp = target.with_name(f".{target.name}.tmp-{os.getpid()}")
            tmp.write_text("".join(f"{sequence_name(i)}\n" for i in ids))
            os.replace(tmp, target)
    write_manifest(dst, build_manifest(dst))
    return names
