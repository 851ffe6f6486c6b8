"""Dataset directories: content digests, manifest.json, split files and checksums.

A dataset directory holds `seq_*.h5` sequence files, `splits/<split>.txt` (one sequence name per
line) and `manifest.json`. The content digest of a sequence covers its arrays and object list,
independent of HDF5 byte layout; a split's checksum covers its sorted (name, content digest) pairs
and is what the benchmark pins and the leaderboard checks.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from dsr_bench.constants import SCHEMA_VERSION
from dsr_bench.errors import UserError

MANIFEST_NAME = "manifest.json"
DATASET_FORMAT = "dsr-bench-dataset"


def content_digest(arrays: Mapping[str, np.ndarray], objects: list[dict]) -> str:
    """SHA-256 over the sorted dataset names, dtypes, shapes and little-endian C-order bytes, and the
    canonical JSON of the object list."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.asarray(arrays[name])
        a = np.ascontiguousarray(a.astype(a.dtype.newbyteorder("<"), copy=False))
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    h.update(json.dumps(objects, sort_keys=True).encode())
    return h.hexdigest()


def sequence_content_digest(path: str | Path) -> str:
    """Recompute a sequence file's content digest from its arrays (everything but `meshes/`)."""
    from dsr_bench.sequence import SequenceReader

    arrays: dict[str, np.ndarray] = {}
    with SequenceReader(path) as seq:
        def visit(name, obj):
            import h5py

            if isinstance(obj, h5py.Dataset) and not name.startswith("meshes/"):
                arrays[name] = obj[()]

        seq._file.visititems(visit)
        return content_digest(arrays, seq.objects)


def file_sha256(path: str | Path, chunk: int = 1 << 22) -> str:
    """SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def _split_names(data_dir: Path) -> dict[str, list[str]]:
    out = {}
    for path in sorted((data_dir / "splits").glob("*.txt")):
        out[path.stem] = [line.strip() for line in path.read_text().splitlines() if line.strip()]
    return out


def split_digest(manifest: Mapping, split: str) -> str:
    """The split checksum: SHA-256 over the split's sorted (name, content digest) pairs."""
    splits = manifest.get("splits", {})
    if split not in splits:
        raise UserError(f"split {split!r} is not in the manifest; available: {', '.join(sorted(splits)) or 'none'}")
    digests = {s["name"]: s["content_sha256"] for s in manifest["sequences"]}
    h = hashlib.sha256()
    for name in sorted(splits[split]["names"]):
        h.update(f"{name}:{digests[name]}\n".encode())
    return h.hexdigest()


def build_manifest(data_dir: str | Path) -> dict:
    """A manifest of the sequence files and split files present in `data_dir`."""
    import h5py

    from dsr_bench import __version__

    data_dir = Path(data_dir)
    sequences = []
    for path in sorted(data_dir.glob("seq_*.h5")):
        try:
            with h5py.File(path, "r") as f:
                attrs = dict(f.attrs)
        except OSError as exc:
            raise UserError(f"{path}: unreadable sequence file ({exc}); delete it and rerun the generator") from None
        if "content_sha256" not in attrs:
            raise UserError(f"{path}: no content digest attribute; regenerate it or run `dsr-bench import-official`")
        sequences.append({
            "name": path.stem, "file": path.name, "sha256": file_sha256(path),
            "content_sha256": str(attrs["content_sha256"]), "num_steps": int(attrs["num_steps"]),
            "num_objects": int(attrs["num_objects"]), "object_set": str(attrs.get("object_set", "")),
            "objects": json.loads(attrs["objects"]) if isinstance(attrs.get("objects"), str) else [],
        })
    known = {s["name"] for s in sequences}
    splits = {}
    for split, names in _split_names(data_dir).items():
        missing = [n for n in names if n not in known]
        if missing:
            raise UserError(f"splits/{split}.txt names {len(missing)} sequences with no file (e.g. {missing[0]}); "
                            "finish generating them or fix the split file")
        splits[split] = {"file": f"splits/{split}.txt", "sequences": len(names), "names": names}
    manifest = {"format": DATASET_FORMAT, "schema_version": SCHEMA_VERSION, "toolkit_version": __version__,
                "sequences": sequences, "splits": splits}
    for split in splits:
        splits[split]["content_sha256"] = split_digest(manifest, split)
    return manifest


def write_manifest(data_dir: str | Path, manifest: Mapping) -> Path:
    """Write manifest.json atomically."""
    path = Path(data_dir) / MANIFEST_NAME
    tmp = path.with_name(f".{MANIFEST_NAME}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, path)
    return path


def load_manifest(data_dir: str | Path) -> dict:
    """Read and check a dataset's manifest."""
    data_dir = Path(data_dir)
    path = data_dir / MANIFEST_NAME
    if not data_dir.is_dir():
        raise UserError(f"dataset directory not found: {data_dir}")
    if not path.is_file():
        raise UserError(f"{data_dir} has no {MANIFEST_NAME}; build it with `dsr-bench manifest {data_dir}`")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: unreadable manifest ({exc}); rebuild it with `dsr-bench manifest {data_dir}`") from None
    if not isinstance(manifest, dict) or manifest.get("format") != DATASET_FORMAT or "sequences" not in manifest:
        raise UserError(f"{path}: not a dsr-bench manifest; rebuild it with `dsr-bench manifest {data_dir}`")
    if manifest.get("schema_version") != SCHEMA_VERSION:
        raise UserError(f"{path}: schema version {manifest.get('schema_version')}, this toolkit reads {SCHEMA_VERSION}")
    return manifest


def read_split(data_dir: str | Path, split: str | None) -> tuple[str, list[str]]:
    """(split name, sequence names) of a dataset; `None` picks the only split, if there is one."""
    data_dir = Path(data_dir)
    splits = _split_names(data_dir)
    if split is None:
        if len(splits) != 1:
            raise UserError(f"{data_dir} has splits {', '.join(sorted(splits)) or 'none'}; choose one with --split")
        split = next(iter(splits))
    if split not in splits:
        raise UserError(f"split {split!r} not found in {data_dir}/splits; available: {', '.join(sorted(splits)) or 'none'}")
    return split, splits[split]


def resolve_sequence(data_dir: str | Path | None, name: str) -> Path:
    """A sequence file from a name within a dataset (`seq_0042`) or a path to a file."""
    candidate = Path(name)
    if candidate.suffix == ".h5" and candidate.is_file():
        return candidate
    if data_dir is not None:
        path = Path(data_dir) / f"{candidate.stem}.h5"
        if path.is_file():
            return path
        raise UserError(f"no sequence {name!r} in {data_dir} (expected {path})")
    raise UserError(f"sequence {name!r} not found: give a path to a .h5 file or --data DIR with a sequence name")
