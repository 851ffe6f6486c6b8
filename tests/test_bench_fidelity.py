"""bench/bench_fidelity.py and bench/fidelity_stats.py: each statistic on hand-made records with known
answers, the resampling, the three readers and the argument handling. No generation here."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from dsr_bench.constants import GRID_SHAPE

BENCH = Path(__file__).resolve().parents[1] / "bench"
sys.path.insert(0, str(BENCH))
import bench_fidelity
import fidelity_stats as fs

REFERENCE = bench_fidelity.DEFAULT_REFERENCE
needs_reference = pytest.mark.skipif(not REFERENCE.is_file(), reason=f"{REFERENCE} not present")
IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])


def yaw(deg: float) -> np.ndarray:
    """Quaternion (x, y, z, w) of a rotation by `deg` about world z."""
    h = np.radians(deg) / 2
    return np.array([0.0, 0.0, np.sin(h), np.cos(h)])


def cell(x: float, y: float) -> tuple[int, int]:
    """(row, col) of the workspace cell holding world (x, y)."""
    return int(np.floor((y + 0.256) / 0.004)), int(np.floor((x - 0.244) / 0.004))


def record(positions, quaternions=None, actions=None, voxels=None, bands=None, name="hand") -> fs.Record:
    """A record from (T+1, N, 3) positions; identity rotations, 1000 voxels, some bands by default."""
    positions = np.asarray(positions, dtype=np.float64)
    T1, n = positions.shape[:2]
    if quaternions is None:
        quaternions = np.broadcast_to(IDENTITY, (T1, n, 4)).copy()
    if actions is None:
        actions = np.tile([0, *cell(0.3, 0.0)], (T1 - 1, 1))
    if voxels is None:
        voxels = np.full((T1, n), 1000)
    if bands is None:
        bands = np.tile([0.02, 0.03, 0.95], (T1 - 1, 1))
    return fs.Record(name, positions, np.asarray(quaternions, dtype=np.float64), np.asarray(actions, dtype=np.int64),
                     np.asarray(voxels, dtype=np.int64), np.asarray(bands, dtype=np.float64))


def one_push_scene() -> fs.Record:
    """Object 0 at (0.402, 0, 0.03) pushed along +x from the cell centre (0.342, 0.002): it moves by exactly
    1 cm along x and turns 90 degrees about z; object 1 at (0.6, 0.15) stays. 1000 voxels each (a 4 cm cube)."""
    row, col = cell(0.342, 0.002)
    before = [[0.402, 0.0, 0.03], [0.6, 0.15, 0.03]]
    after = [[0.412, 0.0, 0.03], [0.6, 0.15, 0.03]]
    quats = [[IDENTITY, IDENTITY], [yaw(90), IDENTITY]]
    return record([before, after], quats, [[0, row, col]])


# --- geometry ----------------------------------------------------------------------------------------


def test_rotation_angle_of_relative_rotations():
    assert fs.rotation_angle(IDENTITY, yaw(90)) == pytest.approx(np.pi / 2)
    assert fs.rotation_angle(yaw(30), yaw(120)) == pytest.approx(np.pi / 2)
    assert fs.rotation_angle(yaw(10), -yaw(10)) == pytest.approx(0.0, abs=1e-7)  # q and -q: one rotation
    assert fs.rotation_angle(IDENTITY, 3 * yaw(45)) == pytest.approx(np.pi / 4)  # not normalised
    # x-axis quarter turn after a z-axis one: the relative rotation is the x quarter turn
    qx = np.array([np.sin(np.pi / 4), 0, 0, np.cos(np.pi / 4)])
    assert fs.rotation_angle(yaw(90), fs.quat_multiply(qx, yaw(90))) == pytest.approx(np.pi / 2)


def test_push_starts_are_cell_centres_and_directions_follow_d():
    row, col = cell(0.342, 0.002)
    assert (row, col) == (64, 24)
    np.testing.assert_allclose(fs.push_starts(np.array([[0, row, col]])), [[0.342, 0.002]])
    np.testing.assert_allclose(fs.push_directions(np.array([[2, 0, 0], [5, 0, 0]])),
                               [[0, 1], [-np.sqrt(0.5), -np.sqrt(0.5)]], atol=1e-15)


def test_pushed_object_is_nearest_to_the_segment_ahead_of_the_start():
    row, col = cell(0.402, 0.002)  # start (0.402, 0.002), push +x: segment x in [0.422, 0.522], y = 0.002
    behind = [0.372, 0.002, 0.03]  # 3 cm behind the start: 5 cm from the segment
    ahead = [0.50, 0.042, 0.03]  # 4 cm beside the segment
    rec = record([[behind, ahead], [behind, ahead]], actions=[[0, row, col]])
    assert fs.pushed_objects(rec).tolist() == [1]
    far_end = [0.56, 0.002, 0.03]  # beyond the segment's end by 3.8 cm
    rec = record([[far_end, ahead], [far_end, ahead]], actions=[[0, row, col]])
    assert fs.pushed_objects(rec).tolist() == [0]


# --- the statistics on known scenes ---------------------------------------------------------------------


def test_one_push_translated_1cm_and_rotated_90_degrees():
    rec = one_push_scene()
    assert fs.pushed_objects(rec).tolist() == [0]
    translation, rotation = fs.object_motion(rec)
    np.testing.assert_allclose(translation, [[0.01, 0.0]], atol=1e-12)
    np.testing.assert_allclose(rotation, [[90.0, 0.0]], atol=1e-9)
    s = fs.sequence_statistics(rec)
    assert s["pushed_translation_cm"] == pytest.approx(1.0)
    assert s["pushed_rotation_deg"] == pytest.approx(90.0)
    assert s["moving_per_push"] == 1.0
    assert s["multi_move_pct"] == 0.0
    assert s["first_push_cos"] == pytest.approx(1.0)  # straight at the centre
    assert s["start_distance_cm"] == pytest.approx(100 * np.hypot(0.06, 0.002))
    assert s["voxels_t0"] == 1000
    assert s["initial_distance_cm"] == pytest.approx(100 * (0.098 + np.hypot(0.1, 0.15)) / 2)
    assert s["edge_pct"] == 0.0
    assert s["direction_resultant"] == pytest.approx(1.0)
    assert s["axis_direction_pct"] == 100.0
    assert np.isnan(s["same_object_pct"])  # one push: no previous push
    assert s["tsdf_negative_pct"] == pytest.approx(2.0)
    assert s["tsdf_near_pct"] == pytest.approx(3.0)
    assert s["tsdf_free_pct"] == pytest.approx(95.0)
    # the lattice of the 4 cm cube: 1 cm of translation plus (Rz(90) - I) x, summed point by point here
    side = 0.04
    expected = []
    for gx in (np.arange(5) + 0.5) / 5 - 0.5:
        for gy in (np.arange(5) + 0.5) / 5 - 0.5:
            for _gz in range(5):
                x, y = gx * side, gy * side
                expected.append(np.hypot(0.01 + (-y - x), (x - y)) / 0.004)
    assert s["point_displacement_vox"] == pytest.approx(np.mean(expected))


def test_point_displacement_of_a_pure_translation_and_a_pure_turn():
    rec = record([[[0.5, 0.0, 0.03]], [[0.5, 0.01, 0.03]]])
    np.testing.assert_allclose(fs.point_displacement(rec), [[2.5]])  # 1 cm = 2.5 voxels, every point
    rec = record([[[0.5, 0.0, 0.03]], [[0.5, 0.0, 0.03]]], [[IDENTITY], [yaw(180)]], voxels=[[8000], [8000]])
    g = (np.arange(5) + 0.5) / 5 - 0.5  # side 20 voxels: a half turn moves (x, y) by 2 |(x, y)|
    expected = np.mean([2 * np.hypot(a, b) * 20 for a in g for b in g])
    np.testing.assert_allclose(fs.point_displacement(rec), [[expected]])


def test_moving_thresholds():
    still = [0.6, 0.15, 0.03]
    rec = record([[[0.5, 0, 0.03], [0.5, 0.1, 0.03], [0.4, 0.1, 0.03], still],
                  [[0.5045, 0, 0.03], [0.5035, 0.1, 0.03], [0.4, 0.1, 0.03], still]],
                 [[IDENTITY] * 4, [IDENTITY, IDENTITY, yaw(2.5), yaw(1.5)]])
    assert fs.moving(rec).tolist() == [[True, False, True, False]]
    s = fs.sequence_statistics(rec)
    assert s["moving_per_push"] == 2.0
    assert s["multi_move_pct"] == 100.0


def test_no_moving_object_leaves_the_displacement_undefined():
    rec = record([[[0.5, 0.0, 0.03]], [[0.5, 0.0, 0.03]]])
    assert np.isnan(fs.sequence_statistics(rec)["point_displacement_vox"])


def test_first_pushes_same_object_and_directions():
    a, b = [0.40, 0.0, 0.03], [0.60, 0.1, 0.03]
    # three pushes: a along +x (straight at the centre: cos 1), a again, then b along -y (from b the centre
    # lies along (-0.1, -0.1): cos sqrt(1/2))
    pushes = [[0, *cell(0.34, 0.0)], [0, *cell(0.34, 0.0)], [6, *cell(0.6, 0.16)]]
    rec = record([[a, b]] * 4, actions=pushes)
    assert fs.pushed_objects(rec).tolist() == [0, 0, 1]
    s = fs.sequence_statistics(rec)
    assert s["first_push_cos"] == pytest.approx((1 + np.sqrt(0.5)) / 2)
    assert s["same_object_pct"] == pytest.approx(50.0)
    assert s["axis_direction_pct"] == 100.0
    assert s["direction_resultant"] == pytest.approx(np.hypot(2, -1) / 3)
    opposite = record([[a, b]] * 3, actions=[[0, *cell(0.34, 0.0)], [4, *cell(0.46, 0.0)]])
    assert fs.sequence_statistics(opposite)["direction_resultant"] == pytest.approx(0.0, abs=1e-12)
    diagonal = record([[a, b]] * 3, actions=[[1, *cell(0.34, -0.06)], [0, *cell(0.34, 0.0)]])
    assert fs.sequence_statistics(diagonal)["axis_direction_pct"] == 50.0


def test_edge_counts_centres_within_half_a_side_of_the_bounds_or_outside():
    inside = [0.5, 0.0, 0.03]
    for where, edge in (([0.254, 0.0, 0.03], True),  # 1 cm from x min, half side 2 cm
                        ([0.5, 0.246, 0.03], True),  # 1 cm from y max
                        ([0.80, 0.0, 0.03], True),  # outside
                        ([0.274, 0.0, 0.03], False),  # 3 cm from x min
                        ([0.5, -0.2, 0.03], False)):  # 5.6 cm from y min
        rec = record([[inside, inside], [inside, where]])
        assert fs.at_edge(rec).tolist() == [edge], where
    # the side comes from t = 0: an object that left the grid (0 voxels now) still counts its size
    rec = record([[inside, inside], [inside, [0.254, 0.0, 0.03]]], voxels=[[1000, 1000], [1000, 0]])
    assert fs.at_edge(rec).tolist() == [True]


def test_tsdf_bands_and_voxel_counts():
    v = np.array([-1.0, -0.5, -1e-7, 0.0, 0.5, 0.999, 1.0, 1.0]).reshape(2, 2, 2)
    np.testing.assert_allclose(fs.tsdf_bands(v), [2 / 8, 3 / 8, 2 / 8])  # -1 is in no band
    np.testing.assert_allclose(fs.tsdf_bands(np.stack([v, np.ones_like(v)])), [[2 / 8, 3 / 8, 2 / 8], [0, 0, 1]])
    mask = np.array([0, 1, 1, 3, 3, 3, 5])  # id 5 beyond N = 4 is ignored
    assert fs.voxel_counts(mask, 4).tolist() == [2, 0, 3, 0]


def test_statistics_table_has_one_value_per_sequence_and_statistic():
    table = fs.statistics_table([one_push_scene(), one_push_scene()])
    assert list(table) == list(fs.STATISTICS)
    assert all(v.shape == (2,) for v in table.values())


def test_record_rejects_inconsistent_shapes():
    with pytest.raises(ValueError, match="voxels_per_object"):
        record([[[0.5, 0, 0.03]], [[0.5, 0, 0.03]]], voxels=[[1000, 1000], [1000, 1000]])


# --- resampling ------------------------------------------------------------------------------------------


def test_permutation_pvalue_of_identical_and_of_far_apart_samples():
    rng = np.random.default_rng(0)
    x = rng.normal(size=30)
    assert fs.permutation_pvalue(x, x.copy(), 2000, np.random.default_rng(1)) == pytest.approx(1.0)
    far = fs.permutation_pvalue(rng.normal(0, 1, 25), rng.normal(10, 1, 25), 2000, np.random.default_rng(1))
    assert far < 0.01
    assert far == pytest.approx(1 / 2001)  # no permutation is as extreme as the observed split
    # NaN values are left out; an empty side gives NaN
    assert fs.permutation_pvalue(np.array([1.0, np.nan]), np.array([1.0]), 10, rng) == pytest.approx(1.0)
    assert np.isnan(fs.permutation_pvalue(np.array([np.nan]), np.array([1.0]), 10, rng))


def test_bootstrap_interval():
    mean, low, high = fs.bootstrap_interval(np.full(10, 3.0), 500, np.random.default_rng(0))
    assert (mean, low, high) == (3.0, 3.0, 3.0)
    x = np.random.default_rng(1).normal(5, 1, 200)
    mean, low, high = fs.bootstrap_interval(x, 2000, np.random.default_rng(2))
    assert low < mean < high
    assert high - low == pytest.approx(2 * 1.96 / np.sqrt(200), rel=0.2)  # about +-1.96 standard errors
    assert all(np.isnan(fs.bootstrap_interval(np.array([np.nan]), 10, np.random.default_rng(0))))


def test_compare_is_reproducible_and_flags_differences():
    near = [one_push_scene() for _ in range(6)]
    moved = []
    for i in range(6):
        rec = one_push_scene()
        positions = rec.positions.copy()
        positions[1, 0, 0] += 0.05 + 0.001 * i  # the pushed object goes 5-6 cm further
        moved.append(fs.Record(f"m{i}", positions, rec.quaternions, rec.actions, rec.voxels_per_object,
                               rec.tsdf_bands))
    rows = bench_fidelity.compare(near, moved, 200, 500)
    again = bench_fidelity.compare(near, moved, 200, 500)
    assert json.dumps(rows) == json.dumps(again)
    by_key = {row["key"]: row for row in rows}
    assert by_key["pushed_translation_cm"]["marked"] and by_key["pushed_translation_cm"]["p"] <= 0.01
    assert not by_key["voxels_t0"]["marked"] and by_key["voxels_t0"]["p"] == pytest.approx(1.0)
    table = bench_fidelity.format_table(rows, 6, 6, 200, 500)
    marked = [line.split("|")[1].strip() for line in table.splitlines()
              if line.startswith("| ") and line.split("|")[-2].strip().endswith("*")]
    assert "pushed object: translation (cm)" in marked and "voxels per object at t=0" not in marked
    assert bench_fidelity.PUSHED_OBJECT_RULE in table


def test_paired_difference_of_a_constant_shift_and_of_the_same_values():
    rng = np.random.default_rng(0)
    x = rng.normal(10, 3, 40)
    shifted = fs.paired_difference(x + 0.1, x, 2000, np.random.default_rng(1))
    # a shift far below the spread across sequences, but the same for every pair: the paired test sees it
    assert shifted["mean"] == pytest.approx(0.1) and shifted["se"] == pytest.approx(0.0, abs=1e-12)
    assert shifted["n"] == 40 and shifted["p"] == pytest.approx(1 / 2001)
    assert fs.permutation_pvalue(x + 0.1, x, 2000, np.random.default_rng(1)) > 0.5  # unpaired, it is lost
    same = fs.paired_difference(x, x.copy(), 500, np.random.default_rng(1))
    assert same["mean"] == 0.0 and same["p"] == pytest.approx(1.0)
    # NaN on either side leaves the pair out
    part = fs.paired_difference(np.array([1.0, np.nan, 3.0]), np.array([0.0, 5.0, np.nan]), 10, rng)
    assert part["n"] == 1 and part["mean"] == 1.0 and np.isnan(part["se"])


def test_compare_paired_matches_sequences_by_name():
    base = [fs.Record(f"seq_{i}", *_fields(one_push_scene())) for i in range(5)]
    further = []
    for rec in base:
        positions = rec.positions.copy()
        positions[1, 0, 0] += 0.002  # the pushed object 2 mm further in every sequence
        further.append(fs.Record(rec.name, positions, *_fields(rec)[1:]))
    rows = {row["key"]: row for row in bench_fidelity.compare_paired(further[::-1], base, 500)}
    assert rows["pushed_translation_cm"]["mean"] == pytest.approx(0.2) and rows["pushed_translation_cm"]["n"] == 5
    assert rows["voxels_t0"]["mean"] == 0.0 and not rows["voxels_t0"]["marked"]
    table = bench_fidelity.format_paired(list(rows.values()), 500)
    assert "+0.200 ± 0.000" in table
    with pytest.raises(bench_fidelity.UserError, match="--paired-with"):
        bench_fidelity.compare_paired(base, [fs.Record("other", *_fields(base[0]))], 10)


def _fields(rec: fs.Record) -> tuple:
    return rec.positions, rec.quaternions, rec.actions, rec.voxels_per_object, rec.tsdf_bands


def test_docstring_and_footnote_hold_the_same_definitions():
    doc = " ".join(bench_fidelity.__doc__.split())
    table = bench_fidelity.format_table(bench_fidelity.compare([one_push_scene()], [one_push_scene()], 10, 10),
                                        1, 1, 10, 10)
    for label, definition in fs.STATISTICS.values():
        assert " ".join(f"{label}: {definition}".split()) in doc, label
        assert f"{label}: {definition}" in table, label
    assert " ".join(fs.PUSHED_OBJECT_RULE.split()) in doc


# --- readers -----------------------------------------------------------------------------------------------


@needs_reference
def test_reference_reader():
    records = bench_fidelity.read_reference(REFERENCE)
    assert len(records) == 36
    for rec in records:
        assert rec.positions.shape == (11, 4, 3) and rec.actions.shape == (10, 3)
        np.testing.assert_allclose(np.linalg.norm(rec.quaternions, axis=-1), 1.0, atol=1e-6)
        np.testing.assert_allclose(rec.tsdf_bands.sum(-1), 1.0, atol=1e-9)
        assert rec.actions[:, 0].min() >= 0 and rec.actions[:, 0].max() <= 7
    with h5py.File(REFERENCE, "r") as f:  # our band and count functions give the stored values
        for rec in records[:4]:
            g = f[rec.name]
            np.testing.assert_allclose(fs.tsdf_bands(g["tsdf_step0"][()]), rec.tsdf_bands[0], atol=1e-12)
            assert fs.voxel_counts(g["mask_3d_step0"][()], 4).tolist() == rec.voxels_per_object[0].tolist()
    # the inferred pushed object is plausible: its centre 4-9 cm ahead of the start, as the authors' policy puts it
    start = np.concatenate([fs.push_starts(r.actions) for r in records])
    pushed_xy = np.concatenate([r.positions[np.arange(10), fs.pushed_objects(r), :2] for r in records])
    assert np.median(np.linalg.norm(pushed_xy - start, axis=-1)) == pytest.approx(0.065, abs=0.015)


def test_reference_reader_errors(tmp_path):
    from dsr_bench.errors import UserError

    with pytest.raises(UserError, match="file not found"):
        bench_fidelity.read_reference(tmp_path / "missing.h5")
    (tmp_path / "text.h5").write_text("not hdf5")
    with pytest.raises(UserError, match="not a readable HDF5"):
        bench_fidelity.read_reference(tmp_path / "text.h5")
    with h5py.File(tmp_path / "partial.h5", "w") as f:
        f.create_dataset("seq_0000/positions", data=np.zeros((2, 1, 3)))
    with pytest.raises(UserError, match="lacks orientations"):
        bench_fidelity.read_reference(tmp_path / "partial.h5")


def _write_official(root: Path, rec: fs.Record, seq_id: str, masks: np.ndarray, tsdfs: np.ndarray) -> None:
    """The datasets the reader uses, in the official per-step layout (<id>_<t>.hdf5, final in next/)."""
    T = rec.num_pushes
    for t in range(T):
        with h5py.File(root / f"{seq_id}_{t}.hdf5", "w") as f:
            f["action"] = rec.actions[t].astype(np.int64)
            f["positions"], f["orientations"] = rec.positions[t], rec.quaternions[t]
            f.create_dataset("mask_3d", data=masks[t].astype(np.int64), compression="gzip")
            f.create_dataset("tsdf", data=tsdfs[t].astype(np.float32), compression="gzip")
            if t == T - 1:
                f["next/positions"], f["next/orientations"] = rec.positions[T], rec.quaternions[T]
                f.create_dataset("next/mask_3d", data=masks[T].astype(np.int64), compression="gzip")


def test_official_dir_reader(tmp_path):
    rec = one_push_scene()
    masks = np.zeros((2,) + GRID_SHAPE, np.int64)
    masks[0, :10, :10, :10] = 1
    masks[0, 50:52, 50:55, :3] = 2
    masks[1, :5, :5, :5] = 1
    tsdfs = np.ones((1,) + GRID_SHAPE, np.float32)
    tsdfs[0, :, :, :6] = -0.5
    tsdfs[0, :, :, 6:9] = 0.25
    _write_official(tmp_path, rec, "3", masks, tsdfs)
    (got,) = bench_fidelity.read_official_dir(tmp_path)
    np.testing.assert_array_equal(got.positions, rec.positions)
    np.testing.assert_array_equal(got.quaternions, rec.quaternions)
    np.testing.assert_array_equal(got.actions, rec.actions)
    assert got.voxels_per_object.tolist() == [[1000, 30], [125, 0]]
    np.testing.assert_allclose(got.tsdf_bands, [[6 / 48, 3 / 48, 39 / 48]])
    from dsr_bench.errors import UserError

    with pytest.raises(UserError, match="not a directory"):
        bench_fidelity.read_official_dir(tmp_path / "nope")
    (tmp_path / "3_0.hdf5").unlink()
    with pytest.raises(UserError, match="no <seq>_<step>.hdf5 files"):
        bench_fidelity.read_official_dir(tmp_path)


def test_ours_reader(tmp_path):
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.testing import write_synthetic_dataset

    data = write_synthetic_dataset(tmp_path / "data", num_sequences=2, num_steps=2, num_objects=2)
    records, chosen = bench_fidelity.read_ours(data)
    assert [r.name for r in records] == ["seq_0000", "seq_0001"]
    with SequenceReader(data / "seq_0001.h5") as seq:
        poses = seq.read("object_poses")
        np.testing.assert_array_equal(records[1].positions, poses[..., :3])
        np.testing.assert_array_equal(records[1].quaternions, poses[..., 3:])
        np.testing.assert_array_equal(records[1].actions, seq.read("action"))
        assert records[1].voxels_per_object[2].tolist() == fs.voxel_counts(seq.read("mask_3d", 2), 2).tolist()
        np.testing.assert_allclose(records[1].tsdf_bands[1], fs.tsdf_bands(seq.read("tsdf", 1)))
    assert all(c is not None and len(c) == 2 for c in chosen)
    assert bench_fidelity.inference_agreement(records, chosen) == 1.0


# --- the command line ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("args, match", [
    (["--ours", "{tmp}/missing"], "--ours"),
    (["--ours", "{tmp}", "--reference", "{tmp}/missing.h5"], "--reference"),
    (["--ours", "{tmp}", "--official-dir", "{tmp}/missing"], "--official-dir"),
    (["--ours", "{tmp}", "--json", "{tmp}/no/such/dir/out.json"], "--json"),
    (["--bootstrap", "0"], "--bootstrap"),
    (["--ours", "{tmp}", "--paired-with", "{tmp}/missing"], "--paired-with"),
    (["--ours", "{tmp}", "{tmp}", "--paired-with", "{tmp}"], "2 of --ours"),
])
def test_bad_arguments_give_one_line_and_exit_2(tmp_path, capsys, args, match):
    from official import run_main

    with pytest.raises(SystemExit) as exc:
        run_main(bench_fidelity.main, [a.format(tmp=tmp_path) for a in args])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ") and match in err


def test_bad_path_from_a_real_process(tmp_path):
    proc = subprocess.run([sys.executable, str(BENCH / "bench_fidelity.py"), "--ours", str(tmp_path / "missing")],
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and "--ours" in proc.stderr
    assert proc.stdout == ""


def test_end_to_end_on_synthetic_sequences(tmp_path, capsys):
    from dsr_bench.testing import write_synthetic_dataset

    ours = write_synthetic_dataset(tmp_path / "ours", num_sequences=3, num_steps=2, num_objects=2)
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    records, _ = bench_fidelity.read_ours(ours)
    for i, rec in enumerate(records):  # our own sequences, written in the official layout
        masks = np.zeros((rec.num_pushes + 1,) + GRID_SHAPE, np.int64)
        masks[:, :10, :10, :10] = 1
        masks[:, 20:30, 20:30, :10] = 2
        _write_official(theirs, rec, str(i), masks, np.ones((rec.num_pushes,) + GRID_SHAPE, np.float32))
    out = tmp_path / "out.json"
    payload = bench_fidelity.main(["--ours", str(ours), "--official-dir", str(theirs), "--bootstrap", "50",
                                   "--permutations", "50", "--json", str(out)])
    printed = capsys.readouterr().out
    assert "objects moving per push" in printed and "3 sequences" in printed
    saved = json.loads(out.read_text())
    assert [row["key"] for row in saved["statistics"]] == list(fs.STATISTICS)
    assert saved["bootstrap"] == 50 and saved["permutations"] == 50 and saved["ours"]["sequences"] == 3
    by_key = {row["key"]: row for row in saved["statistics"]}
    # same poses and actions on both sides: those rows agree exactly
    for key in ("pushed_translation_cm", "start_distance_cm", "direction_resultant"):
        assert by_key[key]["authors"]["mean"] == pytest.approx(by_key[key]["ours"]["mean"])
        assert by_key[key]["p"] == pytest.approx(1.0)
    assert by_key["voxels_t0"]["authors"]["mean"] == 1000
    assert payload["statistics"][0]["key"] == "moving_per_push"

    paired = bench_fidelity.main(["--ours", str(ours), str(ours), "--official-dir", str(theirs), "--paired-with",
                                  str(ours), str(ours), "--bootstrap", "50", "--permutations", "50"])
    assert "paired with" in capsys.readouterr().out
    assert paired["ours"]["sequences"] == 6  # two directories pooled, their sequences paired directory by directory
    assert all(row["n"] == 6 and row["mean"] == 0.0 for row in paired["paired"]["statistics"])
