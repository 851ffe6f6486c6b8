"""Shared fixtures: a small dataset made by the real generator (procedural-novel objects), and a simulated
two-camera capture with its true poses for the annotator's tests (a module may define its own capture_dir)."""

from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="session")
def generated_dataset(tmp_path_factory) -> Path:
    """2 sequences x 3 pushes of 3 procedural-novel objects, seed 3: the pinned-score fixture."""
    pytest.importorskip("pybullet")
    from dsr_bench.cli import main

    out = tmp_path_factory.mktemp("generated") / "data"
    assert main(["generate", "--objects", "procedural-novel", "-n", "2", "--steps", "3", "--objects-per-scene", "3",
                 "--seed", "3", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    pytest.importorskip("pybullet")
    pytest.importorskip("open3d")
    from dsr_bench.generators.capture import generate_capture

    out = tmp_path_factory.mktemp("captures") / "seq_000"
    return generate_capture(out, name="seq_000", seed=1, steps=3, objects_per_scene=3, noise="none",
                            image_shape=(240, 320))


@pytest.fixture(scope="module")
def truth(capture_dir) -> np.ndarray:
    from dsr_bench.dataset.capture import load_capture

    return load_capture(capture_dir).truth_poses()


@pytest.fixture
def board(tmp_path, monkeypatch):
    """An empty leaderboard directory with the paper's rows, procedural-novel-mini pinned to "c" * 64."""
    import shutil

    from dsr_bench.dataset.splits import SPLITS, Split

    root = tmp_path / "leaderboard"
    root.mkdir()
    shutil.copy(Path(__file__).resolve().parents[1] / "leaderboard" / "paper.json", root / "paper.json")
    spec = SPLITS["procedural-novel-mini"]
    monkeypatch.setitem(SPLITS, spec.name, Split(**{**spec.__dict__, "pinned_checksum": "c" * 64}))
    return root


@pytest.fixture(scope="session")
def sim(tmp_path_factory):
    """A simulated two-camera capture without sensor noise (2 pushes, 3 objects, 240 x 320): the scene the importer
    tests write in each real input form (PNG folder, RealSense bags)."""
    pytest.importorskip("pybullet")
    pytest.importorskip("open3d")
    from dsr_bench.dataset.capture import load_capture
    from dsr_bench.generators.capture import generate_capture

    out = tmp_path_factory.mktemp("sim") / "seq_000"
    generate_capture(out, name="seq_000", seed=1, steps=2, objects_per_scene=3, noise="none", image_shape=(240, 320))
    return load_capture(out)
