"""The sequence file: schema-checked atomic writes and validated lazy reads."""

import h5py
import numpy as np
import pytest

from dsr_bench.constants import SCHEMA_VERSION
from dsr_bench.dataset.schema import FIELDS, resolve_shape
from dsr_bench.dataset.sequence import SequenceFormatError, SequenceReader, write_sequence
from dsr_bench.testing import synthetic_arrays, write_synthetic_sequence


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    path = tmp_path_factory.mktemp("seq") / "seq_0007.h5"
    return write_synthetic_sequence(path, num_steps=2, num_objects=2, seed=7)


def test_round_trip_shapes_dtypes_and_values(synthetic):
    arrays, _, meshes = synthetic_arrays(2, 2, 7)
    with SequenceReader(synthetic) as seq:
        assert (seq.name, seq.num_steps, seq.num_objects) == ("seq_0007", 2, 2)
        for name, array in arrays.items():
            stored = seq.read(name)
            assert stored.dtype == array.dtype and stored.shape == array.shape, name
            assert np.array_equal(stored, array, equal_nan=True), name
        assert seq.read("tsdf", 1).shape == resolve_shape(FIELDS["tsdf"], 2, 2)[1:]
        assert seq.dataset("scene_flow_3d").chunks == (1, 3, 128, 128, 48)  # one chunk per step
        assert seq.dataset("mask_3d").attrs["units"] == "instance id"
        v, f = seq.mesh(1)
        assert np.allclose(v, meshes[1][0]) and np.array_equal(f, meshes[1][1])
        assert seq.mesh(5) is None
        cam = seq.camera("front")
        assert cam.intrinsics.shape == (3, 3) and cam.extrinsics.shape == (4, 4)
        assert seq.attrs["schema_version"] == SCHEMA_VERSION and seq.attrs["axis_order"] == "y,x,z"


def test_refuses_bad_shapes_and_leaves_nothing(tmp_path):
    arrays, attrs, meshes = synthetic_arrays(2, 2, 1)
    arrays["mask_3d"] = arrays["mask_3d"][:, :64].astype(np.int64)
    del arrays["heightmap"]
    target = tmp_path / "seq_0001.h5"
    with pytest.raises(SequenceFormatError) as err:
        write_sequence(target, arrays, attrs, meshes)
    message = str(err.value)
    assert "mask_3d: shape" in message and "dtype int64, expected uint8" in message
    assert "missing dataset 'heightmap'" in message
    assert list(tmp_path.iterdir()) == []


def test_reader_rejects_foreign_files(tmp_path):
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not hdf5 at all")
    with pytest.raises(SequenceFormatError, match="not a readable HDF5 file"):
        SequenceReader(junk)
    official = tmp_path / "0_0.hdf5"
    with h5py.File(official, "w") as f:
        f["tsdf"] = np.zeros((2, 2, 2), np.float32)
    with pytest.raises(SequenceFormatError, match="import-official"):
        SequenceReader(official)
    with pytest.raises(FileNotFoundError):
        SequenceReader(tmp_path / "missing.h5")


def test_reader_rejects_newer_schema(tmp_path, synthetic):
    path = tmp_path / "future.h5"
    path.write_bytes(synthetic.read_bytes())
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = SCHEMA_VERSION + 1
    with pytest.raises(SequenceFormatError, match="schema version"):
        SequenceReader(path)


@pytest.mark.parametrize("pattern", ["zeros", "sparse", "dense", "tail"])
def test_sparse_deflate_round_trips(pattern):
    """The chunk compressor (zero blocks spliced in precompressed) inflates back to the exact bytes."""
    import zlib

    from dsr_bench.dataset.sequence import _deflate_sparse

    rng = np.random.default_rng(0)
    data = np.zeros(128 * 128 * 48, dtype=np.float32)
    if pattern == "sparse":
        data[rng.integers(0, data.size, 500)] = rng.normal(size=500)
    elif pattern == "dense":
        data[:] = rng.normal(size=data.size)
    elif pattern == "tail":
        data[-7:] = 1.5
    assert zlib.decompress(_deflate_sparse(data.view(np.uint8))) == data.tobytes()


def test_read_steps_equals_h5py_for_every_layout(tmp_path):
    """The raw-chunk reader returns exactly what h5py decodes, for our layout and for others (fallback)."""
    from dsr_bench.dataset.sequence import read_steps

    rng = np.random.default_rng(1)
    data = (rng.normal(size=(4, 6, 8, 5)) * (rng.random((4, 6, 8, 5)) > 0.7)).astype(np.float32)
    with h5py.File(tmp_path / "f.h5", "w") as f:
        f.create_dataset("ours", data=data, chunks=(1, 6, 8, 5), compression="gzip", compression_opts=1)
        f.create_dataset("shuffled", data=data, chunks=(1, 6, 8, 5), compression="gzip", shuffle=True)
        f.create_dataset("plain", data=data)
        f.create_dataset("sparse", shape=data.shape, dtype=np.float32, chunks=(1, 6, 8, 5), compression="gzip")
        f["sparse"][1] = data[1]
    with h5py.File(tmp_path / "f.h5", "r") as f:
        for name in ("ours", "shuffled", "plain", "sparse"):
            for start, stop in ((0, 4), (1, 3), (2, 2)):
                np.testing.assert_array_equal(read_steps(f[name], start, stop), f[name][start:stop])


def test_reader_read_matches_h5py_for_steps_ranges_and_other_indices(tmp_path):
    """SequenceReader.read goes through the raw-chunk reader for steps and ranges; values equal h5py's."""
    path = write_synthetic_sequence(tmp_path / "seq_0000.h5", num_steps=3)
    with SequenceReader(path) as seq, h5py.File(path, "r") as f:
        for name in ("tsdf", "mask_3d", "scene_flow_3d", "action"):
            for index in (0, 2, -1, slice(None), slice(1, 3), slice(2, 1), slice(0, 3, 2), None):
                expected = f[name][()] if index is None else f[name][index]
                got = seq.read(name, index)
                assert got.dtype == expected.dtype and np.array_equal(got, expected), (name, index)
