"""The sequence file: schema-checked atomic writes and validated lazy reads."""

import json

import h5py
import numpy as np
import pytest

from dsr_bench.constants import SCHEMA_VERSION
from dsr_bench.dataset.schema import FIELDS, resolve_shape
from dsr_bench.dataset.sequence import SequenceFormatError, SequenceReader, write_sequence
from dsr_bench.errors import UserError
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
        assert seq.dataset("tsdf").chunks == (1, 128, 128, 48)  # one chunk per step
        flow = seq.dataset("scene_flow_3d")  # (Y, X) tiles, byte-shuffled, all-zero tiles never written
        assert flow.chunks == (1, 3, 16, 16, 48) and flow.shuffle and flow.compression == "gzip"
        written = flow.id.get_num_chunks()
        empty = sum(not arrays["scene_flow_3d"][t, :, y:y + 16, x:x + 16].any()
                    for t in range(2) for y in range(0, 128, 16) for x in range(0, 128, 16))
        assert written == 2 * 64 - empty and empty > 0
        # a plain h5py read (HDF5's own filters and fill value) sees the same arrays
        with h5py.File(synthetic, "r") as plain:
            for name in ("scene_flow_3d", "mask_3d", "tsdf"):
                assert np.array_equal(plain[name][()], arrays[name]), name
        assert seq.dataset("mask_3d").attrs["units"] == "instance id"
        v, f = seq.mesh(1)
        assert np.allclose(v, meshes[1][0]) and np.array_equal(f, meshes[1][1])
        assert seq.mesh(5) is None
        cam = seq.camera("front")
        assert cam.intrinsics.shape == (3, 3) and cam.extrinsics.shape == (4, 4)
        assert seq.attrs["schema_version"] == SCHEMA_VERSION and seq.attrs["axis_order"] == "y,x,z"


def test_the_writer_computes_the_digests_the_callers_used_to(tmp_path):
    """`write_sequence` writes `digest_attrs` of the arrays and extras it is given, after the caller's attributes,
    where each caller used to add them: a file written without digests is the same bytes as one written with them
    computed beforehand (the way before), and digests that describe other arrays are replaced."""
    from dsr_bench.dataset.digests import digest_attrs
    from dsr_bench.dataset.sequence import file_digests

    arrays, attrs, meshes = synthetic_arrays(2, 2, 4)
    extras = {"official/extra": np.arange(6, dtype=np.float32).reshape(2, 3)}  # an import's: digested too
    expected = digest_attrs({**arrays, **extras}, attrs["objects"])
    written = write_sequence(tmp_path / "now.h5", arrays, attrs, meshes, extras)
    before = write_sequence(tmp_path / "before.h5", arrays, {**attrs, **expected}, meshes, extras)
    stale = write_sequence(tmp_path / "stale.h5", arrays, {**attrs, **digest_attrs({"tsdf": arrays["tsdf"]}, [])},
                           meshes, extras)
    assert "content_sha256" not in attrs  # the caller's attributes are left as they were
    assert written.read_bytes() == before.read_bytes() == stale.read_bytes()
    with SequenceReader(written) as seq:
        assert list(seq.attrs) == ["format", "schema_version", *attrs, *expected]  # (the points are stored)
        assert {key: seq.attrs[key] for key in expected} == expected
    recomputed = file_digests(written)
    assert {key: recomputed[key] for key in expected} == expected


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
    with pytest.raises(FileNotFoundError):  # callers that catch FileNotFoundError still do
        SequenceReader(tmp_path / "missing.h5")
    with pytest.raises(UserError, match="sequence file not found: .*missing.h5; check the path"):
        SequenceReader(tmp_path / "missing.h5")


