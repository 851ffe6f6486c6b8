"""Leaderboard entries never trusted: validation of a results dict, its difference from a recomputed one, its file name.

`check_entry(results)` lists what keeps a results dict off the leaderboard, one short phrase per problem (an empty
list: nothing found). `dsr-bench leaderboard add` runs it on the results it recomputed (never on the submitted
file's numbers) before writing, and `leaderboard build` on every file of entries/ and planning/, skipping a file
it rejects. For `dsr-bench evaluate`'s results it checks schema and types (date a string, meta.parameters.grid a
list of positive ints, ...), ranges (IoUs in [0, 1], flow MSEs >= 0, metrics finite), coverage (complete, scored =
expected = per_sequence's count, never partial), consistency (each metric exactly the mean of its per-step values,
as `dsr_bench.scoring.evaluate.aggregate` computes it, and the mean of per_sequence; the moved/static breakdowns
likewise; a 3D result holds the four 3D metrics: one cut to motion_2d shows in its per-step, per-sequence values or
breakdowns), the split (a named split with a pin; `pinned` true exactly when split_checksum is that pin, then the
split's size and sequence names; another split's pin under its name is a relabelled result; an entry of an earlier
pin stays, shown apart; or a real split's test part pinned to its own pins, `real_split`) and, where present,
`predictions_sha256` against `predictions_checksum`. Planning results
(`dsr-bench plan`) are checked by `dsr_bench.planning.verify.check_results`, and must be pinned and complete. Both:
the method's name can be shown (`names.name_problem`) and reads as a reference row's only where it is that row by
provenance (`provenance.reference_of`).

Every untrusted JSON file of the leaderboard (a submitted results file, an entry) is read by
`dsr_bench.jsonfile.read_json`: whatever the file holds, its value or `UnreadableJSON` saying why in a few words.

`first_difference(submitted, recomputed)` names the first field where a submitted results file differs from the
results recomputed from its predictions (`date` and `label` excepted: `toolkit_version` must be this toolkit's, a
results file of another version is remade with this one). `entry_name` derives an
entry's file name from its method, split and predictions (or plans) checksum, so two entries never share a file
unless they are the same method on the same split with the same predictions.
"""

from __future__ import annotations

import hashlib
import html
import json
import math
import re

from dsr_bench import __version__
from dsr_bench.jsonfile import UnreadableJSON, read_json  # noqa: F401 - read here and by the board
from dsr_bench.leaderboard.names import name_problem
from dsr_bench.leaderboard.provenance import reference_of
from dsr_bench.scoring.evaluate import _mean as aggregate_mean, checksum_of, expected_scored_checksum
from dsr_bench.scoring.metrics import METRICS, OBJECT_IOUS, metric_keys

RESULTS_FORMAT = "dsr-bench-results"
PLAN_RESULTS_FORMAT = "dsr-bench-plan-results"
#: the keys of the table of metrics (`dsr_bench.scoring.metrics.METRICS`): the 3D track's headline and official ones
HEADLINE = metric_keys(("3D",), ("headline",))
OFFICIAL = metric_keys(("3D",), ("official",))
#: per-step values that have no metric of their own (the moved/static breakdowns are their means)
STEP_ONLY = metric_keys(roles=("breakdown",))
BREAKDOWNS = tuple(key for pair in OBJECT_IOUS for key in pair) + tuple(m.breakdown for m in METRICS if m.breakdown)
#: fields never compared between a submitted and a recomputed results file
UNCOMPARED = ("date", "label")
#: the order in which `first_difference` looks (the rest after these, sorted)
_FIRST = ("format", "version", "split", "task_set", "split_checksum", "task_checksum", "pinned",
          "ground_truth_verified", "coverage", "predictions_checksum", "plans_checksum", "predictions_sha256", "method",
          "metrics", "per_step", "per_sequence", "per_task", "breakdowns", "meta", "planner", "parameters")
