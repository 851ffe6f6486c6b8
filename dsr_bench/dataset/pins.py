"""Pins of the benchmark's named splits: making them, and comparing a dataset with them.

A pin (`dsr_bench/dataset/split_pins.json`, see `dsr_bench.dataset.splits.pinned_digests`) holds a split's
ground-truth checksum, its observations' checksum, and per sequence its two group digests and a
`dsr_bench.dataset.digests.Fingerprint` of every array. Comparing a dataset with its pin says, for each
sequence that differs, which arrays differ and by how much: a ground-truth array that differs at
all is a different benchmark; an observation array that differs within the stated tolerance
(`dsr_bench.dataset.digests.within_tolerance`) is rendering noise of another CPU or library, reported as a
note and never as a changed benchmark.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from dsr_bench.dataset.digests import (
    GROUND_TRUTH_KEY, OBSERVATIONS_KEY, Fingerprint, describe_difference, is_ground_truth, split_checksum,
    within_tolerance,
)
from dsr_bench.dataset.manifest import split_digest
from dsr_bench.dataset.scored import differing_fields, file_scored_digests
from dsr_bench.dataset.sequence import file_digests
from dsr_bench.dataset.splits import SPLITS


def build_pin(data_dir: str | Path, names: list[str], manifest: Mapping, split: str,
              digests: Callable[[Path], dict] = file_digests, workers: int = 1, fingerprints: bool = True) -> dict:
    """The pin of split `split` of a dataset: its sequences `names` are read (every array, one step at a
    time; in `workers` processes) and must match the manifest's digests (SystemExit naming the sequence
    otherwise); each sequence's `scored` digests (`dsr_bench.dataset.scored`) are what `evaluate` recomputes
    while it scores. Without `fingerprints` no array's fingerprint is kept (a training split of thousands of
    sequences: a sequence that differs is then named with its group, ground truth or observations, not its
    arrays)."""
    from functools import partial

    from dsr_bench.parallel import as_finished, in_order

    listed = {s["name"]: s for s in manifest["sequences"]}
    paths = [Path(data_dir) / listed[name]["file"] for name in names]
    read = in_order(as_finished(partial(_read_for_pin, digests), paths, workers), len(paths))
    found, scored = {}, {}
    for name, (d, s) in zip(names, read):
        found[name], scored[name] = d, s
        for key in (GROUND_TRUTH_KEY, OBSERVATIONS_KEY):
            if d[key] != listed[name][key]:
                raise SystemExit(f"{name}: {key} of the file differs from the manifest; run `dsr-bench validate`")
    fields = sorted({f for d in found.values() for f in d["fingerprints"]}) if fingerprints else []
    sequences = {
        name: {"ground_truth": d[GROUND_TRUTH_KEY], "observations": d[OBSERVATIONS_KEY],
               "arrays": [d["fingerprints"][f].to_list() if f in d["fingerprints"] else None for f in fields],
               "scored": scored[name]}
        for name, d in found.items()
    }
    return {"checksum": split_digest(manifest, split),
            "observations_checksum": split_checksum((n, d[OBSERVATIONS_KEY]) for n, d in found.items()),
            "fields": fields, "sequences": sequences}


def _read_for_pin(digests: Callable[[Path], dict], path: Path) -> tuple[dict, dict]:
    """A sequence file's digests (`digests(path)`) and its scored digests."""
    return digests(path), file_scored_digests(path)


@dataclass
class PinComparison:
    """How a dataset's split compares with its pin.

    ground_truth: per sequence, the ground-truth arrays that differ, described ("mask_3d: -3 non-zero
    values, ..."), or a note that only the object list differs; observations_out: the same for
    observation arrays beyond the tolerance; observations_within: sequences whose observations
    differ within the tolerance only; missing: pinned sequences the dataset lacks."""

    ground_truth: dict[str, list[str]] = field(default_factory=dict)
    observations_out: dict[str, list[str]] = field(default_factory=dict)
    observations_within: dict[str, list[str]] = field(default_factory=dict)
    missing: list[str] = field(default_factory=list)

    @property
    def reproduced(self) -> bool:
        """Whether the split reproduces its pin (ground truth exactly, observations within tolerance)."""
        return not (self.ground_truth or self.observations_out or self.missing)


