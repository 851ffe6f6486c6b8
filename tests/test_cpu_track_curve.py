"""scripts/cpu_track_curve.py: the learning curve's points from cpu_track_evidence summaries (sample-steps counted
from the weights' own stage records, one point a file, the --against namesakes included), its refusals, and the
command end to end with the plot."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import cpu_track_curve  # noqa: E402


def _stages(chunks: int) -> dict:
    """A CPU-track file's stages: the recipe (24k + 16k sample-steps, an older record counted from its batches)
    and `chunks` continued chunks of 40k each."""
    return {"single": {"batches": 3000, "window": 1}, "multi": {"batches": 200, "window": 10},
            "continued": [{"batches": 500, "window": 10, "sample_steps": 40_000} for _ in range(chunks)]}


def _means(iou: float) -> dict:
    return {"iou_ordered": iou, "iou_unordered": iou + 0.05, "motion_visible": 20 - 10 * iou, "motion_full": 0.2}


def _summary(sha: str, chunks: int, iou: float, against: tuple[str, int, float] | None = None,
             checksum: str = "abc") -> dict:
    summary = {"split": "cpu-novel-test", "split_checksum": checksum, "sequences": 100,
               "weights": {"dsr": {"file": "dsr.pt", "sha256": sha, "stages": _stages(chunks)}},
               "means": {"static": _means(0.1), "dsr": _means(iou)},
               "vs_static": {"dsr": {"iou_ordered": {"mean": iou - 0.1, "se": 0.01, "n": 100}}}}
    if against:
        a_sha, a_chunks, a_iou = against
        summary["against"] = {"dsr": {"file": "dsr.pt", "sha256": a_sha, "stages": _stages(a_chunks)}}
        summary["against_means"] = {"dsr": _means(a_iou)}
    return summary


def test_points_are_one_per_file_sorted_by_sample_steps_with_the_namesakes():
    shipped = ("s" * 64, 0, 0.30)
    curve = cpu_track_curve.curve_points([_summary("b" * 64, 8, 0.40, shipped), _summary("a" * 64, 4, 0.35, shipped)])
    points = curve["dsr"]
    assert [p["sample_steps"] for p in points] == [40_000, 200_000, 360_000]
    assert [p["sha256"][0] for p in points] == ["s", "a", "b"]
    assert [p["means"]["iou_ordered"] for p in points] == [0.30, 0.35, 0.40]
    assert points[0]["vs_static"] is None and points[2]["vs_static"]["iou_ordered"]["mean"] == pytest.approx(0.30)


def test_summaries_of_different_splits_or_disagreeing_scores_are_refused():
    with pytest.raises(ValueError, match="different splits"):
        cpu_track_curve.curve_points([_summary("a" * 64, 1, 0.3), _summary("b" * 64, 2, 0.3, checksum="other")])
    with pytest.raises(ValueError, match="more than rounding"):
        cpu_track_curve.curve_points([_summary("a" * 64, 1, 0.3), _summary("a" * 64, 1, 0.31)])


def test_one_file_scored_twice_within_rounding_keeps_the_first_score_and_says_how_far_apart():
    first, again = _summary("a" * 64, 1, 0.3), _summary("a" * 64, 1, 0.3 + 2e-5)
    (point,) = cpu_track_curve.curve_points([first, again])["dsr"]
    assert point["means"]["iou_ordered"] == 0.3
    assert point["rescored_within"] == pytest.approx(2e-4)  # motion_visible moves 10x the IoU in _means


def test_the_command_writes_the_curve_and_the_plot(tmp_path):
    paths = []
    for i, (chunks, iou) in enumerate([(2, 0.33), (6, 0.38)]):
        paths.append(tmp_path / f"s{i}.json")
        paths[-1].write_text(json.dumps(_summary(str(i) * 64, chunks, iou, ("s" * 64, 0, 0.30))))
    out, png = tmp_path / "curve.json", tmp_path / "curve.png"
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "cpu_track_curve.py"), *map(str, paths), "--out",
                           str(out), "--plot", str(png), "--cap", "0.642", "--mark", "208000:more data"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    record = json.loads(out.read_text())
    assert record["marks"] == [{"sample_steps": 208_000, "label": "more data"}]
    assert record["cap_iou_ordered"] == 0.642 and record["command"].startswith("python scripts/cpu_track_curve.py")
    assert [p["sample_steps"] for p in record["models"]["dsr"]] == [40_000, 120_000, 280_000]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "120,000" in done.stdout

    paths[0].write_text("{not json")
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "cpu_track_curve.py"), *map(str, paths), "--out",
                           str(tmp_path / "again.json")], capture_output=True, text=True)
    assert done.returncode != 0 and "s0.json: not a readable cpu_track_evidence summary" in done.stderr
    assert not (tmp_path / "again.json").exists()
