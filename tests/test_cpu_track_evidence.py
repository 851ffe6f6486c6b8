"""scripts/cpu_track_evidence.py reuses the predictions and results already in its WORK folder only when they
record the SHA-256 of the weights file they stand for: work left from other weights stops the script with a line
naming the file and the fix, before anything is predicted or written."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import cpu_track_evidence  # noqa: E402

from dsr_bench.dataset.manifest import file_sha256  # noqa: E402


def _meta(sha: str | None) -> dict:
    """A prediction's meta as results files carry it (the weights under "parameters")."""
    parameters = {"grid": [32, 32, 16], "num_slots": 4}
    if sha is not None:
        parameters["weights"] = {"source": "a test", "file": "dsr.pt", "sha256": sha}
    return {"name": "dsr-cpu", "parameters": parameters}


def test_the_recorded_weights_are_read_from_meta_json_and_from_results():
    assert cpu_track_evidence.recorded_weights_sha256({"weights": {"sha256": "ab"}}) == "ab"  # meta.json
    assert cpu_track_evidence.recorded_weights_sha256(_meta("cd")) == "cd"  # a results file's "meta"
    assert cpu_track_evidence.recorded_weights_sha256(_meta(None)) is None  # a yardstick
    assert cpu_track_evidence.recorded_weights_sha256("not a dict") is None


def test_reused_work_must_record_the_weights_it_stands_for(tmp_path):
    weights = tmp_path / "dsr.pt"
    weights.write_bytes(b"some weights")
    cpu_track_evidence.check_reused(tmp_path / "dsr.json", _meta(file_sha256(weights)), weights)  # the same: kept
    cpu_track_evidence.check_reused(tmp_path / "static.json", _meta(None), None)  # a yardstick: no weights
    with pytest.raises(SystemExit, match=r"dsr.json: reused work made from weights 000000000000, not .*dsr.pt"):
        cpu_track_evidence.check_reused(tmp_path / "dsr.json", _meta("0" * 64), weights)
    with pytest.raises(SystemExit, match="made from no weights file, not"):
        cpu_track_evidence.check_reused(tmp_path / "dsr.json", _meta(None), weights)
    with pytest.raises(SystemExit, match="made from weights 000000000000, not no weights file"):
        cpu_track_evidence.check_reused(tmp_path / "static.json", _meta("0" * 64), None)


def test_the_script_stops_on_results_left_from_other_weights(tmp_path):
    """WORK holds the yardsticks' results and DSR-Net's from other weights (as after a chunk more of training):
    the script stops on DSR-Net's with the fix, and writes no summary."""
    work, weights = tmp_path / "work", tmp_path / "weights"
    work.mkdir(), weights.mkdir()
    (weights / "dsr.pt").write_bytes(b"the next chunk's weights")
    for name in cpu_track_evidence.REFERENCES:
        (work / f"{name}.json").write_text(json.dumps({"meta": _meta(None)}))
    (work / "dsr.json").write_text(json.dumps({"meta": _meta("1" * 64)}))
    out = tmp_path / "summary.json"
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "cpu_track_evidence.py"), "--data",
                           str(tmp_path / "no-data"), "--weights", str(weights), "--work", str(work), "--models",
                           "dsr", "--out", str(out)], capture_output=True, text=True)
    assert done.returncode != 0
    assert done.stderr.strip().splitlines()[-1] == (
        f"{work / 'dsr.json'}: reused work made from weights 111111111111, not {weights / 'dsr.pt'} "
        f"({file_sha256(weights / 'dsr.pt')[:12]}); delete it to predict again")
    assert not out.exists()
