"""`dsr-bench validate`: check a dataset directory and report every problem at once.

Checks the manifest against the files (missing, extra, checksums, split files and checksums), every
file against the schema (format, version, attributes, shapes, dtypes), its values and ground truth
(`dsr_bench.dataset.checks`: value ranges and, unless disabled, flow recomputed from poses and amodal
masks, flow zero off objects, amodal masks at t + 1 against the masks at t moved by the flow, the TSDF's
sign against the front depth image) and content digests, a named split against its pin, and a real split
(`dsr_bench.dataset.real`) against its own pins. A damaged
file is a problem, never a crash.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from dsr_bench.dataset.digests import GROUND_TRUTH_KEY, OBSERVATIONS_KEY
from dsr_bench.dataset.manifest import MANIFEST_NAME, file_sha256, load_manifest, missing_dataset, split_digest
from dsr_bench.dataset.pins import compare_with_pin, summarize
from dsr_bench.dataset.real import real_split_problems
from dsr_bench.dataset.schema import FIELDS, REQUIRED_ATTRS, SEQUENCE_SCHEMA, check_array, dataset_path, resolve_shape
from dsr_bench.dataset.sequence import SequenceFormatError, SequenceReader, file_digests, file_fingerprints
from dsr_bench.errors import UserError
from dsr_bench.parallel import run_in_order
from dsr_bench.dataset.checks import (  # noqa: F401 - the per-sequence checks, importable from here as before
    FLOW_TOLERANCE, MASK_WARP_IOU, MIN_WARP_VOXELS, TSDF_SIGN_AGREEMENT, action_problems, content_problems,
    OFFICIAL_POSE_DRIFT, mask_warp_iou, rotation_angle, rounding_excess,
)


@dataclass(frozen=True)
class Problem:
    """One problem found: where (a sequence name, a file, or 'dataset') and what. A note (`note`) is
    reported but does not make the dataset invalid (e.g. observations within the pin's tolerance)."""

    where: str
    message: str
    note: bool = False


def schema_markdown_table() -> str:
    """The sequence schema (`dsr_bench.dataset.schema.SEQUENCE_SCHEMA`) as a markdown table for docs/format.md."""
    rows = ["| dataset | shape | dtype | units | required | group | meaning |", "|---|---|---|---|---|---|---|"]
    for f in SEQUENCE_SCHEMA:
        name = f"cameras/<cam>/{f.name}" if f.camera else f.name
        required = "yes" if f.required else "no"
        rows.append(f"| `{name}` | ({', '.join(f.shape)}) | {f.dtype} | {f.units} | {required} | {f.group} | "
                    f"{f.description} |")
    return "\n".join(rows) + "\n"


# --- one sequence file ---------------------------------------------------------------------------------
def _open(path: str | Path):
    """(reader, None) or (None, the problem) for a sequence file."""
    try:
        return SequenceReader(path), None
    except SequenceFormatError as exc:
        return None, str(exc).replace(f"{path}: ", "")
    except KeyError as exc:
        return None, f"missing root attribute {exc}"
    except Exception as exc:  # noqa: BLE001 - truncated or garbage files
        return None, f"unreadable: {type(exc).__name__}: {exc}"


def schema_problems(seq) -> tuple[list[str], set[str]]:
    """Structural problems of an open sequence (missing datasets, shapes, dtypes) and the names of
    the datasets that passed. Shared by `validate` and the viewer."""
    from types import SimpleNamespace

    problems: list[str] = []
    ok: set[str] = set()
    for field in FIELDS.values():
        for cam in (list(seq.cameras) if field.camera else [None]):
            name = dataset_path(field, cam)
            if name not in seq:
                if field.required:
                    problems.append(f"missing dataset {name!r}")
                continue
            try:
                image = (int(seq.cameras[cam]["height"]), int(seq.cameras[cam]["width"])) if cam else None
                shape = (resolve_shape(field, seq.num_steps, seq.num_objects, image) if image
                         else resolve_shape(field, seq.num_steps, seq.num_objects))
                stored_shape, dtype = seq.shape_and_dtype(name)
                found = check_array(field, SimpleNamespace(shape=stored_shape, dtype=dtype), shape, name)
            except Exception as exc:  # noqa: BLE001 - malformed camera attributes, unreadable dataset
                found = [f"{name}: cannot check ({type(exc).__name__}: {exc})"]
            problems += found
            if not found:
                ok.add(name)
    return problems, ok


def validate_sequence(path: str | Path, check_gt: bool = True, expected: dict | None = None) -> list[str]:
    """Every problem of one sequence file (empty if none): see `_check_sequence`."""
    return _check_sequence(path, check_gt, expected)[0]


def _check_sequence(path: str | Path, check_gt: bool = True, expected: dict | None = None
                    ) -> tuple[list[str], dict | None]:
    """Every problem of one sequence file (empty if none), and its array fingerprints when computed.

    Schema (attributes, every dataset's shape and dtype), value ranges, and with `check_gt` the
    ground-truth consistency (`dsr_bench.dataset.checks.content_problems`) and the digests, recomputed from the
    arrays (`dsr_bench.dataset.digests`): the file's own (naming the arrays changed since writing) and `expected`
    (the manifest's entry).
    """
    seq, problem = _open(path)
    if seq is None:
        return [problem], None
    problems: list[str] = []
    prints = None
    try:
        problems += [f"missing attribute {a!r}" for a in REQUIRED_ATTRS if a not in seq.attrs]
        found, ok = schema_problems(seq)
        problems += found
        problems += content_problems(seq, ok, check_gt)
        stored = {k: seq.attrs.get(k) for k in ("content_sha256", GROUND_TRUTH_KEY, OBSERVATIONS_KEY, "array_sha256")}
    finally:
        seq.close()
    if check_gt or expected is not None:
        try:
            actual = file_digests(path)
        except Exception as exc:  # noqa: BLE001 - unreadable data is reported, not raised
            problems.append(f"digests: unreadable data ({type(exc).__name__}: {exc})")
        else:
            prints = actual["fingerprints"]
            if any(stored[k] is not None and stored[k] != actual[k] for k in ("content_sha256", GROUND_TRUTH_KEY,
                                                                              OBSERVATIONS_KEY)):
                listed = stored["array_sha256"] if isinstance(stored["array_sha256"], dict) else {}
                changed = sorted(n for n in set(listed) | set(actual["array_sha256"])
                                 if listed.get(n) != actual["array_sha256"].get(n))
                problems.append("digests do not match the arrays (file modified after writing"
                                + (f": {', '.join(changed)})" if changed else ")"))
            for key in (GROUND_TRUTH_KEY, OBSERVATIONS_KEY):
                if expected is not None and expected.get(key) != actual[key]:
                    problems.append(f"{key} differs from the manifest's (run `dsr-bench manifest DIR` if the file "
                                    "was replaced on purpose)")
    return problems, prints


def validate_file(path: str | Path, check_gt: bool = True) -> tuple[list[str], dict]:
    """(every problem, what it is) of one sequence file given alone (`dsr-bench validate FILE.h5`, e.g. an
    annotator's export): what the file alone can prove, the checks of `_check_sequence` (schema, value ranges, and
    with `check_gt` the ground truth against the poses and masks and the file's own digests against its arrays).
    What it is: {"steps", "objects", "source"} read from the file (empty when it cannot be opened). A manifest's
    digests and the split pins need a dataset directory: a single file is checked against neither."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file; give a sequence file (.h5) or a dataset directory")
    problems, _ = _check_sequence(path, check_gt)
    about: dict = {}
    seq, _ = _open(path)
    if seq is not None:
        try:
            about = {"steps": int(seq.num_steps), "objects": int(seq.num_objects),
                     "source": str(seq.attrs.get("source", "?"))}
        except Exception:  # noqa: BLE001 - reported as problems above
            about = {}
        finally:
            seq.close()
    return problems, about


SINGLE_FILE_LIMITS = ("a single file is checked on its own: its schema, value ranges, ground truth and its digests "
                      "against its arrays; the split pins (is it a benchmark split's sequence, bit for bit?) and a "
                      "manifest's checksums need a dataset directory: put the file in one, run `dsr-bench manifest "
                      "DIR`, then `dsr-bench validate DIR`")


def _validate_one(args: tuple[str, bool, dict | None]) -> tuple[str, list[str], dict | None]:
    path, check_gt, expected = args
    return (Path(path).stem, *_check_sequence(path, check_gt, expected))


# --- the dataset -------------------------------------------------------------------------------------
def _check_manifest(data_dir: Path, manifest: dict, files: dict[str, Path]) -> tuple[list[Problem], dict[str, dict]]:
    """Manifest against the files and split files; returns (problems, manifest entries by name)."""
    problems: list[Problem] = []
    listed = {s["name"]: s for s in manifest["sequences"]}
    for name in sorted(set(listed) - set(files)):
        problems.append(Problem(name, "listed in the manifest but the file is missing"))
    for name in sorted(set(files) - set(listed)):
        problems.append(Problem(name, "file present but not in the manifest (run `dsr-bench manifest DIR`)"))
    digests: dict[str, dict] = {}
    for name in sorted(set(files) & set(listed)):
        if file_sha256(files[name]) != listed[name]["sha256"]:
            problems.append(Problem(name, "SHA-256 of the file differs from the manifest"))
        digests[name] = listed[name]
    splits = manifest.get("splits", {})
    for split, info in sorted(splits.items()):
        path = data_dir / info["file"]
        if not path.is_file():
            problems.append(Problem(info["file"], f"split file of {split!r} is missing"))
            continue
        try:
            names = [line.strip() for line in path.read_text().splitlines() if line.strip()]
        except (OSError, UnicodeDecodeError) as exc:
            problems.append(Problem(info["file"], f"split file of {split!r} is unreadable ({exc})"))
            continue
        if names != info["names"]:
            problems.append(Problem(info["file"], "split file differs from the manifest"))
        problems += [Problem(info["file"], f"names {n!r}, which has no file") for n in names if n not in files]
        try:
            if split_digest(manifest, split) != info["content_sha256"]:
                problems.append(Problem(info["file"], f"split checksum of {split!r} in the manifest does not match "
                                                      "its sequences' ground-truth digests"))
        except UserError as exc:
            problems.append(Problem(info["file"], str(exc)))
    for path in sorted((data_dir / "splits").glob("*.txt")):
        if path.stem not in splits:
            problems.append(Problem(f"splits/{path.name}",
                                    "split file not in the manifest (run `dsr-bench manifest DIR`)"))
    return problems, digests


def _check_pinned(data_dir: Path, manifest: dict, fingerprints: dict[str, dict]) -> list[Problem]:
    """A named benchmark split must reproduce the toolkit's pin: its ground truth bit for bit, its
    observations within the stated tolerance (`dsr_bench.dataset.pins`); differences name the sequences and
    arrays, and say by how much. fingerprints: those already computed, by sequence name."""
    from dsr_bench.dataset.splits import pinned_digests  # looked up on each call: tests stand in their own pins

    listed = {s["name"]: s for s in manifest["sequences"]}
    problems = []
    for split, pin in pinned_digests().items():
        info = manifest.get("splits", {}).get(split)
        if info is None:
            continue
        digests = {n: listed[n] for n in info["names"] if n in listed}

        def prints(name: str) -> dict:
            if fingerprints.get(name) is None:
                fingerprints[name] = file_fingerprints(data_dir / listed[name]["file"])[0]
            return fingerprints[name]

        comparison = compare_with_pin(pin, digests, prints)
        problems += [Problem(where, message, note=message.startswith("note:"))
                     for where, message in summarize(split, comparison)]
    return problems


def _check_real_pins(data_dir: Path, manifest: dict, fingerprints: dict[str, dict]) -> list[Problem]:
    """A real split (`dsr_bench.dataset.real`) must reproduce its own pins, as a named split reproduces the toolkit's;
    nothing for another directory. fingerprints: those already computed, by sequence name."""
    listed = {s["name"]: s for s in manifest["sequences"]}

    def prints(name: str) -> dict:
        if fingerprints.get(name) is None:
            fingerprints[name] = file_fingerprints(data_dir / listed[name]["file"])[0]
        return fingerprints[name]

    return [Problem(where, message, note=message.startswith("note:"))
            for where, message in real_split_problems(data_dir, manifest, prints)]


def validate_dataset(data_dir: str | Path, check_gt: bool = True, workers: int = 1,
                     progress: Callable[[int, int], None] | None = None) -> tuple[list[Problem], int]:
    """(every problem found, number of sequence files checked) for a dataset directory. `progress(done, total)`:
    called once per sequence file checked, as each finishes."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise missing_dataset(data_dir)
    if workers < 1:
        raise UserError(f"--workers {workers}: must be at least 1")
    problems: list[Problem] = []
    files = _sequence_files(data_dir)
    digests: dict[str, dict] = {}
    manifest = None
    try:
        manifest = load_manifest(data_dir)
    except UserError as exc:
        alone = " (or check a sequence file alone: `dsr-bench validate FILE.h5`)" if files and not (
            data_dir / MANIFEST_NAME).exists() else ""
        problems.append(Problem(MANIFEST_NAME, f"{exc}{alone}"))
    else:
        found, digests = _check_manifest(data_dir, manifest, files)
        problems += found
    jobs = [(str(p), check_gt, digests.get(name)) for name, p in files.items()]
    import multiprocessing as mp
    from concurrent.futures.process import BrokenProcessPool

    try:
        results = run_in_order(_validate_one, jobs, workers, progress, mp_context=mp.get_context("spawn"))
    except BrokenProcessPool:
        raise UserError(f"--workers {workers}: a worker process died while checking {data_dir} (out of "
                        "memory?); run again with fewer workers") from None
    fingerprints = {}
    for name, found, prints in results:
        problems += [Problem(name, m) for m in found]
        fingerprints[name] = prints
    if manifest is not None:
        problems += _check_pinned(data_dir, manifest, fingerprints)
        problems += _check_real_pins(data_dir, manifest, fingerprints)
    if not files:
        others = sorted(p.name for p in data_dir.glob("*.h5"))
        hint = (f" ({len(others)} other .h5 file{'s' if len(others) != 1 else ''}: {', '.join(others[:3])}"
                f"{' ...' if len(others) > 3 else ''}; check one alone with `dsr-bench validate FILE.h5`)"
                if others else "")
        problems.append(Problem("dataset", f"no seq_*.h5 files in {data_dir}{hint}"))
    return problems, len(files)


def _sequence_files(data_dir: Path) -> dict[str, Path]:
    """The sequence files `validate` checks, by name."""
    return {p.stem: p for p in sorted(Path(data_dir).glob("seq_*.h5"))}


def summary_line(problems: list[Problem], count: int, data_dir: str | Path, named: int = 3) -> str:
    """The last line of a failed `validate`: files checked and those with problems, and the problems that
    belong to no checked sequence file (manifest, split files, pins, files listed but missing, an empty
    directory), counted and the first `named` of them named, so the line alone says why it failed."""
    files = _sequence_files(Path(data_dir))
    notes = [p for p in problems if p.note]
    problems = [p for p in problems if not p.note]
    bad = len({p.where for p in problems if p.where in files})
    line = f"{count} sequence files checked, {bad} with problems"
    dataset = [p for p in problems if p.where not in files]
    if dataset:
        shown = "; ".join(f"{p.where}: {p.message}" for p in dataset[:named])
        more = f"; and {len(dataset) - named} more above" if len(dataset) > named else ""
        line += (f"; {len(dataset)} dataset-level problem{'s' if len(dataset) != 1 else ''} "
                 f"({shown}{more})")
    if notes:
        line += f"; {len(notes)} note{'s' if len(notes) != 1 else ''} (not problems)"
    return line
