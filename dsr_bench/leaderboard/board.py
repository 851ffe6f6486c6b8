"""The leaderboard: results entries (one JSON per entry) and the tables built from them.

leaderboard/entries/*.json are results of `dsr-bench evaluate` as `add` (`dsr_bench.leaderboard.add`) recomputed
them from the predictions (plus an optional "label"), never a submitted file's numbers; leaderboard/planning/*.json
likewise results of `dsr-bench plan` recomputed from the plan files (complete runs on a pinned task set), shown in
the planning IoU column. `dsr_bench.leaderboard.entries` validates both before `add` writes and when `build` reads
(a file that fails is skipped with one warning line). leaderboard/paper.json holds the paper's published numbers,
always shown apart and marked "reported in the paper". A 2D-only entry (results holding motion_2d alone) joins the
2D track's table only. `build` writes leaderboard/README.md (a table per split and track, best per column in bold;
every text cell escaped), a static, sortable leaderboard/index.html and, for each table of reproduced rows whose
entries hold per-step values, leaderboard/plots/<split>-3d.png (-2d.png for the 2D track; an earlier version of a
split: <split>-<checksum>-3d.png) comparing the rows step by step, shown under the table. A row is a reference
row (label "reference", a yardstick of the paired differences and the marks) by its provenance
(`provenance.reference_of`, under `table.REFERENCE`), never by its name alone. A missing --root is a one-line error;
an empty one builds a leaderboard that says it has no entries.
"""

from __future__ import annotations

import functools
import html
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dsr_bench.atomic import write_text
from dsr_bench.constants import GRID_SHAPE, IMAGE_SHAPE
from dsr_bench.errors import UserError
from dsr_bench.leaderboard.add import _first, add_entry  # noqa: F401 - `add`, the command's entry, beside `build`
from dsr_bench.leaderboard.entries import (PLAN_RESULTS_FORMAT, RESULTS_FORMAT, UnreadableJSON, check_entry,
                                           is_2d_only, markdown_cell, read_json, show)
from dsr_bench.leaderboard.provenance import reference_of
from dsr_bench.leaderboard.table import (COLUMN_TITLES, LOWER_IS_BETTER, NO_MOTION, NO_PUSH, REFERENCE,  # noqa: F401
                                         SEQ, SORT_SCRIPT, TRACKS, _WORSE_MARK, _difference, _yardsticks,
                                         html_table, is_named, is_oracle_row, is_reference_row, md_row, named,
                                         render_table)
from dsr_bench.scoring.plots import FIGURE_WIDTH_PX
from dsr_bench.scoring.spread import paired_difference, unit_values


def _read_valid(paths, kind: str, warn) -> list[tuple[Path, dict]]:
    """The files that are valid entries of their kind (results or planning results); one warning line for each
    that is not, naming the file and its (first) problem."""
    valid = []
    for path in paths:
        try:
            r = read_json(path)
        except UnreadableJSON as exc:
            warn(f"skipped {path}: {exc}")
            continue
        problems = check_entry(r) if isinstance(r, dict) and r.get("format") == kind else \
            [f"not a {kind} file (format {show(r.get('format') if isinstance(r, dict) else r)})"]
        if problems:
            warn(f"skipped {path}: {_printable(_first(problems))}")
        else:
            valid.append((path, r))
    return valid


def _printable(text: str) -> str:
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _stderr(line: str) -> None:
    print(f"warning: {line}", file=sys.stderr)


def _kind(results: dict) -> str:
    """The table an entry belongs to, beside its split: the split's current pin, or an earlier version of it."""
    from dsr_bench.dataset.splits import SPLITS

    expected = SPLITS[results["split"]].expected_digest if results["split"] in SPLITS else None
    checksum = results.get("split_checksum", "")
    if "real_split" in results:  # a lab's real split: one table per split and checksum (its own pins)
        return f"{REAL_KIND}, checksum {checksum[:12]}"
    # an entry scored on an earlier pin of its split stays visible, in its own table, unranked against the rest
    return "reproduced" if checksum == expected else f"reproduced on an earlier version of the split, {checksum[:12]}"


