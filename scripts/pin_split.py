"""Pin a named split in the toolkit from a freshly generated, validated dataset.

    python scripts/pin_split.py DATA_DIR [--split NAME]

Writes dsr_bench/dataset/split_pins.json["splits"][NAME] (`dsr_bench.dataset.pins.build_pin`): the split's
ground-truth checksum, its observations' checksum, and per sequence the two group digests and a
fingerprint of every array. Run it after `dsr-bench generate --split NAME --out DATA_DIR` and
`dsr-bench validate DATA_DIR`, whenever the generator changes what it writes (and say so in the
commit, with why the new pin still verifies on a CPU other than yours).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data", type=Path)
    parser.add_argument("--split")
    args = parser.parse_args()

    from dsr_bench.atomic import write_text
    from dsr_bench.dataset.manifest import load_manifest, read_split
    from dsr_bench.dataset.pins import build_pin
    from dsr_bench.dataset.splits import PINNED_FILE, PINS_FORMAT, PINS_VERSION, get_split

    split, names = read_split(args.data, args.split)
    spec = get_split(split)
    if len(names) != spec.num_sequences:
        raise SystemExit(f"{args.data}: split {split} has {len(names)} sequences, expected {spec.num_sequences}")
    pin = build_pin(args.data, names, load_manifest(args.data), split)
    pins = json.loads(PINNED_FILE.read_text()) if PINNED_FILE.exists() else {}
    if pins.get("format") != PINS_FORMAT or pins.get("version") != PINS_VERSION:
        pins = {"format": PINS_FORMAT, "version": PINS_VERSION, "splits": {}}
    pins["splits"][split] = pin
    # one line per sequence keeps the file diffable
    text = json.dumps(pins, sort_keys=True, separators=(",", ":")).replace('},"seq_', '},\n"seq_') + "\n"
    write_text(PINNED_FILE, text)
    print(f"pinned {split}: {pin['checksum']}")


if __name__ == "__main__":
    main()
