"""Reference rows by provenance, never by name: a row is the reference row static (push, oracle; in planning random,
oracle) only when the toolkit made what it scored, and no other row may read like one.

`leaderboard add` establishes it: a results entry whose method reads as a reference row (`names.reference_claim`:
look-alike letters, case, spaces, punctuation, notes and -cpu suffixes aside) must be named exactly that row, and
its predictions must be exactly those `dsr-bench predict --model NAME` writes for every sequence, with its
meta.json's name, description and parameters (`check_reference_predictions`, predicted again here); planning results
named random or oracle must come from plans that planner made: every plan is replayed in the simulator, its
candidates drawn again from its seeds, and its planner is the model that made it
(`dsr_bench.planning.verify.recompute_results`, `dsr_bench.planning.replay`).
`reference_of` is what `entries.check_entry` and `build` read back from an entry, which `add` wrote only after
those checks: the reference row it is (its method exactly that row's name, and what the entry records of its
making not contradicting it: meta.name and meta.parameters those `dsr-bench predict` writes for the toolkit's
predictor, the planner's name and description), or the problem that keeps a row reading as one without being one
off the leaderboard. `build` cannot predict again (it has no data): an entry file edited by hand in the repository
with a reference row's exact name and record is taken as written, as its numbers are (docs/evaluation.md).
"""

from __future__ import annotations

from pathlib import Path

from dsr_bench.errors import UserError
from dsr_bench.leaderboard.names import reference_claim

#: the reference rows of each kind of entry: `dsr-bench predict --model NAME`'s (`models.registry`), the planners'
PREDICTION_REFERENCES = ("static", "push", "oracle")
PLANNING_REFERENCES = ("random", "oracle")
_FIX = "give your method another name (meta.json's name)"
_FIX_PLANS = "give your planner another name (the plan files' planner)"


def reference_parameters(model: str) -> dict:
    """meta.json's parameters that `dsr-bench predict --model MODEL` writes for a reference model."""
    from dsr_bench.constants import GRID_SHAPE
    from dsr_bench.models import registry

    predictor = registry.model_entry(model).make_predictor()
    return {"num_slots": predictor.num_slots, "grid": list(GRID_SHAPE)}


def _object(results: dict, key: str) -> dict:
    """results[key] where it is a JSON object, else {}."""
    value = results.get(key)
    return value if isinstance(value, dict) else {}


def _planner_descriptions() -> dict[str, str]:
    from dsr_bench.planning.planners import OraclePlanner, RandomPlanner

    return {"random": RandomPlanner.description, "oracle": OraclePlanner.description}


def claim_problem(method: str, planning: bool) -> str | None:
    """Why `method` cannot be an entry's name by itself, as a phrase: it reads as a reference row
    (`names.reference_claim`) of the other track, or that no entry can be (no push), or without being exactly its
    name; None otherwise. `planning`: the name of `dsr-bench plan` results."""
    claim = reference_claim(method)
    if claim is None:
        return None
    shown, fix = ascii(method[:60]), _FIX_PLANS if planning else _FIX
    if claim not in (PLANNING_REFERENCES if planning else PREDICTION_REFERENCES):
        whose = ("the tasks' start states" if claim == "no push" else
                 f"the {'planning' if claim == 'random' else 'predictions'} track's")
        return f"method {shown} reads as the reference row {claim!r} ({whose}), which no entry can be; {fix}"
    if method != claim:
        return (f"method {shown} reads as the reference row {claim!r} (look-alike letters, case, spaces or "
                f"punctuation aside) without being it: only the toolkit's own {claim} is that row; {fix}")
    return None


def reference_of(results: dict, planning: bool) -> tuple[str, str | None]:
    """(the reference row an entry is by provenance, "" for none; the problem of an entry whose method reads as a
    reference row without being it, or None). `planning`: a `dsr-bench plan` results dict, else `evaluate`'s."""
    method = results.get("method")
    if not isinstance(method, str):
        return "", None
    claim = reference_claim(method)
    if claim is None:
        return "", None
    problem = claim_problem(method, planning)
    if problem:
        return "", problem
    if planning:  # the record of the plans: the planner's name and description, where the entry holds them
        planner, description = _object(results, "planner"), _planner_descriptions()[claim]
        if planner.get("name", claim) != claim or planner.get("description", description) != description:
            why = f"its plans (planner name, description) are not the {claim} planner's"
            return "", f"method {claim!r} names a reference row, but {why}; {_FIX_PLANS}"
        return claim, None
    meta, parameters = _object(results, "meta"), reference_parameters(claim)  # the record of the predictions
    if meta.get("name", claim) != claim or meta.get("parameters", parameters) != parameters:
        return "", (f"method {claim!r} is named like the reference row {claim!r}, but its meta (name, parameters) is "
                    f"not what `dsr-bench predict --model {claim}` writes; {_FIX}")
    return claim, None


def check_reference_predictions(path: Path, results: dict, predictions: Path, data: Path, split: str,
                                model: str) -> None:
    """UserError unless every prediction file holds exactly the arrays `dsr-bench predict --model MODEL` writes for
    it and `results`' meta its name, description and parameters (predicted again here): a reference row's name is
    the toolkit's to give, never a submitter's."""
    import json
    import tempfile

    import h5py
    import numpy as np

    from dsr_bench.dataset.manifest import read_split
    from dsr_bench.models.predictors import load_predictor, predict_split

    _, names = read_split(data, split)
    with tempfile.TemporaryDirectory(prefix="dsr-bench-reference-") as tmp:
        predict_split(load_predictor(model), data, names, tmp)
        want_meta = json.loads((Path(tmp) / "meta.json").read_text())
        meta = _object(results, "meta")
        differs = next((k for k in ("name", "description", "parameters") if meta.get(k) != want_meta.get(k)), None)
        if differs is not None:
            raise UserError(f"{path}: its method is named like the reference row {model!r}, but meta.json's {differs} "
                            f"is not what `dsr-bench predict --model {model}` writes; {_FIX}")
        for name in names:
            with h5py.File(Path(tmp) / f"{name}.h5", "r") as want, h5py.File(predictions / f"{name}.h5", "r") as got:
                same = set(want) == set(got) and want.attrs.get("num_slots") == got.attrs.get("num_slots") and all(
                    want[k].dtype == got[k].dtype and np.array_equal(want[k][()], got[k][()]) for k in want)
            if not same:
                raise UserError(f"{path}: its method is named like the reference row {model!r}, but "
                                f"{predictions / (name + '.h5')} is not what `dsr-bench predict --model {model}` "
                                f"writes; {_FIX}")
