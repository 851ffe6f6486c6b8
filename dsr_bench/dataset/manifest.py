"""Dataset directories: content digests, manifest.json, split files and checksums.

A dataset directory holds `seq_*.h5` sequence files, `splits/<split>.txt` (one sequence name per
line) and `manifest.json`. Each sequence's digests (`dsr_bench.dataset.digests`: its ground truth, its
observations, both) are independent of HDF5 byte layout; a split's checksum covers its sorted
(name, ground-truth digest) pairs and is what the benchmark pins and the leaderboard checks.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from dsr_bench import __version__
from dsr_bench.atomic import write_text
from dsr_bench.constants import READABLE_SCHEMA_VERSIONS, SCHEMA_VERSION
from dsr_bench.dataset.digests import GROUND_TRUTH_KEY, OBSERVATIONS_KEY, split_checksum
from dsr_bench.dataset.splits import SPLITS
from dsr_bench.errors import UserError

MANIFEST_NAME = "manifest.json"
DATASET_FORMAT = "dsr-bench-dataset"


def mesh_sha256(vertices: np.ndarray, faces: np.ndarray) -> str:
    """SHA-256 of a mesh: its vertices as float64, then its faces as int64, little-endian (stored in every
    object identity as `mesh_sha256`)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(faces, dtype="<i8").tobytes())
    return h.hexdigest()


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
    """The split checksum: SHA-256 over `name:ground_truth_sha256\\n` of the split's sequences, sorted by
    name (`dsr_bench.dataset.digests.split_checksum`): what scores a model, not how it was rendered."""
    splits = manifest.get("splits", {})
    if split not in splits:
        raise UserError(f"split {split!r} is not in the manifest; available: {', '.join(sorted(splits)) or 'none'}")
    digests = {s["name"]: s[GROUND_TRUTH_KEY] for s in manifest["sequences"]}
    missing = [n for n in splits[split]["names"] if n not in digests]
    if missing:
        raise UserError(f"manifest split {split!r} names {missing[0]}, which the manifest does not list; "
                        "rebuild it with `dsr-bench manifest DIR`")
    return split_checksum((name, digests[name]) for name in splits[split]["names"])


def _json_attr(value, default):
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, str):
        try:
            return json.loads(value)
        except json.JSONDecodeError:
            return value
    return default if value is None else value


def _sequence_entry(path: Path) -> dict:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            attrs = dict(f.attrs)
    except OSError as exc:
        raise UserError(f"{path}: unreadable sequence file ({exc}); delete it and regenerate or re-import it") from None
    for key in ("content_sha256", GROUND_TRUTH_KEY, OBSERVATIONS_KEY, "num_steps", "num_objects"):
        if key not in attrs:
            raise UserError(f"{path}: no {key!r} attribute (not a complete dsr-bench sequence); regenerate it or "
                            "run `dsr-bench import-official`")
    args = _json_attr(attrs.get("generator_args"), {})
    objects = _json_attr(attrs.get("objects"), [])
    return {
        "name": path.stem, "file": path.name, "sha256": file_sha256(path),
        "content_sha256": str(attrs["content_sha256"]), GROUND_TRUTH_KEY: str(attrs[GROUND_TRUTH_KEY]),
        OBSERVATIONS_KEY: str(attrs[OBSERVATIONS_KEY]), "num_steps": int(attrs["num_steps"]),
        "num_objects": int(attrs["num_objects"]), "object_set": str(attrs.get("object_set", "")),
        "objects": objects if isinstance(objects, list) else [], "source": str(attrs.get("source", "")),
        "policy": str(attrs.get("policy", "")), "toolkit_version": str(attrs.get("toolkit_version", "")),
        "generator_args": args if isinstance(args, dict) else {},
    }


def build_manifest(data_dir: str | Path) -> dict:
    """A manifest of the `seq_*.h5` files and `splits/*.txt` present in `data_dir`.

    Reads each file's root attributes (not its arrays) and hashes its bytes. Raises UserError for an
    unreadable file or a split naming a sequence with no file.
    """
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise missing_dataset(data_dir)
    sequences = [_sequence_entry(path) for path in sorted(data_dir.glob("seq_*.h5"))]
    known = {s["name"] for s in sequences}
    splits = {}
    for split, names in _split_names(data_dir).items():
        missing = [n for n in names if n not in known]
        if missing:
            raise UserError(f"splits/{split}.txt names {len(missing)} sequences with no file (e.g. {missing[0]}); "
                            "finish generating them or fix the split file")
        repeated = sorted({n for n in names if names.count(n) > 1})
        if repeated:
            raise UserError(f"splits/{split}.txt lists {repeated[0]} more than once; remove the duplicate line")
        splits[split] = {"file": f"splits/{split}.txt", "sequences": len(names), "names": names}
    manifest = {"format": DATASET_FORMAT, "schema_version": SCHEMA_VERSION, "toolkit_version": __version__,
                "sequences": sequences, "splits": splits}
    for split in splits:
        splits[split]["content_sha256"] = split_digest(manifest, split)
    return manifest