_HEX64 = re.compile(r"[0-9a-f]{64}")
_FILE_NAME = re.compile(r"[^/\\\x00]{1,200}")  # a bare file name: no folder, no NUL
_DATE = re.compile(r"\d{4}-\d{2}-\d{2}")


def is_2d_only(metrics: dict) -> bool:
    """Whether a results file's metrics are a 2D-only submission's: none of the 3D track's, motion_2d present."""
    return isinstance(metrics, dict) and "motion_2d" in metrics and not any(k in metrics for k in HEADLINE)


def show(value, width: int = 40) -> str:
    """A value of an untrusted file for a one-line message: JSON, printable ASCII, at most `width` characters."""
    try:
        text = json.dumps(value, ensure_ascii=True, sort_keys=True)
    except (TypeError, ValueError):
        text = ascii(value)
    return text if len(text) <= width else text[: width - 3] + "..."


def _real(x) -> bool:
    """A JSON number (NaN and inf included), not a bool."""
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _finite(x) -> bool:
    return _real(x) and math.isfinite(x)


def _in_range(key: str, x) -> bool:
    """A finite value in its metric's range: an IoU in [0, 1], a flow MSE (or anything else) >= 0."""
    return _finite(x) and (0 <= x <= 1 if key.startswith("iou") else x >= 0)


def _value_problem(where: str, key: str, x, nan_ok: bool) -> str | None:
    if nan_ok and _nan(x):
        return None
    if _in_range(key, x):
        return None
    what = "an IoU in [0, 1]" if key.startswith("iou") else "a finite flow MSE >= 0"
    return f"{where} is {show(x)}, not {what}"


def _nan(x) -> bool:
    return x is None or (_real(x) and math.isnan(x))


def _same(a, b) -> bool:
    """JSON values equal: NaN equals NaN (and null, a per-step NaN), true is not 1, 1 is 1.0."""
    if _nan(a) and _nan(b):
        return True
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    if _real(a) and _real(b):
        return a == b
    return type(a) is type(b) and a == b


def step_mean(values: list) -> float:
    """`dsr_bench.scoring.evaluate._mean` of a per-step list (null read as NaN): the very computation `aggregate`
    made."""
    return aggregate_mean([float("nan") if v is None else v for v in values])


def check_entry(results) -> list[str]:
    """Problems that keep a results dict (of `dsr-bench evaluate` or `dsr-bench plan`) off the leaderboard."""
    if not isinstance(results, dict):
        return [f"not a results object but a JSON {type(results).__name__}; produce it with `dsr-bench evaluate`"]
    if results.get("format") == PLAN_RESULTS_FORMAT:
        return check_plan_entry(results)
    if results.get("format") != RESULTS_FORMAT:
        return [f"not a dsr-bench results file (format {show(results.get('format'))}); produce it with "
                "`dsr-bench evaluate`"]
    p = _check_fields(results)
    metrics = results.get("metrics")
    if not isinstance(metrics, dict) or not metrics:
        return p + ["metrics is not an object of numbers"]
    p += _check_track(results, metrics)
    p += _check_coverage(results)
    p += _check_split(results)
    return p + _check_name(results, planning=False)


def _check_name(results: dict, planning: bool) -> list[str]:
    """A method's name that cannot be shown, or that reads as a reference row's without its provenance
    (`provenance.reference_of`)."""
    method = results.get("method")
    if not isinstance(method, str):
        return []
    problem = name_problem(method) or reference_of(results, planning)[1]
    return [problem] if problem else []


