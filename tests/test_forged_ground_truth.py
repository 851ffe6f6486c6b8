"""Forged ground truth: `evaluate` recomputes the digests of what it scores and compares them with the toolkit's pin,
never with the files' own digest attributes (dsr_bench/dataset/scored.py, dsr_bench/dataset/pins.verify_scored)."""

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from dsr_bench.cli import main
from dsr_bench.dataset.manifest import build_manifest, write_manifest
from dsr_bench.dataset.scored import SCORED_FIELDS, ScoredDigests, file_scored_digests, nonzero_rows
from dsr_bench.dataset.splits import pinned_digests
from dsr_bench.dataset.storage import read_step_and_columns
from dsr_bench.scoring.evaluate import score_sequence
from dsr_bench.testing import write_synthetic_dataset
from helpers import pin_split

SPLIT = "procedural-novel-mini"


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    data = write_synthetic_dataset(tmp_path_factory.mktemp("gt") / "data", num_sequences=2, num_steps=2, split=SPLIT)
    assert main(["predict", "--model", "oracle", "--data", str(data), "--out", str(data.parent / "oracle")]) == 0
    return data


@pytest.fixture
def pinned(clean, monkeypatch, tmp_path) -> Path:
    """A copy of the pinned synthetic split, to forge."""
    pin_split(monkeypatch, clean, SPLIT)
    data = tmp_path / "data"
    shutil.copytree(clean, data)
    return data


def _edit(path: Path, name: str, edit) -> None:
    """Rewrite one array of a file in place (its digest attributes left as they were)."""
    with h5py.File(path, "r+") as f:
        values = f[name][()]
        edit(values)
        f[name][...] = values


def _evaluate(clean: Path, data: Path, capsys, out: Path) -> tuple[dict, list[str]]:
    capsys.readouterr()
    assert main(["evaluate", str(clean.parent / "oracle"), "--data", str(data), "--out", str(out),
                 "--workers", "1"]) == 0
    err = capsys.readouterr().err
    return json.loads(out.read_text()), [line for line in err.splitlines() if line.startswith("warning:")]


def test_a_pinned_split_scores_pinned_and_records_what_it_scored(clean, pinned, capsys, tmp_path):
    results, warnings = _evaluate(clean, pinned, capsys, tmp_path / "r.json")
    assert warnings == [] and results["pinned"] is True and results["ground_truth_verified"] is True
    assert len(results["ground_truth_sha256"]) == 64
    files = results["predictions_sha256"]
    assert sorted(files) == ["seq_0000", "seq_0001"] and all(len(v) == 64 for v in files.values())


@pytest.mark.parametrize("array, field", [
    ("mask_3d", "mask_3d"),  # one voxel of one object's amodal mask
    ("scene_flow_3d", "scene_flow_3d"),  # one flow value
    ("tsdf", "tsdf"),  # an object voxel moved into the visible surface band
])
def test_one_edited_value_unpins_the_results(clean, pinned, capsys, tmp_path, array, field):
    path = pinned / "seq_0001.h5"
    with h5py.File(path, "r") as f:
        mask = f["mask_3d"][1]
    y, x, z = np.argwhere(mask > 0)[0]

    def edit(values):
        if array == "mask_3d":
            values[1, y, x, z] = 0
        elif array == "scene_flow_3d":
            values[1, 0, y, x, z] += 3.0
        else:
            values[1, y, x, z] = -0.5 if not -0.99 < values[1, y, x, z] < 0 else 0.5

    _edit(path, array, edit)
    results, warnings = _evaluate(clean, pinned, capsys, tmp_path / "r.json")
    assert results["pinned"] is False and results["ground_truth_verified"] is False
    assert len(warnings) == 1 and str(path) in warnings[0] and " differ from the pinned" in warnings[0], warnings
    assert field in warnings[0].split(f"{path}: ")[1].split(" differ")[0].split(", ")
    assert f"dsr-bench generate --split {SPLIT}" in warnings[0]


def test_zeroed_flow_with_rewritten_attributes_and_manifest_is_caught(clean, pinned, capsys, tmp_path):
    """A careful forger rewrites the files' digest attributes and the manifest after zeroing every flow: the static
    model would score 0; the manifest's checksum now differs from the pin, and the recomputed digests too."""
    from dsr_bench.dataset.sequence import file_digests

    for path in sorted(pinned.glob("seq_*.h5")):
        _edit(path, "scene_flow_3d", lambda v: v.fill(0))
        found = file_digests(path)
        with h5py.File(path, "r+") as f:
            for key in ("ground_truth_sha256", "observations_sha256", "content_sha256"):
                f.attrs[key] = found[key]
            f.attrs["array_sha256"] = json.dumps(found["array_sha256"], sort_keys=True)
    write_manifest(pinned, build_manifest(pinned))
    results, warnings = _evaluate(clean, pinned, capsys, tmp_path / "r.json")
    assert results["pinned"] is False and results["ground_truth_verified"] is False
    assert len(warnings) == 1 and "not this toolkit's pin" in warnings[0]


