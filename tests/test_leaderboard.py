"""The leaderboard: strict entries, paper rows kept apart, tables and a sortable page."""

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from dsr_bench.cli import main
from dsr_bench.errors import UserError
from dsr_bench.scoring.leaderboard import add_entry, build, check_entry
from dsr_bench.dataset.splits import SPLITS, Split

ROOT = Path(__file__).resolve().parents[1]


def _results(split="procedural-novel-mini", checksum="c" * 64, **metrics):
    base = {"motion_visible": 5.0, "motion_full": 0.08, "iou_unordered": 0.7, "iou_ordered": 0.6}
    return {"format": "dsr-bench-results", "version": 1, "method": "MyNet", "split": split,
            "split_checksum": checksum, "date": "2026-11-22T00:00:00Z",
            "coverage": {"scored": 8, "expected": 8, "partial": False}, "metrics": {**base, **metrics}}


@pytest.fixture
def board(tmp_path, monkeypatch):
    root = tmp_path / "leaderboard"
    root.mkdir()
    shutil.copy(ROOT / "leaderboard" / "paper.json", root / "paper.json")
    spec = SPLITS["procedural-novel-mini"]
    monkeypatch.setitem(SPLITS, spec.name, Split(**{**spec.__dict__, "expected_digest": "c" * 64}))
    return root


def test_entries_are_checked(board, tmp_path):
    assert check_entry(_results()) == []
    assert any("differs from the toolkit's" in p for p in check_entry(_results(checksum="d" * 64)))
    assert any("not one of the benchmark's named splits" in p for p in check_entry(_results(split="mine")))
    partial = _results()
    partial["coverage"]["partial"] = True
    assert any("partial" in p for p in check_entry(partial))
    missing = _results()
    del missing["metrics"]["iou_ordered"]
    assert any("iou_ordered" in p for p in check_entry(missing))
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(_results(checksum="e" * 64)))
    with pytest.raises(UserError, match="cannot join the leaderboard"):
        add_entry(path, board)
    assert not (board / "entries").exists()


def _add(board, tmp_path, method, label=None, **metrics):
    results = _results(**metrics)
    results["method"] = method
    path = tmp_path / f"{method}.json"
    path.write_text(json.dumps(results))
    assert main(["leaderboard", "add", str(path), "--root", str(board), *(["--label", label] if label else [])]) == 0


def test_build_tables_keep_paper_rows_apart_and_mark_the_best(board, tmp_path):
    good = tmp_path / "good.json"
    good.write_text(json.dumps(_results()))
    other = _results(motion_visible=4.0, iou_unordered=0.5, iou_ordered=0.4)
    other["method"] = "Other"
    (tmp_path / "other.json").write_text(json.dumps(other))
    assert main(["leaderboard", "add", str(good), "--root", str(board), "--label", "short schedule"]) == 0
    assert main(["leaderboard", "add", str(tmp_path / "other.json"), "--root", str(board)]) == 0
    _add(board, tmp_path, "static", "reference (no training)", motion_visible=6.0, motion_full=0.07,
         iou_unordered=0.3, iou_ordered=0.2)
    md = (board / "README.md").read_text()
    assert "## procedural-novel-mini: 3D track (reproduced)" in md
    assert "## ycb-test: 3D track (reported in the paper)" in md and "## real-test: 2D track (reported in the paper)" in md
    mine = next(line for line in md.splitlines() if line.startswith("| MyNet"))
    theirs = next(line for line in md.splitlines() if line.startswith("| Other"))
    assert "**0.700**" in mine and "**4**" in theirs and "short schedule" in mine
    dsr = next(line for line in md.splitlines() if line.startswith("| DSR-Net |") and "0.772" in line)
    assert "**5.54**" in dsr and "**0.772**" in dsr  # best among the paper's sim rows that are not oracles
    gtwarp = next(line for line in md.splitlines() if line.startswith("| GTWarp (oracle warp)") and "0.807" in line)
    assert "**" not in gtwarp  # the oracle warp is higher, but an oracle is never the best
    page = (board / "index.html").read_text()
    assert "sortTable" in page and page.count("<table") == md.count("## ")


def test_oracles_are_never_best_and_rows_worse_than_no_motion_are_marked(board, tmp_path):
    _add(board, tmp_path, "oracle", "reference (no training)", motion_visible=0.0, motion_full=0.0, iou_unordered=1.0,
         iou_ordered=1.0)
    _add(board, tmp_path, "static", "reference (no training)", motion_visible=40.0, motion_full=0.27,
         iou_unordered=0.19, iou_ordered=0.13)
    _add(board, tmp_path, "Trained", motion_visible=43.6, motion_full=0.20, iou_unordered=0.36, iou_ordered=0.33)
    md = build(board)[0].read_text()
    rows = {line.split(" | ")[0][2:]: line for line in md.splitlines() if line.startswith("| ")}
    assert "**" not in rows["oracle"]
    assert "43.6 \u25bc" in rows["Trained"] and "**0.2**" in rows["Trained"] and "**0.360**" in rows["Trained"]
    assert "**40**" in rows["static"] and "\u25bc" not in rows["static"]
    page = (board / "index.html").read_text()
    assert page.count('class="worse"') == 1 and 'class="best"' in page


def test_a_table_without_the_no_motion_row_marks_no_best(board, tmp_path):
    _add(board, tmp_path, "Trained", motion_visible=43.6)
    md = build(board)[0].read_text()
    current = md.split("## procedural-novel-mini: 3D track (reproduced)")[1].split("## ")[0]
    assert "No no-motion (static) row" in current and "**" not in current


def test_real_headless_browser_renders_the_page(board):
    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if browser is None:
        pytest.skip("no headless Chromium installed (apt-get install chromium)")
    _, page = build(board)
    dom = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--dump-dom", page.as_uri()],
                         capture_output=True, text=True, timeout=60).stdout
    assert "DSR-Net" in dom and "<table" in dom


def test_repository_leaderboard_builds(tmp_path):
    root = tmp_path / "lb"
    shutil.copytree(ROOT / "leaderboard", root)
    md, _ = build(root)
    assert "reported in the paper" in md.read_text()


def test_entry_of_an_earlier_pin_is_shown_apart_and_unranked(board, tmp_path):
    """After a split is re-pinned, entries scored on its earlier version keep their own table and never win bold."""
    good = tmp_path / "good.json"
    good.write_text(json.dumps(_results()))
    assert main(["leaderboard", "add", str(good), "--root", str(board)]) == 0
    _add(board, tmp_path, "static", "reference (no training)", motion_visible=6.0, motion_full=0.09,
         iou_unordered=0.3, iou_ordered=0.2)
    old = _results(checksum="0123456789ab" + "f" * 52, iou_ordered=0.9)
    old["method"] = "OldNet"
    (board / "entries" / "oldnet-procedural-novel-mini.json").write_text(json.dumps(old))
    md, _ = build(board)
    text = md.read_text()
    current = text.split("## procedural-novel-mini: 3D track (reproduced)")[1].split("## ")[0]
    earlier = text.split("## procedural-novel-mini: 3D track (reproduced on an earlier version of the split, "
                         "0123456789ab)")[1].split("## ")[0]
    assert "| MyNet" in current and "OldNet" not in current and "**0.600**" in current
    assert "| OldNet" in earlier and "MyNet" not in earlier
    assert "No no-motion (static) row" in earlier and "**" not in earlier  # nothing to compare it with there
