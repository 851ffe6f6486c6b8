"""Pin a named split's checksums in the toolkit from a freshly generated, validated dataset.

    python scripts/pin_split.py DATA_DIR [--split NAME]

Writes dsr_bench/data/split_digests.json[NAME] = {"checksum", "sequences": {name: content digest}}.
Run it after `dsr-bench generate --split NAME --out DATA_DIR` and `dsr-bench validate DATA_DIR`,
whenever the generator changes what it writes (and say so in the commit).
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data", type=Path)
    parser.add_argument("--split")
    args = parser.parse_args()

    from dsr_bench.manifest import load_manifest, read_split, split_digest
    from dsr_bench.splits import PINNED_FILE, get_split

    split, names = read_split(args.data, args.split)
    spec = get_split(split)
    manifest = load_manifest(args.data)
    if len(names) != spec.num_sequences:
        raise SystemExit(f"{args.data}: split {split} has {len(names)} sequences, expected {spec.num_sequences}")
    digests = {s["name"]: s["content_sha256"] for s in manifest["sequences"]}
    pins = json.loads(PINNED_FILE.read_text()) if PINNED_FILE.exists() else {}
    pins[split] = {"checksum": split_digest(manifest, split), "sequences": {n: digests[n] for n in names}}
    tmp = PINNED_FILE.with_name(f".{PINNED_FILE.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(pins, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, PINNED_FILE)
    print(f"pinned {split}: {pins[split]['checksum']}")


if __name__ == "__main__":
    main()