def check_plan_entry(results: dict) -> list[str]:
    """Problems of a planning results dict as an entry: `dsr_bench.planning.verify.check_results`'s, plus pinned
    and complete."""
    from dsr_bench.planning.verify import check_results

    wrong = [k for k in ("method", "task_set", "split", "task_checksum", "split_checksum") if not isinstance(
        results.get(k), str)]
    if wrong:  # what check_results looks up by
        return [f"{wrong[0]} is {show(results.get(wrong[0]))}, not a string; produce the results with `dsr-bench plan`"]
    try:
        p = check_results(results)
    except (TypeError, ValueError, AttributeError, KeyError) as exc:  # a file the checker cannot read is not valid
        return [f"malformed planning results ({type(exc).__name__}: {' '.join(str(exc).split())[:80]})"]
    grid = (results.get("planner") or {}).get("grid") if isinstance(results.get("planner"), dict) else None
    if grid is not None and not (isinstance(grid, list) and len(grid) == 3 and all(
            isinstance(g, int) and not isinstance(g, bool) and g > 0 for g in grid)):
        p.append(f"planner.grid is {show(grid)}, not a list of 3 positive integers")
    planner: dict = results["planner"] if isinstance(results.get("planner"), dict) else {}
    if "weights" in planner and (problem := weights_problem(planner["weights"], "planner.weights")):
        p.append(problem)
    if results.get("pinned") is not True:
        p.append("its task set is not this toolkit's pinned one (pinned is not true); plan on a pinned task set "
                 "(`dsr-bench generate-plan-tasks --tasks plan-novel-test`)")
    coverage = results.get("coverage")
    if not isinstance(coverage, dict) or coverage.get("partial") is not False:
        p.append("it covers only part of the task set (coverage.partial is not false); run `dsr-bench plan` on "
                 "every task")
    if "label" in results and not isinstance(results["label"], str):
        p.append("label is not a string")
    return p + _check_name(results, planning=True)


def weights_problem(value, where: str) -> str | None:
    """Why a weights record (one object or a list of them, as predictions' meta.json parameters "weights" and a
    plan's planner "weights" hold them: source, file, sha256) is malformed, or None: each an object (or null), its
    file a bare file name and its sha256 a SHA-256 where they are given."""
    for record in value if isinstance(value, list) else [value]:
        if record is None:  # a model without a weights file (a planner's member)
            continue
        if not isinstance(record, dict):
            return f"{where} is {show(record)}, not an object (source, file, sha256)"
        file, sha = record.get("file"), record.get("sha256")
        if file is not None and not (isinstance(file, str) and _FILE_NAME.fullmatch(file) and file not in (".", "..")):
            return f"{where}.file is {show(file)}, not a file name"
        if sha is not None and not (isinstance(sha, str) and _HEX64.fullmatch(sha)):
            return f"{where}.sha256 is {show(sha)}, not a SHA-256 (64 lowercase hex digits)"
    return None