def test_sequence_header_is_the_required_attributes_in_order(synthetic):
    from dsr_bench.dataset.schema import REQUIRED_ATTRS, sequence_header
    from dsr_bench.geometry import make_camera

    front = make_camera("front", 24, 32)
    header = sequence_header(sequence="s", seed=3, num_steps=2, num_objects=1, object_set="set", policy="p",
                             generator_args={"a": 1}, source="test", objects=[{"model_id": "m"}],
                             cameras={"front": front}, versions={"tool_version": 7}, late=1, later=2)
    required = [k for k in REQUIRED_ATTRS if k not in ("format", "schema_version")]
    assert [k for k in header if k in REQUIRED_ATTRS] == required
    keys = list(header)
    assert keys[keys.index("toolkit_version") + 1] == "tool_version" and keys[-2:] == ["late", "later"]
    assert header["cameras"] == {"front": front.as_attrs()} and header["grid_shape"] == [128, 128, 48]
    with pytest.raises(ValueError, match="grid_shape"):
        sequence_header(sequence="s", seed=3, num_steps=2, num_objects=1, object_set="set", policy="p",
                        generator_args={}, source="test", objects=[], cameras={}, grid_shape=[1, 1, 1])
    with SequenceReader(synthetic) as seq:  # a producer's file: the header as written, then format and version
        written = [k for k in seq.attrs if k in REQUIRED_ATTRS]
        assert written == ["format", "schema_version"] + required
        assert seq.camera("front").as_attrs() == seq.cameras["front"]


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

    from dsr_bench.dataset.storage import _deflate_sparse

    rng = np.random.default_rng(0)
    data = np.zeros(128 * 128 * 48, dtype=np.float32)
    if pattern == "sparse":
        data[rng.integers(0, data.size, 500)] = rng.normal(size=500)
    elif pattern == "dense":
        data[:] = rng.normal(size=data.size)
    elif pattern == "tail":
        data[-7:] = 1.5
    assert zlib.decompress(_deflate_sparse(data.view(np.uint8))) == data.tobytes()


def test_tiled_grids_round_trip_bit_for_bit_and_read_steps_agrees(tmp_path):
    """write_array's tiled, shuffled layout: read_step / read_steps / h5py return the written bits (signed zeros,
    denormals, NaN payloads included), tiles that are all zero are not stored, and a step in one chunk comes back
    without a copy (read-only)."""
    from dsr_bench.dataset.storage import read_step, read_steps, write_array

    rng = np.random.default_rng(3)
    flow = np.zeros((3, 3, 128, 128, 48), dtype=np.float32)
    flow[:, :, 20:40, 70:90] = rng.normal(size=(3, 3, 20, 20, 48)).astype(np.float32)
    flow[1, 0, 5, 5, 5], flow[1, 1, 5, 5, 6], flow[2, 2, 100, 3, 0] = -0.0, 1e-42, np.float32("nan")
    mask = (flow[:, 0] != 0).astype(np.uint8) * 3
    tsdf = rng.random((3, 128, 128, 48), dtype=np.float32)
    with h5py.File(tmp_path / "f.h5", "w") as f:
        for name, array in (("scene_flow_3d", flow), ("mask_3d", mask), ("tsdf", tsdf)):
            write_array(f, name, array)
    with h5py.File(tmp_path / "f.h5", "r") as f:
        assert f["scene_flow_3d"].id.get_num_chunks() == 3 * 4 + 1 + 1  # the objects' tiles and the two odd voxels
        assert f["mask_3d"].chunks == (1, 128, 128, 48) and f["mask_3d"].id.get_num_chunks() == 3
        for name, array in (("scene_flow_3d", flow), ("mask_3d", mask), ("tsdf", tsdf)):
            bits = array.view(np.uint8)
            assert np.array_equal(read_steps(f[name], 0, 3).view(np.uint8), bits), name
            assert np.array_equal(f[name][()].view(np.uint8), bits), name
            for t in range(3):
                assert np.array_equal(read_step(f[name], t).view(np.uint8), bits[t]), name
        assert not read_step(f["tsdf"], 1).flags.writeable


