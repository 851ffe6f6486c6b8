"""The leaderboard: strict entries, paper rows kept apart, tables and a sortable page (seen in headless Chromium)."""

import base64
import html
import fcntl
import hashlib
import io
import json
import os
import select
import shutil
import subprocess
import sys
from pathlib import Path
from urllib.parse import urlparse
from urllib.request import url2pathname

import numpy as np
import pytest
from PIL import Image

from dsr_bench.errors import UserError
from dsr_bench.leaderboard.entries import check_entry, entry_name
from dsr_bench.leaderboard.board import add_entry, build

ROOT = Path(__file__).resolve().parents[1]


SPLIT = "procedural-novel-mini"
BASE = {"motion_visible": 5.0, "motion_full": 0.08, "iou_unordered": 0.7, "iou_ordered": 0.6}


def _results(method="MyNet", split=SPLIT, checksum="c" * 64, per_step=None, **metrics):
    """A valid entry as `evaluate` writes it (8 sequences, the board's pinned split): its per-step values `per_step`,
    or two steps of each metric's value; metrics, per-sequence means and breakdowns from them by `aggregate`. A
    2D-only entry: metrics (or per_step) motion_2d alone."""
    from dsr_bench import __version__
    from dsr_bench.scoring.evaluate import aggregate

    two_d = set(metrics) == {"motion_2d"} or (per_step is not None and set(per_step) == {"motion_2d"})
    steps = per_step or {k: [v, v] for k, v in (metrics if two_d else {**BASE, **metrics}).items()}
    n = len(next(iter(steps.values())))
    if two_d:
        seq = {"motion_2d": steps["motion_2d"], "has_2d": True, "has_3d": False}
    else:
        seq = {**steps, "iou_unordered_official": steps["iou_unordered"], "iou_ordered_official": steps["iou_ordered"],
               "motion_moved": [1.0] * n, "motion_static": [0.0] * n, "motion_2d": steps.get("motion_2d", [0.0] * n),
               "iou_occluded_objects": [[] for _ in range(n)], "iou_visible_objects": [[0.5] for _ in range(n)],
               "has_2d": "motion_2d" in steps, "has_3d": True}
    return {"format": "dsr-bench-results", "version": 1, "method": method, "meta": {"name": method}, "split": split,
            "split_checksum": checksum, "pinned": True, "toolkit_version": __version__,
            "predictions_checksum": hashlib.sha256(method.encode()).hexdigest(), "date": "2026-11-22T00:00:00Z",
            "coverage": {"scored": 8, "expected": 8, "partial": False},
            **json.loads(json.dumps(aggregate({f"seq_{i:04d}": seq for i in range(8)})))}


def _put(board, results, label=None):
    """An entry file in the board (as `leaderboard add` writes one after recomputing it)."""
    results = {**results, **({"label": label} if label else {})}
    assert check_entry(results) == []
    (board / "entries").mkdir(exist_ok=True)
    (board / "entries" / entry_name(results)).write_text(json.dumps(results))


def test_entries_are_checked(board, tmp_path):
    assert check_entry(_results()) == []
    assert any("is not this toolkit's pin" in p for p in check_entry(_results(checksum="d" * 64)))
    assert check_entry({**_results(checksum="d" * 64), "toolkit_version": "0.1.0"}) == []  # an earlier pin's entry
    assert any("not one of the benchmark's named splits" in p for p in check_entry(_results(split="mine")))
    partial = _results()
    partial["coverage"]["partial"] = True
    assert any("partial" in p for p in check_entry(partial))
    missing = _results()
    del missing["metrics"]["iou_ordered"]
    assert any("iou_ordered" in p for p in check_entry(missing))
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(_results()))
    with pytest.raises(UserError, match="recomputes every score from the predictions"):
        add_entry(path, board)
    assert not (board / "entries").exists()


def _add(board, tmp_path, method, label=None, **metrics):
    _put(board, _results(method, **metrics), label)
    build(board)


def test_build_tables_keep_paper_rows_apart_and_mark_the_best(board, tmp_path):
    _put(board, _results(), "short schedule")
    _put(board, _results("Other", motion_visible=4.0, iou_unordered=0.5, iou_ordered=0.4))
    _add(board, tmp_path, "static", "reference (no training)", motion_visible=6.0, motion_full=0.07,
         iou_unordered=0.3, iou_ordered=0.2)
    md = _plain((board / "README.md").read_text())
    assert "## procedural-novel-mini: 3D track (reproduced)" in md
    assert "## ycb-test: 3D track (reported in the paper)" in md
    assert "## real-test: 2D track (reported in the paper)" in md
    mine = next(line for line in md.splitlines() if line.startswith("| MyNet"))
    theirs = next(line for line in md.splitlines() if line.startswith("| Other"))
    assert "**0.700**" in mine and "**4.000**" in theirs and "short schedule" in mine
    dsr = next(line for line in md.splitlines() if line.startswith("| DSR-Net |") and "0.772" in line)
    assert "**5.54**" in dsr and "**0.772**" in dsr  # best among the paper's sim rows that are not oracles
    gtwarp = next(line for line in md.splitlines() if line.startswith("| GTWarp (oracle warp)") and "0.807" in line)
    assert "**" not in gtwarp  # the oracle warp is higher, but an oracle is never the best
    page = (board / "index.html").read_text()
    assert "sortTable" in page and page.count("<table class=board") == md.count("## ")


