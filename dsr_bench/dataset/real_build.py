"""`dsr-bench real-split`: a folder of the annotator's exports -> a real split (`dsr_bench.dataset.real`).

Every export is checked before anything is written (`export_problem`, shared with the challenge's `add-hidden-set`):
an annotated sequence file (root attribute source "annotated", an annotation record), complete (every pose of every
object at every step snapped or confirmed, not exported with --allow-unchecked), none flagged (a snapped pose whose
fit score the annotator did not accept: what its window lists as a "poor fit" to check; a confirmed pose is the
annotator's call), and passing `validate` (schema, ranges, ground truth against the poses, digests). A refused
export is named with the reason and the fix; nothing is written until all pass.

The parts are drawn with `numpy.random.default_rng(seed)`: a permutation of the exports (sorted by file name), the
first `finetune` to fine-tune on, the next `test` held out; the rest, if the counts leave any, are left out (not
copied) and listed in the record. The directory is built beside `out` and renamed when complete (`atomic_directory`).
"""

from __future__ import annotations

import datetime as dt
import json
import re
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dsr_bench import __version__
from dsr_bench.atomic import atomic_directory
from dsr_bench.dataset.manifest import build_manifest, file_sha256, write_manifest
from dsr_bench.dataset.pins import build_pin
from dsr_bench.dataset.real import BY_HAND, PAPER_COUNTS, PARTS, REAL_FORMAT, REAL_SPLIT_FILE, REAL_VERSION, part_split
from dsr_bench.dataset.sequence import SequenceReader
from dsr_bench.dataset.splits import SPLITS, sequence_name
from dsr_bench.dataset.validate import validate_sequence
from dsr_bench.errors import UserError
from dsr_bench.parallel import run_in_order

#: a real split's name: its splits are <name>-finetune and <name>-test
NAME_PATTERN = re.compile(r"[a-z][a-z0-9]*(?:-[a-z0-9]+)*")


def _annotation(path: Path) -> tuple[str, dict | None, int, int, list]:
    """(source, annotation record, steps, objects, object names) of a sequence file; UserError if it cannot be read."""
    try:
        with SequenceReader(path) as seq:
            record = seq.attrs.get("annotation")
            names = [str(o.get("name", f"object {i + 1}")) for i, o in enumerate(seq.attrs.get("objects") or [])]
            return str(seq.attrs.get("source")), record if isinstance(record, dict) else None, int(seq.num_steps), \
                int(seq.num_objects), names
    except Exception as exc:  # noqa: BLE001 - not HDF5, or not a sequence file: named, one line
        raise UserError(f"{path}: not a sequence file ({type(exc).__name__}); give a folder of the annotator's "
                        "exports (`dsr-bench annotate CAPTURE --export FOLDER/NAME.h5`) only") from None


def export_problem(path: str | Path, check_gt: bool = True) -> str | None:
    """Why an export cannot join a real split (one phrase with its fix), or None: not an annotated export, incomplete
    (a pose neither snapped nor confirmed, or exported with --allow-unchecked), flagged (a snapped pose whose fit score
    the annotator did not accept), or failing `validate` (with `check_gt`: its ground truth too)."""
    path = Path(path)
    source, record, _, _, names = _annotation(path)
    if source != "annotated":
        return (f"not an annotated export (its source is {source!r}, not 'annotated'); give `dsr-bench annotate "
                "--export` files only")
    if record is None:
        return "has no annotation record; export it again with `dsr-bench annotate CAPTURE --export`"
    capture = record.get("capture", path.stem)
    status = record.get("status") or []
    scores = record.get("fit_scores") or [[None] * len(step) for step in status]
    unfinished = [(t, i, s) for t, step in enumerate(status) for i, s in enumerate(step)
                  if s not in ("snapped", "confirmed")]
    if unfinished or record.get("unchecked_allowed"):
        listed = ", ".join(f"step {t} {_object(names, i)} ({s})" for t, i, s in unfinished[:3])
        why = f"{len(unfinished)} poses are neither snapped nor confirmed ({listed})" if unfinished else \
            "it was exported with --allow-unchecked"
        return (f"its annotation is incomplete: {why}; finish annotating capture {capture} (`dsr-bench annotate "
                f"{capture}`) and export it again")
    flagged = [(t, i, (score or {}).get("reason", "")) for t, (step, step_scores) in enumerate(zip(status, scores))
               for i, (s, score) in enumerate(zip(step, step_scores))
               if s != "confirmed" and isinstance(score, dict) and not score.get("accepted", True)]
    if flagged:
        t, i, reason = flagged[0]
        more = f" (and {len(flagged) - 1} more)" if len(flagged) > 1 else ""
        return (f"its annotation is flagged: step {t} {_object(names, i)} is snapped with a fit the annotator does "
                f"not accept ({reason[:120]}){more}; check it in `dsr-bench annotate {capture}` (fix or confirm it) "
                "and export it again")
    problems = validate_sequence(path, check_gt=check_gt)
    if problems:
        return f"fails `dsr-bench validate` ({problems[0]}); export it again"
    return None


