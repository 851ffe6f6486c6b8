"""Pin a named split in the toolkit from a freshly generated, validated dataset.

    python scripts/pin_split.py DATA_DIR [--split NAME] [--workers N] [--no-fingerprints]

Writes dsr_bench/dataset/split_pins.json["splits"][NAME] (`dsr_bench.dataset.pins.build_pin`): the split's
ground-truth checksum, its observations' checksum, and per sequence the two group digests and a
fingerprint of every array. Run it after `dsr-bench generate --split NAME --out DATA_DIR` and
`dsr-bench validate DATA_DIR`, whenever the generator changes what it writes (and say so in the
commit, with why the new pin still verifies on a CPU other than yours). `--workers N` reads the files in N
processes; `--no-fingerprints` keeps no per-array fingerprint (for a training split of thousands of sequences:
a sequence that differs is then named by its group, ground truth or observations, not by its arrays).

    python scripts/pin_split.py DATA_DIR --split NAME --scored-only

adds to an existing pin only each sequence's `scored` digests (`dsr_bench.dataset.scored`, what `evaluate`
recomputes while it scores), after checking that every sequence's ground-truth and observation digests,
recomputed from the files, equal the pin's: the pinned benchmark itself does not change.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data", type=Path)
    parser.add_argument("--split")
    parser.add_argument("--scored-only", action="store_true", help="add the scored digests to an existing pin")
    parser.add_argument("--workers", type=int, default=1, help="processes reading the files")
    parser.add_argument("--no-fingerprints", action="store_true",
                        help="pin no per-array fingerprints (large training splits)")
    args = parser.parse_args()

    from dsr_bench.atomic import write_text
    from dsr_bench.dataset.manifest import load_manifest, read_split
    from dsr_bench.dataset.pins import build_pin
    from dsr_bench.dataset.splits import PINNED_FILE, PINS_FORMAT, PINS_VERSION, get_split

    split, names = read_split(args.data, args.split)
    spec = get_split(split)
    if len(names) != spec.num_sequences:
        raise SystemExit(f"{args.data}: split {split} has {len(names)} sequences, expected {spec.num_sequences}")
    pins = json.loads(PINNED_FILE.read_text()) if PINNED_FILE.exists() else {}
    if pins.get("format") != PINS_FORMAT or pins.get("version") != PINS_VERSION:
        pins = {"format": PINS_FORMAT, "version": PINS_VERSION, "splits": {}}
    if args.scored_only:
        pin = add_scored(pins["splits"].get(split), args.data, names, split)
    else:
        pin = build_pin(args.data, names, load_manifest(args.data), split, workers=args.workers,
                        fingerprints=not args.no_fingerprints)
    pins["splits"][split] = pin
    # one line per sequence keeps the file diffable
    text = json.dumps(pins, sort_keys=True, separators=(",", ":")).replace('},"seq_', '},\n"seq_') + "\n"
    write_text(PINNED_FILE, text)
    print(f"pinned {split}: {pin['checksum']}")


def add_scored(pin: dict | None, data: Path, names: list[str], split: str) -> dict:
    """`pin` with each sequence's scored digests added, once the files are shown to be the pinned ones."""
    from dsr_bench.dataset.digests import GROUND_TRUTH_KEY, OBSERVATIONS_KEY
    from dsr_bench.dataset.manifest import load_manifest
    from dsr_bench.dataset.scored import file_scored_digests
    from dsr_bench.dataset.sequence import file_digests

    if pin is None:
        raise SystemExit(f"{split} is not pinned yet: pin it without --scored-only")
    if sorted(names) != sorted(pin["sequences"]):
        raise SystemExit(f"{data}: split {split} lists other sequences than its pin")
    listed = {s["name"]: s["file"] for s in load_manifest(data)["sequences"]}
    for name in sorted(names):
        path = data / listed[name]
        found = file_digests(path)
        entry = pin["sequences"][name]
        if (found[GROUND_TRUTH_KEY], found[OBSERVATIONS_KEY]) != (entry["ground_truth"], entry["observations"]):
            raise SystemExit(f"{path}: its digests, recomputed, differ from the pin: not the pinned {split}")
        entry["scored"] = file_scored_digests(path)
    return pin


if __name__ == "__main__":
    main()