def test_a_chunk_that_inflates_beyond_its_size_is_refused_not_inflated(tmp_path):
    """A file we did not write: a raw chunk whose stream holds more (or fewer) bytes than the chunk is never inflated
    past its size, by the fast reader nor by HDF5's decoder (which would inflate it whole first): reading that step
    raises OSError naming the chunk; the other steps read as h5py decodes them."""
    import zlib

    from dsr_bench.dataset.storage import inflate_exact, read_step, read_steps

    big = zlib.compress(bytes(10_000_000))
    assert inflate_exact(big, 4096) is None and inflate_exact(zlib.compress(bytes(4096)), 4096) == bytes(4096)
    with h5py.File(tmp_path / "f.h5", "w") as f:
        ds = f.create_dataset("x", shape=(2, 32, 32), dtype=np.float32, chunks=(1, 32, 32), compression="gzip")
        ds.id.write_direct_chunk((0, 0, 0), big)
        ds[1] = 1.0
        spanning = f.create_dataset("y", shape=(2, 32, 32), dtype=np.float32, chunks=(2, 32, 32), compression="gzip")
        spanning.id.write_direct_chunk((0, 0, 0), big)  # a layout HDF5 decodes itself
    with h5py.File(tmp_path / "f.h5", "r") as f:
        assert np.array_equal(read_step(f["x"], 1), np.ones((32, 32), np.float32))
        for read in (lambda: read_step(f["x"], 0), lambda: read_steps(f["x"], 0, 2), lambda: read_step(f["y"], 1)):
            with pytest.raises(OSError, match="does not inflate to its"):
                read()


def test_read_steps_equals_h5py_for_every_layout(tmp_path):
    """The raw-chunk reader returns exactly what h5py decodes, for our layout and for others (fallback)."""
    from dsr_bench.dataset.storage import read_steps

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


def test_points_that_follow_from_depth_are_derived_not_stored_and_read_back_bit_for_bit(tmp_path):
    """A camera's points equal to `derive_points` of its depth (as the generator's are) are left out of the file and
    listed in derived_arrays; the reader derives exactly them (step, range, whole), says they exist, validates them
    and digests them like stored ones (so pins are unchanged). Points that differ by one bit are stored as given."""
    from dsr_bench.dataset.digests import digest_attrs
    from dsr_bench.dataset.sequence import DERIVED_ATTR, derive_points, file_digests
    from dsr_bench.dataset.validate import validate_sequence
    from dsr_bench.geometry import make_camera

    arrays, attrs, meshes = synthetic_arrays(2, 2, 5)
    spec = attrs["cameras"]["front"]
    camera = make_camera("front", spec["height"], spec["width"])
    points = derive_points(arrays["cameras/front/depth"], camera)
    assert np.isnan(points).any() and np.isfinite(points).any()
    arrays["cameras/front/points"] = points
    written = digest_attrs(arrays, attrs["objects"])  # the digests of every array, the derived ones too
    write_sequence(tmp_path / "derived.h5", arrays, attrs, meshes)
    with h5py.File(tmp_path / "derived.h5", "r") as f:
        assert "cameras/front/points" not in f and DERIVED_ATTR in f.attrs
    with SequenceReader(tmp_path / "derived.h5") as seq:
        assert "cameras/front/points" in seq and seq.derived == {"cameras/front/points"}
        assert seq.shape_and_dtype("cameras/front/points") == (points.shape, np.dtype(np.float32))
        assert np.array_equal(seq.read("cameras/front/points").view(np.uint32), points.view(np.uint32))
        assert np.array_equal(seq.read("cameras/front/points", 1).view(np.uint32), points[1].view(np.uint32))
        assert np.array_equal(seq.read("cameras/front/points", slice(1, 3)).view(np.uint32),
                              points[1:3].view(np.uint32))
        assert DERIVED_ATTR not in seq.attrs
    digests = file_digests(tmp_path / "derived.h5")
    assert digests["observations_sha256"] == written["observations_sha256"]
    assert digests["ground_truth_sha256"] == written["ground_truth_sha256"]
    assert validate_sequence(tmp_path / "derived.h5") == []

    nudged = points.copy()
    nudged.view(np.uint32)[0, 120, 160, 0] ^= 1  # one ulp off: not the derivation, kept as given
    arrays["cameras/front/points"] = nudged
    write_sequence(tmp_path / "stored.h5", arrays, attrs, meshes)
    with SequenceReader(tmp_path / "stored.h5") as seq:
        assert not seq.derived and np.array_equal(seq.read("cameras/front/points").view(np.uint32),
                                                  nudged.view(np.uint32))