def compare_with_pin(pin: Mapping, digests: Mapping[str, Mapping],
                     fingerprints: Callable[[str], Mapping[str, Fingerprint]]) -> PinComparison:
    """Compare a split with its pin. digests: per sequence name its "ground_truth_sha256" and
    "observations_sha256" (the manifest's); fingerprints(name): the sequence's array fingerprints,
    computed only for the sequences whose digests differ from the pin."""
    out = PinComparison()
    fields = list(pin["fields"])
    for name, pinned in sorted(pin["sequences"].items()):
        have = digests.get(name)
        if have is None:
            out.missing.append(name)
            continue
        gt_same = have[GROUND_TRUTH_KEY] == pinned["ground_truth"]
        obs_same = have[OBSERVATIONS_KEY] == pinned["observations"]
        if gt_same and obs_same:
            continue
        gt: list[str] = []
        obs_out: list[str] = []
        obs_within: list[str] = []
        if not fields:  # a pin without fingerprints (`build_pin(fingerprints=False)`): only the groups are known
            gt += [] if gt_same else ["its ground truth differs from the pin (this split pins no array fingerprints)"]
            obs_out += [] if obs_same else ["its observations differ from the pin (this split pins no array "
                                            "fingerprints, so no tolerance applies)"]
        actual = fingerprints(name) if fields else {}
        expected = {f: Fingerprint.from_list(v) for f, v in zip(fields, pinned["arrays"]) if v is not None}
        for array in sorted(set(actual) | set(expected)):
            a, e = actual.get(array), expected.get(array)
            if a is None or e is None:
                (gt if is_ground_truth(array) else obs_out).append(
                    f"{array}: {'missing' if a is None else 'not in the pin'}")
                continue
            if a.sha256[:16] == e.sha256[:16]:
                continue
            if is_ground_truth(array):
                gt.append(describe_difference(array, a, e))
            elif within_tolerance(a, e):
                obs_within.append(describe_difference(array, a, e))
            else:
                obs_out.append(describe_difference(array, a, e))
        if not gt_same and not gt:
            gt.append("the object list differs (meshes, scales, colours or masses)")
        for target, found in ((out.ground_truth, gt), (out.observations_out, obs_out),
                              (out.observations_within, obs_within)):
            if found:
                target[name] = found
    return out


def summarize(split: str, comparison: PinComparison, limit: int = 3, fix: str | None = None) -> list[tuple[str, str]]:
    """(where, message) lines of a comparison for `validate`: problems first, then notes (prefixed
    'note:'), each naming the sequences and arrays (at most `limit` sequences spelled out). `fix`: what to do
    about a difference (default: regenerate the named split; a real split's says to rebuild it)."""
    lines: list[tuple[str, str]] = []
    fix = fix or f"regenerate it with `dsr-bench generate --split {split}` on this toolkit version"
    if comparison.missing:
        lines.append((f"splits/{split}.txt", f"lacks {len(comparison.missing)} pinned sequences "
                      f"(e.g. {', '.join(comparison.missing[:limit])}); {fix}"))
    for kind, found in (("ground truth", comparison.ground_truth),
                        ("observations beyond the tolerance", comparison.observations_out)):
        for name, details in list(found.items())[:limit]:
            lines.append((name, f"{kind} differs from the pinned {split}: {'; '.join(details)}; {fix}"))
        if len(found) > limit:
            lines.append((f"splits/{split}.txt", f"{len(found) - limit} more sequences whose {kind} differs "
                          f"from the pin; {fix}"))
    if comparison.observations_within:
        names = list(comparison.observations_within)
        arrays = sorted({d.split(":")[0] for details in comparison.observations_within.values() for d in details})
        lines.append((f"splits/{split}.txt", f"note: {len(names)} sequences (e.g. {', '.join(names[:limit])}) have "
                      f"observations ({', '.join(arrays)}) that differ from the pin within the stated tolerance "
                      "(rendering noise of another CPU or library); their ground truth is identical"))
    return lines


