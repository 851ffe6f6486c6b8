"""PyTorch datasets: model-ready windows from our format and the official layout, with workers."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dsr_bench.errors import UserError  # noqa: E402
from dsr_bench.sequence import SequenceReader  # noqa: E402
from dsr_bench.testing import write_synthetic_dataset  # noqa: E402
from dsr_bench.torch_data import OfficialWindowDataset, SequenceWindowDataset, action_map  # noqa: E402


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("td") / "data", num_sequences=2, num_steps=3)


def test_windows_shapes_values_and_count(data):
    ds = SequenceWindowDataset(data, "test", window=2)
    assert len(ds) == 2 * 2  # starts 0 and 1 in each 3-push sequence
    item = ds[1]
    assert item["sequence"] == "seq_0000" and item["start"] == 1
    assert item["tsdf"].shape == (2, 128, 128, 48) and item["tsdf"].dtype == torch.float32
    assert item["action"].shape == (2, 8, 128, 128) and item["action"].sum() == 2
    assert item["mask_3d"].dtype == torch.int64 and item["scene_flow_3d"].shape == (2, 3, 128, 128, 48)
    with SequenceReader(data / "seq_0000.h5") as seq:
        assert np.array_equal(item["tsdf"].numpy(), seq.read("tsdf", slice(1, 3)))
        assert np.array_equal(item["scene_flow_3d"].numpy(), seq.read("scene_flow_3d", slice(1, 3)))
        d, r, c = seq.read("action", 1)
        assert item["action"][0, d, r, c] == 1


def test_action_map_one_hot():
    m = action_map(np.array([[3, 5, 7], [0, 127, 0]]))
    assert m.shape == (2, 8, 128, 128) and m[0, 3, 5, 7] == 1 and m[1, 0, 127, 0] == 1 and m.sum() == 2


def test_dataloader_with_workers(data):
    ds = SequenceWindowDataset(data, None, window=1, fields=("tsdf", "mask_3d"))
    loader = torch.utils.data.DataLoader(ds, batch_size=3, num_workers=2, shuffle=False)
    batches = list(loader)
    assert sum(len(b["sequence"]) for b in batches) == len(ds) == 6
    assert batches[0]["tsdf"].shape == (3, 1, 128, 128, 48) and "action" not in batches[0]


def test_errors(data):
    with pytest.raises(UserError, match="fewer than the window"):
        SequenceWindowDataset(data, "test", window=4)
    with pytest.raises(UserError, match="not found"):
        SequenceWindowDataset(data, "train")
    with pytest.raises(UserError, match="unknown fields"):
        SequenceWindowDataset(data, "test", fields=("rgb",))


def test_official_layout_windows(tmp_path):
    from test_official import write_official_fixture

    truth = write_official_fixture(tmp_path, ids=("4",))
    (tmp_path / "train.txt").write_text("4\n")
    ds = OfficialWindowDataset(tmp_path, "train", window=2)
    assert len(ds) == 2
    item = ds[0]
    assert item["scene_flow_3d"].shape == (2, 3, 128, 128, 48)
    assert np.array_equal(item["mask_3d"][1].numpy(), truth["4"][1]["mask_3d"])
    assert np.array_equal(item["tsdf"][0].numpy(), truth["4"][0]["tsdf"])
