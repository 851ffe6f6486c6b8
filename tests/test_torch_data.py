"""PyTorch datasets: model-ready windows from our format and the official layout, with workers."""

import shutil

import h5py
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dsr_bench.errors import UserError  # noqa: E402
from dsr_bench.dataset.official import import_official  # noqa: E402
from dsr_bench.dataset.sequence import SequenceReader  # noqa: E402
from dsr_bench.testing import write_synthetic_dataset  # noqa: E402
from dsr_bench.models.data import (OfficialWindowDataset, SequenceWindowDataset, action_map,  # noqa: E402
                                  batch_to_device, collate_compact)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("td") / "data", num_sequences=2, num_steps=3)


def test_windows_shapes_values_and_count(data):
    ds = SequenceWindowDataset(data, "test", window=2)
    assert len(ds) == 2 * 2  # starts 0 and 1 in each 3-push sequence
    item = ds[1]
    assert item["sequence"] == "seq_0000" and item["start"] == 1
    assert item["tsdf"].shape == (2, 128, 128, 48) and item["tsdf"].dtype == torch.float32
    assert item["action"].shape == (2, 8, 128, 128) and item["action"].dtype == torch.float32
    assert item["action"].sum() == 2
    assert item["mask_3d"].dtype == torch.uint8 and item["scene_flow_3d"].shape == (2, 3, 128, 128, 48)
    with SequenceReader(data / "seq_0000.h5") as seq:
        assert np.array_equal(item["tsdf"].numpy(), seq.read("tsdf", slice(1, 3)))
        assert np.array_equal(item["mask_3d"].numpy(), seq.read("mask_3d", slice(1, 3)))
        assert np.array_equal(item["scene_flow_3d"].numpy(), seq.read("scene_flow_3d", slice(1, 3)))
        for k in range(2):
            d, r, c = seq.read("action", 1 + k)
            assert item["action"][k, d, r, c] == 1


def test_stride_and_no_manifest(data, tmp_path):
    ds = SequenceWindowDataset(data, "test", window=1, stride=2)
    assert [(i[1], i[2]) for i in ds.items] == [("seq_0000", 0), ("seq_0000", 2), ("seq_0001", 0), ("seq_0001", 2)]
    copy = tmp_path / "d"
    shutil.copytree(data, copy)
    (copy / "manifest.json").unlink()  # step counts then come from the files
    assert [i[1:] for i in SequenceWindowDataset(copy, "test", window=3).items] == [("seq_0000", 0), ("seq_0001", 0)]


def test_compact_batches_rebuild_the_dense_tensors_exactly(data):
    """collate_compact sends the flow as its non-zero voxels and the actions as indices; batch_to_device
    rebuilds default_collate's tensors bit for bit, also through worker processes."""
    ds = SequenceWindowDataset(data, "test", window=2)
    items = [ds[i] for i in range(len(ds))]
    dense = torch.utils.data.default_collate(items)
    compact = collate_compact(items)
    assert set(compact) == {"tsdf", "mask_3d", "action_index", "action_shape", "flow_index", "flow_value",
                            "flow_shape", "sequence", "start"}
    moving = int(dense["scene_flow_3d"].ne(0).any(2).sum())
    assert 0 < moving == len(compact["flow_index"]) < dense["mask_3d"].numel() // 10  # a few % of the voxels
    assert compact["action_index"].shape == (4, 2) and compact["flow_value"].shape == (moving, 3)
    rebuilt = batch_to_device(compact, "cpu")
    assert set(rebuilt) == {"tsdf", "mask_3d", "action", "scene_flow_3d"}
    for key in rebuilt:
        assert rebuilt[key].dtype == dense[key].dtype and torch.equal(rebuilt[key], dense[key]), key
    pinned_like = {**compact, "action_shape": list(compact["action_shape"]), "flow_shape": list(compact["flow_shape"])}
    # the DataLoader's pinning turns the shape tuples into lists
    assert all(torch.equal(v, rebuilt[k]) for k, v in batch_to_device(pinned_like, "cpu").items())
    sent = sum(v.numel() * v.element_size() for v in compact.values() if isinstance(v, torch.Tensor))
    full = sum(v.numel() * v.element_size() for v in dense.values() if isinstance(v, torch.Tensor))
    assert sent < 0.4 * full
    loader = torch.utils.data.DataLoader(ds, batch_size=4, num_workers=2, collate_fn=collate_compact)
    through_workers = batch_to_device(next(iter(loader)), "cpu")
    assert all(torch.equal(through_workers[k], dense[k]) for k in rebuilt)
    assert torch.equal(batch_to_device(dense, "cpu")["scene_flow_3d"], dense["scene_flow_3d"])  # dense passes through
    items[0]["action"][0, 1, 0, 0] = 1.0  # two entries: not one-hot
    with pytest.raises(ValueError, match="one-hot"):
        collate_compact(items)


