"""Digests (dsr_bench.dataset.digests), manifest.json, split files and split checksums (dsr_bench.dataset.manifest)."""

import hashlib
import json

import h5py
import numpy as np
import pytest

from dsr_bench.dataset.digests import array_digest, digest_attrs, group_digests
from dsr_bench.dataset.sequence import file_digests
from dsr_bench.errors import UserError
from dsr_bench.dataset.manifest import (
    build_manifest,
    file_sha256,
    load_manifest,
    name_ranges,
    read_split,
    resolve_sequence,
    split_digest,
    write_manifest,
)
from dsr_bench.testing import write_synthetic_dataset


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("man") / "data", num_sequences=2, num_steps=1)


def test_digest_definitions():
    a = np.arange(6, dtype=np.float32).reshape(2, 3)
    b = np.array([1, 2], np.uint8)
    objects = [{"model_id": "m", "scale": 1.5}]
    # an array: name, little-endian dtype, shape, C-order bytes
    expected_a = hashlib.sha256(f"a|{a.dtype.str}|{a.shape}|".encode() + a.tobytes()).hexdigest()
    assert array_digest("a", a) == expected_a
    assert array_digest("a", a.astype(">f4")) == array_digest("a", np.asfortranarray(a)) == expected_a
    for other in (a.astype(np.float64), a.reshape(3, 2), a + 1):
        assert array_digest("a", other) != expected_a
    assert array_digest("c", a) != expected_a
    # groups: the ground truth (schema group) with the object list, the observations; content of both
    arrays = {"mask_3d": b, "tsdf": a}
    per = {n: array_digest(n, x) for n, x in arrays.items()}
    gt = hashlib.sha256(f"mask_3d:{per['mask_3d']}\n".encode() + json.dumps(objects, sort_keys=True).encode())
    obs = hashlib.sha256(f"tsdf:{per['tsdf']}\n".encode())
    content = hashlib.sha256(f"{gt.hexdigest()}\n{obs.hexdigest()}\n".encode())
    attrs = digest_attrs(arrays, objects)
    assert attrs == {"array_sha256": per, "ground_truth_sha256": gt.hexdigest(),
                     "observations_sha256": obs.hexdigest(), "content_sha256": content.hexdigest()}
    # an observation changes the observations and the content only; the object list the ground truth
    changed = digest_attrs({"mask_3d": b, "tsdf": a + 1}, objects)
    assert changed["ground_truth_sha256"] == attrs["ground_truth_sha256"]
    assert changed["observations_sha256"] != attrs["observations_sha256"]
    assert changed["content_sha256"] != attrs["content_sha256"]
    other = group_digests(per, [{"scale": 1.25, "model_id": "m"}])
    assert other["ground_truth_sha256"] != attrs["ground_truth_sha256"]
    assert group_digests(per, [{"scale": 1.5, "model_id": "m"}]) == group_digests(per, objects)  # canonical keys


def test_file_digests_match_the_stored_ones(data):
    path = data / "seq_0001.h5"
    with h5py.File(path, "r") as f:
        stored = {k: f.attrs[k] for k in ("content_sha256", "ground_truth_sha256", "observations_sha256")}
        per = json.loads(f.attrs["array_sha256"])
    found = file_digests(path)
    assert {k: found[k] for k in stored} == stored and found["array_sha256"] == per
    assert {n: fp.sha256 for n, fp in found["fingerprints"].items()} == per
    assert file_sha256(path) == hashlib.sha256(path.read_bytes()).hexdigest()


def test_file_digests_see_any_array_change(data, tmp_path):
    path = tmp_path / "s.h5"
    path.write_bytes((data / "seq_0000.h5").read_bytes())
    before = file_digests(path)
    with h5py.File(path, "r+") as f:
        f["policy/attempts"][0] += 1
    after = file_digests(path)
    assert after["ground_truth_sha256"] != before["ground_truth_sha256"]
    assert after["observations_sha256"] == before["observations_sha256"]
    assert [n for n in after["array_sha256"] if after["array_sha256"][n] != before["array_sha256"][n]] == [
        "policy/attempts"]


