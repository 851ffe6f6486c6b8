"""Real splits: a lab's annotated captures as a benchmark split, pinned by pins of its own (the real track).

A real split directory (`dsr-bench real-split EXPORTS --out DIR`, `dsr_bench.dataset.real_build`) is a dataset
directory: the annotator's exports (`dsr-bench annotate --export`, root attribute source "annotated") copied byte
for byte as `seq_0000.h5`, ... (in the order of their file names), two split files, `splits/<name>-finetune.txt`
(what models are fine-tuned on: the paper's 50 sequences) and `splits/<name>-test.txt` (held out and scored: the
paper's 100), `manifest.json`, and `real_split.json`, this module's record:

- `format` "dsr-bench-real-split", `version` 1, `name`, `seed` (the draw of the parts), `parts` {"finetune":
  split name, "test": split name}, `unused` (exports left out by the counts asked for), `toolkit_version`,
  `created`;
- `pins` {split: the pin `dsr_bench.dataset.pins.build_pin` makes of a toolkit split: the ground-truth checksum, the
  observations' checksum, per sequence its two group digests, every array's fingerprint and the `scored` digests
  `evaluate` recomputes}: what `validate` and `evaluate` check the split against, as they check a named split
  against `split_pins.json`;
- `sequences` {name: provenance}: the export's file name and SHA-256 (the copy's bytes), the capture and its kind
  (simulation or real), the annotator and state versions, who or what annotated it (`annotated_by`, from the
  annotator's action counts) and the checks' verdicts (every pose snapped or confirmed, none flagged, `validate`
  passed).

A lab's split cannot be in the toolkit's `split_pins.json`, so it is pinned to this file: `evaluate` verifies the
ground truth it reads against these pins (`verify_real_scored`) and records `real_split` in the results ("pinned to
its own real-split pins"); the leaderboard keeps a real split's rows in a table of their own, named by the split and
its checksum. The pins prove that the files have not changed since the split was made, not who made it: two labs'
real splits are the same only when their checksums are.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

from dsr_bench.dataset.manifest import split_digest
from dsr_bench.dataset.pins import changed_ground_truth, compare_with_pin, summarize
from dsr_bench.errors import UserError
from dsr_bench.jsonfile import UnreadableJSON, read_json

REAL_SPLIT_FILE = "real_split.json"
REAL_FORMAT, REAL_VERSION = "dsr-bench-real-split", 1
#: the two parts of a real split, in the order they are drawn
PARTS = ("finetune", "test")
#: the paper's real data: 50 sequences to fine-tune on, 100 to test (Sec. 4, "Train/Test split")
PAPER_COUNTS = {"finetune": 50, "test": 100}
#: the annotator's actions a person takes in its window (the rest: placing from a file, snapping, carrying, stepping)
BY_HAND = ("pick", "nudge", "confirm", "previous", "recarry", "undo", "redo")


def part_split(name: str, part: str) -> str:
    """The split name of a real split's part: `real-finetune`, `real-test`."""
    return f"{name}-{part}"


def read_real_split(data_dir: str | Path) -> dict | None:
    """DATA_DIR/real_split.json, checked for its format, version and structure; None where the directory holds
    none (not a real split). A broken file is a UserError naming it and the fix."""
    path = Path(data_dir) / REAL_SPLIT_FILE
    if not path.is_file():
        return None
    fix = f"rebuild the split with `dsr-bench real-split EXPORTS --out {data_dir}` (a new --out)"
    try:
        record = read_json(path)
    except UnreadableJSON as exc:
        raise UserError(f"{path}: {exc}; {fix}") from None
    if not isinstance(record, dict) or record.get("format") != REAL_FORMAT:
        raise UserError(f"{path}: not a dsr-bench real split record (format {REAL_FORMAT!r}); {fix}")
    if record.get("version") != REAL_VERSION:
        raise UserError(f"{path}: version {record.get('version')!r}, this toolkit reads {REAL_VERSION}; {fix}")
    parts, pins, sequences = record.get("parts"), record.get("pins"), record.get("sequences")
    if not (isinstance(parts, dict) and set(parts) == set(PARTS) and isinstance(pins, dict)
            and all(isinstance(pins.get(s), dict) and isinstance(pins[s].get("sequences"), dict)
                    for s in parts.values()) and isinstance(sequences, dict) and isinstance(record.get("name"), str)):
        raise UserError(f"{path}: lacks its name, parts, pins or sequences; {fix}")
    return record


def real_pin(data_dir: str | Path, split: str) -> tuple[dict, dict] | None:
    """(the real split's record, the pin of `split`) when DATA_DIR is a real split holding that split; else None."""
    record = read_real_split(data_dir)
    if record is None or split not in record["pins"]:
        return None
    return record, record["pins"][split]


