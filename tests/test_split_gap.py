"""scripts/split_gap.py: one model's scores on the scenes it trained on against new ones, each mean ± its standard
error, their difference ± the standard error of two independent means, and each IoU as a fraction of its split's
ceiling; a folder without results is one line."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import split_gap  # noqa: E402


def _results(split: str, iou: list[float]) -> dict:
    """`evaluate` results whose sequences have two steps each, the first at `iou[i]` and the second 0.1 above."""
    per = {f"seq_{i:04d}": {m: [v, v + 0.1] for m in split_gap.METRICS} for i, v in enumerate(iou)}
    return {"split": split, "per_sequence": per, "metrics": {m: float(np.mean(iou)) + 0.05 for m in split_gap.METRICS},
            "meta": {"parameters": {"weights": {"file": "dsr.pt", "sha256": "ab" * 32}}}}


def _work(folder: Path, split: str, iou: list[float], ceiling: float) -> Path:
    folder.mkdir()
    (folder / "dsr.json").write_text(json.dumps(_results(split, iou)))
    (folder / "oracle-pooled.json").write_text(json.dumps(
        {"split": split, "per_sequence": {"seq_0000": {m: [ceiling] for m in split_gap.METRICS}},
         "metrics": {m: ceiling for m in split_gap.METRICS}}))
    return folder


def test_the_gap_its_standard_error_and_the_fraction_of_each_ceiling(tmp_path, capsys):
    seen = _work(tmp_path / "seen", "train-first100", [0.4, 0.5, 0.6], 0.8)
    unseen = _work(tmp_path / "unseen", "cpu-val", [0.3, 0.5], 0.5)
    assert split_gap.main(["--seen", str(seen), "--unseen", str(unseen), "--models", "dsr",
                           "--out", str(tmp_path / "gap.json")]) == 0
    row = json.loads((tmp_path / "gap.json").read_text())["models"]["dsr"]["iou_ordered"]
    se_seen, se_unseen = 0.1 / np.sqrt(3), np.sqrt(0.02) / np.sqrt(2)  # sequence means 0.45, 0.55, 0.65; 0.35, 0.55
    assert row["seen"] == pytest.approx([0.55, se_seen]) and row["unseen"] == pytest.approx([0.45, se_unseen])
    assert row["difference"] == pytest.approx([0.10, np.hypot(se_seen, se_unseen)])
    assert row["of_ceiling"] == pytest.approx([0.55 / 0.8, 0.45 / 0.5])
    assert "dsr iou_ordered: seen 0.5500" in capsys.readouterr().out
    summary = json.loads((tmp_path / "gap.json").read_text())
    assert (summary["seen"], summary["unseen"]) == ({"split": "train-first100", "sequences": 3},
                                                    {"split": "cpu-val", "sequences": 2})
    assert summary["weights"] == {"dsr": "ab" * 32}


def test_a_folder_without_a_models_results_is_one_line(tmp_path):
    seen = _work(tmp_path / "seen", "a", [0.4, 0.5], 0.8)
    with pytest.raises(SystemExit) as exc:
        split_gap.main(["--seen", str(seen), "--unseen", str(tmp_path), "--models", "dsr"])
    assert str(exc.value).startswith(f"error: {tmp_path / 'dsr.json'}: not readable") and "\n" not in str(exc.value)


def test_two_weights_files_are_refused(tmp_path):
    seen = _work(tmp_path / "seen", "a", [0.4, 0.5], 0.8)
    unseen = _work(tmp_path / "unseen", "b", [0.4, 0.5], 0.8)
    other = json.loads((unseen / "dsr.json").read_text())
    other["meta"]["parameters"]["weights"]["sha256"] = "cd" * 32
    (unseen / "dsr.json").write_text(json.dumps(other))
    with pytest.raises(SystemExit, match="were not predicted with one recorded weights file"):
        split_gap.main(["--seen", str(seen), "--unseen", str(unseen), "--models", "dsr"])