@functools.cache
def _shipped_sha256() -> dict[str, str]:
    """{file name: SHA-256} of the toolkit's shipped CPU-track weights files."""
    from dsr_bench.dataset.manifest import file_sha256
    from dsr_bench.models.predictors import SHIPPED_WEIGHTS

    return {path.name: file_sha256(path) for path in sorted(SHIPPED_WEIGHTS.glob("*.pt"))}


def superseded_weights(records: Any) -> str:
    """The note of a row whose results record shipped CPU-track weights (`predictors.SHIPPED_SOURCE`; one record or
    a list, as predictions' meta.json parameters "weights" and a plan's planner "weights" hold them) that are not
    the files the toolkit ships now: "weights 84983793, 36d93c9c: shipped before, not now" (SHA-256 prefixes), else
    "". Such a row stands for the weights it names, not for `--model M` today. Records are looked up by name, never
    opened: `entries.weights_problem` keeps malformed ones off the leaderboard."""
    from dsr_bench.models.predictors import SHIPPED_SOURCE

    shipped = _shipped_sha256()
    old = [r["sha256"][:8] for r in (records if isinstance(records, list) else [records])
           if isinstance(r, dict) and r.get("source") == SHIPPED_SOURCE and isinstance(r.get("sha256"), str)
           and r["sha256"] and shipped.get(r.get("file")) != r["sha256"]]  # type: ignore[arg-type]
    return f"weights {', '.join(old)}: shipped before, not now" if old else ""


def _joined(*notes: str) -> str:
    return "; ".join(n for n in notes if n)


def load_entries(root: str | Path = "leaderboard", warn: Callable[[str], None] | None = None) -> list[dict]:
    """Every valid entry's results (entries/*.json, sorted by file name), each with its table's "kind" added; an
    invalid file is skipped with one `warn` line (default: on stderr)."""
    paths = sorted((Path(root) / "entries").glob("*.json"))
    return [{**r, "kind": _kind(r)} for _, r in _read_valid(paths, RESULTS_FORMAT, warn or _stderr)]


def load_rows(root: str | Path = "leaderboard", warn: Callable[[str], None] | None = None,
              entries: list[dict] | None = None) -> list[dict]:
    """Flat rows (method, split, kind, metrics, date, checksum, label) of every valid entry (`entries`, default
    `load_entries`), valid planning entry and paper row."""
    root = Path(root)
    rows = []
    for r in load_entries(root, warn) if entries is None else entries:
        kind = r["kind"]
        # the model's grid, or the image an image-space model works on (parameters "image"; a 2D-only entry
        # that names neither: the front camera's)
        params = (r.get("meta") or {}).get("parameters") or {}
        default = IMAGE_SHAPE if is_2d_only(r.get("metrics") or {}) else GRID_SHAPE
        grid = params.get("grid") or params.get("image") or list(default)
        label = _joined(str(r.get("label", "")), superseded_weights(params.get("weights")))
        rows.append({"method": r["method"], "split": r["split"], "kind": kind, "label": label,
                     REFERENCE: reference_of(r, planning=False)[0],
                     "grid": "x".join(str(int(g)) for g in grid), "toolkit": str(r.get("toolkit_version", "")),
                     "date": r.get("date", "")[:10], "checksum": r.get("split_checksum", "")[:12],
                     SEQ: r.get("per_sequence") or {}, **{k: v for k, v in r["metrics"].items()}})
    plans = _read_valid(sorted((root / "planning").glob("*.json")), PLAN_RESULTS_FORMAT, warn or _stderr)
    rows += planning_rows([path for path, _ in plans], include_paper=False)  # paper.json has them
    paper = root / "paper.json"
    if paper.exists():
        try:
            published = read_json(paper)["rows"]
        except (UnreadableJSON, TypeError, KeyError) as exc:
            raise UserError(f"{paper}: {exc if isinstance(exc, UnreadableJSON) else 'no list of rows'}; restore it "
                            "from the repository (git checkout leaderboard/paper.json)") from None
        for r in published:
            # an image-space model of the paper (2D flow alone) has no voxel grid, and the paper gives its image
            # size nowhere we quote: "-", never the 3D models' grid
            grid = "-" if set(r["metrics"]) == {"motion_2d"} else "x".join(map(str, GRID_SHAPE))
            rows.append({"method": r["method"], "split": r["split"], "kind": "reported in the paper", "grid": grid,
                         "toolkit": "", "label": r.get("source", ""), "date": "2020", "checksum": "", SEQ: {},
                         REFERENCE: None, **r["metrics"]})  # the repository's own rows: by their names
    return rows