def write_manifest(data_dir: str | Path, manifest: Mapping) -> Path:
    """Write DATA_DIR/manifest.json atomically (`dsr_bench.atomic`: temporary name in the same directory, then
    rename)."""
    return write_text(Path(data_dir) / MANIFEST_NAME, json.dumps(manifest, indent=1, sort_keys=True) + "\n")


#: Keys of a manifest entry that older manifests lack and `completed_entry` reads from the file's root attributes.
FILE_ATTR_KEYS = ("source", "policy", "toolkit_version", "generator_args")


def completed_entry(data_dir: str | Path, entry: Mapping) -> dict:
    """A manifest entry, completed from its file's root attributes (`FILE_ATTR_KEYS`) where an older manifest
    lacks a key; the entry unchanged when it has them all or its file is missing or unreadable."""
    import h5py

    data_dir = Path(data_dir)
    if all(k in entry for k in FILE_ATTR_KEYS) or not (data_dir / entry["file"]).is_file():
        return dict(entry)
    try:
        with h5py.File(data_dir / entry["file"], "r") as f:
            attrs = {k: f.attrs[k] for k in FILE_ATTR_KEYS if k in f.attrs}
    except OSError:
        return dict(entry)
    if isinstance(attrs.get("generator_args"), str):
        attrs["generator_args"] = json.loads(attrs["generator_args"])
    merged = dict(entry)
    for key, value in attrs.items():
        merged.setdefault(key, value if key == "generator_args" else str(value))
    return merged


def common_generator_args(entries: Sequence[Mapping]) -> tuple[dict, list[str]]:
    """The generator arguments shared by every entry (with the same value), and the sorted names of those that
    vary or are missing from some."""
    args = [e.get("generator_args") or {} for e in entries]
    keys = sorted({k for a in args for k in a})
    common = {k: args[0].get(k) for k in keys if all(k in a and a[k] == args[0].get(k) for a in args)}
    return common, [k for k in keys if k not in common]


_SEQUENCE_KEYS = {"name": str, "file": str, "sha256": str, "content_sha256": str, GROUND_TRUTH_KEY: str,
                  OBSERVATIONS_KEY: str, "num_steps": int, "num_objects": int}
_SPLIT_KEYS = {"file": str, "sequences": int, "names": list, "content_sha256": str}


def _manifest_structure_problem(manifest) -> str | None:
    if not isinstance(manifest, dict) or manifest.get("format") != DATASET_FORMAT:
        return "not a dsr-bench manifest"
    if not isinstance(manifest.get("sequences"), list) or not isinstance(manifest.get("splits", {}), dict):
        return "'sequences' must be a list and 'splits' an object"
    for i, entry in enumerate(manifest["sequences"]):
        for key, kind in _SEQUENCE_KEYS.items():
            if not isinstance(entry, dict) or not isinstance(entry.get(key), kind):
                return f"sequences[{i}] lacks {key!r} ({kind.__name__})"
    for name, entry in manifest.get("splits", {}).items():
        for key, kind in _SPLIT_KEYS.items():
            if not isinstance(entry, dict) or not isinstance(entry.get(key), kind):
                return f"splits[{name!r}] lacks {key!r} ({kind.__name__})"
    return None


def load_manifest(data_dir: str | Path) -> dict:
    """Read DATA_DIR/manifest.json and check its format, version and structure (UserError if not)."""
    data_dir = Path(data_dir)
    path = data_dir / MANIFEST_NAME
    if not data_dir.is_dir():
        raise missing_dataset(data_dir)
    if not path.is_file():
        raise UserError(f"{data_dir} has no {MANIFEST_NAME}; build it with `dsr-bench manifest {data_dir}`")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: unreadable manifest ({exc}); "
                        f"rebuild it with `dsr-bench manifest {data_dir}`") from None
    problem = _manifest_structure_problem(manifest)
    if problem:
        raise UserError(f"{path}: {problem}; rebuild it with `dsr-bench manifest {data_dir}`")
    if manifest.get("schema_version") not in READABLE_SCHEMA_VERSIONS:
        raise UserError(f"{path}: schema version {manifest.get('schema_version')}, "
                        f"this toolkit reads {', '.join(map(str, READABLE_SCHEMA_VERSIONS))}; "
                        "use the dsr-bench version that wrote it or regenerate the dataset")
    return manifest


