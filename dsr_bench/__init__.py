"""dsr-bench: the dataset and benchmark toolkit for 3D dynamic scene representations (DSR).

The public API is what this module exports (`__all__`); everything else is importable from its own module but may
change between versions. Each name is imported on first use (PEP 562), so `import dsr_bench` costs nothing and
names needing torch (`load_predictor`'s learned models, the window datasets) or rerun (`view`) import them only then:

    from dsr_bench import SequenceReader, write_predictions, evaluate

- sequences: `SequenceReader` (lazy reader of one sequence file), `write_sequence` (schema-checked atomic
  writer, digests computed), `validate_sequence`, `validate_dataset`
- splits: `SPLITS` (the named splits, name -> `Split`), `get_split`
- predictions and scores: `write_predictions` (the contract, checked, atomic), `evaluate` (-> `Evaluation`)
- models: `load_predictor` (a reference or learned model by name -> `Predictor`)
- PyTorch: `SequenceWindowDataset`, `OfficialWindowDataset` (windows of consecutive pushes, torch)
- viewer: `view` (a sequence, with predictions, in rerun)
- planning: `verify_tasks` (tasks against their pins), `recompute_results` (a plan run's results, replayed)
- `UserError` (every error of bad input: one line naming it and the fix), `__version__`
"""

from __future__ import annotations

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any

try:
    __version__ = version("dsr-bench")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.3.0"

#: name -> the module it lives in (imported on first use)
_HOMES = {
    "UserError": "dsr_bench.errors",
    "SequenceReader": "dsr_bench.dataset.sequence",
    "write_sequence": "dsr_bench.dataset.sequence",
    "validate_sequence": "dsr_bench.dataset.validate",
    "validate_dataset": "dsr_bench.dataset.validate",
    "SPLITS": "dsr_bench.dataset.splits",
    "Split": "dsr_bench.dataset.splits",
    "get_split": "dsr_bench.dataset.splits",
    "write_predictions": "dsr_bench.scoring.predictions",
    "evaluate": "dsr_bench.scoring.evaluate",
    "Evaluation": "dsr_bench.scoring.evaluate",
    "load_predictor": "dsr_bench.models.predictors",
    "Predictor": "dsr_bench.models.predictors",
    "SequenceWindowDataset": "dsr_bench.models.data",
    "OfficialWindowDataset": "dsr_bench.models.data",
    "view": "dsr_bench.viewer",
    "verify_tasks": "dsr_bench.planning.verify",
    "recompute_results": "dsr_bench.planning.verify",
}

__all__ = [
    "__version__", "UserError",
    "SequenceReader", "write_sequence", "validate_sequence", "validate_dataset",
    "SPLITS", "Split", "get_split",
    "write_predictions", "evaluate", "Evaluation",
    "load_predictor", "Predictor", "SequenceWindowDataset", "OfficialWindowDataset",
    "view",
    "verify_tasks", "recompute_results",
]

if TYPE_CHECKING:  # what type checkers and editors see; at run time __getattr__ imports each on use
    from dsr_bench.dataset.sequence import SequenceReader, write_sequence
    from dsr_bench.dataset.splits import SPLITS, Split, get_split
    from dsr_bench.dataset.validate import validate_dataset, validate_sequence
    from dsr_bench.errors import UserError
    from dsr_bench.models.data import OfficialWindowDataset, SequenceWindowDataset
    from dsr_bench.models.predictors import Predictor, load_predictor
    from dsr_bench.planning.verify import recompute_results, verify_tasks
    from dsr_bench.scoring.evaluate import Evaluation, evaluate
    from dsr_bench.scoring.predictions import write_predictions
    from dsr_bench.viewer import view


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(home), name)
    globals()[name] = value  # once: later lookups do not come here
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