#: Leaderboard rows of the paper (Sec. 4.3), planning IoU over its 100 simulated targets.
PLANNING_PAPER_ROWS = (("DSR-Net", 0.72), ("SE3-Net (planning)", 0.31), ("SE3Pose-Net (planning)", 0.32))


def planning_rows(results_files: list[str | Path], include_paper: bool = True) -> list[dict]:
    """Rows for the leaderboard's planning tables, in `load_rows`'s shape (method, split, kind, label, grid,
    toolkit, date, checksum, planning_iou, and the per-task IoUs under `SEQ`): one per results file of `dsr-bench
    plan` (`dsr_bench.planning.results.build_results`; kind "reproduced" when its task set matches the pin), a
    "no push" reference row per task set and kind (the tasks' start IoUs, as the first of its results files
    holds them: every planner starts from the same states), and the paper's three rows."""
    rows, start_rows = [], {}
    for path in results_files:
        r = read_json(path)
        # the planner's model grid where the results record it (a learned planner); "-" for oracle and random
        grid = "x".join(str(int(g)) for g in (r.get("planner") or {}).get("grid") or ()) or "-"
        kind = "reproduced" if r.get("pinned") else f"task set not pinned ({r.get('task_checksum', '')[:12]})"
        partial = r["coverage"]["partial"]
        tasks = r.get("per_task") or {}
        common = {"split": r["task_set"], "kind": kind, "toolkit": str(r.get("toolkit_version", "")),
                  "date": r.get("date", "")[:10], "checksum": r.get("task_checksum", "")[:12]}
        rows.append({"method": f"{r['method']} (planning)", **common, REFERENCE: reference_of(r, planning=True)[0],
                     "label": _joined(f"{r['coverage']['scored']}/{r['coverage']['expected']} tasks"
                                      + (" (partial)" if partial else ""),
                                      superseded_weights((r.get("planner") or {}).get("weights"))), "grid": grid,
                     SEQ: {t: {"planning_iou": v.get("iou")} for t, v in tasks.items()},
                     "planning_iou": r["metrics"]["iou"]})
        if (r["task_set"], kind) not in start_rows and "start_iou" in r["metrics"]:
            start_rows[(r["task_set"], kind)] = {
                "method": NO_PUSH, **common, "label": "the start state's IoU with the target", "grid": "-",
                REFERENCE: "no push",
                SEQ: {t: {"planning_iou": v.get("start_iou")} for t, v in tasks.items()},
                "planning_iou": r["metrics"]["start_iou"]}
    rows += list(start_rows.values())
    if include_paper:
        rows += [{"method": m, "split": "ycb-test", "kind": "reported in the paper", "label": "Sec. 4.3",
                  "grid": "x".join(map(str, GRID_SHAPE)), "toolkit": "", REFERENCE: None,
                  "date": "2020", "checksum": "", SEQ: {}, "planning_iou": v} for m, v in PLANNING_PAPER_ROWS]
    return rows


def _references_last(group):
    """The rows of a table, in order, the reference rows (by provenance, `table.is_reference_row`) last."""
    return group.iloc[sorted(range(len(group)), key=lambda i: is_reference_row(group.iloc[i]))]


def _tables(rows: list[dict]):
    import pandas as pd

    if not rows:  # an empty leaderboard: no table
        return
    frame = pd.DataFrame(rows)
    for (split, kind), group in frame.groupby(["split", "kind"], sort=True):
        if "planning_iou" in group and group["planning_iou"].notna().all():  # a planning task set's own table
            group = _references_last(group)
            yield split, kind, "planning", group[["method", "grid", "planning_iou", "label", "toolkit", "date",
                                                  "checksum", SEQ, REFERENCE]].reset_index(drop=True), ["planning_iou"]
            continue
        for track, columns in TRACKS.items():
            cols = [c for c in columns + (("planning_iou",) if track == "3D" else ()) if c in group]
            sub = group.dropna(subset=[c for c in cols if c in group], how="all")
            cols = [c for c in cols if sub[c].notna().any()]  # a column no row of this table has a value of
            if sub.empty or not cols:
                continue
            sub = _references_last(sub)
            table = sub[["method", "grid", *cols, "label", "toolkit", "date", "checksum", SEQ,
                         REFERENCE]].reset_index(drop=True)
            yield split, kind, track, table, cols