def test_an_object_voxel_outside_the_band_may_change_without_changing_the_score(clean, pinned, capsys, tmp_path):
    """The TSDF enters the score only as the band at object voxels: a change that keeps every band bit is no
    different benchmark (and scores the same)."""
    path = pinned / "seq_0000.h5"
    with h5py.File(path, "r") as f:
        mask, tsdf = f["mask_3d"][0], f["tsdf"][0]
    free = np.argwhere((mask == 0) & (tsdf > 0))[0]
    _edit(path, "tsdf", lambda v: v.__setitem__((0, *free), 0.25))
    results, warnings = _evaluate(clean, pinned, capsys, tmp_path / "r.json")
    assert warnings == [] and results["pinned"] is True


def test_a_split_list_with_a_sequence_left_out_is_not_the_pinned_split(clean, pinned, capsys, tmp_path):
    (pinned / "splits" / f"{SPLIT}.txt").write_text("seq_0000\n")
    (pinned / "seq_0001.h5").unlink()
    write_manifest(pinned, build_manifest(pinned))
    oracle = tmp_path / "oracle"
    shutil.copytree(clean.parent / "oracle", oracle)
    (oracle / "seq_0001.h5").unlink()
    capsys.readouterr()
    out = tmp_path / "r.json"
    assert main(["evaluate", str(oracle), "--data", str(pinned), "--out", str(out), "--workers", "1"]) == 0
    err = capsys.readouterr().err
    assert json.loads(out.read_text())["pinned"] is False and "warning:" in err


def test_the_fast_tiled_reader_and_the_plain_reader_give_the_same_digests(clean, tmp_path):
    """evaluate's digests (tiles never written skipped) equal the plain definition's, and equal them for the same
    arrays stored in h5py's own layout (a file we did not write)."""
    src = clean / "seq_0000.h5"
    name, problems, out = score_sequence(("seq_0000", str(clean.parent / "oracle" / "seq_0000.h5"), str(src)))
    assert problems == [] and out["scored_digests"] == file_scored_digests(src)
    assert set(out["scored_digests"]) == set(SCORED_FIELDS)
    plain = tmp_path / "plain.h5"
    with h5py.File(src, "r") as f, h5py.File(plain, "w") as g:
        for key, value in f.attrs.items():
            g.attrs[key] = value

        def copy(name, obj):  # h5py's default layout: auto-chunked, no filters, every chunk written
            if isinstance(obj, h5py.Dataset):
                g.create_dataset(name, data=obj[()], chunks=True if obj.ndim > 1 else None)

        f.visititems(copy)
    assert file_scored_digests(plain) == file_scored_digests(src)
    with h5py.File(src, "r") as f, h5py.File(plain, "r") as g:
        for t in range(f["scene_flow_3d"].shape[0]):
            a, cols_a = read_step_and_columns(f["scene_flow_3d"], t)
            b, cols_b = read_step_and_columns(g["scene_flow_3d"], t)
            assert np.array_equal(a, b) and np.array_equal(cols_a, cols_b)
            assert cols_a.any() and not cols_a.all()


def test_the_digests_see_bytes_steps_and_dtypes():
    """-0.0 is not 0.0, the same values at another step or in another dtype are another ground truth."""
    flow = np.zeros((3, 4, 4, 8), np.float32)
    flow[1, 2, 3, 5] = 1.5

    def digest(f, t=0):
        d = ScoredDigests()
        d.flow_step(t, f)
        return d.hexdigests()["scene_flow_3d"]

    negative_zero = flow.copy()
    negative_zero[0, 0, 0, 0] = -0.0
    assert nonzero_rows(negative_zero.reshape(-1, 8))[0]
    assert len({digest(flow), digest(negative_zero), digest(flow, t=1), digest(flow.astype(np.float64))}) == 4
    moved = np.zeros_like(flow)
    moved[1, 3, 2, 5] = 1.5  # the same column content at another (y, x)
    assert digest(moved) != digest(flow)


def test_every_shipped_pin_holds_the_scored_digests():
    """evaluate can verify every pinned split: each pinned sequence has every 3D field's scored digest."""
    pins = pinned_digests()
    assert pins, "no pinned splits"
    for split, pin in pins.items():
        for name, entry in pin["sequences"].items():
            scored = entry.get("scored")
            assert scored is not None, f"{split}/{name} has no scored digests"
            assert {"objects", "mask_3d", "tsdf", "scene_flow_3d", "visible_fraction"} <= set(scored), (split, name)
            assert all(len(v) == 32 for v in scored.values())


def test_an_entry_must_name_the_pinned_ground_truth_it_was_scored_on(clean, pinned, capsys, tmp_path):
    """An entry's ground_truth_sha256 is checked against the pin's scored digests (by `add` and by `build`), so an
    entry cannot claim the pinned split while holding the digest of other ground truth."""
    from dsr_bench.leaderboard.entries import check_entry

    results, _ = _evaluate(clean, pinned, capsys, tmp_path / "r.json")
    assert check_entry(results) == []
    forged = {**results, "ground_truth_sha256": "0" * 64}
    assert any("ground_truth_sha256 is not that of the pinned" in p for p in check_entry(forged))
