"""`dsr-bench leaderboard add`: a results file recomputed from its predictions (`dsr-bench evaluate`) or plans
(`dsr_bench.planning.verify.recompute_results`), refused in one line unless the recomputed results are pinned,
complete, a valid entry (`entries.check_entry`) and equal to the file in every field but date and label (its
toolkit_version this toolkit's); the method's name readable, a reference row's only with its provenance
(`provenance`), and like no other entry's (`names`). `board` builds the tables from what it writes.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from dsr_bench.atomic import check_writable, write_text
from dsr_bench.errors import UserError
from dsr_bench.leaderboard.entries import (PLAN_RESULTS_FORMAT, RESULTS_FORMAT, UnreadableJSON, check_entry,
                                           entry_identity, entry_name, first_difference, read_json, show)
from dsr_bench.leaderboard.names import confusable_with, name_problem
from dsr_bench.leaderboard.provenance import check_reference_predictions, claim_problem, reference_of


def add_entry(results_path: str | Path, root: str | Path = "leaderboard", label: str | None = None,
              predictions: str | Path | None = None, data: str | Path | None = None, plans: str | Path | None = None,
              tasks: str | Path | None = None, workers: int = 0) -> tuple[Path, bool]:
    """Recompute a results file from its predictions (`evaluate`) or plans (`planning.verify.recompute_results`),
    refuse it (UserError, one line, nothing written) unless the recomputed results are pinned, complete, a valid
    entry and equal to the file in every field but date and label, and write the recomputed
    results (plus `label`). Returns (the entry's file, whether it replaced the entry of the same method, split and
    predictions)."""
    path, root = Path(results_path), Path(root)
    try:
        submitted = read_json(path)
    except UnreadableJSON as exc:
        raise UserError(f"{path}: unreadable results file ({exc}); give the results JSON of "
                        "`dsr-bench evaluate --out` or `dsr-bench plan`") from None
    kind = submitted.get("format") if isinstance(submitted, dict) else None
    if kind not in (PLAN_RESULTS_FORMAT, RESULTS_FORMAT):
        raise UserError(f"{path} is not a dsr-bench results file (format {show(kind)}); produce it with "
                        "`dsr-bench evaluate --out` or `dsr-bench plan`")
    source, folder = ("plans", "planning") if kind == PLAN_RESULTS_FORMAT else ("predictions", "entries")
    _check_method_name(path, submitted.get("method"), root / folder, planning=source == "plans")  # before scoring
    if kind == PLAN_RESULTS_FORMAT:
        recomputed = _recompute_plans(path, plans, tasks, root, workers)
    else:
        recomputed, data = _recompute_predictions(path, submitted, predictions, data, root, workers)
    difference = first_difference(submitted, recomputed, source)
    if difference:
        again = "`dsr-bench plan`" if source == "plans" else "`dsr-bench evaluate`"
        raise UserError(f"{path}: {difference}; re-run {again} and add the results it writes")
    entry = {**recomputed, **({"label": label} if label else {})}
    # the file itself must be well formed too (its date and label were not compared)
    problems = check_entry(entry) or check_entry(submitted)
    if problems:
        raise UserError(f"{path} cannot join the leaderboard: {_first(problems)}")
    made_from = plans if source == "plans" else predictions
    assert made_from is not None  # the recomputation needed it
    _check_provenance(path, entry, Path(made_from), data)
    target, replaced = _entry_path(root / folder, entry)
    write_text(target, json.dumps(entry, indent=1, sort_keys=True) + "\n")
    return target, replaced


def _check_provenance(path: Path, entry: dict, made_from: Path, data) -> None:
    """UserError unless an entry of predictions named as a reference row (`provenance.reference_of`) is that row by
    provenance: its predictions those `dsr-bench predict --model NAME` writes (`made_from`: the predictions
    directory; `data`: the dataset they were scored on). A planning reference row's plans were replayed and its
    planner is the model that made them (`planning.verify.recompute_results`)."""
    planning = entry.get("format") == PLAN_RESULTS_FORMAT
    reference = reference_of(entry, planning)[0]
    if reference and not planning:
        check_reference_predictions(path, entry, made_from, Path(data), entry["split"], reference)


def _check_method_name(path: Path, method, folder: Path, planning: bool) -> None:
    """UserError unless `method` can be shown (`names.name_problem`), reads as a reference row only where it is
    exactly its name (`provenance.claim_problem`; the predictions or plans prove the rest) and reads like no entry of
    `folder` of another name (`names.confusable_with`: NFKC, look-alike letters, case, spaces, punctuation aside)."""
    if not isinstance(method, str):
        return  # not a results file's method: the comparison with the recomputed results names it
    problem = name_problem(method) or claim_problem(method, planning)
    if problem:
        raise UserError(f"{path}: {problem}")
    clash = confusable_with(method, (str(r.get("method")) for _, r in _existing(folder)))
    if clash is not None:
        raise UserError(f"{path}: method {ascii(method[:60])} reads like the entry {ascii(clash[:60])} already on the "
                        f"leaderboard (look-alike letters, case, spaces or punctuation aside); name it exactly "
                        f"{ascii(clash[:60])} if it is that method, else give it a name of its own (meta.json's name)")


def _first(problems: list[str]) -> str:
    return problems[0] + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else "")


def _recompute_predictions(path: Path, submitted: dict, predictions, data, root: Path,
                           workers: int) -> tuple[dict, Path]:
    """(the results of `evaluate` on the predictions, on the file's split: pinned and complete, else UserError; the
    dataset they were scored on)."""
    from dsr_bench.scoring.evaluate import evaluate
    from dsr_bench.scoring.predictions import infer_source

    if predictions is None:
        raise UserError(f"{path}: the leaderboard recomputes every score from the predictions and never reads one "
                        "from a results file; give --predictions PRED_DIR (the directory `dsr-bench evaluate` scored)")
    split = submitted.get("split")
    if not isinstance(split, str):
        raise UserError(f"{path}: split is {show(split)}, not a split's name; produce the results with "
                        "`dsr-bench evaluate`")
    check_writable(root / "entries", "--root")
    predictions = Path(predictions)
    if not predictions.is_dir():
        raise UserError(f"--predictions {predictions}: not a directory; give the predictions `dsr-bench evaluate` "
                        "scored")
    data, _, _ = infer_source(predictions, Path(data) if data is not None else None, split)  # split as given
    evaluation = evaluate(predictions, data, split, workers=workers)
    if evaluation.results is None:
        where, problem = evaluation.problems[0] if evaluation.problems else ("", "nothing scored")
        raise UserError(f"{predictions}: {len(evaluation.problems)} problems (first: {where}: {problem}); run "
                        f"`dsr-bench evaluate {predictions}` to see them all")
    results = json.loads(json.dumps(evaluation.results))  # as a results file holds it
    if results.get("pinned") is not True:
        why = evaluation.warnings[0] if evaluation.warnings else f"split {split!r} is not pinned in this toolkit"
        raise UserError(f"{path} cannot join the leaderboard: recomputed on {data}, its results are not pinned: {why}")
    if results["coverage"]["partial"]:
        raise UserError(f"{path} cannot join the leaderboard: the predictions cover only part of {split}")
    return results, data


def _recompute_plans(path: Path, plans, tasks, root: Path, workers: int) -> dict:
    """The planning results recomputed from the plan files, each replayed in `workers` processes (0: one per core),
    and the verified tasks: pinned and complete, else UserError."""
    from dsr_bench.planning.verify import recompute_results

    if plans is None:
        raise UserError(f"{path}: the leaderboard recomputes every planning score from the plan files and never reads "
                        "one from a results file; give --plans PLANS_DIR (the --out directory of `dsr-bench plan`)")
    check_writable(root / "planning", "--root")
    results = json.loads(json.dumps(recompute_results(Path(plans), tasks, workers=workers or os.cpu_count() or 1)))
    problems = check_entry(results)
    if problems:
        raise UserError(f"{path} cannot join the leaderboard: recomputed from {plans}, {_first(problems)}")
    return results


def _entry_path(folder: Path, entry: dict) -> tuple[Path, bool]:
    """Where an entry goes: the file already holding the same method, split and predictions (plans), replaced,
    or its own new file (`entries.entry_name`)."""
    identity = entry_identity(entry)
    for existing, old in _existing(folder):
        if entry_identity(old) == identity:
            return existing, True
    folder.mkdir(parents=True, exist_ok=True)
    return folder / entry_name(entry), False


def _existing(folder: Path) -> list[tuple[Path, dict]]:
    """The entry files of `folder` that hold a JSON object (valid or not), sorted by name."""
    found = []
    for path in sorted(folder.glob("*.json")):
        try:
            value = read_json(path)
        except UnreadableJSON:
            continue
        if isinstance(value, dict):
            found.append((path, value))
    return found
