"""Progress bars of the long commands (`validate` and `evaluate` per sequence, `train` per batch): a rich bar on
stderr when stderr is a terminal, and nothing at all otherwise (a pipe, a log file, a test), so what a script
reads is the same with or without them. One style everywhere; rich is imported only when a bar is shown."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager


def no_progress(done: int, total: int, note: str = "") -> None:
    """The callback when no bar is shown (also for callers that show none)."""


@contextmanager
def progress_bar(description: str, console=None) -> Iterator[Callable[..., None]]:
    """Yield a callback `progress(done, total, note="")` for the library's loops: it moves a transient rich bar
    on stderr (or on `console`, a rich Console) if that is a terminal, `note` (e.g. the loss) shown after the
    description, and does nothing otherwise."""
    from rich.console import Console

    console = console if console is not None else Console(stderr=True)
    if not console.is_terminal:
        yield no_progress
        return
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TimeRemainingColumn(), console=console, transient=True) as bar:
        task = bar.add_task(description, total=None)

        def progress(done: int, total: int, note: str = "") -> None:
            bar.update(task, completed=done, total=total, description=f"{description} {note}".rstrip())

        yield progress
