"""Per-step plots: the series are the results' own values, `evaluate --out` writes a valid PNG beside the results,
a results file without per-step values is skipped with a note, and the leaderboard writes and shows one plot per
table of reproduced rows."""

import json
import math
from hashlib import sha256
from pathlib import Path

from PIL import Image

from dsr_bench import __version__
from dsr_bench.cli import main
from dsr_bench.leaderboard.entries import step_mean
from dsr_bench.leaderboard.board import build
from dsr_bench.scoring.plots import (FIGURE_WIDTH_PX, leaderboard_figure, leaderboard_series, method_style,
                                     step_series, steps_figure, steps_plot_path, write_leaderboard_plot,
                                     write_steps_plot)
from dsr_bench.scoring.spread import spread
from dsr_bench.testing import write_synthetic_dataset

ROOT = Path(__file__).resolve().parents[1]


def _results(method="MyNet", per_step=True, **extra):
    results = {"format": "dsr-bench-results", "version": 1, "method": method, "split": "procedural-novel-mini",
               "split_checksum": "c" * 64, "date": "2026-11-24T00:00:00Z",
               "coverage": {"scored": 8, "expected": 8, "partial": False},
               "metrics": {"motion_visible": 5.0, "motion_full": 0.08, "iou_unordered": 0.7, "iou_ordered": 0.6},
               "breakdowns": {"iou_occluded_objects": 0.25, "occluded_object_steps": 7, "iou_visible_objects": 0.5,
                              "visible_object_steps": 40, "motion_moved_objects": 9.0, "motion_static_objects": 0.1}}
    if per_step:
        results["per_step"] = {"iou_unordered": [0.7, 0.8, 0.6], "iou_ordered": [0.6, 0.7, None],
                               "motion_visible": [5.0, 6.0, 4.0], "motion_full": [0.08, 0.09, 0.07],
                               "motion_moved": [1.0, 2.0, 3.0], "motion_static": [0.0, 0.0, 0.0]}
        # a valid leaderboard entry: each metric the mean of its per-step values, as `evaluate` computes it
        results["metrics"] = {k: step_mean(results["per_step"][k]) for k in results["metrics"]}
        results["breakdowns"].update(motion_moved_objects=2.0, motion_static_objects=0.0)
    results.update(pinned=True, toolkit_version=__version__, predictions_checksum=sha256(method.encode()).hexdigest())
    return {**results, **extra}


def _png(path: Path) -> tuple[int, int]:
    with Image.open(path) as image:
        assert image.format == "PNG"
        image.load()  # the whole file decodes
        return image.size


def _svg_size(path: Path) -> tuple[int, int]:
    """The CSS pixels an SVG of matplotlib's is shown at (its width and height are in points: 1 pt = 4/3 px); for a
    PNG path, the SVG beside it."""
    import re

    head = path.with_suffix(".svg").read_text()[:2000]
    width, height = (float(re.search(rf'{k}="([0-9.]+)pt"', head).group(1)) for k in ("width", "height"))
    return round(width * 4 / 3), round(height * 4 / 3)


def _same(a: list[float], b: list) -> bool:
    return len(a) == len(b) and all((x != x and y is None) or x == y for x, y in zip(a, b))


def test_step_series_is_what_the_results_hold():
    results = _results()
    series, why = step_series(results)
    assert why is None and series["title"] == "MyNet on procedural-novel-mini (8/8 sequences)"
    panels = {p["title"]: p for p in series["panels"]}
    assert list(panels) == ["mask IoU", "flow MSE, visible surface", "flow MSE, full volume"]
    assert all(p["steps"] == [0, 1, 2] for p in panels.values())
    iou = panels["mask IoU"]["lines"]
    assert _same(iou["unordered"], results["per_step"]["iou_unordered"])
    assert _same(iou["ordered"], results["per_step"]["iou_ordered"]) and math.isnan(iou["ordered"][2])  # null: NaN
    assert panels["flow MSE, visible surface"]["lines"] == {"visible surface (3D)": [5.0, 6.0, 4.0]}  # no 2D scored
    assert panels["flow MSE, full volume"]["lines"] == {"full volume": [0.08, 0.09, 0.07]}
    # occluded vs visible: results hold one value each over all steps, drawn as bars with their counts
    assert series["objects"] == {"per_step": False, "bars": {"mostly occluded": 0.25, "visible": 0.5},
                                 "counts": {"mostly occluded": 7, "visible": 40}}


