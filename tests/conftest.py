"""Shared fixtures: a small dataset made by the real generator (procedural-novel objects)."""

from pathlib import Path

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