def _difference_tables(table, track: str, cols: list[str]) -> tuple[list[str], str]:
    """Markdown and HTML of a reproduced table's paired differences: per yardstick, every other row that is not an
    oracle, row - yardstick per sequence (task), mean and standard error over the units both scored."""
    unit = "task" if track == "planning" else "sequence"
    md: list[str] = []
    page = []
    for yard in _yardsticks(table, track):
        base = named(table, yard).iloc[0]
        others = [r for _, r in table.iterrows() if not is_named(r, yard) and not is_oracle_row(r)]
        if not others:
            continue
        name = yard.replace(" (planning)", "")
        cols = [c for c in cols if len(unit_values(base[SEQ], c)) >= 2]
        if not cols:
            continue
        header = ["method", *[f"{COLUMN_TITLES[c]} - {name}" for c in cols], f"{unit}s"]
        title = (f"Paired differences from {name} (row - {name}, {unit} by {unit}; mean \u00b1 standard error over "
                 f"the {unit}s both scored):")
        md += [title, "", md_row(header), "|" + "---|" * len(header)]
        html_rows = []
        for r in others:
            diffs = [paired_difference(unit_values(r[SEQ], c), unit_values(base[SEQ], c)) for c in cols]
            n = max((d.n for d in diffs), default=0)
            md.append(md_row([markdown_cell(r["method"]), *[_difference(d, c) for d, c in zip(diffs, cols)],
                               str(n)]))
            html_rows.append([(html.escape(str(r["method"])), None, ""),
                              *[(html.escape(_difference(d, c)), "" if d.n < 2 else repr(d.mean), "")
                                for d, c in zip(diffs, cols)], (str(n), str(n), "")])
        md.append("")
        page.append(f"<p class=note>{html.escape(title)}</p>" + html_table(header, html_rows, "diff"))
    return md, "".join(page)


#: the kind of a real split's tables (`dsr_bench.dataset.real`), followed by the split's checksum
REAL_KIND = "real split"


def _finetune_tables(table, cols: list[str]) -> tuple[list[str], str]:
    """Markdown and HTML of a real split's fine-tuning effect: every fine-tuned row (`NAME-ft`, the name a model
    fine-tuned by `dsr-bench train --finetune` predicts under) against its zero-shot row (`NAME`), sequence by
    sequence, mean and standard error."""
    rows = {str(r["method"]): r for _, r in table.iterrows()}
    pairs = [(rows[m], rows[m[:-3]]) for m in sorted(rows) if m.endswith("-ft") and m[:-3] in rows]
    cols = [c for c in cols if any(len(unit_values(ft[SEQ], c)) >= 2 for ft, _ in pairs)]
    if not pairs or not cols:
        return [], ""
    header = ["model", *[f"{COLUMN_TITLES[c]}: ft - zero-shot" for c in cols], "sequences"]
    title = ("Fine-tuning on the real split's fine-tune part (ft - zero-shot, sequence by sequence; mean \u00b1 "
             "standard error over the sequences both scored):")
    md, html_rows = [title, "", md_row(header), "|" + "---|" * len(header)], []
    for ft, zero in pairs:
        diffs = [paired_difference(unit_values(ft[SEQ], c), unit_values(zero[SEQ], c)) for c in cols]
        n = max((d.n for d in diffs), default=0)
        md.append(md_row([markdown_cell(zero["method"]), *[_difference(d, c) for d, c in zip(diffs, cols)], str(n)]))
        html_rows.append([(html.escape(str(zero["method"])), None, ""),
                          *[(html.escape(_difference(d, c)), "" if d.n < 2 else repr(d.mean), "")
                            for d, c in zip(diffs, cols)], (str(n), str(n), "")])
    return md + [""], f"<p class=note>{html.escape(title)}</p>" + html_table(header, html_rows, "diff")


