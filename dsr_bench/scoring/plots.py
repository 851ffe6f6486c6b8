"""Per-step plots (PNG) of a results file and of the leaderboard's rows.

`dsr-bench evaluate --out results.json` writes `results-steps.png` beside it (`steps_plot_path`): mask IoU
(unordered, ordered) against the step index, flow MSE (visible surface, full volume: a panel each) against it,
and the IoU of mostly occluded vs visible objects; a 2D-only submission's results (motion_2d alone) get the 2D
flow's panel only. Results hold the latter as one value each over all steps
(`breakdowns`), not per step, so it is drawn as two bars (with the number of object-steps behind each); a
results file whose `per_step` carries `iou_occluded_objects` / `iou_visible_objects` lists gets curves instead.
`dsr-bench leaderboard build` writes one PNG per table of reproduced results (split, version of the split,
track) comparing its rows step by step (`leaderboard_series`).

The series are prepared by plain functions (`step_series`, `leaderboard_series`: lists of floats, NaN where a
step has no value), separately from the rendering, which imports matplotlib lazily (Agg, no pyplot: no window,
no global backend switched) and writes through `dsr_bench.atomic`.
"""

from __future__ import annotations

import math
from pathlib import Path

from dsr_bench.atomic import atomic_path

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
    per_step = results.get("per_step")
    if not isinstance(per_step, dict):
        return {}
    return {k: v for k, v in per_step.items() if isinstance(v, list) and v}


def step_series(results: dict) -> tuple[dict | None, str | None]:
    """The data of a results file's per-step plot, or (None, why not).

    Returns ({"title", "panels": [{"title", "ylabel", "steps": [0..T-1], "lines": {legend: [floats]}}],
    "objects": {"per_step": bool, "lines" or "bars": {legend: ...}, "counts": {legend: object-steps}} or None},
    None). Values are the results' own, as floats (NaN where a step has none)."""
    lists = _per_step_lists(results)
    panels = []
    for title, ylabel, keys in STEP_PANELS:
        lines = {legend: _floats(lists[key]) for key, legend in keys if key in lists}
        if lines:
            steps = max(len(v) for v in lines.values())
            if set(lines) == {TWO_D_LEGEND}:  # a 2D-only submission: the front camera's flow alone
                title = TWO_D_TITLE
            panels.append({"title": title, "ylabel": ylabel, "steps": list(range(steps)), "lines": lines})
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
    return {"title": title, "panels": panels, "objects": objects}, None


def _save(fig, path: Path) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:  # the temporary has no .png suffix: the format is given
        fig.savefig(tmp, format="png", dpi=100, metadata={"Software": None})
    return path