def _check_fields(r: dict) -> list[str]:
    """The scalar fields and meta: types and formats."""
    p = []
    if r.get("version") != 1 or isinstance(r.get("version"), bool):
        p.append(f"version is {show(r.get('version'))}, not 1")
    for key in ("method", "split", "split_checksum", "predictions_checksum", "toolkit_version", "date"):
        if not isinstance(r.get(key), str) or not r[key].strip():
            p.append(f"{key} is {show(r.get(key))}, not a string")
    if "ground_truth_sha256" in r and not (isinstance(r["ground_truth_sha256"], str) and
                                           _HEX64.fullmatch(r["ground_truth_sha256"])):
        p.append("ground_truth_sha256 is not a SHA-256")
    for key in ("split_checksum", "predictions_checksum"):
        if isinstance(r.get(key), str) and not _HEX64.fullmatch(r[key]):
            p.append(f"{key} is not a SHA-256 (64 lowercase hex digits)")
    if isinstance(r.get("date"), str) and not _DATE.match(r["date"]):
        p.append(f"date {show(r['date'])} is not an ISO date (YYYY-MM-DD...)")
    if isinstance(r.get("method"), str) and len(r["method"]) > 200:
        p.append("method is longer than 200 characters")
    if "label" in r and not isinstance(r["label"], str):
        p.append(f"label is {show(r['label'])}, not a string")
    for key in ("pinned", "ground_truth_verified"):
        if key in r and not isinstance(r[key], bool):
            p.append(f"{key} is {show(r[key])}, not true or false")
    if r.get("pinned") is True and r.get("ground_truth_verified") is False:
        p.append("pinned is true but ground_truth_verified is false")
    meta = r.get("meta", {})
    params = meta.get("parameters", {}) if isinstance(meta, dict) else {}
    if not isinstance(meta, dict) or not isinstance(params, dict):
        p.append("meta (or meta.parameters) is not an object")
    else:
        if "name" in meta and not isinstance(meta["name"], str):
            p.append("meta.name is not a string")
        for key, size in (("grid", 3), ("image", 2)):
            value = params.get(key)
            if value is not None and not (isinstance(value, list) and len(value) == size and
                                          all(isinstance(g, int) and not isinstance(g, bool) and g > 0 for g in value)):
                p.append(f"meta.parameters.{key} is {show(value)}, not a list of {size} positive integers")
        if "weights" in params and (problem := weights_problem(params["weights"], "meta.parameters.weights")):
            p.append(problem)
    sha = r.get("predictions_sha256")
    if sha is not None:
        if not isinstance(sha, dict) or not sha or not all(isinstance(v, str) and _HEX64.fullmatch(v)
                                                            for v in sha.values()):
            p.append("predictions_sha256 is not an object of SHA-256s")
        else:
            if checksum_of(sha) != r.get("predictions_checksum"):
                p.append("predictions_checksum is not the checksum of predictions_sha256")
            if isinstance(r.get("per_sequence"), dict) and set(sha) != set(r["per_sequence"]):
                p.append("predictions_sha256 and per_sequence name different sequences")
    return p


def _check_track(r: dict, metrics: dict) -> list[str]:
    """Metrics, per-step values, per-sequence means and breakdowns: complete for the track, in range, consistent."""
    two_d = is_2d_only(metrics)
    steps, seqs, breakdowns = r.get("per_step"), r.get("per_sequence"), r.get("breakdowns")
    if not isinstance(steps, dict) or not steps:
        return ["per_step is not an object of per-step values (each metric is checked against them)"]
    if not all(isinstance(v, list) and v for v in steps.values()) or len({len(v) for v in steps.values()}) != 1:
        return ["per_step is not lists of equal length, one per metric"]
    if two_d:  # a genuine 2D-only result holds motion_2d alone, everywhere
        held = set(steps) | {k for s in (seqs.values() if isinstance(seqs, dict) else ()) if isinstance(s, dict)
                             for k in s}
        held |= set(breakdowns) if isinstance(breakdowns, dict) else {"breakdowns"} if breakdowns else set()
        shown = sorted(held - {"motion_2d"})
        if set(metrics) != {"motion_2d"} or shown:
            return [f"a 3D result cut down to motion_2d (it holds {', '.join(shown[:3]) or show(sorted(metrics))}"
                    "): a 2D-only result holds motion_2d alone and empty breakdowns"]
        allowed = {"motion_2d"}
        seq_keys: tuple[str, ...] = ("motion_2d",)
    else:
        missing = [k for k in HEADLINE if k not in metrics]
        if missing:
            return [f"metrics missing: {', '.join(missing)} (a 3D result holds all four; a 2D-only one motion_2d "
                    "alone)"]
        allowed = set(HEADLINE + OFFICIAL + metric_keys(("2D",)))
        seq_keys = HEADLINE + (("motion_2d",) if "motion_2d" in metrics else ())
    unknown = sorted(set(metrics) - allowed) + sorted(set(steps) - allowed - set(STEP_ONLY))
    if unknown:
        return [f"unknown metrics: {show(unknown)}"]
    found = [_value_problem(f"metrics.{key}", key, value, nan_ok=False) for key, value in metrics.items()]
    for key, values in steps.items():
        bad = next((x for x in values if _value_problem("", key, x, nan_ok=True)), None)
        if bad is not None:
            found.append(_value_problem(f"a value of per_step.{key}", key, bad, nan_ok=True))
    p = [x for x in found if x]
    if p:  # the means below need numbers
        return p
    for key, value in metrics.items():
        if key not in steps:
            p.append(f"metrics.{key} has no per_step.{key} to be the mean of")
        elif not _same(value, step_mean(steps[key])):
            p.append(f"metrics.{key} is {show(value)} but the mean of per_step.{key} is {show(step_mean(steps[key]))}")
    if "motion_2d" in steps and "motion_2d" not in metrics:
        p.append("per_step.motion_2d without metrics.motion_2d")
    if not two_d:
        p += _check_breakdowns(breakdowns, steps)
    if seqs is not None:
        p += _check_per_sequence(seqs, seq_keys, metrics, steps)
    return p