def _version_line(split: str, kind: str, table) -> str:
    """Which version of the split a table's rows were scored on, and by which toolkit versions."""
    from dsr_bench.dataset.splits import SPLITS

    if kind == "reported in the paper":
        return ""
    checksums = sorted({c for c in table["checksum"] if c})
    toolkits = ", ".join(sorted({t for t in table["toolkit"] if t})) or "?"
    if kind.startswith(REAL_KIND):
        return (f"The real track: every row was scored on the held-out test part of the real split {split[:-5]!r} "
                f"(annotated captures, `dsr-bench real-split`; checksum {', '.join(checksums)}, verified against the "
                f"split's own pins, not the toolkit's; toolkit {toolkits}). A row NAME is the model trained in "
                "simulation and scored directly (zero-shot); NAME-ft the same model fine-tuned on the split's "
                "fine-tune part (`dsr-bench train --finetune`). Real splits of another checksum are other tables.")
    what = "task set" if split not in SPLITS or kind.startswith("task set") else "split"
    if kind == "reproduced":
        return (f"Every row was scored on this {what}'s pinned version (checksum {', '.join(checksums)}; toolkit "
                f"{toolkits}). Rows scored on another version of it are in a table of their own, never in this one.")
    return (f"These rows were scored on a {what} version that is not this toolkit's pin (checksum "
            f"{', '.join(checksums)}; toolkit {toolkits}): they are kept apart and compared with nothing else.")


