"""The benchmark's fixed named splits: what `dsr-bench generate --split NAME` reproduces.

A split is fully determined by its object set, size, base seed and scene parameters; sequence i is
generated from `sequence_seed(base_seed, i)`, so any worker count, shard or CPU gives the same
files' contents. `dsr_bench/dataset/split_pins.json` pins, for the splits generated with this toolkit
version, the split checksum (`dsr_bench.dataset.manifest.split_digest`: the ground truth), the checksum of
the observations, and per sequence its two group digests and a fingerprint of every array
(`dsr_bench.dataset.digests`), so `validate` can say which arrays of which sequence differ and by how much
(`scripts/pin_split.py DATA_DIR` writes it); `expected_digest` is None for splits not pinned yet.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import json
from pathlib import Path

import numpy as np

from dsr_bench.constants import DEFAULT_OBJECTS_PER_SCENE, DEFAULT_STEPS
from dsr_bench.errors import UserError


@dataclass(frozen=True)
class Split:
    """A named, reproducible split of simulated sequences."""

    name: str
    objects: str
    num_sequences: int
    base_seed: int
    role: str  # "train" | "test" | "val" (a validation split: where training choices are made, never ranked)
    description: str
    steps: int = DEFAULT_STEPS
    objects_per_scene: int = DEFAULT_OBJECTS_PER_SCENE
    policy: str = "heuristic"
    #: the split checksum to expect instead of the pin file's ("": not pinned; tests); None: the pin file's, if any
    pinned_checksum: str | None = None

    @property
    def expected_digest(self) -> str | None:
        """The ground-truth split checksum this split is pinned to (split_pins.json, read on first use), or None."""
        if self.pinned_checksum is not None:
            return self.pinned_checksum or None
        pin = pinned_digests().get(self.name)
        return pin["checksum"] if pin else None


SPLITS: dict[str, Split] = {
    s.name: s
    for s in (
        Split("cube-train", "cube", 4000, 10_000, "train",
              "Paper stage 1-2 training set: boxes (official scripts: 4000)"),
        Split("cube-test", "cube", 400, 11_000, "test", "Held-out boxes"),
        Split("shapenet-train", "shapenet", 8000, 20_000, "train", "Paper stage 3 training set: 44 ShapeNet models"),
        Split("shapenet-test", "shapenet", 400, 21_000, "test", "Held-out ShapeNet scenes"),
        Split("ycb-test", "ycb", 400, 30_000, "test", "The paper's novel-object sim test set: YCB objects"),
        Split("procedural-train", "procedural", 8000, 40_000, "train",
              "Built-in stand-in for shapenet-train (procedural mugs, bottles, cans, phones, sofas)"),
        Split("procedural-test", "procedural", 400, 41_000, "test", "Held-out procedural scenes (seen categories)"),
        Split("procedural-novel-test", "procedural-novel", 400, 50_000, "test",
              "Built-in stand-in for ycb-test: novel YCB-like shapes"),
        Split("procedural-mini", "procedural", 8, 60_000, "train", "Eight procedural sequences for a first look"),
        Split("procedural-novel-mini", "procedural-novel", 8, 61_000, "test",
              "Eight novel-object sequences for a first look and the quick-start evaluation"),
        # The CPU track (docs/models.md, "The CPU track"): models that work on a 32 x 32 x 16 grid, trained and
        # scored on 2 CPU cores. Its splits are prefixes of the benchmark's (the same base seeds: sequence i
        # is the same file), scored on the benchmark's full grid like every other entry.
        Split("cpu-train", "procedural", 400, 40_000, "train",
              "CPU track training set: the first 400 sequences of procedural-train"),
        Split("cpu-train-4k", "procedural", 4000, 40_000, "train",
              "CPU track training set at the paper's size: the first 4,000 sequences of procedural-train"),
        Split("cpu-novel-test", "procedural-novel", 100, 50_000, "test",
              "CPU track test set: the first 100 sequences of procedural-novel-test (novel objects)"),
        Split("cpu-val", "procedural", 100, 41_000, "val",
              "CPU track validation set: the first 100 sequences of procedural-test (seen categories, held-out "
              "scenes), where the long runs' choices are made; never reported as a result"),
    )
}
SPLIT_NAMES: tuple[str, ...] = tuple(SPLITS)
PINNED_FILE = Path(__file__).resolve().parent / "split_pins.json"
PINS_FORMAT, PINS_VERSION = "dsr-bench-pins", 2


@functools.cache
def pinned_digests() -> dict[str, dict]:
    """The pinned splits: {split: {"checksum": ground-truth split checksum, "observations_checksum",
    "fields": [array names], "sequences": {name: {"ground_truth", "observations", "arrays": [one
    `Fingerprint.to_list()` per field, None where the sequence lacks it]}}}}."""
    if not PINNED_FILE.is_file():
        return {}
    pins = json.loads(PINNED_FILE.read_text())
    if pins.get("format") != PINS_FORMAT or pins.get("version") != PINS_VERSION:
        raise RuntimeError(f"{PINNED_FILE}: not {PINS_FORMAT} version {PINS_VERSION} (a broken installation)")
    return pins["splits"]


def get_split(name: str) -> Split:
    """The named split, or a UserError listing the known names."""
    if name not in SPLITS:
        raise UserError(f"unknown split {name!r}; choose one of: {', '.join(SPLIT_NAMES)}")
    return SPLITS[name]


def sequence_seed(base_seed: int, index: int) -> int:
    """The 63-bit seed of sequence `index` of a run with base seed `base_seed` (independent streams)."""
    state = np.random.SeedSequence(entropy=int(base_seed), spawn_key=(int(index),)).generate_state(2, np.uint32)
    return int((int(state[0]) << 31) ^ int(state[1]))


def sequence_name(index: int) -> str:
    """File stem of sequence `index`: seq_0000, seq_0001, ... (at least four digits)."""
    return f"seq_{index:04d}"