def test_oracles_are_never_best_and_rows_worse_than_no_motion_are_marked(board, tmp_path):
    _add(board, tmp_path, "oracle", "reference (no training)", motion_visible=0.0, motion_full=0.0, iou_unordered=1.0,
         iou_ordered=1.0)
    _add(board, tmp_path, "static", "reference (no training)", motion_visible=40.0, motion_full=0.27,
         iou_unordered=0.19, iou_ordered=0.13)
    _add(board, tmp_path, "Trained", motion_visible=43.6, motion_full=0.20, iou_unordered=0.36, iou_ordered=0.33)
    _add(board, tmp_path, "gtwarp-cpu", motion_visible=39.0, motion_full=0.25, iou_unordered=0.30, iou_ordered=0.40)
    md = _plain(build(board)[0].read_text())
    table = _markdown_tables(md)["procedural-novel-mini: 3D track (reproduced)"]
    rows = {row[0]: " | ".join(row) for row in table[1:]}
    assert "**" not in rows["oracle"]
    assert "**" not in rows["gtwarp-cpu"] and "**0.330**" in rows["Trained"]  # GTWarp warps by the true flow: an oracle
    assert "43.60 \u25bc" in rows["Trained"] and "**0.2000**" in rows["Trained"] and "**0.360**" in rows["Trained"]
    assert "**40.00**" in rows["static"] and "\u25bc" not in rows["static"]
    page = (board / "index.html").read_text()
    assert page.count('class="worse"') == 1 and 'class="best"' in page


def test_a_table_without_the_no_motion_row_marks_no_best(board, tmp_path):
    _add(board, tmp_path, "Trained", motion_visible=43.6)
    md = build(board)[0].read_text()
    current = md.split("## procedural-novel-mini: 3D track (reproduced)")[1].split("## ")[0]
    assert "No no-motion (static) row" in current and "**" not in current
    assert "Paired differences" not in current  # nothing to pair with


_BROWSERS = ("chromium", "chromium-browser", "chromium-headless-shell", "google-chrome", "google-chrome-stable")