def test_build_manifest_fields_and_split_checksum(data):
    m = build_manifest(data)
    assert m["format"] == "dsr-bench-dataset" and m["schema_version"] == 3
    assert [s["name"] for s in m["sequences"]] == ["seq_0000", "seq_0001"]
    entry = m["sequences"][0]
    assert entry["file"] == "seq_0000.h5" and entry["num_steps"] == 1 and entry["num_objects"] == 2
    assert entry["sha256"] == file_sha256(data / "seq_0000.h5")
    found = file_digests(data / "seq_0000.h5")
    for key in ("content_sha256", "ground_truth_sha256", "observations_sha256"):
        assert entry[key] == found[key]
    assert entry["objects"][0]["category"] == "box" and entry["source"] == "synthetic"
    assert entry["generator_args"] == {"seed": 0, "steps": 1}
    split = m["splits"]["test"]
    assert split["file"] == "splits/test.txt" and split["sequences"] == 2
    # the split checksum covers the ground truth only
    expected = hashlib.sha256("".join(f"{s['name']}:{s['ground_truth_sha256']}\n" for s in m["sequences"]).encode())
    assert split["content_sha256"] == split_digest(m, "test") == expected.hexdigest()


def test_write_and_load_round_trip(data, tmp_path):
    m = build_manifest(data)
    d = tmp_path / "d"
    d.mkdir()
    write_manifest(d, m)
    assert load_manifest(d) == m
    assert [p.name for p in d.iterdir()] == ["manifest.json"]  # no temporary file left


@pytest.mark.parametrize("content, match", [
    (None, "has no manifest.json; build it with `dsr-bench manifest"),
    ("{not json", "unreadable manifest"),
    ('{"format": "other"}', "not a dsr-bench manifest"),
    ('{"format": "dsr-bench-dataset", "schema_version": 2, "sequences": [{"name": "x"}], "splits": {}}',
     r"sequences\[0\] lacks 'file'"),
    ('{"format": "dsr-bench-dataset", "schema_version": 2, "sequences": [], "splits": {"t": {"file": "f"}}}',
     r"splits\['t'\] lacks 'sequences'"),
    ('{"format": "dsr-bench-dataset", "schema_version": 99, "sequences": [], "splits": {}}', "schema version 99"),
])
def test_load_manifest_errors(tmp_path, content, match):
    if content is not None:
        (tmp_path / "manifest.json").write_text(content)
    with pytest.raises(UserError, match=match):
        load_manifest(tmp_path)


def test_split_errors(data, tmp_path):
    with pytest.raises(UserError, match="available: test"):
        read_split(data, "train")
    with pytest.raises(UserError, match="is not in the manifest; available: test"):
        split_digest(build_manifest(data), "train")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "seq_0000.h5").write_bytes((data / "seq_0000.h5").read_bytes())
    (bad / "splits").mkdir()
    (bad / "splits" / "a.txt").write_text("seq_0000\nseq_0005\n")
    with pytest.raises(UserError, match=r"splits/a.txt names 1 sequences with no file \(e.g. seq_0005\)"):
        build_manifest(bad)
    (bad / "splits" / "a.txt").write_text("seq_0000\nseq_0000\n")
    with pytest.raises(UserError, match="more than once"):
        build_manifest(bad)
    (bad / "splits" / "b.txt").write_text("seq_0000\n")
    with pytest.raises(UserError, match="has splits a, b; choose one"):
        read_split(bad, None)


def test_unreadable_file_and_missing_dir(data, tmp_path):
    (tmp_path / "seq_0000.h5").write_bytes(b"not hdf5")
    with pytest.raises(UserError, match="seq_0000.h5: unreadable sequence file"):
        build_manifest(tmp_path)
    with pytest.raises(UserError, match="dataset directory not found"):
        build_manifest(tmp_path / "nope")


def test_resolve_sequence(data):
    assert resolve_sequence(data, "seq_0001") == data / "seq_0001.h5"
    assert resolve_sequence(None, str(data / "seq_0000.h5")) == data / "seq_0000.h5"
    with pytest.raises(UserError, match=f"no sequence 'seq_0042' in {data}: it holds seq_0000..seq_0001 "
                                        r"\(2 sequences\); all names: `dsr-bench info .* --sequences`"):
        resolve_sequence(data, "seq_0042")
    with pytest.raises(UserError, match="dataset directory not found: .*; give --data the directory"):
        resolve_sequence(data / "nope", "seq_0042")
    with pytest.raises(UserError, match="give a path"):
        resolve_sequence(None, "seq_0042")