def test_a_file_of_schema_2_is_read_and_a_bad_derived_list_is_refused(tmp_path, synthetic):
    """Schema 2 (every array stored) stays readable; a derived_arrays naming something that cannot be derived (not a
    camera's points, or points also stored) is a one-line format error."""
    import shutil

    from dsr_bench.dataset.sequence import DERIVED_ATTR

    old = tmp_path / "old.h5"
    shutil.copy(synthetic, old)
    with h5py.File(old, "r+") as f:
        f.attrs["schema_version"] = 2
    with SequenceReader(old) as seq:
        assert seq.read("tsdf", 0).shape == (128, 128, 48)
    for listed in (["tsdf"], ["cameras/front/points"], ["cameras/side/points"]):
        with h5py.File(old, "r+") as f:
            f.attrs[DERIVED_ATTR] = json.dumps(listed)
        with pytest.raises(SequenceFormatError, match="cannot be derived"):
            SequenceReader(old)


def _bits(a) -> bytes:
    return np.ascontiguousarray(a).tobytes()


def test_an_import_stores_the_releases_arrays_once_and_reads_their_casts_back_bit_for_bit(tmp_path):
    """An import's float32 points and 2D flow are its `official/` float64 arrays cast (the points' last observation
    from the depth): the file stores the originals once (byte-shuffled, deflate level 6) and lists the casts in
    derived_from; the reader casts them again, every step, range and whole array bit for bit, and the file's
    digests are the arrays'. The same file with the casts stored (an import of an earlier version) reads the same,
    and one listing a cast whose source is missing is refused in one line."""
    import shutil

    from test_official import write_official_fixture

    from dsr_bench.cli import main
    from dsr_bench.dataset.derived import DERIVED_FROM_ATTR
    from dsr_bench.dataset.digests import digest_attrs
    from dsr_bench.dataset.official import convert_sequence, find_official_sequences
    from dsr_bench.dataset.sequence import file_digests
    from dsr_bench.dataset.storage import OFFICIAL_LEVEL

    src, dst = tmp_path / "release", tmp_path / "data"
    src.mkdir()
    write_official_fixture(src, ids=("3",))
    assert main(["import-official", str(src), str(dst)]) == 0
    arrays, extras, attrs = convert_sequence(find_official_sequences(src)["3"])
    casts = {"cameras/front/points": "official/pts_small", "cameras/front/scene_flow_2d": "official/scene_flow_2d"}
    path = dst / "seq_0003.h5"
    with h5py.File(path, "r") as f:
        assert json.loads(f.attrs[DERIVED_FROM_ATTR]) == casts
        assert not {f"cameras/front/{k}" for k in f["cameras/front"]} & set(casts)  # not stored
        for name in ("official/pts_small", "official/depth_image"):
            assert f[name].shuffle and f[name].compression_opts == OFFICIAL_LEVEL
    with SequenceReader(path) as seq:
        assert set(casts) <= seq.derived and seq.derived_from == casts
        for name, array in {**arrays, **extras}.items():
            assert seq.shape_and_dtype(name) == (array.shape, array.dtype), name
            assert _bits(seq.read(name)) == _bits(array), name
            if array.ndim > 1:
                for index in (0, -1, slice(1, None), slice(0, 2)):
                    assert _bits(seq.read(name, index)) == _bits(array[index]), (name, index)
    written = digest_attrs({**arrays, **extras}, attrs["objects"])
    assert file_digests(path)["content_sha256"] == written["content_sha256"]

    earlier = tmp_path / "earlier.h5"  # the casts stored, no derived_from: how earlier versions wrote imports
    shutil.copy(path, earlier)
    with h5py.File(earlier, "r+") as f:
        for name in casts:
            f.create_dataset(name, data=arrays[name])
        del f.attrs[DERIVED_FROM_ATTR]
    with SequenceReader(earlier) as seq:
        assert not seq.derived_from and all(_bits(seq.read(n)) == _bits(arrays[n]) for n in casts)
    with h5py.File(path, "r+") as f:
        del f["official/scene_flow_2d"]
    with pytest.raises(SequenceFormatError, match="derived_from lists") as err:
        SequenceReader(path)
    assert "\n" not in str(err.value)