def _object(names: list, i: int) -> str:
    return f"object {i + 1}" + (f" ({names[i]})" if i < len(names) else "")


def annotated_by(counts: dict) -> str:
    """Who or what annotated a sequence, from the annotator's action counts: automatically (step 0 placed from a
    poses file, every later pose carried and snapped by --auto) or by a person in the window (the actions named)."""
    hand = {k: int(counts.get(k, 0)) for k in BY_HAND if counts.get(k)}
    if not hand:
        return ("automatically: step 0 placed from a poses file (--place), the rest carried and snapped by --auto"
                if counts.get("place") else "automatically: carried and snapped by --auto")
    return "by hand in the annotator's window (" + ", ".join(f"{k} {v}" for k, v in hand.items()) + ")"


def provenance(path: Path) -> dict:
    """What a real split records of an export that passed `export_problem`: its file and SHA-256, the capture and its
    kind, the annotator's versions, who or what annotated it, the action counts and the checks' verdicts."""
    _, record, steps, objects, _ = _annotation(path)
    assert record is not None  # checked by export_problem
    status = [s for step in record.get("status") or [] for s in step]
    source = record["capture_source"] if isinstance(record.get("capture_source"), dict) else {}
    counts = record["action_counts"] if isinstance(record.get("action_counts"), dict) else {}
    return {"export": path.name, "export_sha256": file_sha256(path), "capture": str(record.get("capture", path.stem)),
            "capture_kind": str(source.get("kind", "unknown")), "steps": steps, "objects": objects,
            "annotator_version": str(record.get("annotator_version", "?")),
            "state_version": str(record.get("state_version", "?")), "annotated_by": annotated_by(counts),
            "action_counts": counts,
            "checks": {"poses": len(status), "snapped": status.count("snapped"), "confirmed": status.count("confirmed"),
                       "flagged": 0, "unchecked_allowed": bool(record.get("unchecked_allowed", False)),
                       "validate": "passed"}}


def part_counts(available: int, finetune: int | None, test: int | None) -> tuple[int, int]:
    """(fine-tune, test) counts: as given; one of them given, the other the rest; neither, the paper's proportion
    (50 of 150 to fine-tune, `real.PAPER_COUNTS`) of `available`. UserError where they do not fit."""
    if finetune is None and test is None:
        share = PAPER_COUNTS["finetune"] / (PAPER_COUNTS["finetune"] + PAPER_COUNTS["test"])
        finetune = int(round(available * share))
    if finetune is None:
        finetune = available - (test or 0)
    if test is None:
        test = available - finetune
    if finetune < 1 or test < 1:
        raise UserError(f"--fine-tune {finetune} --test {test}: each part needs at least 1 sequence (the paper: 50 and "
                        f"100); {available} exports given")
    if finetune + test > available:
        raise UserError(f"--fine-tune {finetune} --test {test}: {finetune + test} sequences asked for, the folder "
                        f"holds {available} exports; annotate more captures or ask for fewer")
    return finetune, test