def test_step_series_draws_2d_flow_and_per_step_object_ious_when_the_results_have_them():
    results = _results()
    results["per_step"].update(motion_2d=[3.0, 2.0, 1.0], iou_occluded_objects=[0.1, 0.2, 0.3],
                               iou_visible_objects=[0.4, 0.5, 0.6])
    series, _ = step_series(results)
    assert series["panels"][1]["lines"]["front camera (2D)"] == [3.0, 2.0, 1.0]
    assert series["objects"] == {"per_step": True, "lines": {"mostly occluded": [0.1, 0.2, 0.3],
                                                             "visible": [0.4, 0.5, 0.6]}}


def test_results_without_per_step_values_are_skipped_with_a_note(tmp_path):
    for results in (_results(per_step=False), _results(per_step=False) | {"per_step": {}},
                    {"method": "x"}, _results(per_step=False) | {"per_step": "garbage"}):
        series, why = step_series(results)
        assert series is None and "no per-step values" in why
        assert write_steps_plot(results, tmp_path / "r-steps.png") == (None, why)
    assert list(tmp_path.iterdir()) == []


def test_steps_plot_is_a_valid_png_written_atomically(tmp_path):
    path, why = write_steps_plot(_results(), tmp_path / "deep" / "results-steps.png")
    assert why is None and path == tmp_path / "deep" / "results-steps.png"
    width, height = _png(path)
    assert 600 <= width <= 2000 and 400 <= height <= 1500
    assert sorted(p.name for p in path.parent.iterdir()) == ["results-steps.png"]  # no temporary or lock left
    assert steps_plot_path(tmp_path / "results.json") == tmp_path / "results-steps.png"
    assert steps_plot_path("out/static.json") == Path("out/static-steps.png")


def test_evaluate_writes_the_steps_plot_beside_the_results(tmp_path, capsys):
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=2, num_steps=3)
    assert main(["predict", "--model", "static", "--data", str(data), "--out", str(tmp_path / "pred")]) == 0
    out = tmp_path / "res" / "results.json"
    assert main(["evaluate", str(tmp_path / "pred"), "--out", str(out)]) == 0
    assert f"per-step plots written to {tmp_path / 'res' / 'results-steps.png'}" in capsys.readouterr().err
    assert sorted(p.name for p in out.parent.iterdir()) == ["results-steps.png", "results.json"]
    width, height = _png(out.parent / "results-steps.png")
    assert width >= 600 and height >= 400
    results = json.loads(out.read_text())
    series, _ = step_series(results)
    lines = {k: v for p in series["panels"] for k, v in p["lines"].items()}
    assert lines["unordered"] == results["per_step"]["iou_unordered"]
    assert lines["ordered"] == results["per_step"]["iou_ordered"]
    assert lines["visible surface (3D)"] == results["per_step"]["motion_visible"]
    assert lines["full volume"] == results["per_step"]["motion_full"]
    assert lines["front camera (2D)"] == results["per_step"]["motion_2d"]  # static writes motion_2d


def _entry(board: Path, results: dict, name: str) -> None:
    (board / "entries").mkdir(exist_ok=True)
    (board / "entries" / f"{name}.json").write_text(json.dumps(results))


def test_leaderboard_series_are_the_entries_per_step_values():
    a, b, c = _results("static"), _results("MyNet"), _results("NoSteps", per_step=False)
    b["per_step"]["iou_ordered"] = [0.1, 0.2, 0.3]
    panels = leaderboard_series([a, b, c], "3D")
    assert [p["key"] for p in panels] == ["iou_ordered", "motion_full"]
    assert panels[0]["lines"].keys() == {"static", "MyNet"}  # an entry without per-step values is left out
    assert panels[0]["lines"]["MyNet"] == [0.1, 0.2, 0.3] and panels[1]["lines"]["static"] == [0.08, 0.09, 0.07]
    assert leaderboard_series([a, b], "2D") == []  # nobody has 2D per-step values: no plot
    twice = leaderboard_series([a, _results("static", label="long schedule")], "3D")[0]["lines"]
    assert list(twice) == ["static", "static (long schedule)"]