def build(root: str | Path = "leaderboard", warn: Callable[[str], None] | None = None) -> tuple[Path, Path]:
    """Write README.md and index.html of the leaderboard from its valid entries and paper rows; each entry file
    that is not valid is skipped with one `warn` line naming it and its problem (default: on stderr)."""
    from dsr_bench.dataset.splits import SPLITS

    root = Path(root)
    if not root.is_dir():
        raise UserError(f"--root {root}: {'not a directory' if root.exists() else 'no such directory'}; give the "
                        "leaderboard's folder (leaderboard in a clone), or make an empty one to start a leaderboard")
    entries = load_entries(root, warn)
    rows = load_rows(root, warn, entries)
    plotted: set[Path] = set()
    md = ["# dsr-bench leaderboard", "",
          "Built by `dsr-bench leaderboard build` from `entries/` and `planning/` (results of `dsr-bench evaluate`",
          "and `dsr-bench plan`, recomputed by `leaderboard add` from the predictions and plans) and `paper.json`",
          "(numbers reported in the paper, never mixed with reproduced rows). In each table of reproduced results the",
          "reference rows (oracle; static = predicting no motion; push = every object voxel moved along the push; in",
          "planning: no push and random pushes) sit beside the trained rows of the same version of the split.",
          "",
          "A reproduced value is the benchmark's metric \u00b1 the half-width of the 95% confidence interval of the",
          "mean over the sequences (tasks), from each row's per-sequence (per-task) values (Student t). Under each",
          "table, paired differences from the reference rows (row - reference, sequence by sequence) with their",
          "standard errors. Bold: the best value that is not an oracle's, marked only where the table holds the",
          "no-motion row to compare with; in a planning table, the best planner only where it beats both no push",
          "and random (the 95% interval of each paired difference above 0). " + _WORSE_MARK + ": worse than",
          "predicting no motion. Outside planning, bold marks the best mean, not a significant difference: the paired",
          "differences say whether two rows differ.",
          "Model grid: a 3D model's voxel grid, or the image (H x W) of an image-space model (\"-\" where the paper",
          "does not say).", ""]
    body = []
    for split, kind, track, table, cols in _tables(rows):
        md += [f"## {split}: {track} track ({kind})", ""]
        if split in SPLITS:
            md += [f"{SPLITS[split].description}.", ""]
        version = _version_line(split, kind, table)
        if version:
            md += [version, ""]
        paper = kind == "reported in the paper"
        rendered = render_table(table, track, cols, published=paper)
        comparable, inline = rendered.comparable, track == "planning"
        if not paper and not comparable:
            md += [("This table lacks the no push or the random reference row: no planner is marked best." if
                    track == "planning" else "No no-motion (static) row was scored on this version of the split: "
                    "these rows cannot be compared with predicting no motion, and none is marked best."), ""]
        md += rendered.markdown
        md.append("")
        diff_md, diff_html = _difference_tables(table, track, cols) if not paper and not inline else ([], "")
        if kind.startswith(REAL_KIND):
            ft_md, ft_html = _finetune_tables(table, cols)
            diff_md, diff_html = diff_md + ft_md, diff_html + ft_html
        md += diff_md
        plot = _table_plot(root, entries, split, kind, track) if track != "planning" else \
            _planning_plot(root, table, split, kind)
        figure = ""
        if plot is not None:
            plotted |= {plot, plot.with_suffix(".svg")}
            rel = plot.relative_to(root).as_posix()
            svg = plot.with_suffix(".svg").relative_to(root).as_posix()
            caption = PLANNING_CAPTION if track == "planning" else STEPS_CAPTION
            alt = f"{split}, {track} track: " + ("planning IoU and paired differences" if track == "planning" else
                                                  "per-step curves and 95% intervals")
            width = FIGURE_WIDTH_PX
            md += [caption, "", f'<img src="{rel}" width="{width}" alt="{html.escape(alt)}">', ""]
            figure = (f'<figure><a href="{html.escape(svg)}"><img src="{html.escape(svg)}" alt="{html.escape(alt)}">'
                      f"</a><figcaption>{html.escape(caption)}</figcaption></figure>")
        note = ("" if comparable or paper else
                "<p class=note>" + ("No no push or random row: no planner marked best." if track == "planning" else
                                    "No no-motion (static) row on this version of the split: not comparable, none "
                                    "marked best.") + "</p>")
        about = f"<p>{html.escape(SPLITS[split].description)}.</p>" if split in SPLITS else ""
        about += f"<p class=note>{html.escape(version)}</p>" if version else ""
        anchor = re.sub(r"[^a-z0-9]+", "-", f"{split} {track} {kind}".lower()).strip("-")  # a link to the table
        body.append(f"<h2 id=\"{anchor}\">{html.escape(split)}: {track} track ({html.escape(kind)})</h2>\n"
                    f"{about}{note}"
                    f"{rendered.html('board')}{diff_html}{figure}")
    if not rows:
        md.append("No entries yet.")
    page = _PAGE.replace("{body}", "\n".join(body) or "<p>No entries yet.</p>")
    write_text(root / "README.md", "\n".join(md) + "\n")
    write_text(root / "index.html", page)
    for stale in sorted((root / PLOTS_DIR).glob("*")):  # a plot of a table that no longer exists
        if stale.suffix in (".png", ".svg") and stale not in plotted:
            stale.unlink(missing_ok=True)
    return root / "README.md", root / "index.html"


STEPS_CAPTION = ("Top: each row step by step (reference rows dashed or dotted, open markers). Bottom: each row's "
                 "mean over the sequences with its 95% interval.")
PLANNING_CAPTION = ("Left: each row's planning IoU, mean over the tasks with its 95% interval. Right: each "
                    "planner's paired difference from no push and from random, task by task, with its 95% interval.")

#: Where `build` writes the figures, under the leaderboard's root.
PLOTS_DIR = "plots"


def plot_name(split: str, kind: str, track: str) -> str:
    """The file name of a table's figure (PNG; the SVG beside it has .svg): <split>-3d.png (-2d, -planning), or
    <split>-<checksum>-3d.png for an earlier version of the split."""
    version = "" if kind == "reproduced" else "-" + kind.rsplit(", ", 1)[-1].strip("()").rsplit(" ", 1)[-1]
    return re.sub(r"[^A-Za-z0-9._-]+", "-", f"{split}{version}") + f"-{track.lower()}.png"


