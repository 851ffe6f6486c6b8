"""Per-sequence work in worker processes, with the outcomes in a fixed order and a progress callback
(`dsr-bench validate`, `dsr-bench evaluate`, `dsr-bench generate`). `dsr_bench.engines` runs the same jobs on a
Ray cluster or a SLURM array, through `in_order` too."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator

from dsr_bench.memory import keep_freed_memory


def as_finished(function, jobs: list, workers: int, mp_context=None) -> Iterator[tuple[int, object]]:
    """(position, `function(jobs[position])`) for every job, in the order they finish: in `workers` processes when
    more than one (and more than one job), else here, one after the other. An exception of a job is raised here."""
    if workers > 1 and len(jobs) > 1:
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=mp_context, initializer=keep_freed_memory) as pool:
            index = {pool.submit(function, job): i for i, job in enumerate(jobs)}
            for future in as_completed(index):
                yield index[future], future.result()
        return
    for position, job in enumerate(jobs):
        yield position, function(job)


def in_order(finished: Iterable[tuple[int, object]], total: int,
             progress: Callable[[int, int], None] | None = None) -> list:
    """The outcomes of `finished` ((position, outcome) pairs, any order, positions 0..total-1) in the order of
    their positions; `progress(done, total)` is called once per outcome as it arrives (done = 1..total)."""
    outcomes: list = [None] * total
    for done, (position, outcome) in enumerate(finished, 1):
        outcomes[position] = outcome
        if progress is not None:
            progress(done, total)
    return outcomes


def run_in_order(function, jobs: list, workers: int, progress: Callable[[int, int], None] | None = None,
                 mp_context=None) -> list:
    """`[function(j) for j in jobs]`, in `workers` processes when more than one (and more than one job), the
    outcomes in the order of `jobs` whatever order they finish in; `progress(done, total)` is called once per
    job as each finishes (done = 1..total)."""
    return in_order(as_finished(function, jobs, workers, mp_context), len(jobs), progress)
