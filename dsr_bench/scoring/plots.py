"""Per-step plots of a results file and the leaderboard's figures, one colour per method everywhere.

`dsr-bench evaluate --out results.json` writes `results-steps.png` beside it (`steps_plot_path`): mask IoU
(unordered, ordered) against the step index, flow MSE (visible surface, full volume: a panel each) against it,
and the IoU of mostly occluded vs visible objects; a 2D-only submission's results (motion_2d alone) get the 2D
flow's panel only. Each line gets a band, the per-step 95% interval of the mean over the sequences, when the
sequences' own per-step values are given (`evaluate` has them; a results file keeps only their means), and the
no-motion row's line (the leaderboard's `static` entry of the same split version) where one is given. Every
axis starts at 0. Results hold the occluded/visible IoUs as one value each over all steps (`breakdowns`), not
per step, so they are drawn as two bars (with the number of object-steps behind each); a results file whose
`per_step` carries `iou_occluded_objects` / `iou_visible_objects` lists gets curves instead.

`dsr-bench leaderboard build` draws one figure per table of reproduced results (split, version of the split,
track: `leaderboard_series`, `write_leaderboard_plot`): the rows step by step, and each row's mean over the
sequences with its 95% interval (from the entries' per-sequence values); and one per planning table
(`write_planning_plot`): each planner's mean IoU with its interval, and its paired differences from not pushing
and from random pushes. A method has one colour, line style and marker wherever it is drawn (`method_style`);
an oracle that would squeeze the other rows' axis is named on the panel instead of drawn (the styles:
`dsr_bench.scoring.styles`).

Figures are drawn at the size they are shown (`FIGURE_WIDTH_PX` CSS pixels wide at most, fonts in points):
SVG for the leaderboard's web page, PNG (at twice the pixels, for sharp display) where a markdown file embeds
one. The series are prepared by plain functions (lists of floats, NaN where a step has no value), separately
from the rendering, which imports matplotlib lazily (Agg, no pyplot: no window, no global backend switched) and
writes through `dsr_bench.atomic`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

from dsr_bench.atomic import atomic_path
from dsr_bench.scoring.spread import Spread, paired_difference, spread, step_bands
from dsr_bench.scoring.styles import (  # noqa: F401 - METHOD_STYLES and method_key importable from here as before
    METHOD_STYLES, is_oracle, is_reference_method, method_key, method_style,
)

#: `results.json` -> `results-steps.png`
STEPS_PLOT_SUFFIX = "-steps.png"
#: (panel title, y label, [(per_step key, legend)]) of the per-step line panels of one results file
#: (the two flow MSEs differ by orders of magnitude: a panel each; the 2D flow of image-based methods, when
#: scored, beside the visible surface's)
STEP_PANELS = (
    ("mask IoU", "IoU", (("iou_unordered", "unordered"), ("iou_ordered", "ordered"))),
    ("flow MSE, visible surface", "cm²", (("motion_visible", "visible surface (3D)"),
                                          ("motion_2d", "front camera (2D)"))),
    ("flow MSE, full volume", "cm²", (("motion_full", "full volume"),)),
)
#: the 2D flow's legend, and the panel's title when a results file (2D-only) has no 3D flow
TWO_D_LEGEND = "front camera (2D)"
TWO_D_TITLE = "2D flow MSE, front camera (visible pixels)"
OBJECT_KEYS = (("iou_occluded_objects", "mostly occluded"), ("iou_visible_objects", "visible"))
#: leaderboard track -> [(per_step key, panel title, y label)]
TRACK_PANELS = {
    "3D": (("iou_ordered", "mask IoU, ordered", "IoU"), ("motion_full", "flow MSE, full volume", "cm²")),
    "2D": (("motion_2d", "2D flow MSE, visible", "cm²"),),
}
#: a panel's short name, for the titles of its intervals
SHORT_TITLES = {"iou_ordered": "ordered IoU", "motion_full": "full-volume flow MSE", "motion_2d": "2D flow MSE"}
#: the legend prefix of the no-motion row's lines in a results file's plot
NO_MOTION_LEGEND = "no motion (static)"

#: the widest a figure is drawn, in CSS pixels (the leaderboard page's and a README's text column)
FIGURE_WIDTH_PX = 860
#: CSS pixels per inch (a figure's size in inches is its shown size / 96; fonts are in points, 1 pt = 4/3 px)
CSS_DPI = 96
#: PNGs carry twice the pixels of their shown size: sharp on high-density screens
PNG_SCALE = 2

#: why nothing is drawn when matplotlib (a dependency since 0.2) is missing from an environment installed before
MISSING_MATPLOTLIB = "matplotlib is not installed: run `pip install -e .` (or `pip install matplotlib`)"


def matplotlib_missing() -> bool:
    """Whether matplotlib cannot be imported (checked without importing it)."""
    import importlib.util

    return importlib.util.find_spec("matplotlib") is None


def steps_plot_path(results_path: str | Path) -> Path:
    """Where the per-step plot of a results file goes: beside it, `NAME-steps.png` for `NAME.json`."""
    path = Path(results_path)
    return path.with_name(path.stem + STEPS_PLOT_SUFFIX)


def _floats(values) -> list[float]:
    """`values` as floats, NaN for None or anything that is not a number (JSON has no NaN of its own)."""
    out = []
    for v in values:
        try:
            out.append(float(v))
        except (TypeError, ValueError):
            out.append(math.nan)
    return out


def _per_step_lists(results: dict) -> dict[str, list]:
    per_step = results.get("per_step") if isinstance(results, dict) else None
    if not isinstance(per_step, dict):
        return {}
    return {k: v for k, v in per_step.items() if isinstance(v, list) and v}


def step_series(results: dict, per_sequence_steps: Mapping[str, Mapping[str, Sequence]] | None = None,
                no_motion: dict | None = None) -> tuple[dict | None, str | None]:
    """The data of a results file's per-step plot, or (None, why not).

    Returns ({"title", "method", "panels": [{"title", "ylabel", "steps": [0..T-1], "lines": {legend: [floats]},
    "bands": {legend: ([low], [high])}, "references": {legend: [floats]}}], "objects": {"per_step": bool, "lines"
    or "bars": {legend: ...}, "counts": {legend: object-steps}} or None, "sequences": n or None}, None). Lines are
    the results' own values, as floats (NaN where a step has none); bands the per-step 95% intervals from
    `per_sequence_steps` ({sequence: {per_step key: [values]}}, as `evaluate` scored them); references the
    per-step values of `no_motion` (the static row's results on the same split version), legend prefixed
    `NO_MOTION_LEGEND`."""
    lists = _per_step_lists(results)
    reference = _per_step_lists(no_motion) if no_motion is not None else {}
    panels = []
    for title, ylabel, keys in STEP_PANELS:
        lines = {legend: _floats(lists[key]) for key, legend in keys if key in lists}
        if not lines:
            continue
        steps = max(len(v) for v in lines.values())
        if set(lines) == {TWO_D_LEGEND}:  # a 2D-only submission: the front camera's flow alone
            title = TWO_D_TITLE
        bands = {}
        for key, legend in keys:
            band = step_bands(per_sequence_steps, key) if per_sequence_steps and legend in lines else None
            if band is not None:
                bands[legend] = band
        references = {f"{NO_MOTION_LEGEND}: {legend}": _floats(reference[key]) for key, legend in keys
                      if legend in lines and key in reference}
        panels.append({"title": title, "ylabel": ylabel, "steps": list(range(steps)), "lines": lines,
                       "bands": bands, "references": references})
    if not panels:
        return None, "the results hold no per-step values (per_step), nothing to plot"
    objects = None
    if all(key in lists for key, _ in OBJECT_KEYS):
        objects = {"per_step": True, "lines": {legend: _floats(lists[key]) for key, legend in OBJECT_KEYS}}
    else:
        b = results.get("breakdowns") or {}
        bars = {legend: _floats([b.get(key)])[0] for key, legend in OBJECT_KEYS}
        if any(not math.isnan(v) for v in bars.values()):
            objects = {"per_step": False, "bars": bars,
                       "counts": {"mostly occluded": b.get("occluded_object_steps"),
                                  "visible": b.get("visible_object_steps")}}
    coverage = results.get("coverage") or {}
    scored = f" ({coverage['scored']}/{coverage['expected']} sequences)" if "scored" in coverage else ""
    title = f"{results.get('method', '?')} on {results.get('split', '?')}{scored}"
    return {"title": title, "method": str(results.get("method", "?")), "panels": panels, "objects": objects,
            "sequences": len(per_sequence_steps) if per_sequence_steps else None}, None


def save_figure(fig, path: Path) -> Path:
    """Write `fig` to `path` (atomically) in the format its suffix names: SVG at its shown size (text as text,
    no date: the same figure gives the same bytes), else PNG at `PNG_SCALE` times its pixels."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:  # the temporary has no suffix: the format is given
        if path.suffix == ".svg":
            with matplotlib.rc_context({"svg.hashsalt": "dsr-bench", "svg.fonttype": "none"}):
                fig.savefig(tmp, format="svg", metadata={"Date": None, "Creator": None})
        else:
            fig.savefig(tmp, format="png", dpi=CSS_DPI * PNG_SCALE, metadata={"Software": None})
    return path


def _new_figure(width_px: int, height_px: int, title: str):
    """A figure shown at width_px x height_px CSS pixels, laid out by matplotlib's constrained layout."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_px / CSS_DPI, height_px / CSS_DPI), dpi=CSS_DPI, layout="constrained")
    fig.suptitle(title, fontsize=10)
    return fig


def _figure(panels: int, title: str, panel_height_px: int = 300):
    """A figure of `panels` axes, at most 2 a row (a 2 x 2 grid for 4), `FIGURE_WIDTH_PX` wide (one panel: 60%
    of it), and the axes in reading order."""
    columns = min(panels, 2)
    rows = -(-panels // columns)
    width = FIGURE_WIDTH_PX if columns == 2 else round(FIGURE_WIDTH_PX * 0.6)
    fig = _new_figure(width, panel_height_px * rows + 40, title)
    axes = fig.subplots(rows, columns, squeeze=False).ravel()
    for ax in axes[panels:]:
        ax.set_visible(False)
    return fig, axes[:panels]


def _step_axis(ax, steps: list[int]) -> None:
    ax.set_xlabel("step index t (push)", fontsize=8)
    if len(steps) <= 12:
        ax.set_xticks(steps)
    ax.tick_params(labelsize=8)
    ax.grid(True, alpha=0.3)


def _finite(values) -> list[float]:
    return [v for v in values if isinstance(v, float) and math.isfinite(v)]


def _zero_based(ax, values: list[float], iou: bool) -> None:
    """The y axis from 0 to a little above the largest of `values` (an IoU axis never above 1)."""
    top = max(_finite(values), default=1.0)
    top = top * 1.12 if top > 0 else 1.0
    ax.set_ylim(0, min(top, 1.02) if iou else top)


def _same_values(a: list[float], b: list[float]) -> bool:
    return len(a) == len(b) and all((math.isnan(x) and math.isnan(y)) or abs(x - y) <= 1e-12 * max(1, abs(y))
                                    for x, y in zip(a, b))


def _with_band(ax, steps, band, colour) -> None:
    low, high = band
    ax.fill_between(steps[: len(low)], low, high, color=colour, alpha=0.18, linewidth=0)


def write_steps_plot(results: dict, path: str | Path,
                     per_sequence_steps: Mapping[str, Mapping[str, Sequence]] | None = None,
                     no_motion: dict | None = None, no_motion_note: str | None = None
                     ) -> tuple[Path | None, str | None]:
    """Render `step_series(results, per_sequence_steps, no_motion)` to a PNG at `path` (atomically): (path,
    None), or (None, why not) when the results hold no per-step values. `no_motion_note`: why there is no
    no-motion line, written under the figure when `no_motion` is None."""
    fig, why = steps_figure(results, per_sequence_steps, no_motion, no_motion_note)
    if fig is None:
        return None, why
    return save_figure(fig, Path(path)), None


def steps_figure(results: dict, per_sequence_steps: Mapping[str, Mapping[str, Sequence]] | None = None,
                 no_motion: dict | None = None, no_motion_note: str | None = None):
    """The matplotlib Figure of `write_steps_plot` (not saved), or (None, why not)."""
    series, why = step_series(results, per_sequence_steps, no_motion)
    if series is None:
        return None, why
    if matplotlib_missing():
        return None, MISSING_MATPLOTLIB
    panels, objects = series["panels"], series["objects"]
    fig, axes = _figure(len(panels) + (objects is not None), series["title"], panel_height_px=280)
    style = method_style(series["method"])
    still = method_style("static")
    variants = ("-", "--")  # a panel's first and second line (e.g. unordered, ordered)
    markers = ("o", "s")
    for ax, panel in zip(axes, panels):
        iou = panel["ylabel"] == "IoU"
        drawn: list[float] = []
        for i, (legend, values) in enumerate(panel["lines"].items()):
            if legend in panel["bands"]:
                _with_band(ax, panel["steps"], panel["bands"][legend], style["color"])
                drawn += panel["bands"][legend][1]
            ax.plot(panel["steps"][: len(values)], values, color=style["color"], linestyle=variants[i % 2],
                    marker=markers[i % 2], markersize=3.5, linewidth=1.5, label=legend)
            drawn += values
        for i, (legend, values) in enumerate(panel["references"].items()):
            ax.plot(range(len(values)), values, color=still["color"], linestyle=variants[i % 2], linewidth=1.1,
                    marker=markers[i % 2], markersize=3, markerfacecolor="none", label=legend)
            drawn += values
        ax.set_title(panel["title"], fontsize=9)
        ax.set_ylabel(panel["ylabel"], fontsize=8)
        _step_axis(ax, panel["steps"])
        _zero_based(ax, drawn, iou)
        ax.legend(fontsize=7)
    if objects is not None:
        ax = axes[len(panels)]
        ax.set_title("IoU of mostly occluded vs visible objects", fontsize=9)
        ax.set_ylabel("IoU", fontsize=8)
        if objects["per_step"]:
            for i, (legend, values) in enumerate(objects["lines"].items()):
                ax.plot(range(len(values)), values, color=style["color"], linestyle=variants[i % 2],
                        marker=markers[i % 2], markersize=3.5, label=legend)
            _step_axis(ax, list(range(max(len(v) for v in objects["lines"].values()))))
            ax.legend(fontsize=7)
            ax.set_ylim(0, 1.02)
        else:
            names = list(objects["bars"])
            values = [0.0 if math.isnan(v) else v for v in objects["bars"].values()]
            ax.bar(names, values, color=style["color"], alpha=0.55, edgecolor=style["color"])
            for i, name in enumerate(names):
                count = objects["counts"].get(name)
                text = "-" if math.isnan(objects["bars"][name]) else f"{objects['bars'][name]:.3f}"
                ax.annotate(f"{text}\n({count} object-steps)" if count is not None else text, (i, values[i]),
                            ha="center", va="bottom", fontsize=7)
            ax.set_ylim(0, max(1.0, max(values) * 1.25))
            ax.set_xlabel("over all steps", fontsize=8)
            ax.tick_params(labelsize=8)
    notes = []
    if series["sequences"]:
        notes.append(f"bands: 95% interval of the mean over the {series['sequences']} sequences, per step")
    if not any(p["references"] for p in panels):
        notes.append(no_motion_note or "no no-motion line: no static results of this split version given")
    if notes:
        fig.supxlabel("; ".join(notes), fontsize=7, color="#555555")
    return fig, None


def leaderboard_series(entries: list[dict], track: str) -> list[dict]:
    """The panels of a leaderboard plot for the results `entries` of one table (one split, one version of it)
    and `track`: [{"key", "title", "ylabel", "steps", "lines": {row label: [floats]}, "methods": {row label:
    method}, "spread": {row label: Spread of the row's per-sequence means}}], only panels that some entry has
    per-step values for; an entry without them is left out (empty list: no plot)."""
    from dsr_bench.scoring.spread import unit_values

    panels = []
    for key, title, ylabel in TRACK_PANELS[track]:
        lines, methods, spreads = {}, {}, {}
        names = [str(e.get("method", "?")) for e in entries]
        for e, method in zip(entries, names):
            values = _per_step_lists(e).get(key)
            if values:
                label = method
                if names.count(method) > 1 and e.get("label"):  # two rows of one method: their notes tell them apart
                    note = str(e["label"])
                    label += f" ({note[:28]}...)" if len(note) > 30 else f" ({note})"
                while label in lines:
                    label += "'"
                lines[label] = _floats(values)
                methods[label] = method
                spreads[label] = spread(list(unit_values(e.get("per_sequence"), key).values()))
        if lines:
            steps = list(range(max(len(v) for v in lines.values())))
            panels.append({"key": key, "title": title, "short": SHORT_TITLES.get(key, title), "ylabel": ylabel,
                           "steps": steps, "lines": lines, "methods": methods, "spread": spreads})
    return panels


def _note(ax, text: str) -> None:
    """A note in the panel's top left corner (e.g. an oracle not drawn because it lies off the axis chosen on
    the other rows, or a row drawn over an equal one)."""
    ax.annotate(text, xy=(0.01, 0.99), xycoords="axes fraction", ha="left", va="top", fontsize=7, zorder=5,
                bbox={"boxstyle": "round,pad=0.25", "fc": "white", "ec": "#bbbbbb", "lw": 0.5, "alpha": 0.9})


def _draw_steps(ax, panel: dict) -> dict:
    """The per-step lines of one leaderboard panel, each in its method's style; a line equal to one drawn before
    says so in its legend; an oracle outside the axis chosen on the other rows is named, not drawn. Returns the
    legend handles by row label."""
    iou = panel["ylabel"] == "IoU"
    methods = panel.get("methods") or {label: label for label in panel["lines"]}
    others = [v for label, values in panel["lines"].items() if not is_oracle(methods[label]) for v in values]
    _zero_based(ax, others, iou)
    low, high = ax.get_ylim()
    handles: dict = {}
    drawn: dict[str, list[float]] = {}
    notes: list[str] = []
    for label, values in panel["lines"].items():
        style = method_style(methods[label])
        finite = _finite(values)
        if is_oracle(methods[label]) and finite and (max(finite) > high or min(finite) < low):
            shown = f"{finite[0]:.3f}" if len(set(finite)) == 1 else f"{min(finite):.3g}-{max(finite):.3g}"
            notes.append(f"{label}: {shown} at every step (off this axis)")
            continue
        same = next((other for other, v in drawn.items() if _same_values(values, v)), None)
        if same:
            notes.append(f"{label} = {same} at every step (drawn over it)")
        reference = is_reference_method(methods[label])
        (handles[label],) = ax.plot(range(len(values)), values, label=label, linewidth=1.2 if reference else 1.6,
                                    markersize=7 if same else 4, markerfacecolor="none" if reference else None,
                                    zorder=3 if same else 2, **style)
        drawn[label] = values
    if notes:  # room above the lines for the note
        ax.set_ylim(low, high + (high - low) * 0.13 * len(notes))
        _note(ax, "\n".join(notes))
    ax.set_title(panel["title"] + ", per step", fontsize=9)
    ax.set_ylabel(panel["ylabel"], fontsize=8)
    _step_axis(ax, panel["steps"])
    return handles


def _draw_intervals(ax, panel: dict, order: list[str]) -> None:
    """Each row's mean over the sequences with its 95% interval, one row a line of the y axis (oracles named,
    not drawn: they would squeeze the others)."""
    methods = panel.get("methods") or {label: label for label in panel["lines"]}
    rows = [label for label in order if label in panel["spread"] and not is_oracle(methods[label])
            and panel["spread"][label].n > 0]
    rows = sorted(rows, key=lambda r: is_reference_method(methods[r]))  # reference rows last
    for y, label in enumerate(rows):
        s: Spread = panel["spread"][label]
        style = method_style(methods[label])
        reference = is_reference_method(methods[label])
        ax.errorbar([s.mean], [y], xerr=[[0 if math.isnan(s.half) else s.half]] * 2, color=style["color"],
                    marker=style["marker"], markersize=5, capsize=3, linewidth=1.4,
                    markerfacecolor="white" if reference else style["color"])
    ax.set_yticks(range(len(rows)), rows, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlim(0, max([panel["spread"][r].high for r in rows if not math.isnan(panel["spread"][r].high)]
                       + [panel["spread"][r].mean for r in rows] + [0]) * 1.1 or 1.0)
    oracles = [label for label in order if is_oracle(methods.get(label, "")) and label in panel["spread"]]
    if oracles:
        ax.annotate(f"not shown: {', '.join(oracles)}", xy=(0.99, 0.01), xycoords="axes fraction", ha="right",
                    va="bottom", fontsize=7, color="#555555")
    ax.set_title(f"{panel.get('short', panel['title'])}: mean over sequences, 95% CI", fontsize=9)
    ax.set_xlabel(panel["ylabel"], fontsize=8)
    ax.tick_params(labelsize=8)
    ax.grid(True, axis="x", alpha=0.3)


def write_leaderboard_plot(panels: list[dict], title: str, path: str | Path, svg: bool = False) -> Path:
    """Render `leaderboard_series` panels to a PNG at `path` (and, with `svg`, the same figure as an SVG beside
    it, `path` with .svg), atomically: per panel the rows step by step (one style per method, reference rows
    dashed or dotted) over the rows' means with their 95% intervals. Returns `path`."""
    fig = leaderboard_figure(panels, title)
    path = Path(path)
    save_figure(fig, path)
    if svg:
        save_figure(fig, path.with_suffix(".svg"))
    return path


def leaderboard_figure(panels: list[dict], title: str):
    """The matplotlib Figure of `write_leaderboard_plot` (not saved): a column per panel."""
    fig = _new_figure(FIGURE_WIDTH_PX, 40 + 250 * 2 + 60, title)
    axes = fig.subplots(2, len(panels), squeeze=False, height_ratios=(1.25, 1))
    handles: dict = {}
    for column, panel in enumerate(panels):
        handles.update(_draw_steps(axes[0, column], panel))
    order = list(dict.fromkeys(label for panel in panels for label in panel["lines"]))
    for column, panel in enumerate(panels):
        _draw_intervals(axes[1, column], panel, order)
    labels = [h.get_label() for h in handles.values()]
    fig.legend(list(handles.values()), labels, loc="outside lower center", ncols=min(5, len(labels)), fontsize=8,
               frameon=False)
    return fig


def write_planning_plot(rows: Sequence[tuple[str, Mapping[str, float]]], title: str, path: str | Path,
                        baselines: tuple[str, ...] = ("no push", "random"), svg: bool = False) -> Path:
    """A planning table's figure at `path` (PNG; with `svg` also an SVG beside it): each row's mean IoU over the
    tasks with its 95% interval (rows: (label, {task: IoU})), and each non-reference row's paired difference from
    each of the `baselines` rows (mean over the tasks, 95% interval). Returns `path`."""
    fig = _new_figure(FIGURE_WIDTH_PX, 60 + 22 * max(4, len(rows)) + 80, title)
    left, right = fig.subplots(1, 2)
    for y, (label, values) in enumerate(rows):
        s = spread(list(values.values()))
        style = method_style(label)
        reference = is_reference_method(label)
        left.errorbar([s.mean], [y], xerr=[[0 if math.isnan(s.half) else s.half]] * 2, color=style["color"],
                      marker=style["marker"], markersize=5, capsize=3, markerfacecolor="white" if reference else None)
    left.set_yticks(range(len(rows)), [label for label, _ in rows], fontsize=8)
    left.invert_yaxis()
    left.set_xlim(0, 1)
    left.set_title("planning IoU: mean over tasks, 95% interval", fontsize=9)
    left.set_xlabel("IoU with the target", fontsize=8)
    by_label = dict(rows)
    compared = [label for label, _ in rows if not is_reference_method(label)]
    bases = [b for b in baselines if b in by_label]
    y = 0
    ticks = []
    for label in compared:
        style = method_style(label)
        for j, base in enumerate(bases):
            d = paired_difference(by_label[label], by_label[base])
            right.errorbar([d.mean], [y], xerr=[[0 if math.isnan(d.half) else d.half]] * 2, color=style["color"],
                           marker=("o", "s", "^")[j % 3], markersize=5, capsize=3,
                           markerfacecolor=style["color"] if j == 0 else "white")
            ticks.append(f"{label} - {base}")
            y += 1
    right.axvline(0, color="#4d4d4d", linewidth=0.8)
    right.set_yticks(range(len(ticks)), ticks, fontsize=8)
    right.invert_yaxis()
    right.set_title("paired difference over tasks, 95% interval", fontsize=9)
    right.set_xlabel("IoU difference (> 0: better than the reference)", fontsize=8)
    for ax in (left, right):
        ax.tick_params(labelsize=8)
        ax.grid(True, axis="x", alpha=0.3)
    path = Path(path)
    save_figure(fig, path)
    if svg:
        save_figure(fig, path.with_suffix(".svg"))
    return path