def _check_breakdowns(b, steps: dict) -> list[str]:
    if not isinstance(b, dict) or set(b) != set(BREAKDOWNS):
        return [f"breakdowns is not the six of a 3D result ({', '.join(BREAKDOWNS)})"]
    p = []
    for iou, count in (("iou_occluded_objects", "occluded_object_steps"),
                       ("iou_visible_objects", "visible_object_steps")):
        n = b[count]
        if not isinstance(n, int) or isinstance(n, bool) or n < 0:
            p.append(f"breakdowns.{count} is {show(n)}, not a count")
        elif (b[iou] is None) != (n == 0) or (b[iou] is not None and not _in_range(iou, b[iou])):
            p.append(f"breakdowns.{iou} is {show(b[iou])}, not an IoU in [0, 1] (null only for 0 {count})")
    for key, step in (("motion_moved_objects", "motion_moved"), ("motion_static_objects", "motion_static")):
        if step not in steps:
            p.append(f"breakdowns.{key} has no per_step.{step} to be the mean of")
        elif not _same(b[key], step_mean(steps[step])):
            p.append(f"breakdowns.{key} is {show(b[key])} but the mean of per_step.{step} is "
                     f"{show(step_mean(steps[step]))}")
    return p


def _check_per_sequence(seqs, keys: tuple, metrics: dict, steps: dict) -> list[str]:
    if not isinstance(seqs, dict) or not seqs or not all(isinstance(s, dict) for s in seqs.values()):
        return ["per_sequence is not an object of per-sequence means"]
    p = []
    for name, s in seqs.items():
        if set(s) != set(keys):
            return [f"per_sequence.{show(name)} holds {show(sorted(s))}, not {show(list(keys))}"]
        labelled = (_value_problem(f"per_sequence.{show(name)}.{k}", k, s[k], nan_ok=True) for k in keys)
        problem = next((q for q in labelled if q), None)
        if problem is not None:
            return [problem]
    for key in keys:  # every sequence of a named split has the same steps: the two means agree
        values, per_step = [s[key] for s in seqs.values()], steps.get(key, [])
        if all(_finite(v) for v in values) and all(_finite(v) for v in per_step) and _finite(metrics.get(key)):
            mean = math.fsum(values) / len(values)
            if abs(mean - metrics[key]) > 1e-9 * max(1.0, abs(metrics[key])):
                p.append(f"metrics.{key} is {show(metrics[key])} but the mean of per_sequence is {show(mean)}")
    return p


def _check_coverage(r: dict) -> list[str]:
    c = r.get("coverage")
    if not isinstance(c, dict) or set(c) != {"scored", "expected", "partial"}:
        return ["coverage is not {scored, expected, partial}; produce the results with `dsr-bench evaluate`"]
    if not all(isinstance(c[k], int) and not isinstance(c[k], bool) and c[k] > 0 for k in ("scored", "expected")):
        return [f"coverage {show(c)} does not count sequences"]
    p = []
    if c["partial"] is not False or c["scored"] != c["expected"]:
        p.append(f"partial evaluation (coverage {c['scored']}/{c['expected']}, partial {show(c['partial'])}): the "
                 "leaderboard needs every sequence of the split")
    seqs = r.get("per_sequence")
    if isinstance(seqs, dict) and len(seqs) != c["scored"]:
        p.append(f"coverage says {c['scored']} sequences scored but per_sequence holds {len(seqs)}")
    return p