def verify_real_scored(data_dir: str | Path, split: str, names: list[str], recomputed: Mapping[str, Mapping[str, str]],
                       manifest: Mapping, limit: int = 3) -> tuple[bool, list[str], dict | None]:
    """Whether what `evaluate` scored is the real split's pinned part: the split's list is the pinned sequences, the
    manifest's checksum the pin's, and every scored sequence's recomputed `scored` digests equal the pin's.
    Returns (verified, warning lines, the results' `real_split` record); (False, [], None) where DATA_DIR is not a
    real split holding `split` (a toolkit split is `pins.verify_scored`'s)."""
    found = real_pin(data_dir, split)
    if found is None:
        return False, [], None
    record, pin = found
    fix = (f"the files of {data_dir} changed since `dsr-bench real-split` pinned them; run `dsr-bench validate "
           f"{data_dir}` to see which, and rebuild the split from the annotator's exports")
    lines = []
    pinned = pin["sequences"]
    if sorted(pinned) != sorted(names):
        lines.append(f"{data_dir}: split {split!r} lists other sequences than its real-split pins ({REAL_SPLIT_FILE}); "
                     f"{fix}")
    actual = split_digest(manifest, split)
    if actual != pin.get("checksum"):
        lines.append(f"{data_dir}: split {split!r} has checksum {actual[:12]}... in its manifest, its real-split pins "
                     f"give {str(pin.get('checksum'))[:12]}...; {fix}")
    lines += changed_ground_truth(data_dir, recomputed, pinned, f"the real-split pins of {split}", fix, limit,
                                  "recomputed while scoring")
    about = {"name": record["name"], "part": next(p for p, s in record["parts"].items() if s == split),
             "pins": REAL_SPLIT_FILE, "checksum": pin.get("checksum"), "sequences": len(pinned)}
    return not lines, lines, about


def real_split_problems(data_dir: str | Path, manifest: Mapping,
                        fingerprints: Callable[[str], Mapping]) -> list[tuple[str, str]]:
    """(where, message) lines of `validate` for a real split (none for another directory): its record against the
    manifest (every sequence with its provenance, each file the export's bytes, the parts' split files) and each part
    against its pins (`pins.compare_with_pin`: which arrays of which sequence differ, and by how much; notes start
    with 'note:'). fingerprints(name): a sequence's array fingerprints, computed only where its digests differ."""
    try:
        record = read_real_split(data_dir)
    except UserError as exc:
        return [(REAL_SPLIT_FILE, str(exc))]
    if record is None:
        return []
    fix = "the split's files changed since `dsr-bench real-split` made it: rebuild it from the annotator's exports"
    lines: list[tuple[str, str]] = []
    listed = {s["name"]: s for s in manifest["sequences"]}
    provenance = record["sequences"]
    for name in sorted(set(listed) - set(provenance)):
        lines.append((name, f"not a sequence of the real split ({REAL_SPLIT_FILE} has no provenance of it); {fix}"))
    for name in sorted(set(provenance) - set(listed)):
        lines.append((name, f"a sequence of the real split ({REAL_SPLIT_FILE}) the manifest does not list; {fix}"))
    for name in sorted(set(provenance) & set(listed)):
        if provenance[name].get("export_sha256") != listed[name].get("sha256"):
            lines.append((name, f"its bytes are not those of the export {provenance[name].get('export')!r} the split "
                                f"was made from (SHA-256); {fix}"))
    for part, split in sorted(record["parts"].items()):
        if split not in manifest.get("splits", {}):
            lines.append((f"splits/{split}.txt", f"the real split's {part} part is missing; {fix}"))
            continue
        digests = {n: listed[n] for n in manifest["splits"][split]["names"] if n in listed}
        comparison = compare_with_pin(record["pins"][split], digests, fingerprints)
        lines += summarize(split, comparison, fix=fix)
    return lines


def pin_lines(data_dir: str | Path) -> list[str]:
    """One line per part of a valid real split saying what it is pinned to, for `validate`; none for another
    directory."""
    record = read_real_split(data_dir)
    if record is None:
        return []
    return [f"split {split}: checksum {record['pins'][split]['checksum']}, pinned to its own real-split pins "
            f"({Path(data_dir) / REAL_SPLIT_FILE}; the real split {record['name']!r}, {part} part, "
            f"{len(record['pins'][split]['sequences'])} sequences), its ground truth bit for bit"
            for part, split in record["parts"].items()]


def info_rows(record: Mapping) -> list[tuple[str, str]]:
    """(label, text) rows of `dsr-bench info` for a real split: its parts and seed, and its sequences' provenance
    summed up (captures by kind, annotator versions, who or what annotated them, the checks' verdicts)."""
    from collections import Counter

    def counts(values) -> str:
        return ", ".join(f"{k}: {v}" for k, v in sorted(Counter(values).items())) or "-"

    seqs = list(record["sequences"].values())
    parts = ", ".join(f"{part} {split} ({len(record['pins'][split]['sequences'])})"
                      for part, split in record["parts"].items())
    checks = [s.get("checks") or {} for s in seqs]
    poses = sum(int(c.get("poses", 0)) for c in checks)
    return [("real split", f"{record['name']!r}: {parts}, drawn with seed {record.get('seed')}"
             + (f"; {len(record.get('unused') or [])} exports left out" if record.get("unused") else "")),
            ("captures", counts(s.get("capture_kind", "?") for s in seqs)),
            ("annotator versions", counts(f"annotator {s.get('annotator_version')}, state "
                                          f"{s.get('state_version')}" for s in seqs)),
            ("annotated by", counts(s.get("annotated_by", "?") for s in seqs)),
            ("checks", f"{poses} poses: {sum(int(c.get('snapped', 0)) for c in checks)} snapped, "
                       f"{sum(int(c.get('confirmed', 0)) for c in checks)} confirmed, "
                       f"{sum(int(c.get('flagged', 0)) for c in checks)} flagged; `validate` passed on "
                       f"{sum(c.get('validate') == 'passed' for c in checks)} of {len(seqs)} exports")]