def _figure(panels: int, title: str):
    """A figure of `panels` axes, at most 2 a row (a 2 x 2 grid for 4), and the axes in reading order."""
    from matplotlib.figure import Figure

    columns = min(panels, 2)
    rows = -(-panels // columns)
    fig = Figure(figsize=(5.0 * columns + 0.4, 3.6 * rows + 0.4), layout="constrained")
    fig.suptitle(title, fontsize=10)
    axes = fig.subplots(rows, columns, squeeze=False).ravel()
    for ax in axes[panels:]:
        ax.set_visible(False)
    return fig, axes[:panels]


def _step_axis(ax, steps: list[int]) -> None:
    ax.set_xlabel("step index t (push)")
    if len(steps) <= 12:
        ax.set_xticks(steps)
    ax.grid(True, alpha=0.3)


def write_steps_plot(results: dict, path: str | Path) -> tuple[Path | None, str | None]:
    """Render `step_series(results)` to a PNG at `path` (atomically): (path, None), or (None, why not) when the
    results hold no per-step values."""
    series, why = step_series(results)
    if series is None:
        return None, why
    if matplotlib_missing():
        return None, MISSING_MATPLOTLIB
    panels, objects = series["panels"], series["objects"]
    fig, axes = _figure(len(panels) + (objects is not None), series["title"])
    for ax, panel in zip(axes, panels):
        for legend, values in panel["lines"].items():
            ax.plot(panel["steps"], values, marker="o", markersize=3, label=legend)
        ax.set_title(panel["title"], fontsize=9)
        ax.set_ylabel(panel["ylabel"])
        _step_axis(ax, panel["steps"])
        ax.legend(fontsize=8)
    if objects is not None:
        ax = axes[len(panels)]
        ax.set_title("IoU of mostly occluded vs visible objects", fontsize=9)
        ax.set_ylabel("IoU")
        if objects["per_step"]:
            for legend, values in objects["lines"].items():
                ax.plot(range(len(values)), values, marker="o", markersize=3, label=legend)
            _step_axis(ax, list(range(max(len(v) for v in objects["lines"].values()))))
            ax.legend(fontsize=8)
        else:
            names = list(objects["bars"])
            values = [0.0 if math.isnan(v) else v for v in objects["bars"].values()]
            ax.bar(names, values, color=["tab:gray", "tab:blue"])
            for i, name in enumerate(names):
                count = objects["counts"].get(name)
                text = "-" if math.isnan(objects["bars"][name]) else f"{objects['bars'][name]:.3f}"
                ax.annotate(f"{text}\n({count} object-steps)" if count is not None else text, (i, values[i]),
                            ha="center", va="bottom", fontsize=8)
            ax.set_ylim(0, max(1.0, max(values) * 1.25))
            ax.set_xlabel("over all steps")
    return _save(fig, Path(path)), None


def leaderboard_series(entries: list[dict], track: str) -> list[dict]:
    """The panels of a leaderboard plot for the results `entries` of one table (one split, one version of it)
    and `track`: [{"key", "title", "ylabel", "steps", "lines": {row label: [floats]}}], only panels that some
    entry has per-step values for; an entry without them is left out (empty list: no plot)."""
    panels = []
    for key, title, ylabel in TRACK_PANELS[track]:
        lines = {}
        methods = [str(e.get("method", "?")) for e in entries]
        for e, method in zip(entries, methods):
            values = _per_step_lists(e).get(key)
            if values:
                label = method
                if methods.count(method) > 1 and e.get("label"):  # two rows of one method: their notes tell them apart
                    note = str(e["label"])
                    label += f" ({note[:28]}...)" if len(note) > 30 else f" ({note})"
                while label in lines:
                    label += "'"
                lines[label] = _floats(values)
        if lines:
            steps = list(range(max(len(v) for v in lines.values())))
            panels.append({"key": key, "title": title, "ylabel": ylabel, "steps": steps, "lines": lines})
    return panels


#: rows drawn as references: dashed
REFERENCE_METHODS = ("oracle", "static", "push")


def write_leaderboard_plot(panels: list[dict], title: str, path: str | Path) -> Path:
    """Render `leaderboard_series` panels (one line per row, one colour per row across the panels, reference rows
    dashed) to a PNG at `path`, atomically."""
    from matplotlib import colormaps

    fig, axes = _figure(len(panels), title)
    rows = list(dict.fromkeys(legend for panel in panels for legend in panel["lines"]))
    palette = colormaps["tab10" if len(rows) <= 10 else "tab20"]
    handles = {}
    for ax, panel in zip(axes, panels):
        for legend, values in panel["lines"].items():
            method = legend.split(" (")[0].rstrip("'").lower()
            reference = method in REFERENCE_METHODS or "oracle" in method
            (handles[legend],) = ax.plot(range(len(values)), values, marker="o", markersize=3, label=legend,
                                         color=palette(rows.index(legend) % palette.N),
                                         linestyle="--" if reference else "-")
        ax.set_title(panel["title"], fontsize=9)
        ax.set_ylabel(panel["ylabel"])
        _step_axis(ax, panel["steps"])
    fig.legend([handles[r] for r in rows], rows, loc="outside right upper", fontsize=8)
    return _save(fig, Path(path))