def _check_split(r: dict) -> list[str]:
    """The split: named, pinned in this toolkit, `pinned` consistent with its pin, the split's size and names."""
    from dsr_bench.dataset.splits import SPLITS, pinned_digests

    split, checksum, pinned = r.get("split"), r.get("split_checksum"), r.get("pinned")
    if "real_split" in r:
        return _check_real_split(r)
    if not isinstance(split, str) or split not in SPLITS:
        return [f"split {show(split)} is not one of the benchmark's named splits"]
    spec = SPLITS[split]
    if spec.role == "val":
        return [f"split {split!r} is a validation split (where training choices are made); it is never ranked: "
                "score a test split"]
    expected = spec.expected_digest
    if expected is None:
        return [f"split {split!r} has no pinned checksum in this toolkit version; it cannot be ranked"]
    others = [name for name, s in SPLITS.items() if name != split and s.expected_digest == checksum]
    if others:
        return [f"split_checksum is the pin of {others[0]}, not of {split} (a result relabelled as another split)"]
    if checksum != expected:
        if pinned is True and r.get("toolkit_version") == __version__:
            return [f"pinned is true but split_checksum {str(checksum)[:12]}... is not this toolkit's pin "
                    f"{expected[:12]}... of {split}"]
        return []  # an entry of an earlier pin of the split: kept, in a table of its own, unranked
    p = []
    if pinned is not True:
        p.append(f"pinned is {show(pinned)} but split_checksum is this toolkit's pin of {split}")
    pin = pinned_digests().get(split) or {}
    names = pin.get("sequences") if pin.get("checksum") == expected else None  # the pin's sequences, where known
    count = len(names) if names else spec.num_sequences
    coverage = r.get("coverage")
    if not isinstance(coverage, dict):
        coverage = {}
    if coverage.get("expected") != count:
        p.append(f"coverage expects {show(coverage.get('expected'))} sequences but {split} has {count}")
    seqs = r.get("per_sequence")
    if names and isinstance(seqs, dict) and set(seqs) != set(names):
        p.append(f"per_sequence names sequences that are not those of {split}")
    if names and isinstance(r.get("ground_truth_sha256"), str) and isinstance(r.get("metrics"), dict):
        want = expected_scored_checksum(split, r["metrics"], sorted(names))
        if want is not None and r["ground_truth_sha256"] != want:
            p.append(f"ground_truth_sha256 is not that of the pinned {split}'s ground truth (the scored digests "
                     "this toolkit pins)")
    return p


def _check_real_split(r: dict) -> list[str]:
    """A real split's entry (`dsr_bench.dataset.real`): scored on the test part of a real split, pinned to its own
    pins (`pinned` true: `evaluate` verified the ground truth against them), its record consistent with the results
    (the split's name, checksum and size). What the pins are worth is the split's checksum: rows of real splits of
    the same name but another checksum are other tables."""
    from dsr_bench.dataset.real import part_split
    from dsr_bench.dataset.splits import SPLITS

    real, split = r["real_split"], r.get("split")
    if not isinstance(real, dict) or not all(isinstance(real.get(k), str) for k in ("name", "part", "checksum")) \
            or not isinstance(real.get("sequences"), int):
        return ["real_split is not {name, part, pins, checksum, sequences}; produce the results with `dsr-bench "
                "evaluate` on a real split"]
    if real["part"] != "test":
        return [f"scored on the real split's {real['part']} part ({show(split)}); the leaderboard ranks its held-out "
                f"test part ({part_split(real['name'], 'test')})"]
    if split in SPLITS or split != part_split(real["name"], "test"):
        return [f"split {show(split)} is not the test part of the real split {show(real['name'])}"]
    p = []
    if r.get("pinned") is not True:
        p.append(f"pinned is {show(r.get('pinned'))}: the ground truth was not verified against the real split's own "
                 "pins (`dsr-bench validate` the split, or rebuild it)")
    if r.get("split_checksum") != real["checksum"]:
        p.append("split_checksum is not the checksum of the real split's pins")
    coverage = r["coverage"] if isinstance(r.get("coverage"), dict) else {}
    if coverage.get("expected") != real["sequences"]:
        p.append(f"coverage expects {show(coverage.get('expected'))} sequences but the real split's test part has "
                 f"{real['sequences']}")
    return p


