"""Named splits: seeds, and bit-exact reproduction of a pinned split from the toolkit alone."""

import pytest

from dsr_bench.errors import UserError
from dsr_bench.dataset.sequence import SequenceReader
from dsr_bench.dataset.splits import SPLITS, get_split, pinned_digests, sequence_name, sequence_seed


def test_sequence_seeds_are_stable_and_distinct():
    seeds = [sequence_seed(61_000, i) for i in range(1000)]
    assert len(set(seeds)) == 1000 and all(0 <= s < 2**63 for s in seeds)
    assert sequence_seed(61_000, 3) == sequence_seed(61_000, 3) != sequence_seed(61_001, 3)
    assert sequence_name(42) == "seq_0042" and sequence_name(12345) == "seq_12345"


def test_split_table_and_errors():
    assert get_split("ycb-test").num_sequences == 400 and get_split("ycb-test").objects == "ycb"
    assert {s.role for s in SPLITS.values()} == {"train", "test", "val"}
    with pytest.raises(UserError, match="unknown split 'val'"):
        get_split("val")


@pytest.mark.parametrize("split, shard, sequence", [("procedural-novel-mini", "3/8", "seq_0003"),
                                                     ("procedural-novel-test", "123/400", "seq_0123"),
                                                     ("cube-test", "7/400", "seq_0007")])
def test_pinned_split_reproduces_bit_for_bit(tmp_path, split, shard, sequence):
    """A shard of a pinned split, generated here, has exactly the pinned content digests."""
    pytest.importorskip("pybullet")
    from dsr_bench.cli import main

    pins = pinned_digests()
    assert split in pins, f"{split} must be pinned in dsr_bench/data/split_digests.json"
    spec = get_split(split)
    assert spec.expected_digest == pins[split]["checksum"]
    assert len(pins[split]["sequences"]) == spec.num_sequences
    out = tmp_path / split
    assert main(["generate", "--split", split, "--out", str(out), "--shard", shard]) == 0
    with SequenceReader(out / f"{sequence}.h5") as seq:
        pinned = pins[split]["sequences"][sequence]
        assert seq.attrs["ground_truth_sha256"] == pinned["ground_truth"]
        assert seq.attrs["observations_sha256"] == pinned["observations"]  # the renderer is exact too


def test_validate_compares_named_splits_with_their_pins(tmp_path, monkeypatch):
    import json

    import h5py
    import numpy as np

    import dsr_bench.dataset.splits as splits
    from dsr_bench.dataset.digests import digest_attrs
    from dsr_bench.dataset.manifest import build_manifest, load_manifest, write_manifest
    from dsr_bench.dataset.pins import build_pin
    from dsr_bench.testing import write_synthetic_dataset
    from dsr_bench.dataset.validate import validate_dataset

    data = write_synthetic_dataset(tmp_path / "d", num_sequences=2, num_steps=1, split="procedural-novel-mini")
    pin = build_pin(data, ["seq_0000", "seq_0001"], load_manifest(data), "procedural-novel-mini")
    monkeypatch.setattr(splits, "pinned_digests", lambda: {"procedural-novel-mini": pin})
    assert validate_dataset(data, check_gt=False)[0] == []
    # a ground-truth change of seq_0001, written consistently (its digests and the manifest updated)
    with h5py.File(data / "seq_0001.h5", "r+") as f:
        f["object_poses"][1, 0, 0] += 0.001
        names = []
        f.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) and not n.startswith("meshes/")
                     else None)
        for key, value in digest_attrs({n: f[n][()] for n in names}, json.loads(f.attrs["objects"])).items():
            f.attrs[key] = json.dumps(value, sort_keys=True) if isinstance(value, dict) else value
    write_manifest(data, build_manifest(data))
    problems = validate_dataset(data, check_gt=False)[0]
    (problem,) = problems
    assert problem.where == "seq_0001" and not problem.note
    assert problem.message.startswith("ground truth differs from the pinned procedural-novel-mini: object_poses: ")
    assert "mean " in problem.message and "dsr-bench generate --split procedural-novel-mini" in problem.message
    assert np.isfinite(float(problem.message.split("relative ")[1].split(")")[0]))
