"""scripts/split_gap.py: one model's scores on the scenes it trained on against new ones, each mean ± its standard
error, their difference ± the standard error of two independent means, and each IoU as a fraction of its split's
ceiling; inputs it cannot compare (other weights, a ceiling of another split, a value that is not a number, a folder
without results) are one line and exit 2."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import split_gap  # noqa: E402


def _results(split: str, values: list[float], sha: str = "ab" * 32) -> dict:
    """`evaluate` results as it writes them: each sequence's value of every metric (its mean over the steps)."""
    per = {f"seq_{i:04d}": {m: v for m in split_gap.METRICS} for i, v in enumerate(values)}
    return {"split": split, "split_checksum": f"{split}-checksum", "per_sequence": per,
            "metrics": {m: float(np.mean(values)) for m in split_gap.METRICS},
            "meta": {"parameters": {"weights": {"file": "dsr.pt", "sha256": sha}}}}


def _work(folder: Path, split: str, values: list[float], ceiling: float) -> Path:
    folder.mkdir()
    (folder / "dsr.json").write_text(json.dumps(_results(split, values)))
    cap = _results(split, [ceiling] * len(values))
    del cap["meta"]
    (folder / "oracle-pooled.json").write_text(json.dumps(cap))
    return folder


def _edit(path: Path, change) -> None:
    results = json.loads(path.read_text())
    change(results)
    path.write_text(json.dumps(results))


def test_the_gap_its_standard_error_and_the_fraction_of_each_ceiling(tmp_path, capsys):
    seen = _work(tmp_path / "seen", "train-first100", [0.45, 0.55, 0.65], 0.8)
    unseen = _work(tmp_path / "unseen", "cpu-val", [0.35, 0.55], 0.5)
    assert split_gap.main(["--seen", str(seen), "--unseen", str(unseen), "--models", "dsr",
                           "--out", str(tmp_path / "gap.json")]) == 0
    summary = json.loads((tmp_path / "gap.json").read_text())
    row = summary["models"]["dsr"]["iou_ordered"]
    se_seen, se_unseen = 0.1 / np.sqrt(3), np.sqrt(0.02) / np.sqrt(2)
    assert row["seen"] == pytest.approx([0.55, se_seen]) and row["unseen"] == pytest.approx([0.45, se_unseen])
    assert row["difference"] == pytest.approx([0.10, np.hypot(se_seen, se_unseen)])
    assert row["of_ceiling"] == pytest.approx([0.55 / 0.8, 0.45 / 0.5])
    assert "of_ceiling" not in summary["models"]["dsr"]["motion_visible"]  # a fraction of a ceiling is IoU's alone
    assert "dsr iou_ordered: seen 0.5500" in capsys.readouterr().out
    assert (summary["seen"]["split"], summary["seen"]["sequences"], summary["unseen"]["sequences"]) == \
        ("train-first100", 3, 2)
    assert summary["weights"] == {"dsr": "ab" * 32} and summary["ceiling"]["unseen"]["iou_ordered"] == 0.5


@pytest.mark.parametrize("where, change, message", [
    ("unseen/dsr.json", lambda r: r["meta"]["parameters"]["weights"].update(sha256="cd" * 32),
     "were not predicted with one recorded weights file"),
    ("unseen/oracle-pooled.json", lambda r: r.update(split_checksum="other"), "scored another split than"),
    ("seen/dsr.json", lambda r: r["per_sequence"]["seq_0001"].update(iou_ordered=None),
     "per_sequence seq_0001 iou_ordered is None, not a number"),
    ("seen/dsr.json", lambda r: r["per_sequence"].pop("seq_0001"),  # one sequence left: no standard error
     "not `dsr-bench evaluate` results of two or more sequences"),
    ("seen/dsr.json", lambda r: r.clear(), "not `dsr-bench evaluate` results")])
def test_inputs_that_cannot_be_compared_are_one_line(tmp_path, capsys, where, change, message):
    seen = _work(tmp_path / "seen", "a", [0.4, 0.5], 0.8)
    unseen = _work(tmp_path / "unseen", "b", [0.4, 0.5], 0.8)
    _edit(tmp_path / where, change)
    assert split_gap.main(["--seen", str(seen), "--unseen", str(unseen), "--models", "dsr"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and message in err and "\n" not in err


def test_a_folder_without_a_models_results_is_one_line(tmp_path, capsys):
    seen = _work(tmp_path / "seen", "a", [0.4, 0.5], 0.8)
    assert split_gap.main(["--seen", str(seen), "--unseen", str(tmp_path), "--models", "dsr"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {tmp_path / 'dsr.json'}: not readable") and "\n" not in err