def first_difference(submitted, recomputed: dict, source: str = "predictions") -> str | None:
    """The first field (`_FIRST` order, then sorted; depth first) where `submitted` differs from `recomputed` (the
    results recomputed from the `source`: predictions or plans), as one phrase naming it and both values; None when
    they agree on every field but `UNCOMPARED`."""
    if not isinstance(submitted, dict):
        return f"it is a JSON {type(submitted).__name__}, not a results object"
    top = [k for k in _FIRST if k in submitted or k in recomputed]
    top += sorted((set(submitted) | set(recomputed)) - set(top) - set(UNCOMPARED), key=str)
    return _difference(submitted, recomputed, top, "", source)


def _difference(a: dict, b: dict, keys, prefix: str, source: str) -> str | None:
    for key in keys:
        name = f"{prefix}{key}"
        if key not in b:
            return f"{name} is {show(a[key])} but the {source} give no {name}"
        if key not in a:
            return f"{name} is missing but the {source} score {show(b[key])}"
        found = _differ(a[key], b[key], name, source)
        if found:
            return found
    return None


def _differ(a, b, name: str, source: str) -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        return _difference(a, b, sorted(set(a) | set(b), key=str), f"{name}.", source)
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{name} holds {len(a)} values but the {source} give {len(b)}"
        return next((d for i, (x, y) in enumerate(zip(a, b)) if (d := _differ(x, y, f"{name}[{i}]", source))), None)
    return None if _same(a, b) else f"{name} is {show(a)} but the {source} score {show(b)}"


def entry_identity(results: dict) -> tuple:
    """What makes two entries the same entry: the method, its split (task set) and its predictions' (plans')
    checksum."""
    if results.get("format") == PLAN_RESULTS_FORMAT:
        return ("plan", results.get("method"), results.get("task_set"), results.get("plans_checksum"))
    return ("results", results.get("method"), results.get("split"), results.get("predictions_checksum"))


def entry_name(results: dict) -> str:
    """The entry's file name: readable method and split, and 12 hex digits of a hash of its exact identity, so
    `Static!`, `static` and the reference `static` entry never share a file."""
    _, method, split, checksum = entry_identity(results)
    slug = re.sub(r"[^a-z0-9]+", "-", f"{str(method)[:40]}".lower()).strip("-") or "entry"
    where = re.sub(r"[^a-z0-9]+", "-", str(split).lower()).strip("-")
    key = hashlib.sha256(json.dumps([method, split, checksum]).encode()).hexdigest()[:12]
    return f"{slug}-{where}-{key}.json"


_MARKDOWN = re.compile(r"([\\`*\[\]|~])")


def markdown_cell(text) -> str:
    """`text` as the content of one markdown table cell, shown as written: one line, HTML tags escaped as
    entities, `|` and markdown's emphasis, link and code characters escaped (an underscore only where it could
    start or end emphasis, so snake_case reads as written)."""
    line = " ".join(str(text).split())  # newlines and other whitespace runs: one space
    line = "".join(c if c.isprintable() else " " for c in line)
    line = _MARKDOWN.sub(r"\\\1", html.escape(line, quote=False))
    return re.sub(r"(?<![A-Za-z0-9])_|_(?![A-Za-z0-9])", r"\\_", line)