def test_leaderboard_build_writes_and_shows_one_plot_per_table(board, tmp_path):
    _entry(board, _results("static"), "static")
    _entry(board, _results("MyNet"), "mynet")
    old = _results("OldNet", split_checksum="0123456789ab" + "f" * 52, toolkit_version="0.1.0")  # an earlier pin
    _entry(board, old, "oldnet")
    (board / "plots").mkdir()
    (board / "plots" / "gone-3d.png").write_bytes(b"stale")  # a table that no longer exists
    md, page = build(board)
    plots = sorted(p.name for p in (board / "plots").iterdir())
    assert plots == ["procedural-novel-mini-0123456789ab-3d.png", "procedural-novel-mini-0123456789ab-3d.svg",
                     "procedural-novel-mini-3d.png", "procedural-novel-mini-3d.svg"]
    for name in plots[::2]:
        assert _png(board / "plots" / name) == (2 * FIGURE_WIDTH_PX, 2 * _svg_size(board / "plots" / name)[1])
    text, html = md.read_text(), page.read_text()
    current = text.split("## procedural-novel-mini: 3D track (reproduced)")[1].split("## ")[0]
    # markdown shows the PNG at its drawn size (half its pixels: sharp on dense screens), the page the SVG
    assert f'<img src="plots/procedural-novel-mini-3d.png" width="{FIGURE_WIDTH_PX}"' in current
    earlier = text.split("0123456789ab)")[1].split("## ")[0]
    assert '<img src="plots/procedural-novel-mini-0123456789ab-3d.png"' in earlier
    assert '<img src="plots/procedural-novel-mini-3d.svg"' in html
    assert '<img src="plots/procedural-novel-mini-0123456789ab-3d.svg"' in html
    assert "width=" not in html.split("<figure>")[1]  # the browser shows the SVG at the size it was drawn
    paper = text.split("(reported in the paper)")[1]
    assert "plots/" not in paper  # paper rows have no per-step values


def test_leaderboard_entries_without_per_step_values_get_no_plot(board):
    _entry(board, _results("MyNet", per_step=False), "mynet")
    md, page = build(board)
    assert not (board / "plots").exists() or not list((board / "plots").iterdir())
    assert "plots/" not in md.read_text() and "<img" not in page.read_text()


