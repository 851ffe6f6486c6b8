"""Per-sequence work in worker processes, with the outcomes in a fixed order and a progress callback
(`dsr-bench validate`, `dsr-bench evaluate`)."""

from __future__ import annotations

from collections.abc import Callable


def run_in_order(function, jobs: list, workers: int, progress: Callable[[int, int], None] | None = None,
                 mp_context=None) -> list:
    """`[function(j) for j in jobs]`, in `workers` processes when more than one (and more than one job), the
    outcomes in the order of `jobs` whatever order they finish in; `progress(done, total)` is called once per
    job as each finishes (done = 1..total)."""
    total = len(jobs)
    if workers > 1 and total > 1:
        from concurrent.futures import ProcessPoolExecutor, as_completed

        outcomes: list = [None] * total
        with ProcessPoolExecutor(min(workers, total), mp_context=mp_context) as pool:
            index = {pool.submit(function, job): i for i, job in enumerate(jobs)}
            for done, future in enumerate(as_completed(index), 1):
                outcomes[index[future]] = future.result()
                if progress is not None:
                    progress(done, total)
        return outcomes
    outcomes = []
    for done, job in enumerate(jobs, 1):
        outcomes.append(function(job))
        if progress is not None:
            progress(done, total)
    return outcomes
