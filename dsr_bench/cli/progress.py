"""Progress bars of the commands that go through a dataset sequence by sequence (`validate`, `evaluate`): a rich
bar on stderr when stderr is a terminal, and nothing at all otherwise (a pipe, a log file, a test), so what a
script reads is the same with or without them. Not a command module: `dsr_bench.cli` registers none from it."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager


def _nothing(done: int, total: int) -> None:
    """The callback when no bar is shown."""


@contextmanager
def progress_bar(description: str, console=None) -> Iterator[Callable[[int, int], None]]:
    """Yield a callback `progress(done, total)` for the library's per-sequence loops: it moves a transient rich
    bar on stderr (or on `console`, a rich Console) if that is a terminal, and does nothing otherwise."""
    from rich.console import Console

    console = console if console is not None else Console(stderr=True)
    if not console.is_terminal:
        yield _nothing
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, \
        TimeRemainingColumn

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TimeRemainingColumn(), console=console, transient=True) as bar:
        task = bar.add_task(description, total=None)
        yield lambda done, total: bar.update(task, completed=done, total=total)