def pin_matches(manifest: Mapping, pins: Mapping[str, Mapping] | None = None) -> list[str]:
    """One line per split of a dataset's manifest saying which of this toolkit's pinned splits (`pins`, default
    `dsr_bench.dataset.splits.pinned_digests()`) has its ground-truth checksum, or that none has; for `validate`
    once the manifest's checksums are verified against the arrays."""
    from dsr_bench.dataset.splits import pinned_digests  # looked up on each call: tests stand in their own pins

    pins = pinned_digests() if pins is None else pins
    splits = manifest.get("splits") or {}
    if not splits:
        return ["no split files: the dataset matches none of the pinned splits (`dsr-bench generate --split NAME` "
                "writes one)"]
    lines = []
    for name, info in sorted(splits.items()):
        checksum = info["content_sha256"]
        same = sorted(p for p, pin in pins.items() if pin.get("checksum") == checksum)
        if same:
            lines.append(f"split {name}: checksum {checksum}, matches the pinned split {' and '.join(same)} "
                         "(its ground truth bit for bit)")
        elif name in pins:
            lines.append(f"split {name}: checksum {checksum}, matches no pinned split (the pinned {name} has "
                         f"{pins[name].get('checksum')})")
        else:
            lines.append(f"split {name}: checksum {checksum}, matches none of the {len(pins)} pinned splits "
                         "(not a benchmark split)")
    return lines


def verify_scored(split: str, names: list[str], recomputed: Mapping[str, Mapping[str, str]],
                  data_dir: str | Path, limit: int = 3) -> tuple[bool, list[str]]:
    """Whether what `evaluate` scored is the pinned split: `names` (the split's list in the dataset) are the pinned
    sequences and every scored sequence's recomputed `scored` digests (`recomputed`, {name: {field: digest}})
    equal the pin's. Returns (verified, warning lines); a split this toolkit does not pin is (False, [])."""
    from dsr_bench.dataset.splits import pinned_digests  # looked up on each call: tests stand in their own pins

    spec = SPLITS.get(split)
    if spec is None or spec.expected_digest is None:
        return False, []
    pin = pinned_digests().get(split, {})
    if pin.get("checksum") != spec.expected_digest or any("scored" not in s for s in pin.get("sequences", {}).values()):
        return False, [f"{data_dir}: split {split!r} has no scored digests pinned in this toolkit, so its ground "
                       "truth cannot be verified while scoring; its results are not pinned"]
    fix = f"regenerate it with `dsr-bench generate --split {split} --out {data_dir}`"
    pinned = pin["sequences"]
    lines = []
    missing, extra = sorted(set(pinned) - set(names)), sorted(set(names) - set(pinned))
    if missing or extra:
        what = "; ".join(part for part in (f"lacks {len(missing)} pinned sequences (e.g. {', '.join(missing[:limit])})"
                                           if missing else "", f"adds {len(extra)} (e.g. {', '.join(extra[:limit])})"
                                           if extra else "") if part)
        lines.append(f"{data_dir}: split {split!r} {what}; it is not the pinned split: {fix}")
    lines += changed_ground_truth(data_dir, recomputed, pinned, f"the pinned {split}", fix, limit,
                                  "recomputed while scoring, whatever the file's digest attributes say")
    return not lines, lines


def changed_ground_truth(data_dir: str | Path, recomputed: Mapping[str, Mapping[str, str]],
                         pinned: Mapping[str, Mapping], against: str, fix: str, limit: int, how: str) -> list[str]:
    """Warning lines for the scored sequences whose recomputed `scored` digests differ from their pinned ones: one
    line per sequence (its fields) up to `limit`, then one for the rest; `against` names the pins, `how` how the
    digests were found. Shared by a toolkit split's check (`verify_scored`) and a real split's
    (`dsr_bench.dataset.real`)."""
    changed = {name: differing_fields(d, pinned[name].get("scored", {}))
               for name, d in sorted(recomputed.items()) if name in pinned}
    changed = {name: fields for name, fields in changed.items() if fields}
    lines = [f"{Path(data_dir) / (name + '.h5')}: {', '.join(fields)} differ from {against} ({how}); {fix}"
             for name, fields in list(changed.items())[:limit]]
    if len(changed) > limit:
        lines.append(f"{data_dir}: {len(changed) - limit} more sequences whose ground truth differs from {against}; "
                     f"{fix}")
    return lines
