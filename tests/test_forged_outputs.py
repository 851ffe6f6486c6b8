"""Inputs and outputs a user gets wrong, refused in one line before any work: unwritable outputs (immutable, as
root ignores permission bits), a predictions path that is a file, a 3D submission that holds motion_2d in only some
files, and the refusal's advice when --allow-partial was given already."""

import shutil
import subprocess
from pathlib import Path

import h5py
import pytest

from dsr_bench.cli import main
from dsr_bench.testing import write_synthetic_dataset


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("out") / "data", num_sequences=2, num_steps=2)


@pytest.fixture(scope="module")
def oracle(data) -> Path:
    assert main(["predict", "--model", "oracle", "--data", str(data), "--out", str(data.parent / "oracle")]) == 0
    return data.parent / "oracle"


@pytest.fixture
def immutable(tmp_path):
    """A directory nothing can be created in, even by root (chattr +i); removed from the test's way after it."""
    folder = tmp_path / "immutable"
    folder.mkdir()
    if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode:
        pytest.skip("chattr +i is not available on this file system")
    try:
        yield folder
    finally:
        subprocess.run(["chattr", "-i", str(folder)], check=True)


def _one_line_refusal(capsys, args: list[str]) -> str:
    capsys.readouterr()
    assert main(args) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ") and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("command", ["evaluate", "predict", "import-official"])
def test_an_unwritable_output_is_refused_before_any_work(data, oracle, immutable, capsys, monkeypatch, command):
    import dsr_bench.scoring.evaluate as evaluate_module

    monkeypatch.setattr(evaluate_module, "evaluate", lambda *a, **k: pytest.fail("scored before checking --out"))
    target = immutable / "out"
    args = {"evaluate": ["evaluate", str(oracle), "--data", str(data), "--out", str(target / "r.json")],
            "predict": ["predict", "--model", "static", "--data", str(data), "--out", str(target)],
            "import-official": ["import-official", str(data), str(target)]}[command]
    err = _one_line_refusal(capsys, args)
    assert str(target) in err and "cannot create files in" in err and str(immutable) in err
    assert list(immutable.iterdir()) == []


def test_an_immutable_results_file_is_refused_before_scoring(data, oracle, tmp_path, capsys):
    out = tmp_path / "r.json"
    out.write_text("{}")
    subprocess.run(["chattr", "+i", str(out)], check=False)
    try:
        if subprocess.run(["lsattr", str(out)], capture_output=True, text=True).stdout[:20].count("i") == 0:
            pytest.skip("chattr +i is not available on this file system")
        err = _one_line_refusal(capsys, ["evaluate", str(oracle), "--data", str(data), "--out", str(out)])
        assert f"--out {out}: cannot be replaced" in err and "chattr -i" in err
    finally:
        subprocess.run(["chattr", "-i", str(out)], check=False)
    assert out.read_text() == "{}" and not (tmp_path / "r-steps.png").exists()


def test_a_predictions_path_that_is_a_file_says_so(data, oracle, capsys):
    err = _one_line_refusal(capsys, ["evaluate", str(oracle / "seq_0000.h5"), "--data", str(data)])
    assert "seq_0000.h5 is a file, not a predictions directory" in err
    err = _one_line_refusal(capsys, ["evaluate", str(oracle / "nowhere"), "--data", str(data)])
    assert "predictions directory not found" in err and "dsr-bench predict --out" in err


def test_a_3d_submission_with_motion_2d_in_some_files_says_the_2d_flow_is_not_scored(data, oracle, tmp_path, capsys):
    pred = tmp_path / "pred"
    shutil.copytree(oracle, pred)
    with h5py.File(pred / "seq_0001.h5", "r+") as f:
        assert "motion_2d" in f
        del f["motion_2d"]
    capsys.readouterr()
    out = tmp_path / "r.json"
    assert main(["evaluate", str(pred), "--data", str(data), "--out", str(out), "--workers", "1"]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "the 2D flow is not scored: 1 of 2" in warnings[0] and "seq_0001.h5" in warnings[0]
    assert "motion_2d" not in __import__("json").loads(out.read_text())["metrics"]


def test_nothing_scorable_with_allow_partial_does_not_advise_allow_partial(data, oracle, tmp_path, capsys):
    pred = tmp_path / "pred"
    shutil.copytree(oracle, pred)
    with h5py.File(pred / "seq_0001.h5", "r+") as f:  # a 2D-only file beside a 3D one: nothing passes
        del f["mask"], f["motion"]
    capsys.readouterr()
    assert main(["evaluate", str(pred), "--data", str(data), "--allow-partial", "--workers", "1"]) == 1
    captured = capsys.readouterr()
    text = captured.out + captured.err
    assert "mixed submission" in text and "no sequence could be scored" in text
    assert "with --allow-partial" not in text


def test_an_unwritable_leaderboard_is_refused_before_recomputing(tmp_path, immutable, capsys, monkeypatch):
    """`leaderboard add --root` into an immutable leaderboard: one line, exit 2, before the predictions are scored."""
    import json

    import dsr_bench.scoring.evaluate as evaluate_module
    from helpers import pin_split

    data = write_synthetic_dataset(tmp_path / "data", num_sequences=1, num_steps=1, split="procedural-novel-mini")
    pin_split(monkeypatch, data, "procedural-novel-mini")
    pred = tmp_path / "static"
    assert main(["predict", "--model", "static", "--data", str(data), "--out", str(pred)]) == 0
    results = tmp_path / "results.json"
    assert main(["evaluate", str(pred), "--out", str(results), "--workers", "1"]) == 0
    assert json.loads(results.read_text())["pinned"] is True
    monkeypatch.setattr(evaluate_module, "evaluate", lambda *a, **k: pytest.fail("scored before checking --root"))
    err = _one_line_refusal(capsys, ["leaderboard", "add", str(results), "--predictions", str(pred),
                                     "--root", str(immutable)])
    assert f"--root {immutable / 'entries'}" in err and "cannot create files in" in err
    assert list(immutable.iterdir()) == []