def test_a_sequence_number_however_padded_names_the_sequence(data, tmp_path):
    """`seq_001`, `seq_1`, `1` and `0001` all name seq_0001 (the user's words, not the writer's padding); a number
    two files share is refused naming both, and a number no file has names what the directory holds."""
    import shutil

    from dsr_bench.dataset.manifest import match_sequence_name

    for typed in ("seq_0001", "seq_001", "seq_1", "1", "0001", "seq1"):
        assert resolve_sequence(data, typed) == data / "seq_0001.h5", typed
    assert resolve_sequence(data, "0") == data / "seq_0000.h5"
    with pytest.raises(UserError, match=r"no sequence 'seq_42' in .*: it holds seq_0000..seq_0001 \(2 sequences\)"):
        resolve_sequence(data, "seq_42")
    both = tmp_path / "both"
    shutil.copytree(data, both)
    shutil.copy(both / "seq_0001.h5", both / "seq_01.h5")
    assert resolve_sequence(both, "seq_01") == both / "seq_01.h5"  # the exact name wins
    with pytest.raises(UserError, match="^sequence 'seq_1' is ambiguous: seq_0001 and seq_01 both have number 1; "
                                        "give the full name$"):
        resolve_sequence(both, "seq_1")
    assert match_sequence_name("seq_x", ["seq_x", "seq_0000"]) == "seq_x"  # names that are not numbers: exactly
    assert match_sequence_name("x", ["seq_0000"]) is None and match_sequence_name("seq_", ["seq_0000"]) is None


def test_a_missing_dataset_names_how_to_make_it_and_the_datasets_beside_it(data, tmp_path):
    import shutil

    shutil.copytree(data, tmp_path / "both")
    with pytest.raises(UserError, match=r"dataset directory not found: .*mini; give --data the directory holding the "
                                        r"seq_\*\.h5 files; datasets in .*: .*both$"):
        resolve_sequence(tmp_path / "mini", "seq_1")
    with pytest.raises(UserError, match=r"^dataset directory not found: .*cpu-train; make it with `dsr-bench generate "
                                        r"--split cpu-train --out .*cpu-train`; datasets in .*: .*both$"):
        read_split(tmp_path / "cpu-train", None)


def test_completed_entry_and_common_generator_args(data, tmp_path):
    import shutil

    from dsr_bench.dataset.manifest import FILE_ATTR_KEYS, common_generator_args, completed_entry

    manifest = build_manifest(data)
    full = manifest["sequences"][0]
    old = {k: v for k, v in full.items() if k not in FILE_ATTR_KEYS}  # an older manifest's entry
    assert old != full and completed_entry(data, old) == full  # read back from the file's root attributes
    assert completed_entry(data, full) == full
    shutil.copytree(data, tmp_path / "d")
    (tmp_path / "d" / old["file"]).unlink()
    assert completed_entry(tmp_path / "d", old) == old  # file missing: unchanged
    common, varying = common_generator_args([{"generator_args": {"a": 1, "b": 2}}, {"generator_args": {"a": 1, "b": 3}},
                                             {"generator_args": {"a": 1, "c": 0}}])
    assert common == {"a": 1} and varying == ["b", "c"]
    assert common_generator_args([{}, {"generator_args": None}]) == ({}, [])


def test_name_ranges():
    assert name_ranges([f"seq_{i:04d}" for i in range(400)]) == "seq_0000..seq_0399"
    assert name_ranges(["seq_0007", "seq_0001", "seq_0000", "seq_0002", "seq_0009", "seq_0010"]) == \
        "seq_0000..seq_0002, seq_0007, seq_0009..seq_0010"
    assert name_ranges([f"seq_{i}" for i in range(9998, 10002)]) == "seq_9998..seq_10001"  # natural order
    assert name_ranges(["seq_a", "seq_0001", "seq_b", "x_0002"]) == "seq_0001, seq_a, seq_b, x_0002"
    assert name_ranges([f"seq_{i:04d}" for i in range(0, 20, 2)], limit=3) == \
        "seq_0000, seq_0002, seq_0004, ... (7 more ranges)"
    assert name_ranges([]) == "-"


def test_unknown_sequence_points_at_a_command_that_lists_them(data, capsys):
    """The error of an unknown name ends with a command; run as written, it prints exactly the sequence names."""
    import re
    import shlex

    from dsr_bench.cli import main

    with pytest.raises(UserError) as err:
        resolve_sequence(data, "seq_0042")
    command = shlex.split(re.search(r"`(dsr-bench [^`]*)`", str(err.value)).group(1))
    assert main(command[1:]) == 0
    assert capsys.readouterr().out.splitlines() == ["seq_0000", "seq_0001"]
    assert main(["info", str(data)]) == 0
    out = capsys.readouterr().out
    assert "seq_0000..seq_0001 (all: --sequences)" in out and "2 sequences: seq_0000..seq_0001" in out
