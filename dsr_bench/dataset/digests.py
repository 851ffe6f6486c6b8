"""What "the same sequence" means: digests of its arrays, by group, and fingerprints to compare with.

A sequence's arrays fall in two groups (`dsr_bench.dataset.schema.Field.group`):
- ground truth (poses, actions, pushes, amodal masks, 3D flow, the policy's choices, and the object
  list): what scores a model. Pinned bit for bit: any difference is a different benchmark.
- observations (images, depth, TSDF, heightmap, visible fractions, 2D ground truth, anything else):
  what the cameras render. The generator renders them exactly (`dsr_bench.render`: the same bits on
  every x86-64 CPU with FMA), but they are pinned to a tolerance (`within_tolerance`), so that a
  last-bit difference of a renderer, library or CPU is reported as such and never as a changed
  benchmark.

Every array has a digest (SHA-256 over its name, dtype, shape and little-endian C-order bytes); a
group's digest is the SHA-256 of its arrays' "name:digest" lines in sorted order (the ground truth
adds the canonical JSON of the object list); the content digest is the SHA-256 of the two group
digests. A fingerprint (`fingerprint`) adds a few statistics of an array, so that a difference can
be described ("by how much") without the reference data.

`dsr_bench.dataset.sequence.write_sequence` writes `digest_attrs` into every file; `file_digests` and
`file_fingerprints` there recompute them from a file (this module reads no file).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from dsr_bench.dataset.arraybytes import le_contiguous
from dsr_bench.dataset.schema import FIELDS, GROUND_TRUTH

GROUND_TRUTH_KEY, OBSERVATIONS_KEY = "ground_truth_sha256", "observations_sha256"
#: Observation arrays whose digest differs from the pin still count as reproduced when their counts
#: of finite and non-zero values agree within this share of their elements, and their mean, mean
#: absolute value and position-weighted mean within this share of their mean absolute value (plus
#: an absolute 1e-12): rendering noise of a few ulps moves them by about 1e-7, a different or shifted
#: scene by far more.
COUNT_TOLERANCE = 1e-4
MEAN_TOLERANCE = 1e-5


def is_ground_truth(name: str) -> bool:
    """Whether an HDF5 dataset path of a sequence belongs to the ground-truth group."""
    field = FIELDS.get(name.rsplit("/", 1)[-1] if name.startswith("cameras/") else name)
    return field is not None and field.group == GROUND_TRUTH


def _raw(a: np.ndarray):
    """The C-order bytes of a contiguous array without a copy where it can (hashlib reads buffers)."""
    return a.tobytes() if a.dtype.hasobject else a.reshape(-1).view(np.uint8)


class ArrayHasher:
    """SHA-256 of one array fed in first-axis slices (a whole array, or one step at a time)."""

    def __init__(self, name: str, dtype: np.dtype, shape: tuple[int, ...]):
        self._h = hashlib.sha256(f"{name}|{np.dtype(dtype).newbyteorder('<').str}|{tuple(shape)}|".encode())

    def update(self, part: np.ndarray) -> None:
        self._h.update(_raw(le_contiguous(part)))

    def hexdigest(self) -> str:
        return self._h.hexdigest()


def array_digest(name: str, array: np.ndarray) -> str:
    """SHA-256 of one named array: name, little-endian dtype, shape, then its C-order bytes."""
    a = le_contiguous(array)
    hasher = ArrayHasher(name, a.dtype, a.shape)
    hasher.update(a)
    return hasher.hexdigest()


def _canonical_objects(objects: list[dict]) -> bytes:
    return json.dumps(objects, sort_keys=True).encode()


def group_digests(array_digests: Mapping[str, str], objects: list[dict]) -> dict[str, str]:
    """{"content_sha256", "ground_truth_sha256", "observations_sha256"} from per-array digests."""
    groups = {GROUND_TRUTH_KEY: hashlib.sha256(), OBSERVATIONS_KEY: hashlib.sha256()}
    for name in sorted(array_digests):
        key = GROUND_TRUTH_KEY if is_ground_truth(name) else OBSERVATIONS_KEY
        groups[key].update(f"{name}:{array_digests[name]}\n".encode())
    groups[GROUND_TRUTH_KEY].update(_canonical_objects(objects))
    out = {key: h.hexdigest() for key, h in groups.items()}
    out["content_sha256"] = hashlib.sha256(f"{out[GROUND_TRUTH_KEY]}\n{out[OBSERVATIONS_KEY]}\n".encode()).hexdigest()
    return out


def digest_attrs(arrays: Mapping[str, np.ndarray], objects: list[dict]) -> dict:
    """The digest attributes every sequence file carries: `array_sha256` (JSON {name: digest}), the
    two group digests and `content_sha256`."""
    per_array = {name: array_digest(name, a) for name, a in arrays.items()}
    return {"array_sha256": per_array, **group_digests(per_array, objects)}


# --- fingerprints ------------------------------------------------------------------------------------
def _weights(start: int, count: int) -> np.ndarray:
    """Fixed pseudo-random weights in [0, 1) of flat element indices start..start + count - 1 (a
    multiplicative hash of the index), so that a weighted mean changes when values move around."""
    index = np.arange(start, start + count, dtype=np.uint64)
    return ((index * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(40)).astype(np.float64) / float(1 << 24)


@dataclass
class Fingerprint:
    """An array's digest and statistics: element count, finite and non-zero counts, and the mean,
    mean absolute value and a position-weighted mean (`_weights`) of its finite elements (float64).
    The statistics describe a difference and judge a tolerance; the digest alone says whether two
    arrays are equal."""

    sha256: str
    size: int
    finite: int
    nonzero: int
    mean: float
    mean_abs: float
    mean_weighted: float

    def to_list(self) -> list:
        """Compact JSON form: [sha256[:16], size, finite, nonzero, mean, mean_abs, mean_weighted] (9 digits)."""
        return [self.sha256[:16], self.size, self.finite, self.nonzero,
                *(float(f"{v:.9g}") for v in (self.mean, self.mean_abs, self.mean_weighted))]

    @classmethod
    def from_list(cls, values: list) -> Fingerprint:
        sha, size, finite, nonzero, mean, mean_abs, weighted = values
        return cls(str(sha), int(size), int(finite), int(nonzero), float(mean), float(mean_abs), float(weighted))


class FingerprintAccumulator:
    """A `Fingerprint` built from first-axis slices of an array."""

    def __init__(self, name: str, dtype: np.dtype, shape: tuple[int, ...]):
        self._hash = ArrayHasher(name, dtype, shape)
        self._size, self._finite, self._nonzero = int(np.prod(shape, dtype=np.int64)), 0, 0
        self._sums: list[float] = []
        self._abs: list[float] = []
        self._weighted: list[float] = []
        self._offset = 0

    def update(self, part: np.ndarray) -> None:
        part = np.asarray(part)
        self._hash.update(part)
        values = part.reshape(-1)
        weights = _weights(self._offset, len(values))
        self._offset += len(values)
        if values.dtype.kind == "f":
            keep = np.isfinite(values)
            finite, weights = values[keep].astype(np.float64), weights[keep]
        else:
            finite = values.astype(np.float64)
        self._finite += len(finite)
        self._nonzero += int(np.count_nonzero(finite))
        self._sums.append(float(finite.sum()))
        self._abs.append(float(np.abs(finite).sum()))
        self._weighted.append(float((finite * weights).sum()))

    def result(self) -> Fingerprint:
        n = max(self._finite, 1)
        return Fingerprint(self._hash.hexdigest(), self._size, self._finite, self._nonzero,
                           math.fsum(self._sums) / n, math.fsum(self._abs) / n, math.fsum(self._weighted) / n)


def fingerprint(name: str, array: np.ndarray) -> Fingerprint:
    """The fingerprint of a whole array."""
    a = np.asarray(array)
    acc = FingerprintAccumulator(name, a.dtype, a.shape)
    acc.update(a)
    return acc.result()


def describe_difference(name: str, actual: Fingerprint, pinned: Fingerprint) -> str:
    """One phrase saying how an array differs from its pinned fingerprint."""
    if actual.size != pinned.size:
        return f"{name}: {actual.size} elements, pinned {pinned.size}"
    parts = []
    if actual.finite != pinned.finite:
        parts.append(f"{actual.finite - pinned.finite:+d} finite values")
    if actual.nonzero != pinned.nonzero:
        parts.append(f"{actual.nonzero - pinned.nonzero:+d} non-zero values")
    for label, a, b in (("mean", actual.mean, pinned.mean), ("mean |x|", actual.mean_abs, pinned.mean_abs),
                        ("weighted mean", actual.mean_weighted, pinned.mean_weighted)):
        if a != b:
            parts.append(f"{label} {a:.9g} vs {b:.9g} (relative {abs(a - b) / max(abs(a), abs(b)):.1e})")
    return f"{name}: " + (", ".join(parts) if parts else "same statistics, different bits")


def within_tolerance(actual: Fingerprint, pinned: Fingerprint) -> bool:
    """Whether an observation array reproduces its pin to the stated tolerance (see module doc)."""
    if actual.sha256[:16] == pinned.sha256[:16]:
        return True
    if actual.size != pinned.size:
        return False
    slack = COUNT_TOLERANCE * actual.size
    if abs(actual.finite - pinned.finite) > slack or abs(actual.nonzero - pinned.nonzero) > slack:
        return False
    scale = max(abs(actual.mean_abs), abs(pinned.mean_abs))
    return all(abs(a - b) <= MEAN_TOLERANCE * scale + 1e-12 for a, b in (
        (actual.mean, pinned.mean), (actual.mean_abs, pinned.mean_abs), (actual.mean_weighted, pinned.mean_weighted)))


# --- splits ------------------------------------------------------------------------------------------
def split_checksum(sequences: Iterable[tuple[str, str]]) -> str:
    """SHA-256 over `name:ground_truth_sha256\\n` of a split's sequences, sorted by name."""
    h = hashlib.sha256()
    for name, digest in sorted(sequences):
        h.update(f"{name}:{digest}\n".encode())
    return h.hexdigest()