class _Chromium:
    """Headless Chromium driven over its DevTools pipe (--remote-debugging-pipe: JSON messages ending in NUL on
    fds 3 and 4), with nothing but the standard library: load a page, evaluate script in it, click with the mouse,
    take a screenshot."""

    def __init__(self, binary: str, profile: Path, width: int = 1200, height: int = 1600):
        to_browser, self._to_browser = os.pipe()
        self._from_browser, from_browser = os.pipe()
        # the browser's ends go to fds 3 and 4 through a tiny exec wrapper (no preexec_fn in a threaded test process);
        # high copies first, so that neither end clobbers the other on the way
        ends = [fcntl.fcntl(fd, fcntl.F_DUPFD, 100) for fd in (to_browser, from_browser)]
        for fd in (to_browser, from_browser):
            os.close(fd)
        wrapper = ("import os, sys; os.dup2(int(sys.argv[1]), 3); os.dup2(int(sys.argv[2]), 4); "
                   "os.execv(sys.argv[3], sys.argv[3:])")
        self.proc = subprocess.Popen(
            [sys.executable, "-c", wrapper, *map(str, ends), binary, "--headless", "--no-sandbox", "--disable-gpu",
             "--hide-scrollbars", "--remote-debugging-pipe", f"--user-data-dir={profile}", "about:blank"],
            pass_fds=ends, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for fd in ends:
            os.close(fd)
        self._buffer, self._id, self._events = b"", 0, []
        try:
            target = self.send("Target.createTarget", url="about:blank")["targetId"]
            self.session = self.send("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
            self.send("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                      mobile=False, session=True)
            self.send("Page.enable", session=True)
        except BaseException:
            self.close()
            raise

    def send(self, method: str, session: bool = False, **params):
        self._id += 1
        message = {"id": self._id, "method": method, "params": params}
        if session:
            message["sessionId"] = self.session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        while True:
            answer = self._read()
            if answer.get("id") == self._id:
                assert "error" not in answer, f"{method}: {answer['error']}"
                return answer["result"]
            self._events.append(answer)

    def _read(self) -> dict:
        while b"\0" not in self._buffer:
            # a guard against a hung browser (the test fails instead of hanging), not a measure of speed
            if not select.select([self._from_browser], [], [], 120)[0]:
                raise RuntimeError("headless Chromium did not answer in 120 s")
            chunk = os.read(self._from_browser, 1 << 20)
            if not chunk:
                raise RuntimeError(f"headless Chromium closed its DevTools pipe (exit status {self.proc.poll()})")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def load(self, url: str):
        """Navigate to `url` and wait for its load event (scripts ran, images decoded)."""
        self.send("Page.navigate", url=url, session=True)
        while True:
            event = self._events.pop(0) if self._events else self._read()
            if event.get("method") == "Page.loadEventFired" and event.get("sessionId") == self.session:
                return

    def js(self, expression: str):
        result = self.send("Runtime.evaluate", expression=expression, returnByValue=True, session=True)
        assert "exceptionDetails" not in result, result["exceptionDetails"]
        return result["result"].get("value")

    def click(self, selector: str):
        """A real left click with the mouse at the middle of the element, scrolled into view first."""
        x, y = self.js(f"(() => {{const e = document.querySelector({json.dumps(selector)}); e.scrollIntoView();"
                       "const r = e.getBoundingClientRect(); return [r.x + r.width / 2, r.y + r.height / 2];})()")
        for kind in ("mousePressed", "mouseReleased"):
            self.send("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1, session=True)

    def screenshot(self) -> Image.Image:
        png = base64.b64decode(self.send("Page.captureScreenshot", format="png", session=True)["data"])
        image = Image.open(io.BytesIO(png))
        assert image.format == "PNG"
        image.load()
        return image.convert("RGB")

    def close(self):
        try:
            self.send("Browser.close")
            self.proc.wait(60)
        except Exception:  # noqa: BLE001 - whatever went wrong, the browser started here is ended here
            self.proc.kill()
            self.proc.wait()
        finally:
            os.close(self._to_browser)
            os.close(self._from_browser)


@pytest.fixture
def chromium(tmp_path):
    binary = next(filter(None, map(shutil.which, _BROWSERS)), None)
    if binary is None:
        pytest.skip("no headless Chromium binary found (" + ", ".join(_BROWSERS) + "): apt-get install chromium, "
                    "or run scripts/setup.sh as root")
    browser = _Chromium(binary, tmp_path / "chromium-profile")
    yield browser
    browser.close()


#: What the page shows, read from the rendered DOM: per table, its heading, whether it is drawn, its header cells
#: and rows; per cell its text, whether it is drawn bold (computed font weight), in red (worse than static).
_SEEN = """[...document.querySelectorAll('table.board')].map(t => {
  let h = t.previousElementSibling; while (h.tagName !== 'H2') h = h.previousElementSibling;
  const box = t.getBoundingClientRect();
  const shown = box.width > 0 && box.height > 0 && getComputedStyle(t).visibility === 'visible';
  return {heading: h.textContent, shown, header: [...t.tHead.rows[0].cells].map(c => c.textContent),
    rows: [...t.tBodies[0].rows].map(r => [...r.cells].map(c => {const s = getComputedStyle(c);
      return {text: c.textContent, bold: parseInt(s.fontWeight) >= 600, red: s.color === 'rgb(170, 0, 0)',
              best: c.classList.contains('best'), worse: c.classList.contains('worse')};}))};})"""


def _markdown_tables(md: str) -> dict[str, list[list[str]]]:
    """README.md's first table under each heading (the paired differences that follow it left out): the header
    line's cells, then each row's cells."""
    tables, heading, ended = {}, None, False
    for line in md.splitlines():
        if line.startswith("## "):
            heading, ended = line[3:], False
        elif line.startswith("| ") and heading is not None and not ended:
            tables.setdefault(heading, []).append([c.strip() for c in line.strip("|").split(" | ")])
        elif heading in tables and not line.startswith("|---"):
            ended = True
    return tables


def _plain(md: str) -> str:
    """README.md without the 95% intervals' half-widths (" ± 0.012")."""
    import re

    return re.sub(" \u00b1 [0-9.]+", "", md)


def test_real_headless_browser_shows_the_tables_marks_plots_links_and_sorts(board, tmp_path, chromium):
    # per-step values whose means are the rows' metrics: MyNet 5, 0.08, 0.7, 0.6; Other 4, 0.09, 0.5, 0.4
    _put(board, _results("MyNet", per_step={"motion_visible": [4.0, 6.0], "motion_full": [0.07, 0.09],
                                            "iou_unordered": [0.6, 0.8], "iou_ordered": [0.5, 0.7]}), "short schedule")
    _put(board, _results("Other", per_step={"motion_visible": [5.0, 3.0], "motion_full": [0.1, 0.08],
                                            "iou_unordered": [0.6, 0.4], "iou_ordered": [0.5, 0.3]}))
    _put(board, _results("static", motion_visible=6.0, motion_full=0.07, iou_unordered=0.3, iou_ordered=0.2))
    _put(board, _results("oracle", motion_visible=0.0, motion_full=0.0, iou_unordered=1.0, iou_ordered=1.0))
    md, page = build(board)
    chromium.load(page.as_uri())
    seen = {t["heading"]: t for t in chromium.js(_SEEN)}

    # every table of README.md is on the page with the same header cells, rows, bold cells and ▼ marks, as drawn
    expected = _markdown_tables(md.read_text())
    assert list(seen) == list(expected) and len(seen) == 5
    assert next(iter(seen)) == "procedural-novel-mini: 3D track (reproduced)"  # the first table, sorted below
    for heading, (header, *rows) in expected.items():
        table = seen[heading]
        assert table["shown"] and table["header"] == header
        assert len(table["rows"]) == len(rows)
        for md_row, row in zip(rows, table["rows"]):
            for md_cell, cell in zip(md_row, row):
                assert cell["text"] == md_cell.replace("**", "")
                assert cell["bold"] == cell["best"] == md_cell.startswith("**")
                assert cell["red"] == cell["worse"] == ("\u25bc" in md_cell)

    # the reproduced table: the best non-oracle value of each column in bold, ▼ where worse than predicting no motion
    current = seen["procedural-novel-mini: 3D track (reproduced)"]
    columns = current["header"]
    marked = {(row[0]["text"], columns[i], "best" if c["bold"] else "worse") for row in current["rows"]
              for i, c in enumerate(row) if c["bold"] or c["red"]}
    assert marked == {("Other", "flow MSE visible (cm²)", "best"), ("static", "flow MSE full (cm²)", "best"),
                      ("MyNet", "IoU unordered", "best"), ("MyNet", "IoU ordered", "best"),
                      ("MyNet", "flow MSE full (cm²)", "worse"), ("Other", "flow MSE full (cm²)", "worse")}
    paper = seen["ycb-test: 3D track (reported in the paper)"]
    dsr = next(row for row in paper["rows"] if row[0]["text"] == "DSR-Net")
    assert [c["text"] for c in dsr if c["bold"]] == ["5.54", "0.082", "0.772", "0.767", "0.720"]  # GTWarp: an oracle

    # the plot: one image, under the reproduced table, a file of the build that the browser decoded and drew
    images = chromium.js("[...document.images].map(i => ({src: i.src, w: i.naturalWidth, h: i.naturalHeight,"
                         "shown: i.getBoundingClientRect().width,"
                         "under: (() => {const t = document.querySelector('table.board'), f = i.closest('figure'),"
                         "h = document.querySelectorAll('h2')[1]; return !!(t.compareDocumentPosition(f) & 4) &&"
                         "!!(f.compareDocumentPosition(h) & 4);})()}))")  # after its table, before the next heading
    plot_file = board / "plots" / "procedural-novel-mini-3d.svg"
    assert [Path(url2pathname(urlparse(i["src"]).path)) for i in images] == [plot_file]
    with Image.open(plot_file.with_suffix(".png")) as plot:  # the PNG beside it: the same figure at twice the pixels
        assert (2 * images[0]["w"], 2 * images[0]["h"]) == plot.size
    assert images[0]["shown"] == images[0]["w"] == 860 and images[0]["under"]  # shown at the size it was drawn
    # every link of the page leads to a file of the build
    links = chromium.js("[...document.links].map(a => a.href)")
    assert links and all(urlparse(u).scheme == "file" and Path(url2pathname(urlparse(u).path)).is_file() for u in links)

    # the rendering: a screenshot of the plot's place shows a drawn plot (coloured lines on white), not a blank
    chromium.js("document.images[0].scrollIntoView()")
    box = chromium.js("(() => {const r = document.images[0].getBoundingClientRect(); return [r.left, r.top, r.right,"
                      "Math.min(r.bottom, innerHeight)];})()")
    shot = chromium.screenshot()
    assert shot.size == (1200, 1600)
    drawn = np.asarray(shot.crop(tuple(round(v) for v in box))).astype(int)
    assert (drawn != 255).any(axis=2).mean() > 0.02  # not blank
    assert ((drawn.max(axis=2) - drawn.min(axis=2)) > 80).sum() > 100  # coloured lines, not only black text on white
    assert len(np.unique(np.asarray(shot).reshape(-1, 3), axis=0)) > 20  # the page around it: text, borders, shading
    chromium.js("scrollTo(0, 0)")
    title = chromium.js("(() => {const r = document.querySelector('h1').getBoundingClientRect();"
                        "return [r.left, r.top, r.right, r.bottom];})()")
    heading = np.asarray(chromium.screenshot().crop(tuple(round(v) for v in title)))
    assert (heading.max(axis=2) < 100).sum() > 100  # the page's title is drawn in dark text: fonts render

    # sorting: a real mouse click on a header sorts the rows by it, ascending then descending; rows move whole
    def order():
        rows = chromium.js(_SEEN)[0]["rows"]
        return [r[0]["text"] for r in rows], {(r[0]["text"], i) for r in rows for i, c in enumerate(r) if c["bold"]}

    _, bold = order()
    header = "table th:nth-child(6)"
    assert chromium.js(f"document.querySelector({json.dumps(header)}).textContent") == "IoU ordered"
    chromium.click(header)
    assert order() == (["static", "Other", "MyNet", "oracle"], bold)
    chromium.click(header)
    assert order() == (["oracle", "MyNet", "Other", "static"], bold)
    chromium.click("table th:nth-child(1)")
    assert order() == (["MyNet", "Other", "oracle", "static"], bold)


def test_entry_of_an_earlier_pin_is_shown_apart_and_unranked(board, tmp_path):
    """After a split is re-pinned, entries scored on its earlier version keep their own table and never win bold."""
    _put(board, _results())
    _add(board, tmp_path, "static", "reference (no training)", motion_visible=6.0, motion_full=0.09,
         iou_unordered=0.3, iou_ordered=0.2)
    # scored by an earlier toolkit, whose pin of the split was another
    old = {**_results("OldNet", checksum="0123456789ab" + "f" * 52, iou_ordered=0.9), "toolkit_version": "0.1.0"}
    _put(board, old)
    md, _ = build(board)
    text = _plain(md.read_text())
    current = text.split("## procedural-novel-mini: 3D track (reproduced)")[1].split("## ")[0]
    earlier = text.split("## procedural-novel-mini: 3D track (reproduced on an earlier version of the split, "
                         "0123456789ab)")[1].split("## ")[0]
    assert "| MyNet" in current and "OldNet" not in current and "**0.600**" in current
    assert "| OldNet" in earlier and "MyNet" not in earlier
    assert "No no-motion (static) row" in earlier and "**" not in earlier  # nothing to compare it with there


def _results_2d(method, motion_2d, per_step=None):
    return _results(method, per_step={"motion_2d": per_step} if per_step else None,
                    **({} if per_step else {"motion_2d": motion_2d}))


def test_a_2d_only_entry_joins_the_2d_track_only(board, tmp_path):
    """Results holding motion_2d alone (a 2D-only submission) are a valid entry, a row of the 2D track's table
    (its grid the image's) and never an empty row of the 3D track's; a 3D entry with motion_2d sits in both."""
    assert check_entry(_results_2d("Flow2D", 3.0)) == []
    assert check_entry({**_results_2d("Flow2D", 3.0), "metrics": {}}) == ["metrics is not an object of numbers"]
    assert check_entry({**_results_2d("Flow2D", 3.0), "metrics": {"motion_2d": None}}) == \
        ["metrics.motion_2d is null, not a finite flow MSE >= 0"]
    assert check_entry({**_results(), "metrics": {"motion_visible": 1.0, "motion_2d": 2.0}}) == \
        ["metrics missing: motion_full, iou_unordered, iou_ordered (a 3D result holds all four; a 2D-only one "
         "motion_2d alone)"]
    for method, value in (("Flow2D", 3.0), ("SE3Net", 5.0)):
        results = _results_2d(method, value, [value - 1, value + 1])
        if method == "SE3Net":  # the image the model works on, as `predict` records it for an image-space model
            results["meta"] = {"parameters": {"image": [120, 160]}}
        _put(board, results)
    build(board)
    tables = _markdown_tables(_plain((board / "README.md").read_text()))
    assert "procedural-novel-mini: 3D track (reproduced)" not in tables  # only 2D-only entries: no 3D table
    two_d = tables["procedural-novel-mini: 2D track (reproduced)"]
    assert two_d[0][:3] == ["method", "model grid", "2D flow MSE (cm²)"]
    assert [row[:3] for row in two_d[1:]] == [["Flow2D", "240x320", "3.000"], ["SE3Net", "120x160", "5.000"]]
    assert (board / "plots" / "procedural-novel-mini-2d.png").exists()
    assert not (board / "plots" / "procedural-novel-mini-3d.png").exists()
    _add(board, tmp_path, "static", "reference (no training)", motion_visible=6.0, motion_full=0.07,
         iou_unordered=0.3, iou_ordered=0.2, motion_2d=4.0)
    tables = _markdown_tables(_plain((board / "README.md").read_text()))
    three_d = tables["procedural-novel-mini: 3D track (reproduced)"]
    assert [row[0] for row in three_d[1:]] == ["static"]  # the 2D-only rows are not in it, not even empty
    two_d = tables["procedural-novel-mini: 2D track (reproduced)"]
    assert [(row[0], row[2]) for row in two_d[1:]] == [("Flow2D", "**3.000**"), ("SE3Net", "5.000 \u25bc"),
                                                       ("static", "4.000")]


def _planner(method: str) -> dict:
    """The planner record of `dsr-bench plan --model METHOD`'s results: a reference planner's own description."""
    from dsr_bench.planning.planners import OraclePlanner, RandomPlanner

    described = {"random": RandomPlanner.description, "oracle": OraclePlanner.description}
    return {"name": method, "description": described.get(method, "x")}


def _plan_results(method, iou, pinned=True, partial=False):
    """Valid planning results on plan-novel-test (as `dsr-bench plan` writes them), every task scoring `iou`."""
    from dsr_bench.planning.results import build_results
    from dsr_bench.planning.tasks import pinned_checksums

    scores = {"iou": iou, "iou_identity": 0.5, "iou_occupancy": 0.4, "start_iou": 0.3, "start_iou_identity": 0.3,
              "start_iou_occupancy": 0.2, "iou_per_object": [0.25, 0.75], "seconds": 30.0}
    checksum = pinned_checksums()["plan-novel-test"] if pinned else "0" * 64
    r = build_results({f"task_{i:04d}": scores for i in range(60 if partial else 100)},
                      _planner(method), {"task_set": "plan-novel-test", "checksum": checksum}, 100,
                      [], f"dsr-bench plan --model {method}", {"candidates": 100})
    return {**r, "date": "2026-11-25T00:00:00Z"}


def test_planning_results_fill_the_planning_column_beside_the_papers(board, tmp_path):
    (board / "planning").mkdir()
    for method, iou in (("oracle", 0.61), ("dsr-cpu", 0.29)):
        results = _plan_results(method, iou)
        assert check_entry(results) == []
        (board / "planning" / entry_name(results)).write_text(json.dumps(results))
    build(board)
    md = (board / "README.md").read_text()
    section = md[md.index("## plan-novel-test: planning track (reproduced)"):]
    assert "| dsr-cpu (planning) |" in section and "0.290" in section and "100/100 tasks" in section
    assert "| DSR-Net | " in md and "0.720" in md  # the paper's planning IoU stays in its own table
    for bad, why in ((_plan_results("x", 0.5, pinned=False), "not this toolkit's pinned one"),
                     (_plan_results("y", 0.5, partial=True), "covers only part"),
                     ({**_plan_results("z", 0.5), "metrics": {**_plan_results("z", 0.5)["metrics"], "iou": 1.5}},
                      "metrics iou is not a number in [0, 1]")):
        assert any(why in p for p in check_entry(bad)), check_entry(bad)


def test_a_row_of_weights_no_longer_shipped_says_so(board):
    """A row records the shipped weights it ran (SHA-256); once the toolkit ships other files, its note names the old
    ones, so a row reading "dsr-cpu" never stands for today's `--model dsr` by mistake. A checkpoint of the user's
    own, or the files shipped now, get no such note."""
    from dsr_bench.dataset.manifest import file_sha256
    from dsr_bench.models.predictors import SHIPPED_SOURCE, SHIPPED_WEIGHTS

    now = file_sha256(SHIPPED_WEIGHTS / "dsr.pt")
    before = "0123abcd" + now[8:]
    shipped = {"source": SHIPPED_SOURCE, "file": "dsr.pt"}
    (board / "planning").mkdir()
    for method, weights in (("dsr-cpu", [{**shipped, "sha256": now}]),
                            ("mean(dsr-cpu, single-cpu)", [{**shipped, "sha256": before},
                                                           {**shipped, "file": "single.pt", "sha256": "f" * 64}]),
                            ("mine", [{"source": "dsr-bench", "file": "dsr.pt", "sha256": before}])):
        results = _plan_results(method, 0.4)
        results["planner"]["weights"] = weights
        assert check_entry(results) == []
        (board / "planning" / entry_name(results)).write_text(json.dumps(results))
    for method, sha in (("dsr-cpu", before), ("dsr-now", now)):
        results = _results(method)
        results["meta"]["parameters"] = {"weights": {**shipped, "sha256": sha}}
        _put(board, results, label="mine" if method == "dsr-cpu" else None)
    build(board)
    md = (board / "README.md").read_text()
    note = {cells[0]: cells[-4] for cells in (line.split(" | ") for line in md.splitlines())
            if len(cells) > 5 and cells[0] in ("| dsr-cpu (planning)", "| mean(dsr-cpu, single-cpu) (planning)",
                                               "| mine (planning)", "| dsr-cpu", "| dsr-now")}
    assert note == {"| dsr-cpu (planning)": "100/100 tasks",
                    "| mean(dsr-cpu, single-cpu) (planning)":
                        "100/100 tasks; weights 0123abcd, ffffffff: shipped before, not now",
                    "| mine (planning)": "100/100 tasks",
                    "| dsr-cpu": "mine; weights 0123abcd: shipped before, not now", "| dsr-now": ""}, note


@pytest.mark.parametrize("weights, problem", [
    ("dsr.pt", "weights is \"dsr.pt\", not an object"),
    ([{"file": "dsr.pt", "sha256": "ab" * 32}, 3], "weights is 3, not an object"),
    ({"file": "../../dsr.pt", "sha256": "ab" * 32}, "weights.file is \"../../dsr.pt\", not a file name"),
    ({"file": "a" * 300, "sha256": "ab" * 32}, "not a file name"),
    ({"file": "dsr.pt", "sha256": ""}, "weights.sha256 is \"\", not a SHA-256"),
    ({"file": "dsr.pt", "sha256": 7}, "weights.sha256 is 7, not a SHA-256")])
def test_a_malformed_weights_record_keeps_an_entry_off_and_never_breaks_the_build(board, capsys, weights, problem):
    from dsr_bench.models.predictors import SHIPPED_SOURCE

    record = ({**weights, "source": SHIPPED_SOURCE} if isinstance(weights, dict) else weights)
    results = _results("dsr-cpu")
    results["meta"]["parameters"] = {"weights": record}
    plan = _plan_results("dsr-cpu", 0.4)
    plan["planner"]["weights"] = record
    for entry, where in ((results, "meta.parameters."), (plan, "planner.")):
        assert any(p.startswith(where) and problem in p for p in check_entry(entry)), check_entry(entry)
    (board / "entries").mkdir()
    (board / "entries" / "forged.json").write_text(json.dumps(results))  # placed by hand: build skips it, one line
    build(board)
    assert "forged.json" in capsys.readouterr().err
    assert "| dsr-cpu |" not in (board / "README.md").read_text()


def _varied(method, offset, spread_=0.2):
    """An entry whose 8 sequences differ (ordered IoU 0.1 + offset + spread_ * i / 7, other metrics constant), as
    `evaluate` aggregates them."""
    from dsr_bench import __version__
    from dsr_bench.scoring.evaluate import aggregate

    seqs = {}
    for i in range(8):
        iou = 0.1 + offset + spread_ * i / 7
        seqs[f"seq_{i:04d}"] = {
            "motion_visible": [5.0, 5.0], "motion_full": [0.08, 0.08], "iou_unordered": [iou, iou],
            "iou_ordered": [iou, iou], "iou_unordered_official": [iou, iou], "iou_ordered_official": [iou, iou],
            "motion_moved": [1.0, 1.0], "motion_static": [0.0, 0.0], "motion_2d": [0.0, 0.0],
            "iou_occluded_objects": [[], []], "iou_visible_objects": [[0.5], [0.5]], "has_2d": False, "has_3d": True}
    return {"format": "dsr-bench-results", "version": 1, "method": method, "meta": {"name": method}, "split": SPLIT,
            "split_checksum": "c" * 64, "pinned": True, "toolkit_version": __version__,
            "predictions_checksum": hashlib.sha256(method.encode()).hexdigest(), "date": "2026-11-22T00:00:00Z",
            "coverage": {"scored": 8, "expected": 8, "partial": False},
            **json.loads(json.dumps(aggregate(seqs)))}


def test_intervals_and_paired_differences_come_from_the_per_sequence_values(board):
    """A row's ± is the 95% t-interval of its per-sequence means; the paired differences from static (and push)
    pair the sequences: a row 0.05 better on every sequence differs by +0.050 ± 0.000, though the rows' own
    intervals overlap."""
    from dsr_bench.scoring.spread import spread

    _put(board, _varied("static", 0.0))
    _put(board, _varied("push", 0.0))
    _put(board, _varied("MyNet", 0.05))
    md = build(board)[0].read_text()
    table = _markdown_tables(md)["procedural-novel-mini: 3D track (reproduced)"]
    column = table[0].index("IoU ordered")
    mine = next(row for row in table if row[0] == "MyNet")
    values = [0.15 + 0.2 * i / 7 for i in range(8)]
    s = spread(values)
    assert mine[column] == f"**{s.mean:.3f} \u00b1 {s.half:.3f}**" and s.half > 0.05
    assert [row[0] for row in table[1:]] == ["MyNet", "push", "static"]  # reference rows last
    section = md.split("## procedural-novel-mini: 3D track (reproduced)")[1].split("## ")[0]
    for yardstick in ("static", "push"):
        diffs = section.split(f"Paired differences from {yardstick} ")[1].split("\n\n")[1].splitlines()
        header = [c.strip() for c in diffs[0].strip("|").split(" | ")]
        row = [c.strip() for c in next(line for line in diffs if line.startswith("| MyNet")).strip("|").split(" | ")]
        assert row[header.index(f"IoU ordered - {yardstick}")] == "+0.050 \u00b1 0.000"
        assert row[header.index("sequences")] == "8"
    # a table row holds what the entry's per-sequence values say: change them, and the interval changes with them
    wider = _varied("MyNet", 0.05, spread_=0.4)
    for path in (board / "entries").glob("mynet-*.json"):
        path.unlink()
    _put(board, wider)
    table = _markdown_tables(build(board)[0].read_text())["procedural-novel-mini: 3D track (reproduced)"]
    half = spread([0.15 + 0.4 * i / 7 for i in range(8)]).half
    assert next(row for row in table if row[0] == "MyNet")[column].endswith(f"\u00b1 {half:.3f}**")


def _plan_varied(method, ious, starts):
    from dsr_bench.planning.results import build_results
    from dsr_bench.planning.tasks import pinned_checksums

    per_task = {f"task_{i:04d}": {"iou": iou, "iou_identity": iou, "iou_occupancy": iou, "start_iou": start,
                                  "start_iou_identity": start, "start_iou_occupancy": start,
                                  "iou_per_object": [iou], "seconds": 1.0}
                for i, (iou, start) in enumerate(zip(ious, starts))}
    r = build_results(per_task, _planner(method),
                      {"task_set": "plan-novel-test", "checksum": pinned_checksums()["plan-novel-test"]}, 100, [],
                      f"dsr-bench plan --model {method}", {"candidates": 100})
    return {**r, "date": "2026-11-25T00:00:00Z"}


def _planning_table(board, planners):
    (board / "planning").mkdir(exist_ok=True)
    for path in (board / "planning").glob("*.json"):
        path.unlink()
    for results in planners:
        assert check_entry(results) == []
        (board / "planning" / entry_name(results)).write_text(json.dumps(results))
    md = build(board)[0].read_text()
    return md, _markdown_tables(md)["plan-novel-test: planning track (reproduced)"]


def test_planning_table_bolds_a_planner_only_where_it_beats_no_push_and_random(board):
    """No push (the start IoUs) and random are reference rows, never bold; a learned planner is bold only when its
    paired differences from both have 95% intervals above 0 (issue 30 part 3: 3DFlow's 0.337 against random's
    0.321 and no push's 0.362 is no better than either)."""
    rng = np.random.default_rng(0)
    starts = rng.uniform(0.2, 0.6, 100)
    random_ = np.clip(starts - 0.04 + rng.normal(0, 0.05, 100), 0, 1)
    close = np.clip(random_ + 0.01 + rng.normal(0, 0.2, 100), 0, 1)  # above random on average, within the noise
    md, table = _planning_table(board, [_plan_varied("random", random_, starts),
                                        _plan_varied("3dflow-cpu", close, starts)])
    header = table[0]
    assert header[2:5] == ["planning IoU", "vs no push (paired, \u00b1 SE)", "vs random (paired, \u00b1 SE)"]
    rows = {row[0]: row for row in table[1:]}
    assert list(rows) == ["3dflow-cpu (planning)", "random (planning)", "no push (planning)"]
    assert rows["no push (planning)"][2].startswith(f"{starts.mean():.3f} \u00b1")
    assert "reference" in rows["no push (planning)"][5] and "reference" in rows["random (planning)"][5]
    assert "**" not in "".join(" ".join(r) for r in table)  # the reference rows are higher but never bold
    assert (board / "plots" / "plan-novel-test-planning.png").exists()
    assert (board / "plots" / "plan-novel-test-planning.svg").exists()
    better = np.clip(starts + 0.05 + rng.normal(0, 0.02, 100), 0, 1)  # beats both, task by task
    md, table = _planning_table(board, [_plan_varied("random", random_, starts),
                                        _plan_varied("3dflow-cpu", close, starts),
                                        _plan_varied("dsr-cpu", better, starts)])
    bold = [row[0] for row in table[1:] if any(c.startswith("**") for c in row)]
    assert bold == ["dsr-cpu (planning)"]
    d = float(next(row for row in table if row[0] == "dsr-cpu (planning)")[3].split(" ")[0])
    assert d == pytest.approx(float(np.mean(better - starts)), abs=5e-4)
    md, table = _planning_table(board, [_plan_varied("dsr-cpu", better, starts)])  # random missing: none bold
    assert "**" not in "".join(" ".join(r) for r in table) and "lacks the no push or the random" in md


def test_paper_image_space_rows_show_no_voxel_grid_and_rows_say_their_split_version(board):
    _put(board, _results())
    md = build(board)[0].read_text()
    tables = _markdown_tables(md)
    for row in tables["ycb-test: 2D track (reported in the paper)"][1:]:
        assert row[1] == "-"  # SE3-Net and 2DFlow work on images: no 128x128x48 grid
    three = tables["procedural-novel-mini: 3D track (reproduced)"]
    assert three[0][-3:] == ["toolkit", "date", "split checksum"] and three[1][-3] != ""
    section = md.split("## procedural-novel-mini: 3D track (reproduced)")[1].split("## ")[0]
    assert "pinned version (checksum cccccccccccc" in section


def test_render_table_escapes_every_text_cell_and_link_in_markdown_and_html():
    """The one table renderer (local leaderboard and challenge server): a method, team or note holding markup, a
    pipe or emphasis is shown as written in both forms, and a link's address cannot leave its attribute."""
    from dsr_bench.leaderboard.entries import markdown_cell
    from dsr_bench.leaderboard.table import LINKS, ROLE, render_table

    hostile = '<img src=x onerror=alert(1)>|*x*"'
    rows = [{"rank": "1", "team": hostile, "method": hostile, "grid": "-", "label": hostile, "toolkit": "0.3",
             "date": "2026-11-26", "checksum": "", "iou_ordered": 0.5, "motion_full": None,
             LINKS: {"team": '/teams/"><script>', "method": "/submissions/ab"}},
            {"method": "static", "grid": "-", "iou_ordered": 0.25, "motion_full": 0.01}]
    table = render_table(rows, "3D", ["iou_ordered", "motion_full"], lead=(("#", "rank"), ("team", "team")))
    page, md = table.html(), "\n".join(table.markdown)
    assert "<img" not in page and "<script>" not in page and "<img" not in md
    assert page.count(html.escape(hostile)) == 3 and '<a href="/teams/&quot;&gt;&lt;script&gt;">' in page
    assert md.count(markdown_cell(hostile)) == 3 and "\\|" in markdown_cell(hostile)
    assert table.header[:3] == ["#", "team", "method"] and len(md.splitlines()) == 4
    assert table.comparable and "**0.500**" in md  # the static row is there: the best is marked
    assert "<td>-</td>" in page  # no value: "-", never "None" or "nan"
    # a submission named like the no-motion row is neither that yardstick nor noted "reference", and rows of another
    # role (submissions scored on a challenge's hidden set) are marked apart from the reference rows
    rows = [{"method": "static", "iou_ordered": 0.5, ROLE: "submission"}, {"method": "MyNet", "iou_ordered": 0.4}]
    table = render_table(rows, "3D", ["iou_ordered"])
    assert not table.comparable and "reference" not in "\n".join(table.markdown) and "**" not in table.html()
    rows.append({"method": "static", "iou_ordered": 0.45})
    table = render_table(rows, "3D", ["iou_ordered"])
    assert table.comparable and table.markdown[2].startswith("| static |  | 0.500 |  |")
    assert table.markdown[3].startswith("| MyNet |  | 0.400 \u25bc |")
    assert table.markdown[4].startswith("| static |  | **0.450** | reference |")


def test_build_of_a_missing_root_is_one_line_and_of_an_empty_one_an_empty_board(tmp_path, capsys):
    """`leaderboard build --root` of a folder that does not exist (or is a file): one line naming it, nothing made;
    of an empty folder: a leaderboard that says it has no entries (docs/evaluation.md)."""
    from dsr_bench.cli import main

    missing, a_file, empty = tmp_path / "missing", tmp_path / "a-file", tmp_path / "empty"
    a_file.write_text("")
    empty.mkdir()
    for root, why in ((missing, "no such directory"), (a_file, "not a directory")):
        assert main(["leaderboard", "build", "--root", str(root)]) == 2
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and err.startswith(f"error: --root {root}: {why}"), err
    assert not missing.exists()
    assert main(["leaderboard", "build", "--root", str(empty)]) == 0
    assert capsys.readouterr().err == ""
    assert sorted(p.name for p in empty.iterdir()) == ["README.md", "index.html"]
    assert (empty / "README.md").read_text().rstrip().endswith("No entries yet.")
    assert "<p>No entries yet.</p>" in (empty / "index.html").read_text()


def test_reference_rows_are_so_by_provenance_never_by_name(board, capsys):
    """A row is a reference row (noted "reference", the yardstick others are marked and paired against) only where
    its provenance says so (`table.REFERENCE`, which `build` sets from the entry): a row named static that says it
    is none is a trained row; an entry named like a reference row whose record contradicts it (meta.parameters not
    static's), or named so only in part (`Static (mine)`), is skipped by `build` with a warning."""
    static = _results("static", iou_ordered=0.2)
    _put(board, static)
    (board / "entries" / "other-static.json").write_text(json.dumps(
        {**_results("static", iou_ordered=0.9), "predictions_checksum": "d" * 64,
         "meta": {"name": "static", "parameters": {"grid": [128, 128, 48], "num_slots": 3}}}))
    (board / "entries" / "mine.json").write_text(json.dumps(_results("Static (mine)", iou_ordered=0.95)))
    build(board, warn=lambda line: print(line, file=sys.stderr))
    warnings = capsys.readouterr().err.splitlines()
    assert len(warnings) == 2 and "mine.json" in warnings[0] and "other-static.json" in warnings[1], warnings
    assert "reads as the reference row 'static'" in warnings[0] and "meta (name, parameters)" in warnings[1]
    table = _markdown_tables(build(board, warn=lambda line: None)[0].read_text())[
        "procedural-novel-mini: 3D track (reproduced)"]
    assert [row[0] for row in table[1:]] == ["static"] and "reference" in table[1][-4]

    from dsr_bench.leaderboard.table import REFERENCE, render_table

    rows = [{"method": "static", "iou_ordered": 0.5, REFERENCE: ""}, {"method": "MyNet", "iou_ordered": 0.4}]
    rendered = render_table(rows, "3D", ["iou_ordered"])
    assert not rendered.comparable and "reference" not in "".join(rendered.markdown)  # no yardstick: none marked
    rendered = render_table([{**rows[0], REFERENCE: "static"}, rows[1]], "3D", ["iou_ordered"])
    line = next(m for m in rendered.markdown if m.startswith("| static |"))
    assert rendered.comparable and "**0.500** | reference |" in line
