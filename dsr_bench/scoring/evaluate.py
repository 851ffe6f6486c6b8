"""`dsr-bench evaluate`: score a predictions directory against a split, strictly.

Structure is checked first for every file, reading no array data (names, presence, nothing else in
the directory, regular files of its own (no symlinks), the root's members and links, storage inside the file,
filters, shapes, dtypes, `num_slots`, the attributes stating the sequence and layout, meta.json:
`dsr_bench.scoring.predictions`); the data checks (unreadable chunks, NaN/inf, slot ids out of range, masks
that lie on the observed surface only with y and x swapped) happen in the same streaming pass that scores, one
sequence per worker at a time. Any problem means no score, unless `allow_partial`, which scores the valid
sequences and states the coverage. A named split whose checksum differs from the toolkit's pin
is scored with a warning (`pin_warning`) and `"pinned": false` in the results. A real split (the annotated captures
of `dsr-bench real-split`, `dsr_bench.dataset.real`) is verified against its own pins instead and its results say so
(`real_split`: its name, part, pins file and checksum).
A 2D-only submission (every file motion_2d alone, the 2D track) is scored on the front camera's 2D
flow only (its results hold `motion_2d` alone); it needs data with `cameras/front/scene_flow_2d`,
and a directory mixing it with 3D files is refused.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import stat
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from dsr_bench import __version__
from dsr_bench.dataset.manifest import file_sha256
from dsr_bench.dataset.pins import verify_scored
from dsr_bench.dataset.real import verify_real_scored
from dsr_bench.dataset.scored import FRONT_FLOW_2D, FRONT_MASK, ScoredDigests
from dsr_bench.errors import UserError
from dsr_bench.engines import LOGS_NAME, Engine
from dsr_bench.parallel import run_in_order
from dsr_bench.scoring.metrics import (METRICS, OBJECT_IOUS, TRACKS, Sequence3D, Step2D, Step3D, compute_sequence,
                                       compute_step, metric_keys)
from dsr_bench.scoring.predictions import META_TYPES

RESULTS_FORMAT = "dsr-bench-results"
#: the metric whose value is finite whenever the predicted motion is (a sum over the full volume): a step's
#: elementwise check for NaN or inf runs only when it is not
FINITE_WITNESS = "motion_full"
META_KEYS = tuple(META_TYPES)
#: errors h5py raises on a damaged or hostile file
READ_ERRORS = (OSError, KeyError, ValueError, TypeError, RuntimeError)
#: a 3D prediction's masks look transposed (y and x swapped) when, over its steps, at least SWAP_MIN_SHARE of their
#: voxels lie on the observed surface (tsdf < 0) with y and x swapped and SWAP_RATIO times as many as stored: the
#: toolkit's predictors (oracle, static, push, the CPU-track learned models) put 20-100% of their mask voxels on it
#: as stored and at most 0.58 times as many swapped; swapped, 1.73 times as many or more (docs/evaluation.md)
SWAP_MIN_SHARE = 0.1
SWAP_RATIO = 1.5


@dataclass
class Evaluation:
    """Outcome of an evaluation: problems found (where, what), warnings (one line each) and, if
    scored, the results dictionary."""

    problems: list[tuple[str, str]] = field(default_factory=list)
    results: dict | None = None
    warnings: list[str] = field(default_factory=list)
    #: each scored sequence's per-step values ({sequence: {per_step key: [values]}}), for the plot's spread bands
    per_sequence_steps: dict[str, dict[str, list]] = field(default_factory=dict)


def pin_warning(manifest: dict, split: str, data_dir: str | Path | None = None) -> str | None:
    """One line when `split` is a named split pinned in this toolkit and the dataset's split
    checksum differs from the pin; None otherwise (a matching, unpinned or unnamed split)."""
    from dsr_bench.dataset.manifest import split_digest
    from dsr_bench.dataset.splits import SPLITS

    spec = SPLITS.get(split)
    if spec is None or spec.expected_digest is None:
        return None
    actual = split_digest(manifest, split)
    if actual == spec.expected_digest:
        return None
    where = f"{data_dir}: " if data_dir is not None else ""
    target = f" --out {data_dir}" if data_dir is not None else ""
    return (f"{where}split {split!r} has checksum {actual[:12]}..., not this toolkit's pin "
            f"{spec.expected_digest[:12]}...: its scores are not comparable with the leaderboard's; regenerate it "
            f"with `dsr-bench generate --split {split}{target}`, or run `dsr-bench validate {data_dir or 'DATA_DIR'}` "
            "to see which sequences differ")


#: what a 2D-only prediction is scored against (at the front camera's mask, FRONT_MASK)
GT_2D = FRONT_FLOW_2D


def require_predictions_dir(pred_dir: str | Path) -> Path:
    """`pred_dir` as a Path when it is a directory, else a UserError saying what it is and what to give."""
    path = Path(pred_dir)
    if path.is_dir():
        return path
    if path.exists():
        raise UserError(f"{path} is a file, not a predictions directory; give the directory that holds the "
                        "predictions' .h5 files (one per sequence) and meta.json")
    raise UserError(f"predictions directory not found: {path}; write one with `dsr-bench predict --out DIR`")


def no_2d_ground_truth(gt_path: str | Path) -> str:
    """The problem of a 2D-only prediction scored against a sequence without the 2D ground truth."""
    return (f"a 2D-only prediction (motion_2d without mask and motion), but its ground truth {gt_path} has no "
            f"{GT_2D}; score it against a dataset with the front camera's 2D data (`dsr-bench generate` writes it)")


def surface_counts(mask: np.ndarray, tsdf: np.ndarray) -> np.ndarray:
    """[voxels a mask volume (Y, X, Z) labels, those on the observed surface (tsdf < 0) as stored, and with its y
    and x axes swapped]: the evidence of `transposed_problem`."""
    labelled, surface = mask != 0, tsdf < 0
    return np.array([np.count_nonzero(labelled), np.count_nonzero(labelled & surface),
                     np.count_nonzero(labelled.transpose(1, 0, 2) & surface)], dtype=np.int64)


def transposed_problem(counts: np.ndarray) -> str | None:
    """The problem of masks whose voxels lie on the observed surface far more with y and x swapped than as stored
    (`surface_counts` summed over the steps), else None: volumes stored (X, Y, Z) instead of (Y, X, Z)."""
    labelled, stored, swapped = (int(c) for c in counts)
    if not labelled or swapped < SWAP_MIN_SHARE * labelled or swapped < SWAP_RATIO * stored:
        return None
    return (f"mask: {swapped / labelled:.0%} of its voxels lie on the observed surface (tsdf < 0) with y and x "
            f"swapped, {stored / labelled:.0%} as stored: the volumes look transposed; store mask and motion as "
            "(T, Y, X, Z) = (world y, world x, z), motion components (dy, dx, dz)")


def score_sequence(args: tuple[str, str, str]) -> tuple[str, list[str], dict | None]:
    """Check and score one sequence, args = (name, prediction file, ground-truth file): returns
    (name, problems, per-step values or None): every metric of `metrics.METRICS` that its tracks score, by key.
    Used by `evaluate` and by the viewer's plots. A 2D-only prediction (motion_2d alone) gets the 2D track's
    values only: "has_2d" True and "has_3d" False, no 3D flow and no IoU."""
    from dsr_bench.scoring.predictions import check_prediction_header, is_2d_only
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.dataset.storage import read_step, read_step_and_columns, read_steps

    name, pred_path, gt_path = args
    problems: list[str] = []
    try:
        mode = os.stat(pred_path).st_mode
    except OSError as exc:
        return name, [f"cannot be read ({exc.strerror})"], None
    if not stat.S_ISREG(mode):
        return name, ["not a regular file"], None
    try:
        with SequenceReader(gt_path) as gt, h5py.File(pred_path, "r") as pred:
            problems = check_prediction_header(pred, gt.num_steps, name)  # nothing is read before this passes
            if problems:
                return name, problems, None
            steps = gt.num_steps
            digests = ScoredDigests()  # the ground truth as scored, recomputed as it is read (dataset/scored.py)
            digests.objects(gt.num_objects, gt.objects)
            has_3d = not is_2d_only(pred)
            if not has_3d and GT_2D not in gt:
                return name, [no_2d_ground_truth(gt_path)], None
            has_2d = "motion_2d" in pred and GT_2D in gt
            per_step = {k: np.full(steps, np.nan) for k in metric_keys(TRACKS if has_3d else ("2D",), scope="step")}
            if has_3d:
                num_slots = int(pred.attrs["num_slots"])
                n = gt.num_objects
                pred_mask = read_steps(pred["mask"], 0, steps)
                if int(pred_mask.max(initial=0)) > num_slots:
                    problems.append(f"mask: slot id {int(pred_mask.max())} > num_slots {num_slots}")
                gt_mask = gt.read("mask_3d", slice(0, steps))
                pred_motion, gt_flow, gt_tsdf = pred["motion"], gt.dataset("scene_flow_3d"), gt.dataset("tsdf")
                surface = np.zeros(3, dtype=np.int64)  # the masks against the observed surface (transposed_problem)
            for t in range(steps):
                if has_3d:
                    motion = read_step(pred_motion, t)
                    flow, columns = read_step_and_columns(gt_flow, t)
                    tsdf = read_step(gt_tsdf, t)
                    surface += surface_counts(pred_mask[t], tsdf)
                    # a bool volume's nonzero is 10x faster than a uint8 one's
                    objects = np.flatnonzero(gt_mask[t] != 0)
                    digests.mask_step(t, gt_mask[t], objects)
                    digests.tsdf_step(t, tsdf, objects)
                    digests.flow_step(t, flow, columns)
                    with np.errstate(over="ignore", invalid="ignore"):
                        values = compute_step("3D", Step3D(motion, flow, tsdf, gt_mask[t], n, objects))
                    if not np.isfinite(values[FINITE_WITNESS]) and not np.all(np.isfinite(motion)):
                        problems.append(f"motion[{t}]: NaN or inf")
                        continue
                    for k, v in values.items():
                        per_step[k][t] = v
                if has_2d:
                    m2 = read_step(pred["motion_2d"], t)
                    if not np.all(np.isfinite(m2)):
                        problems.append(f"motion_2d[{t}]: NaN or inf")
                        continue
                    for k, v in compute_step("2D", Step2D(m2, *_truth_2d(gt, t, digests))).items():
                        per_step[k][t] = v
            if has_3d and (swapped := transposed_problem(surface)):
                problems.append(swapped)
            if problems:
                return name, problems, None
            if has_3d:
                visible = gt.read("visible_fraction") if "visible_fraction" in gt else None
                if visible is not None:
                    digests.visible_fraction(visible)
                whole = compute_sequence(Sequence3D(pred_mask, gt_mask, num_slots, n, visible))
    except READ_ERRORS as exc:
        return name, [f"unreadable or truncated: {type(exc).__name__}: {' '.join(str(exc).split())}"], None
    out: dict[str, Any] = {k: v.tolist() for k, v in per_step.items()}
    if has_3d:
        out.update({k: v.tolist() if isinstance(v, np.ndarray) else [x.tolist() for x in v] for k, v in whole.items()})
    out["has_2d"] = has_2d
    out["has_3d"] = has_3d
    out["scored_digests"] = digests.hexdigests()
    return name, [], out


def _partial_2d_warning(scored: Mapping[str, dict]) -> list[str]:
    """One line when some 3D predictions hold motion_2d and others do not: the 2D track's metric is then left out
    (a mean over part of the sequences would not be the benchmark's)."""
    has = {name: s["has_2d"] for name, s in sorted(scored.items()) if s.get("has_3d", True)}
    without = [name for name, h in has.items() if not h]
    if not without or len(without) == len(has):
        return []
    return [f"the 2D flow is not scored: {len(has) - len(without)} of {len(has)} 3D predictions hold motion_2d but "
            f"{without[0]}.h5" + (f" and {len(without) - 1} more lack it" if len(without) > 1 else " lacks it")
            + "; write motion_2d in every file to be scored on the 2D track too"]


def _truth_2d(gt, t: int, digests) -> tuple[np.ndarray, np.ndarray]:
    """The front camera's 2D flow and mask at step t, fed to the scored digests as they are read."""
    mask = gt.read(FRONT_MASK, t)
    flow = gt.read(GT_2D, t)
    digests.mask_2d_step(t, mask)
    digests.flow_2d_step(t, flow, mask)
    return flow, mask


def check_structure(pred_dir: Path, data_dir: Path, names: list[str]) -> tuple[dict[str, Path], list[tuple[str, str]]]:
    """Every structural problem of a predictions directory, as (file name, problem); the files that
    passed. Reads no array data and opens only regular files inside the directory. A directory mixing
    3D predictions (mask and motion) with 2D-only ones (motion_2d alone) is one problem (file name "")
    naming a file of each kind, and then no file passes."""
    from dsr_bench.scoring.predictions import check_prediction_header, file_problem, is_2d_only, read_meta

    problems: list[tuple[str, str]] = extra_entries(pred_dir, names)
    valid: dict[str, Path] = {}
    kinds: dict[bool, str] = {}  # 2D-only? -> the first such file
    for name in names:
        where = f"{name}.h5"
        if "/" in name or "\\" in name or name.startswith(".."):
            problems.append((name, "sequence name escapes the directory"))
            continue
        path = pred_dir / where
        problem = file_problem(path, pred_dir)
        if problem:
            problems.append((where, "missing prediction file" if problem == "missing" else problem))
            continue
        try:
            with h5py.File(data_dir / where, "r") as g:
                steps = int(g.attrs["num_steps"])
                has_gt_2d = GT_2D in g
        except READ_ERRORS as exc:
            problem = (f"its ground truth {data_dir / where} is unreadable ({type(exc).__name__}); "
                       f"run `dsr-bench validate {data_dir}`")
            problems.append((where, problem))
            continue
        try:
            with h5py.File(path, "r") as f:
                found = check_prediction_header(f, steps, name)
                only_2d = not found and is_2d_only(f)
        except READ_ERRORS as exc:
            found = [f"unreadable HDF5 file ({type(exc).__name__}: {' '.join(str(exc).split())})"]
        if not found and only_2d and not has_gt_2d:
            found = [no_2d_ground_truth(data_dir / where)]
        if found:
            problems += [(where, p) for p in found]
        else:
            valid[name] = path
            kinds.setdefault(only_2d, where)
    if len(kinds) == 2:
        problems.append(("", mixed_problem(kinds[False], kinds[True])))
        valid = {}
    problems += [("meta.json", p) for p in read_meta(pred_dir)[1]]
    return valid, problems


def extra_entries(pred_dir: Path, names: list[str]) -> list[tuple[str, str]]:
    """What a predictions directory holds besides its split's SEQUENCE.h5 files and meta.json, as (name, problem):
    strict, as a submission format is, so that nothing is silently left unscored. Allowed too: the folder
    `evaluate --slurm` keeps its logs in by default (`engines.LOGS_NAME`)."""
    from dsr_bench.scoring.predictions import META_NAME

    allowed = {f"{name}.h5" for name in names} | {META_NAME}
    problems = []
    with os.scandir(pred_dir) as found:
        entries = sorted(found, key=lambda e: e.name)
    for entry in entries:
        if entry.name in allowed or (entry.name == LOGS_NAME and entry.is_dir(follow_symlinks=False)):
            continue
        kind = "directory" if entry.is_dir(follow_symlinks=False) else "file"
        if entry.name.endswith(".h5") and kind == "file":
            problems.append((entry.name, "extra file: not a sequence of this split"))
        elif entry.name.startswith(".") and ".tmp-" in entry.name:
            problems.append((entry.name, f"extra {kind}: the temporary of a write still running or interrupted "
                             "(`dsr-bench predict`); let it finish, or remove it"))
        else:
            problems.append((entry.name, f"extra {kind}: a predictions directory holds one SEQUENCE.h5 per "
                             "sequence of the split and meta.json, nothing else; move it out of the directory"))
    return problems


def mixed_problem(file_3d: str, file_2d: str) -> str:
    """The problem of a directory that mixes 3D and 2D-only predictions, naming a file of each kind."""
    return (f"mixed submission: {file_3d} holds mask and motion (3D) but {file_2d} holds motion_2d alone (2D-only); "
            "write every sequence the same way (all with mask and motion, or all with motion_2d alone)")


def _mean(values) -> float:
    arr = np.asarray(values, dtype=np.float64)
    return float(np.nanmean(arr)) if np.isfinite(arr).any() else float("nan")


def aggregate(per_sequence: dict[str, dict]) -> dict:
    """Official averaging (over sequences per step index, then over steps) of every metric of `metrics.METRICS` the
    sequences' tracks score, each reported where its role says, and the breakdowns. When every sequence is 2D-only
    (`score_sequence`'s "has_3d" False), the metrics, per-step values and per-sequence means hold the 2D track's alone
    and the breakdowns are empty; the 2D track of 3D sequences is scored when every one holds it; a mix of 3D and
    2D-only sequences is a UserError."""
    seqs = list(per_sequence.values())
    only_2d = {name: not s.get("has_3d", True) for name, s in sorted(per_sequence.items())}
    if len(set(only_2d.values())) > 1:
        raise UserError(mixed_problem(next(f"{n}.h5" for n, v in only_2d.items() if not v),
                                      next(f"{n}.h5" for n, v in only_2d.items() if v)))
    two_d = all(only_2d.values())
    tracks = ("2D",) if two_d else ("3D",) + (("2D",) if all(s["has_2d"] for s in seqs) else ())
    keys = metric_keys(tracks)
    steps = max(len(s[keys[0]]) for s in seqs)

    def by_step(key):
        table = np.full((len(seqs), steps), np.nan)
        for i, s in enumerate(seqs):
            table[i, : len(s[key])] = s[key]
        with np.errstate(all="ignore"):
            return [_mean(table[:, t]) for t in range(steps)]

    per_step = {k: by_step(k) for k in keys}
    metrics = {k: _mean(per_step[k]) for k in metric_keys(tracks, ("headline", "official"))}
    breakdowns = {}
    if not two_d:
        for values, count in OBJECT_IOUS:  # per-object IoUs, pooled over every object and step
            pooled = [v for s in seqs for step in s[values] for v in step]
            breakdowns.update({values: _mean(pooled) if pooled else None, count: len(pooled)})
        breakdowns.update({m.breakdown: _mean(per_step[m.key]) for m in METRICS if m.breakdown and m.track in tracks})
    headline = metric_keys(tracks, ("headline",))
    with np.errstate(all="ignore"):  # each sequence's mean over its steps: what paired comparisons need
        per_sequence_means = {name: {k: _mean(s[k]) for k in headline} for name, s in sorted(per_sequence.items())}
    return {"metrics": metrics, "per_step": per_step, "breakdowns": breakdowns, "per_sequence": per_sequence_means}


def checksum_of(files: Mapping[str, str]) -> str:
    """The predictions checksum: SHA-256 over the sorted lines `name:sha256` of the prediction files."""
    h = hashlib.sha256()
    for name in sorted(files):
        h.update(f"{name}:{files[name]}\n".encode())
    return h.hexdigest()


def scored_fields(metrics: Mapping[str, float]) -> tuple[str, ...]:
    """The scored ground-truth inputs (`dsr_bench.dataset.scored`) behind a results' metrics: the 3D ones for the
    3D metrics, the 2D ones where the 2D flow is scored; what `ground_truth_sha256` covers."""
    three_d = ("objects", "mask_3d", "tsdf", "scene_flow_3d", "visible_fraction") if "motion_full" in metrics else ()
    two_d = ("objects", "mask_2d", "scene_flow_2d") if "motion_2d" in metrics else ()
    return tuple(dict.fromkeys(three_d + two_d))


def expected_scored_checksum(split: str, metrics: Mapping[str, float], names) -> str | None:
    """The `ground_truth_sha256` that results with these metrics on the pinned sequences `names` of `split` have,
    from the toolkit's pin; None where the pin holds no scored digests for them."""
    from dsr_bench.dataset.splits import pinned_digests

    sequences = (pinned_digests().get(split) or {}).get("sequences") or {}
    fields = scored_fields(metrics)
    if not all("scored" in sequences.get(name, {}) for name in names):
        return None
    return scored_checksum({name: {f: sequences[name]["scored"][f] for f in fields if f in sequences[name]["scored"]}
                            for name in names})


def scored_checksum(truth: Mapping[str, Mapping[str, str]]) -> str:
    """SHA-256 over the sorted lines `name:{field: digest}` (canonical JSON) of the scored sequences' recomputed
    ground-truth digests (`dsr_bench.dataset.scored`): what the results were scored against."""
    h = hashlib.sha256()
    for name in sorted(truth):
        h.update(f"{name}:{json.dumps(dict(truth[name]), sort_keys=True)}\n".encode())
    return h.hexdigest()


def evaluate(pred_dir: str | Path, data_dir: str | Path, split: str | None = None, allow_partial: bool = False,
             workers: int = 0, progress: Callable[[int, int], None] | None = None, engine: Engine | None = None
             ) -> Evaluation:
    """Check and score a predictions directory against a split of a dataset. `progress(done, total)`: called once
    per sequence scored, as each finishes (the sequences that pass the structural checks). `engine`
    (`dsr_bench.engines`: Ray, SLURM) scores the sequences instead of `workers` local processes."""
    from dsr_bench.dataset.manifest import load_manifest, read_split, split_digest
    from dsr_bench.scoring.predictions import read_meta

    pred_dir, data_dir = require_predictions_dir(pred_dir), Path(data_dir)
    manifest = load_manifest(data_dir)
    split, names = read_split(data_dir, split)
    warning = pin_warning(manifest, split, data_dir)
    valid, problems = check_structure(pred_dir, data_dir, names)
    jobs = [(name, str(path), str(data_dir / f"{name}.h5")) for name, path in valid.items()]
    workers = workers or min(len(jobs), os.cpu_count() or 1)
    # in the order of jobs, whoever scores them: results bit-identical
    outcomes = (run_in_order(score_sequence, jobs, workers, progress) if engine is None
                else engine.map(score_sequence, jobs, progress, describe=lambda job: job[0]))
    scored, truth = {}, {}
    for name, found, values in outcomes:
        problems += [(f"{name}.h5", p) for p in found]
        if values is not None:
            truth[name] = values.pop("scored_digests")
            scored[name] = values
    # the ground truth as scored, recomputed while reading, against the toolkit's pin (never the files' attributes)
    verified, verify_warnings = verify_scored(split, names, truth, data_dir)
    real = None
    if warning is None and not verified and not verify_warnings:  # not a toolkit split: a real split's own pins?
        verified, verify_warnings, real = verify_real_scored(data_dir, split, names, truth, manifest)
    warnings = ([warning] if warning else verify_warnings) + _partial_2d_warning(scored)
    evaluation = Evaluation(problems=problems, warnings=warnings)
    if (problems and not allow_partial) or not scored:
        return evaluation
    meta = read_meta(pred_dir)[0]
    files = {name: file_sha256(pred_dir / f"{name}.h5") for name in sorted(scored)}
    scores = aggregate(scored)
    fields = scored_fields(scores["metrics"])
    results = {
        "format": RESULTS_FORMAT, "version": 1, "method": meta.get("name", pred_dir.name), "meta": meta,
        "split": split, "split_checksum": split_digest(manifest, split),
        # verified: a named split pinned here, scored inputs equal to the pin; no warning: its manifest matches too
        "pinned": warning is None and verified,
        "ground_truth_verified": verified,
        "ground_truth_sha256": scored_checksum({name: {f: d[f] for f in fields if f in d}
                                                for name, d in truth.items()}),
        "predictions_checksum": checksum_of(files), "predictions_sha256": files,
        "toolkit_version": __version__, "date": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "coverage": {"scored": len(scored), "expected": len(names), "partial": len(scored) < len(names)},
        **scores,
    }
    if real is not None:  # pinned (where verified) to the real split's own pins, not to the toolkit's
        results["real_split"] = real
    evaluation.results = results
    evaluation.per_sequence_steps = {name: {k: v for k, v in values.items() if k in results["per_step"]}
                                     for name, values in sorted(scored.items())}
    return evaluation