def _table_plot(root: Path, entries: list[dict], split: str, kind: str, track: str) -> Path | None:
    """Write the figure of one table of reproduced rows, PNG and SVG (None: paper rows, or no entry has per-step
    values for the track)."""
    from dsr_bench.scoring.plots import MISSING_MATPLOTLIB, leaderboard_series, matplotlib_missing, \
        write_leaderboard_plot

    if not kind.startswith(("reproduced", REAL_KIND)):
        return None
    panels = leaderboard_series([e for e in entries if e["split"] == split and e["kind"] == kind], track)
    if not panels:
        return None
    if matplotlib_missing():
        raise UserError(f"cannot draw {root / PLOTS_DIR}: {MISSING_MATPLOTLIB}")
    title = f"{split}: {track} track" + ("" if kind == "reproduced" else f" ({kind})")
    return write_leaderboard_plot(panels, title, root / PLOTS_DIR / plot_name(split, kind, track), svg=True)


def _planning_plot(root: Path, table, split: str, kind: str) -> Path | None:
    """Write the figure of one planning table (PNG and SVG): its rows' IoUs and paired differences (None: paper
    rows, or no row holds per-task values)."""
    from dsr_bench.scoring.plots import MISSING_MATPLOTLIB, matplotlib_missing, write_planning_plot

    if kind == "reported in the paper":
        return None
    found = [(str(r["method"]).replace(" (planning)", ""), unit_values(r[SEQ], "planning_iou"), is_reference_row(r))
             for _, r in table.iterrows()]
    found = [r for r in found if r[1]]
    if not found:
        return None
    if matplotlib_missing():
        raise UserError(f"cannot draw {root / PLOTS_DIR}: {MISSING_MATPLOTLIB}")
    # planners first, then the reference rows
    rows = [(m, v) for m, v, ref in found if not ref] + [(m, v) for m, v, ref in found if ref]
    title = f"{split}: planning track" + ("" if kind == "reproduced" else f" ({kind})")
    return write_planning_plot(rows, title, root / PLOTS_DIR / plot_name(split, kind, "planning"), svg=True)


def no_motion_entry(results: dict, root: str | Path | None = None) -> tuple[dict | None, str]:
    """The leaderboard's static (no-motion) entry scored on the same split version as `results`, with per-step
    values, for evaluate's plot; else (None, why not). `root`: the leaderboard directory (default: the one beside
    this package, in a clone of the repository)."""
    root = Path(root) if root is not None else Path(__file__).resolve().parents[2] / "leaderboard"
    if results.get("method") == NO_MOTION:
        return None, "no separate no-motion line: these results are the no-motion row's"
    if not (root / "entries").is_dir():
        return None, f"no no-motion line: no leaderboard at {root}"
    for entry in load_entries(root, warn=lambda line: None):
        if reference_of(entry, planning=False)[0] == NO_MOTION and entry["split"] == results.get("split") and \
                entry.get("split_checksum") == results.get("split_checksum") and entry.get("per_step"):
            return entry, ""
    return None, (f"no no-motion line: the leaderboard holds no static entry scored on this version of "
                  f"{results.get('split')!r}")


_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>dsr-bench leaderboard</title>
<style>
body{font-family:system-ui,sans-serif;margin:2em;max-width:1100px}
table{border-collapse:collapse;margin-bottom:1.2em;font-size:14px}
th,td{border:1px solid #ccc;padding:3px 6px;text-align:right}td{white-space:nowrap}
td:first-child,th:first-child{text-align:left}th{cursor:pointer;background:#f4f4f4}.best{font-weight:bold}
.worse{color:#a00}.note{color:#555}figure{margin:0 0 2em 0}img{max-width:100%}
</style></head><body>
<h1>dsr-bench leaderboard</h1>
<p>Reproduced results (<code>dsr-bench evaluate</code>, <code>dsr-bench plan</code>) and numbers reported in the
paper, in separate tables. Reference rows (oracle; static = predicting no motion; push; in planning: no push and
random) sit beside the trained rows of the same version of a split. A reproduced value is the metric &plusmn; the
half-width of the 95% confidence interval of the mean over the sequences (tasks); under each table, paired
differences from the reference rows with their standard errors. Click a column to sort. Bold: the best value that is
not an oracle's (in planning: only a planner that beats no push and random, paired; elsewhere the best mean, not a
significant difference). &#9660; (red): worse than predicting no motion.</p>
{body}
<script>
{script}</script></body></html>
""".replace("{script}", SORT_SCRIPT)