def _checked(path: str) -> str | None:
    return export_problem(path)


def build_real_split(exports: str | Path, out: str | Path, *, finetune: int | None = None, test: int | None = None,
                     seed: int = 0, name: str = "real", workers: int = 1,
                     progress: Callable[[int, int], None] | None = None) -> dict:
    """Make the real split `out` (a new directory) from the exports in folder `exports` (module doc); returns its
    record (`real_split.json`). `progress(done, total)`: per export checked."""
    exports, out = Path(exports), Path(out)
    if not NAME_PATTERN.fullmatch(name) or len(name) > 40:
        raise UserError(f"--name {name!r}: give lower-case letters, digits and single hyphens, starting with a letter "
                        "(e.g. real, lab-ur5)")
    taken = [s for s in (part_split(name, p) for p in PARTS) if s in SPLITS]
    if name in SPLITS or taken:
        raise UserError(f"--name {name!r}: {taken[0] if taken else name} is a named split of the toolkit; give another "
                        "name")
    if not exports.is_dir():
        raise UserError(f"{exports} is not a directory; give the folder of the annotator's exports")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UserError(f"--out {out} exists; give a new directory for the real split")
    files = sorted(p for p in exports.glob("*.h5") if p.is_file() and not p.is_symlink())
    if len(files) < 2:
        raise UserError(f"{exports} holds {len(files)} sequence file(s) (.h5); a real split needs at least 2 (a "
                        "fine-tune and a test part): export annotated captures into it")
    finetune, test = part_counts(len(files), finetune, test)
    problems = run_in_order(_checked, [str(p) for p in files], workers, progress)
    refused = [(p, why) for p, why in zip(files, problems) if why]
    if refused:
        more = f" ({len(refused) - 1} more refused: {', '.join(p.name for p, _ in refused[1:4])}" \
               f"{' ...' if len(refused) > 4 else ''})" if len(refused) > 1 else ""
        raise UserError(f"{refused[0][0]}: {refused[0][1]}{more}")
    records = [provenance(p) for p in files]
    for key, what in (("capture", "capture"), ("export_sha256", "file")):
        seen: dict[str, str] = {}
        for record in records:
            if record[key] in seen:
                raise UserError(f"{exports / record['export']} and {exports / seen[record[key]]} are the same {what} "
                                f"({record[key][:40]}); keep one of them")
            seen[record[key]] = record["export"]
    names = [sequence_name(i) for i in range(len(files))]  # a dataset's files are seq_*.h5
    order = np.random.default_rng(seed).permutation(len(files))
    chosen = {"finetune": sorted(names[i] for i in order[:finetune]),
              "test": sorted(names[i] for i in order[finetune:finetune + test])}
    unused = sorted(names[i] for i in order[finetune + test:])
    parts = {part: part_split(name, part) for part in PARTS}
    with atomic_directory(out) as tmp:
        (tmp / "splits").mkdir()
        for path, seq in zip(files, names):
            if seq not in unused:
                shutil.copyfile(path, tmp / f"{seq}.h5")  # byte for byte: the export's digests and SHA-256 stay
        for part, split in parts.items():
            (tmp / "splits" / f"{split}.txt").write_text("".join(f"{n}\n" for n in chosen[part]))
        manifest = build_manifest(tmp)
        write_manifest(tmp, manifest)
        record = {"format": REAL_FORMAT, "version": REAL_VERSION, "name": name, "seed": int(seed), "parts": parts,
                  "unused": [{"name": n, "export": records[names.index(n)]["export"]} for n in unused],
                  "toolkit_version": __version__,
                  "created": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                  "pins": {split: build_pin(tmp, chosen[part], manifest, split) for part, split in parts.items()},
                  "sequences": {n: {**r, "part": next(p for p in PARTS if n in chosen[p])}
                                for n, r in zip(names, records) if n not in unused}}
        (tmp / REAL_SPLIT_FILE).write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    return record