def read_split(data_dir: str | Path, split: str | None) -> tuple[str, list[str]]:
    """(split name, sequence names) from DATA_DIR/splits/<split>.txt; `None` picks the only split."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise missing_dataset(data_dir)
    splits = _split_names(data_dir)
    if split is None:
        if len(splits) != 1:
            raise UserError(f"{data_dir} has splits {', '.join(sorted(splits)) or 'none'}; choose one with --split")
        split = next(iter(splits))
    if split not in splits:
        raise UserError(f"split {split!r} not found in {data_dir}/splits; "
                        f"available: {', '.join(sorted(splits)) or 'none'}")
    return split, splits[split]


def name_ranges(names: Iterable[str], limit: int = 6) -> str:
    """Sequence names compactly, in natural order: consecutive numbers of one prefix as a range
    (`seq_0000..seq_0399`), ranges separated by commas, the first `limit` shown and the rest counted
    (`seq_0000..seq_0003, seq_0007, ... (2 more ranges)`); '-' for no names."""
    def key(name: str) -> tuple:
        m = re.fullmatch(r"(.*?)(\d+)", name)
        return (m.group(1), int(m.group(2)), name) if m else (name, -1, name)

    runs: list[list] = []  # [prefix, first number, last number, first name, last name]
    for name in sorted(set(names), key=key):
        prefix, number, _ = key(name)
        if runs and number >= 0 and runs[-1][0] == prefix and runs[-1][2] == number - 1:
            runs[-1][2], runs[-1][4] = number, name
        else:
            runs.append([prefix, number, number, name, name])
    shown = [first if first == last else f"{first}..{last}" for *_, first, last in runs[:limit]]
    if len(runs) > limit:
        shown.append(f"... ({len(runs) - limit} more ranges)")
    return ", ".join(shown) or "-"


def match_sequence_name(name: str, held: Iterable[str], what: str = "sequence") -> str | None:
    """The name among `held` that the typed `name` means: itself, else the one sequence of the same number
    however it is padded (`seq_042`, `seq_42`, `42` -> `seq_0042`); None when none is. Two held names of that
    number (`seq_42` and `seq_0042`): a UserError naming both. `what` names the thing in that message."""
    held = list(held)
    if name in held:
        return name
    typed = re.fullmatch(r"(?:seq_?)?(\d+)", name)
    if typed is None:
        return None
    number = int(typed.group(1))
    same = sorted(h for h in held if (m := re.fullmatch(r"seq_(\d+)", h)) and int(m.group(1)) == number)
    if len(same) > 1:
        raise UserError(f"{what} {name!r} is ambiguous: {' and '.join(same)} both have number {number}; give the "
                        "full name")
    return same[0] if same else None


def missing_dataset(data_dir: str | Path) -> UserError:
    """The error of a dataset directory that does not exist: the command that makes it when its name is a named
    split's (data/cpu-train), and the datasets beside it."""
    data_dir = Path(data_dir)
    make = (f"; make it with `dsr-bench generate --split {data_dir.name} --out {data_dir}`" if data_dir.name in SPLITS
            else "")
    return UserError(f"dataset directory not found: {data_dir}{make}{_datasets_beside(data_dir)}")


def _datasets_beside(data_dir: Path) -> str:
    """'; datasets in data: data/a, data/b' for a dataset directory that does not exist, '' if none is beside it."""
    parent = data_dir.parent
    if not parent.is_dir():
        return ""
    found = sorted(str(d) for d in parent.iterdir() if d.is_dir() and (d / MANIFEST_NAME).is_file())
    if not found:
        return ""
    shown = ", ".join(found[:4]) + (f" and {len(found) - 4} more" if len(found) > 4 else "")
    return f"; datasets in {parent}: {shown}"


def resolve_sequence(data_dir: str | Path | None, name: str) -> Path:
    """A sequence file from a name within a dataset (`seq_0042`, or its number however padded: `seq_42`, `42`)
    or a path to a file. Not found: a UserError that names the sequences the directory holds."""
    candidate = Path(name)
    if candidate.suffix == ".h5" and candidate.is_file():
        return candidate
    if data_dir is not None:
        data_dir = Path(data_dir)
        path = data_dir / f"{candidate.stem}.h5"
        if path.is_file():
            return path
        if data_dir.is_dir():
            found = match_sequence_name(candidate.stem, (p.stem for p in data_dir.glob("seq_*.h5")))
            if found is not None:
                return data_dir / f"{found}.h5"
        if not data_dir.is_dir():
            raise UserError(f"dataset directory not found: {data_dir}; give --data the directory holding the "
                            f"seq_*.h5 files{_datasets_beside(data_dir)}")
        held = [p.stem for p in data_dir.glob("seq_*.h5")]
        if not held:
            raise UserError(f"no sequence {name!r} in {data_dir}: it holds no seq_*.h5 files; give --data a dataset "
                            "directory, or a path to a .h5 file")
        every = (f"; all names: `dsr-bench info {data_dir} --sequences`" if (data_dir / MANIFEST_NAME).is_file()
                 else "")
        raise UserError(f"no sequence {name!r} in {data_dir}: it holds {name_ranges(held)} ({len(held)} "
                        f"sequence{'s' if len(held) > 1 else ''}){every}")
    raise UserError(f"sequence {name!r} not found: give a path to a .h5 file or --data DIR with a sequence name")
