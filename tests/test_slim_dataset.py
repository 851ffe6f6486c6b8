"""scripts/slim_dataset.py: a copy with the arrays training, prediction and scoring read, readable by the toolkit."""

import importlib.util
import json
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

pytest.importorskip("torch")  # the script takes the training fields from dsr_bench.models.data

from dsr_bench.dataset.sequence import DERIVED_ATTR, SequenceReader, derive_points, write_sequence  # noqa: E402
from dsr_bench.testing import synthetic_arrays  # noqa: E402

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "slim_dataset.py"


def _slim_module():
    spec = importlib.util.spec_from_file_location("slim_dataset", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_slim_copy_keeps_the_training_arrays_and_stays_readable(tmp_path, monkeypatch):
    arrays, attrs, meshes = synthetic_arrays(2, 2, 3)
    with SequenceReader(write_sequence(tmp_path / "probe.h5", arrays, attrs, meshes)) as probe:
        camera = probe.camera("front")
    # points exactly the depth's, so the writer leaves them out and lists them as derived (as the generator's files)
    arrays["cameras/front/points"] = derive_points(arrays["cameras/front/depth"], camera)
    src, dst = tmp_path / "src", tmp_path / "dst"
    write_sequence(src / "seq_0000.h5", arrays, attrs, meshes)
    (src / "splits").mkdir()
    (src / "splits" / "test.txt").write_text("seq_0000\n")
    (src / "manifest.json").write_text(json.dumps({"split": "test"}))
    with h5py.File(src / "seq_0000.h5", "r") as f:
        assert json.loads(f.attrs[DERIVED_ATTR]) == ["cameras/front/points"]
        truth = f.attrs["ground_truth_sha256"]  # computed by write_sequence

    monkeypatch.setattr(sys, "argv", ["slim_dataset.py", str(src), str(dst)])
    _slim_module().main()
    with SequenceReader(dst / "seq_0000.h5") as seq:  # the cameras are gone, and so is the list derived from them
        assert seq.array_names() == ["action", "mask_3d", "object_poses", "scene_flow_3d", "tsdf", "visible_fraction"]
        assert not seq.derived and DERIVED_ATTR not in seq.attrs
        for name in seq.array_names():
            assert np.array_equal(seq.read(name), arrays[name]), name
        assert seq.dataset("tsdf").compression_opts == 9 and seq.dataset("scene_flow_3d").chunks == (1, 3, 16, 16, 48)
        assert seq.dataset("tsdf").attrs["units"] == "truncation (0.02 m)"
        assert seq.attrs["cameras"] == attrs["cameras"] and seq.attrs["ground_truth_sha256"] == truth
    assert (dst / "splits" / "test.txt").read_text() == "seq_0000\n"
    assert (dst / "manifest.json").read_bytes() == (src / "manifest.json").read_bytes()