def test_action_map_one_hot():
    m = action_map(np.array([[3, 5, 7], [0, 127, 0]]))
    assert m.shape == (2, 8, 128, 128) and m[0, 3, 5, 7] == 1 and m[1, 0, 127, 0] == 1 and m.sum() == 2


def test_dataloader_with_workers(data):
    ds = SequenceWindowDataset(data, None, window=1, fields=("tsdf", "mask_3d"))
    loader = torch.utils.data.DataLoader(ds, batch_size=3, num_workers=2, shuffle=False)
    batches = list(loader)
    assert sum(len(b["sequence"]) for b in batches) == len(ds) == 6
    assert batches[0]["tsdf"].shape == (3, 1, 128, 128, 48) and "action" not in batches[0]
    assert list(batches[1]["start"]) == [0, 1, 2] and list(batches[1]["sequence"]) == ["seq_0001"] * 3
    assert torch.equal(batches[1]["mask_3d"][2], ds[5]["mask_3d"])  # same values as the main process reads


def test_errors(data, tmp_path):
    with pytest.raises(UserError, match="fewer than the window"):
        SequenceWindowDataset(data, "test", window=4)
    with pytest.raises(UserError, match="not found"):
        SequenceWindowDataset(data, "train")
    with pytest.raises(UserError, match="unknown fields"):
        SequenceWindowDataset(data, "test", fields=("rgb",))
    with pytest.raises(UserError, match="must be at least 1"):
        SequenceWindowDataset(data, "test", stride=0)
    copy = tmp_path / "d"
    shutil.copytree(data, copy)
    ds = SequenceWindowDataset(copy, "test", window=2)
    with h5py.File(copy / "seq_0001.h5", "r+") as f:  # damaged after indexing: named when read
        del f["scene_flow_3d"]
        f["scene_flow_3d"] = np.zeros((3, 3, 128, 128, 40), np.float32)
    assert ds[0]["tsdf"].shape == (2, 128, 128, 48)
    with pytest.raises(UserError, match=r"seq_0001.h5: scene_flow_3d has shape \(3, 3, 128, 128, 40\)"):
        ds[2]


def test_official_layout_matches_the_imported_dataset(tmp_path):
    from test_official import STEPS, write_official_fixture

    rng = np.random.default_rng(1)

    def moving(data):  # integer-valued flow, as in the release
        if "scene_flow_3d" in data:
            data["scene_flow_3d"] = rng.integers(-3, 4, data["scene_flow_3d"].shape).astype(np.float64)

    src = tmp_path / "src"
    src.mkdir()
    truth = write_official_fixture(src, ids=("4",), change=moving)
    official = OfficialWindowDataset(src, "train", window=STEPS)
    assert len(official) == 1
    item = official[0]
    assert item["scene_flow_3d"].shape == (STEPS, 3, 128, 128, 48) and item["scene_flow_3d"].dtype == torch.float32
    assert np.array_equal(item["scene_flow_3d"][1].numpy(), np.moveaxis(truth["4"][1]["scene_flow_3d"], -1, 0))
    assert np.array_equal(item["mask_3d"][1].numpy(), truth["4"][1]["mask_3d"])
    assert np.array_equal(item["tsdf"][0].numpy(), truth["4"][0]["tsdf"])
    d, r, c = truth["4"][1]["action"]
    assert item["action"][1, d, r, c] == 1 and item["action"][1].sum() == 1
    import_official(src, tmp_path / "ours")
    ours = SequenceWindowDataset(tmp_path / "ours", "train", window=STEPS)[0]
    assert ours["sequence"] == "seq_0004" and item["sequence"] == "4"
    for key in ("tsdf", "action", "mask_3d", "scene_flow_3d"):
        assert ours[key].dtype == item[key].dtype and torch.equal(ours[key], item[key]), key
    loader = torch.utils.data.DataLoader(OfficialWindowDataset(src, "train", window=1), batch_size=2, num_workers=2)
    batch = next(iter(loader))
    assert torch.equal(batch["scene_flow_3d"][:, 0], item["scene_flow_3d"])
