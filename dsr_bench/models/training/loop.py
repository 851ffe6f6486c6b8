"""The one training loop. `run_steps` drives a step function over batches: every track trains through it
(the full track's epochs in `trainer.train`, the CPU track's two stages in `cpu_track`, the 2D track in
`image_track`). A step takes (model, batch, optimizer) and returns the loss terms of each of the batch's
time steps as floats, read from the device once, at its end (`trainer.train_step` for DSR-Net and its
baselines, `image_track.image_step`); a window that cannot be trained is a `WindowError`.

`fit` is a recipe's stage (the CPU-sized tracks): Adam (betas 0.9, 0.95) at `lr`, halved at 50% and again
at 75% of the batches (the paper's step decay, in batches), a report every 100 batches, and the mean loss
terms of the first and last tenth.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator

import numpy as np
import torch

from dsr_bench.models.loss import MaskIdError

__all__ = ["WindowError", "fit", "run_steps"]

#: a training step: (model, batch, optimizer) -> the loss terms of each time step (floats)
Step = Callable[[torch.nn.Module, dict, torch.optim.Optimizer], list[dict]]


class WindowError(Exception):
    """A window `run_steps` could not train: an object id beyond the model's slots or a non-finite loss
    (`cause`); `index` counts the windows from 1, `sequences` names the batch's."""

    def __init__(self, index: int, sequences: list[str] | None, cause: Exception):
        super().__init__(f"batch {index}: {cause}")
        self.index, self.sequences, self.cause = index, sequences, cause


def run_steps(step: Step, model, batches: Iterable[dict], optimizer, *,
              start: int = 0) -> Iterator[tuple[dict, list[dict], float]]:
    """`step` on each batch in turn, yielding (batch, its loss terms per time step, seconds the step took).
    A window that cannot be trained raises `WindowError` (numbered from `start` + 1). However the loop ends (done,
    closed early, an error), a DataLoader's worker processes are ended before it returns (`end_workers`)."""
    iterator = iter(batches)
    try:
        for index, batch in enumerate(iterator, start + 1):
            t0 = time.perf_counter()
            try:
                terms = step(model, batch, optimizer)
            except (MaskIdError, FloatingPointError) as exc:
                raise WindowError(index, batch.get("sequence"), exc) from None
            yield batch, terms, time.perf_counter() - t0
    finally:
        end_workers(iterator)


def end_workers(iterator: object) -> None:
    """End the worker processes of a DataLoader's iterator now (nothing for other iterators). An error raised in a
    worker keeps the iterator alive in a reference cycle (the exception's traceback holds its frames), so torch
    would end the workers only in a later garbage collection, at any moment, where an interruption shows as an
    exception ignored in `__del__`."""
    shutdown = getattr(iterator, "_shutdown_workers", None)  # torch's own: what its __del__ calls
    if callable(shutdown):
        shutdown()


def fit(step: Step, net: torch.nn.Module, batches: Iterable[dict], count: int, lr: float, label: str,
        report: Callable[[str], None]) -> dict:
    """Train `net` on `count` batches; returns the stage's record: batches, lr, seconds, the mean loss
    terms of the first and last tenth (each batch's terms averaged over its time steps first), and the curve:
    the mean total loss of every 10 batches."""
    optimizer = torch.optim.Adam(net.parameters(), lr=lr, betas=(0.9, 0.95))
    halve = {int(count * 0.5), int(count * 0.75)}
    net.train()
    start, records = time.perf_counter(), []
    keys: list[str] = []
    for b, (_, terms, _) in enumerate(run_steps(step, net, batches, optimizer)):
        keys = keys or list(terms[0])
        records.append([np.mean([t[k] for t in terms]) for k in keys])
        if b + 1 in halve:
            for group in optimizer.param_groups:
                group["lr"] /= 2
        if (b + 1) % 100 == 0 or b + 1 == count:
            recent = dict(zip(keys, np.mean(records[-100:], 0)))
            shown = ", ".join(f"{k} {v:.4f}" for k, v in recent.items() if k != "total")
            report(f"{label}: batch {b + 1}/{count}, loss {recent['total']:.4f} ({shown}), "
                   f"{time.perf_counter() - start:.0f} s")
    tenth = max(1, count // 10)
    first, last = np.mean(records[:tenth], 0), np.mean(records[-tenth:], 0)
    return {"batches": count, "lr": lr, "seconds": round(time.perf_counter() - start, 1),
            "loss_first_tenth": {k: round(float(v), 5) for k, v in zip(keys, first)},
            "loss_last_tenth": {k: round(float(v), 5) for k, v in zip(keys, last)},
            "loss_every_10": [round(float(np.mean([r[keys.index("total")] for r in records[i:i + 10]])), 5)
                              for i in range(0, len(records), 10)] if "total" in keys else []}
