"""Content digests, manifest.json, split files and split checksums (dsr_bench.manifest)."""

import hashlib
import json

import h5py
import numpy as np
import pytest

from dsr_bench.errors import UserError
from dsr_bench.manifest import (
    build_manifest,
    content_digest,
    file_sha256,
    load_manifest,
    read_split,
    resolve_sequence,
    sequence_content_digest,
    split_digest,
    write_manifest,
)
from dsr_bench.testing import write_synthetic_dataset


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("man") / "data", num_sequences=2, num_steps=1)


def test_content_digest_definition():
    a = np.arange(6, dtype=np.float32).reshape(2, 3)
    b = np.array([1, 2], np.uint8)
    objects = [{"model_id": "m", "scale": 1.5}]
    expected = hashlib.sha256()
    for name, arr in (("a", a), ("b", b)):  # sorted names, dtype, shape, little-endian C-order bytes
        expected.update(f"{name}|{arr.dtype.str}|{arr.shape}|".encode() + arr.tobytes())
    expected.update(json.dumps(objects, sort_keys=True).encode())
    assert content_digest({"b": b, "a": a}, objects) == expected.hexdigest()
    # independent of byte order and memory layout, sensitive to dtype, shape, values, names, objects
    assert content_digest({"a": a.astype(">f4"), "b": b}, objects) == expected.hexdigest()
    assert content_digest({"a": np.asfortranarray(a), "b": b}, objects) == expected.hexdigest()
    base = expected.hexdigest()
    assert content_digest({"a": a.astype(np.float64), "b": b}, objects) != base
    assert content_digest({"a": a.reshape(3, 2), "b": b}, objects) != base
    assert content_digest({"a": a + 1, "b": b}, objects) != base
    assert content_digest({"c": a, "b": b}, objects) != base
    assert content_digest({"a": a, "b": b}, [{"model_id": "m", "scale": 1.25}]) != base
    assert content_digest({"a": a, "b": b}, [{"scale": 1.5, "model_id": "m"}]) == base  # key order is canonical


def test_file_digest_matches_in_memory_digest(data):
    path = data / "seq_0001.h5"
    with h5py.File(path, "r") as f:
        stored = f.attrs["content_sha256"]
    assert sequence_content_digest(path) == stored
    assert file_sha256(path) == hashlib.sha256(path.read_bytes()).hexdigest()


def test_file_digest_sees_any_array_change(data, tmp_path):
    path = tmp_path / "s.h5"
    path.write_bytes((data / "seq_0000.h5").read_bytes())
    before = sequence_content_digest(path)
    with h5py.File(path, "r+") as f:
        f["policy/attempts"][0] += 1
    assert sequence_content_digest(path) != before


def test_build_manifest_fields_and_split_checksum(data):
    m = build_manifest(data)
    assert m["format"] == "dsr-bench-dataset" and m["schema_version"] == 1
    assert [s["name"] for s in m["sequences"]] == ["seq_0000", "seq_0001"]
    entry = m["sequences"][0]
    assert entry["file"] == "seq_0000.h5" and entry["num_steps"] == 1 and entry["num_objects"] == 2
    assert entry["sha256"] == file_sha256(data / "seq_0000.h5")
    assert entry["content_sha256"] == sequence_content_digest(data / "seq_0000.h5")
    assert entry["objects"][0]["category"] == "box" and entry["source"] == "synthetic"
    assert entry["generator_args"] == {"seed": 0, "steps": 1}
    split = m["splits"]["test"]
    assert split["file"] == "splits/test.txt" and split["sequences"] == 2
    expected = hashlib.sha256("".join(f"{s['name']}:{s['content_sha256']}\n" for s in m["sequences"]).encode())
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
    ('{"format": "dsr-bench-dataset", "schema_version": 1, "sequences": [{"name": "x"}], "splits": {}}',
     r"sequences\[0\] lacks 'file'"),
    ('{"format": "dsr-bench-dataset", "schema_version": 1, "sequences": [], "splits": {"t": {"file": "f"}}}',
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
    with pytest.raises(UserError, match="no sequence 'seq_0042'"):
        resolve_sequence(data, "seq_0042")
    with pytest.raises(UserError, match="give a path"):
        resolve_sequence(None, "seq_0042")