def test_leaderboard_plot_is_a_valid_png(tmp_path):
    panels = leaderboard_series([_results("static"), _results("oracle"), _results("MyNet")], "3D")
    path = write_leaderboard_plot(panels, "procedural-novel-mini: 3D track", tmp_path / "p" / "x-3d.png", svg=True)
    width, height = _png(path)
    assert width == 2 * FIGURE_WIDTH_PX and 300 <= height <= 1500
    assert _svg_size(path.with_suffix(".svg")) == (FIGURE_WIDTH_PX, height // 2)  # the same figure, as drawn


def test_without_matplotlib_the_plot_is_skipped_with_the_fix(tmp_path, monkeypatch):
    import dsr_bench.scoring.plots as plots

    monkeypatch.setattr(plots, "matplotlib_missing", lambda: True)
    assert write_steps_plot(_results(), tmp_path / "r-steps.png") == (None, plots.MISSING_MATPLOTLIB)
    assert "pip install" in plots.MISSING_MATPLOTLIB and not (tmp_path / "r-steps.png").exists()


def test_one_style_per_method_whatever_its_track_or_spelling():
    """dsr-cpu, the paper's DSR-Net and the DSR-Net planner are one method: one colour, line and marker; the
    reference rows differ from each other and from every trained row."""
    assert method_style("dsr-cpu") == method_style("DSR-Net") == method_style("dsr-cpu (planning)") == \
        method_style("dsr")
    assert method_style("single-cpu") == method_style("SingleStep")
    assert method_style("GTWarp (oracle warp)") == method_style("gtwarp-cpu")
    known = ["static", "push", "oracle", "random", "dsr", "single", "nowarp", "gtwarp", "3dflow", "2dflow", "se3net",
             "se3posenet"]
    colours = [method_style(m)["color"] for m in known]
    assert len(set(colours)) == len(colours)
    assert method_style("MyNet") == method_style("MyNet")  # an unknown method: the same colour in every figure
    assert {method_style(m)["linestyle"] for m in ("static", "push", "oracle", "random")}.isdisjoint({"-"})


def _drawn_lines(ax) -> dict:
    return {line.get_label(): line for line in ax.get_lines() if not line.get_label().startswith("_")}


def test_a_method_has_its_colour_in_the_3d_2d_and_evaluate_figures():
    entries = [_results("static"), _results("push"), _results("dsr-cpu")]
    for e in entries:
        e["per_step"]["motion_2d"] = [3.0, 2.0, 1.0]
    three = leaderboard_figure(leaderboard_series(entries, "3D"), "3D")
    two = leaderboard_figure(leaderboard_series(entries, "2D"), "2D")
    for fig in (three, two):
        lines = _drawn_lines(fig.axes[0])
        for method in ("static", "push", "dsr-cpu"):
            assert lines[method].get_color() == method_style(method)["color"]
            assert lines[method].get_marker() == method_style(method)["marker"]
    fig, _ = steps_figure(_results("dsr-cpu"))
    assert {line.get_color() for line in _drawn_lines(fig.axes[0]).values()} == {method_style("dsr-cpu")["color"]}


def test_iou_panel_names_the_oracle_off_its_axis_and_shows_push_under_static():
    """The oracle at 1.0 does not squeeze the models (the axis is chosen on them, the oracle named on the panel);
    push's line equal to static's is drawn with its own marker and said to be equal."""
    static, push, oracle, mine = _results("static"), _results("push"), _results("oracle"), _results("MyNet")
    oracle["per_step"]["iou_ordered"] = [1.0, 1.0, 1.0]
    static["per_step"]["iou_ordered"] = push["per_step"]["iou_ordered"] = [0.12, 0.13, 0.11]
    mine["per_step"]["iou_ordered"] = [0.25, 0.3, 0.28]
    fig = leaderboard_figure(leaderboard_series([static, push, oracle, mine], "3D"), "t")
    iou = fig.axes[0]
    lines = _drawn_lines(iou)
    assert "oracle" not in lines and iou.get_ylim()[0] == 0 and iou.get_ylim()[1] < 0.5
    notes = " ".join(t.get_text() for t in iou.texts)
    assert "oracle: 1.000 at every step (off this axis)" in notes and "push = static" in notes
    assert lines["push"].get_marker() != lines["static"].get_marker()
    assert lines["push"].get_linestyle() != lines["static"].get_linestyle()
    flow = _drawn_lines(fig.axes[1])
    assert "oracle" in flow  # 0 flow error lies on the flow axis: drawn there


def test_evaluate_plot_has_bands_the_no_motion_line_and_axes_from_zero():
    results = _results("MyNet")
    per_sequence = {"seq_0000": {"iou_ordered": [0.5, 0.6, 0.7], "iou_unordered": [0.6, 0.7, 0.8]},
                    "seq_0001": {"iou_ordered": [0.7, 0.8, None], "iou_unordered": [0.8, 0.9, 1.0]},
                    "seq_0002": {"iou_ordered": [0.6, 0.5, 0.7], "iou_unordered": [0.7, 0.6, 0.6]}}
    static = _results("static")
    static["per_step"]["iou_ordered"] = [0.1, 0.2, 0.15]
    series, _ = step_series(results, per_sequence, static)
    iou = series["panels"][0]
    low, high = iou["bands"]["ordered"]
    step0 = spread([0.5, 0.7, 0.6])
    assert (low[0], high[0]) == (step0.low, step0.high)
    step2 = spread([0.7, 0.7])  # a sequence without a value at a step is left out there
    assert (low[2], high[2]) == (step2.low, step2.high)
    assert iou["references"]["no motion (static): ordered"] == [0.1, 0.2, 0.15]
    fig, _ = steps_figure(results, per_sequence, static)
    assert all(ax.get_ylim()[0] == 0 for ax in fig.axes if ax.get_visible())
    assert "no motion (static): ordered" in _drawn_lines(fig.axes[0])
    assert len(fig.axes[0].collections) == 2  # a band under each IoU line
    fig, _ = steps_figure(results, no_motion_note="no no-motion line: none of this split")
    assert "no no-motion line: none of this split" in fig.get_supxlabel()


def test_evaluate_finds_the_no_motion_row_of_the_same_split_version(board):
    """evaluate's plot takes the leaderboard's static entry scored on the same version of the split, and says why
    when there is none."""
    from dsr_bench.leaderboard.board import no_motion_entry

    mine = _results("MyNet")
    assert no_motion_entry(mine, board)[0] is None  # an empty leaderboard
    _entry(board, _results("static"), "static")
    found, why = no_motion_entry(mine, board)
    assert found["method"] == "static" and found["per_step"] == _results("static")["per_step"] and why == ""
    other = {**mine, "split_checksum": "0123456789ab" + "f" * 52}  # an earlier version of the split
    found, why = no_motion_entry(other, board)
    assert found is None and "no static entry scored on this version of 'procedural-novel-mini'" in why
    assert no_motion_entry(_results("static"), board)[0] is None  # static's own plot: no second line
    assert "no leaderboard" in no_motion_entry(mine, board / "missing")[1]
