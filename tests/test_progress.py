"""Progress of `validate` and `evaluate`: the library calls back once per sequence as each finishes, with results
identical (and in the same order) to a run without it, serial or in worker processes; the CLI shows a bar only when
stderr is a terminal, so its output without one (pipes, logs, these tests) is unchanged."""

import contextlib
import io

import pytest
from rich.console import Console

import dsr_bench.progress as progress_module
from dsr_bench.cli import main
from dsr_bench.progress import progress_bar
from dsr_bench.dataset.validate import validate_dataset
from dsr_bench.parallel import run_in_order
from dsr_bench.scoring.evaluate import evaluate
from dsr_bench.testing import write_synthetic_dataset


@pytest.fixture(scope="module")
def scored(tmp_path_factory):
    root = tmp_path_factory.mktemp("progress")
    data = write_synthetic_dataset(root / "data", num_sequences=3, num_steps=2)
    assert main(["predict", "--model", "static", "--data", str(data), "--out", str(root / "pred")]) == 0
    return data, root / "pred"


def _square(x: int) -> int:
    return x * x


@pytest.mark.parametrize("workers", [1, 2])
def test_run_in_order_keeps_the_order_and_calls_back_once_per_job(workers):
    calls = []
    outcomes = run_in_order(_square, list(range(7)), workers, lambda d, t: calls.append((d, t)))
    assert outcomes == [x * x for x in range(7)]
    assert calls == [(d, 7) for d in range(1, 8)]
    assert run_in_order(_square, [], workers, lambda d, t: calls.append((d, t))) == [] and len(calls) == 7


def _without_date(results: dict) -> dict:
    return {k: v for k, v in results.items() if k != "date"}


@pytest.mark.parametrize("workers", [1, 2])
def test_evaluate_calls_back_once_per_sequence_and_scores_the_same(scored, workers):
    data, pred = scored
    calls = []
    with_progress = evaluate(pred, data, workers=workers, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(1, 3), (2, 3), (3, 3)]
    without = evaluate(pred, data, workers=1)
    assert _without_date(with_progress.results) == _without_date(without.results)  # exactly, in the same order
    assert list(with_progress.results["per_sequence"]) == list(without.results["per_sequence"])


@pytest.mark.parametrize("workers", [1, 2])
def test_validate_calls_back_once_per_sequence_and_finds_the_same(scored, workers):
    data, _ = scored
    calls = []
    found = validate_dataset(data, check_gt=False, workers=workers, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(1, 3), (2, 3), (3, 3)]
    assert found == validate_dataset(data, check_gt=False, workers=1)


@contextlib.contextmanager
def _no_bar(description, console=None):
    yield lambda done, total: None


@pytest.mark.parametrize("argv", [["validate", "{data}", "--no-gt"], ["evaluate", "{pred}", "--data", "{data}"],
                                  ["evaluate", "{pred}", "--data", "{data}", "--workers", "2"]])
def test_output_without_a_terminal_is_unchanged(scored, capsys, monkeypatch, argv):
    data, pred = scored
    argv = [a.format(data=data, pred=pred) for a in argv]
    assert main(argv) == 0
    shown = capsys.readouterr()
    monkeypatch.setattr(progress_module, "progress_bar", _no_bar)  # what the commands printed before the bars
    assert main(argv) == 0
    assert capsys.readouterr() == shown
    assert "\x1b[" not in shown.err and "\r" not in shown.err


def test_the_bar_shows_on_a_terminal_and_nothing_elsewhere():
    screen = io.StringIO()
    with progress_bar("evaluate", Console(file=screen, force_terminal=True, width=100)) as progress:
        for done in range(1, 4):
            progress(done, 3)
    assert "evaluate" in screen.getvalue() and "3/3" in screen.getvalue()
    pipe = io.StringIO()
    with progress_bar("evaluate", Console(file=pipe)) as progress:  # not a terminal
        progress(1, 1)
    assert pipe.getvalue() == ""
